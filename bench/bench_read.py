#!/usr/bin/env python3
"""Reading speed and memory: a 15-minute recording, radar at 15 Hz with ~200 targets per
frame, NavSatFix and Odometry at 50 Hz. Prints the time to read it split into rosbags
(storage + CDR deserialisation) and our decoding (PointCloud2/NavSatFix/Odometry decoding
and building the Recording), the number of messages, messages per second, and the peak
memory (tracemalloc peak of the read, and the reading process's peak RSS).

The bag comes from ``radar_calib_ros.sim.simulate`` when the simulator is there, else from
our own encoders (their time is printed too: writing must take well under a minute).

    .venv/bin/python bench/bench_read.py [--duration 900] [--storage mcap|sqlite3]
                                         [--targets 200] [--bag DIR]
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path(__file__).resolve().parent / 'out'
T0 = 1_720_000_000_000_000_000
LAT0, LON0, ALT0 = 48.137, 11.575, 520.0


def synthetic_messages(ts: Any, duration_s: float, targets: int,
                       seed: int) -> Iterator[tuple[str, str, int, object]]:
    """Radar frames at 15 Hz (uniform targets in the field of view), a vehicle on a 40 m
    circle with fixes and odometry at 50 Hz, in stamp order."""
    from radar_calib_ros.io import messages as m
    from radar_calib_ros.io.geo import LocalFrame

    rng = np.random.default_rng(seed)
    frame = LocalFrame.at(LAT0, LON0)
    pose_t = np.arange(0.0, duration_s, 0.02)
    angle = pose_t * 10.0 / 40.0
    local = np.column_stack([40 * np.cos(angle), 40 * np.sin(angle), np.zeros_like(angle)])
    lat, lon, alt = frame.local_to_geodetic(local)
    radar_t = np.arange(0.0, duration_s, 1.0 / 15.0)
    events = sorted([(t, 0, i) for i, t in enumerate(radar_t)]
                    + [(t, 1, i) for i, t in enumerate(pose_t)])
    for t, kind, i in events:
        stamp = T0 + int(round(t * 1e9))
        if kind == 0:
            n = int(rng.poisson(targets))
            r = rng.uniform(2, 150, n)
            az = rng.uniform(-1.05, 1.05, n)
            el = rng.uniform(-0.17, 0.17, n)
            positions = np.column_stack([r * np.cos(el) * np.cos(az),
                                         r * np.cos(el) * np.sin(az), r * np.sin(el)])
            yield ('/radar/points', m.POINTCLOUD2, stamp,
                   m.encode_pointcloud(ts, stamp, 'radar', positions, rng.normal(0, 5, n),
                                       extra_fields={'rcs': rng.normal(5, 5, n)
                                                     .astype(np.float32)}))
        else:
            yield ('/vehicle/fix', m.NAVSATFIX, stamp,
                   m.encode_navsatfix(ts, stamp, 'gnss', lat[i], lon[i], alt[i] + ALT0))
            yaw = angle[i] + math.pi / 2
            yield ('/vehicle/odom', m.ODOMETRY, stamp,
                   m.encode_odometry(ts, stamp, 'map', 'base_link', (0.0, 0.0, 0.0),
                                     (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
                                     (10.0, 0.0, 0.0), 0.25))


def make_bag(bag: Path, duration_s: float, storage: str, targets: int) -> None:
    try:
        from radar_calib_ros.sim import simulate
    except ImportError:
        simulate = None
    start = time.perf_counter()
    if simulate is not None:
        simulate(bag, seed=7, duration_s=duration_s, storage=storage)
        print(f'simulated (radar_calib_ros.sim) {duration_s:.0f} s in '
              f'{time.perf_counter() - start:.1f} s')
        return
    from radar_calib_ros.io.bag import write_bag
    from radar_calib_ros.io.messages import get_typestore
    ts = get_typestore()
    count = write_bag(bag, synthetic_messages(ts, duration_s, targets, seed=7),
                      storage=storage, typestore=ts)
    print(f'wrote {count} messages with io.messages encoders + write_bag ({storage}) in '
          f'{time.perf_counter() - start:.1f} s (no simulator yet)')


def measure(bag: Path) -> dict[str, Any]:
    """Runs in a fresh process: plain read, instrumented read, traced read."""
    from rosbags.highlevel import AnyReader

    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.io import bag as bagio
    from radar_calib_ros.io import messages as m
    from radar_calib_ros.recording import RecordingBuilder

    params = bag / 'params.yaml'
    config = CalibConfig.from_file(params) if params.is_file() else CalibConfig()

    # 1. read_recording as the CLI calls it (first, so the peak RSS is one read's)
    start = time.perf_counter()
    recording = bagio.read_recording(bag, config)
    read_s = time.perf_counter() - start
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    # 2. the same loop as read_recording, with a clock around each part
    rosbags_s = decode_s = 0.0
    counts: dict[str, int] = {}
    start = time.perf_counter()
    builder = RecordingBuilder(config)
    with AnyReader([bag], default_typestore=m.get_typestore()) as reader:
        chosen = bagio.select_topics({c.topic: c.msgtype for c in reader.connections}, config)
        roles = {t: r for r, t in chosen.items() if t is not None}
        connections = [c for c in reader.connections if c.topic in roles]
        iterator = reader.messages(connections=connections)
        velocity_field = config.radar.velocity_field
        while True:
            t0 = time.perf_counter()
            item = next(iterator, None)
            if item is None:
                rosbags_s += time.perf_counter() - t0
                break
            connection, _, raw = item
            msg = reader.deserialize(raw, connection.msgtype)
            t1 = time.perf_counter()
            rosbags_s += t1 - t0
            role = roles[connection.topic]
            bagio._add_message(builder, role, connection, msg, velocity_field)
            decode_s += time.perf_counter() - t1
            counts[role] = counts.get(role, 0) + 1
    t2 = time.perf_counter()
    recording = builder.build()
    build_s = time.perf_counter() - t2
    instrumented_s = time.perf_counter() - start

    # 3. peak Python/numpy allocation of one read (tracemalloc slows it; not timed)
    del recording, builder
    tracemalloc.start()
    recording = bagio.read_recording(bag, config)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    size_mb = sum(f.stat().st_size for f in bag.iterdir() if f.is_file()) / 2**20
    return {'counts': counts, 'rosbags_s': rosbags_s, 'decode_s': decode_s,
            'build_s': build_s, 'instrumented_s': instrumented_s, 'read_s': read_s,
            'traced_peak_mb': peak / 2**20, 'rss_mb': rss_mb, 'bag_mb': size_mb,
            'frames': int(recording.frame_stamps_ns.size), 'targets': len(recording.targets),
            'poses': len(recording.vehicle), 'duration_s': recording.duration_s}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=900.0)
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--targets', type=int, default=200)
    parser.add_argument('--bag', type=Path, help='read this bag instead of making one')
    parser.add_argument('--measure', type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return 0
    bag = args.bag
    if bag is None:
        bag = OUT / f'read_{args.storage}_{int(args.duration)}s_{args.targets}t'
        if not bag.exists():
            OUT.mkdir(parents=True, exist_ok=True)
            make_bag(bag, args.duration, args.storage, args.targets)
    # a fresh process, so that the peak RSS is the read's alone
    done = subprocess.run([sys.executable, __file__, '--measure', str(bag)], check=True,
                          capture_output=True, text=True)
    r = json.loads(done.stdout.strip().splitlines()[-1])
    n = sum(r['counts'].values())
    print(f'bag {bag} ({r["bag_mb"]:.0f} MB): {r["duration_s"]:.0f} s, {r["frames"]} radar '
          f'frames, {r["targets"]} targets ({r["targets"] / max(r["frames"], 1):.0f} per '
          f'frame), {r["poses"]} vehicle poses')
    print(f'messages        {n} ({", ".join(f"{k} {v}" for k, v in r["counts"].items())})')
    print(f'read_recording  {r["read_s"]:7.2f} s   {n / r["read_s"]:8.0f} messages/s')
    print(f'  rosbags (storage + deserialisation) {r["rosbags_s"]:7.2f} s')
    print(f'  our decoding (+ builder appends)    {r["decode_s"]:7.2f} s')
    print(f'  RecordingBuilder.build              {r["build_s"]:7.2f} s')
    print(f'  (instrumented total                 {r["instrumented_s"]:7.2f} s)')
    print(f'peak memory     tracemalloc {r["traced_peak_mb"]:.0f} MB, process RSS '
          f'{r["rss_mb"]:.0f} MB')
    return 0


if __name__ == '__main__':
    sys.exit(main())
