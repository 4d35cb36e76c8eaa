#!/usr/bin/env python3
"""The node's message handling: cost per radar frame, buffer memory, trigger-to-result time.

Feeds a simulated 15-minute recording (``radar_calib_ros.sim.simulate``) message by message
through ``LiveCalibrator`` exactly as the node's subscription callbacks do, then:

- prints the cost of handling one radar frame (``on_radar``: decoding the PointCloud2 and
  buffering it; mean, p50, p99, max) and of one fix / odometry message;
- the same for synthetic 500-target frames (the issue's bound: well under 1 ms);
- feeds the recording into a fresh buffer twice, the second time shifted by its duration,
  so that the buffer holds 30 minutes of data, and prints the buffer's memory: measured
  (tracemalloc: what is still allocated once the messages are gone; numpy reports its
  arrays to it) and the buffer's own estimate, which the ``buffer.max_memory_mb`` bound
  uses;
- calls ``calibrate()`` on the 15-minute buffer and prints the time from trigger to result.

Deserialising the bag (rosbags) is not part of the node's cost (rclpy hands over messages)
and is done before the clock starts, in chunks.

    .venv/bin/python bench/bench_node.py [--duration 900] [--seed 1] [--scenario baseline]
                                         [--bag DIR] [--no-calibrate]
"""
from __future__ import annotations

import argparse
import copy
import gc
import json
import sys
import tempfile
import threading
import time
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from radar_calib_ros.config import CalibConfig  # noqa: E402
from radar_calib_ros.io import messages as msgs  # noqa: E402
from radar_calib_ros.live import LiveCalibrator  # noqa: E402

OUT = Path(__file__).resolve().parent / 'out'
_HANDLERS = {msgs.POINTCLOUD2: 'on_radar', msgs.NAVSATFIX: 'on_navsat',
             msgs.ODOMETRY: 'on_odometry'}


def rss_mib() -> float:
    """Current resident set size of this process [MiB] (Linux)."""
    with open('/proc/self/statm', encoding='ascii') as fh:
        pages = int(fh.read().split()[1])
    return pages * 4096 / 2**20


def bag_messages(bag: Path, chunk: int = 5000) -> Iterator[list[tuple[str, Any]]]:
    """(msgtype, message) in bag order, deserialised in chunks ahead of the timing."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=msgs.get_typestore()) as reader:
        connections = [c for c in reader.connections if c.msgtype in _HANDLERS]
        batch: list[tuple[str, Any]] = []
        for connection, _, raw in reader.messages(connections=connections):
            batch.append((connection.msgtype, reader.deserialize(raw, connection.msgtype)))
            if len(batch) == chunk:
                yield batch
                batch = []
        if batch:
            yield batch


def shift(msg: Any, offset_ns: int) -> Any:
    """The message with its header stamp moved by offset_ns (a copy)."""
    moved = copy.copy(msg)
    moved.header = copy.copy(msg.header)
    stamp = msgs.stamp_ns(msg.header) + offset_ns
    moved.header.stamp = type(msg.header.stamp)(sec=stamp // 10**9, nanosec=stamp % 10**9)
    return moved


class GcPauses:
    """Durations of Python's garbage collections by generation (gc.callbacks)."""

    def __init__(self) -> None:
        self.pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
        self._start = 0.0
        gc.callbacks.append(self)

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == 'start':
            self._start = time.perf_counter()
        else:
            self.pauses[info['generation']].append(time.perf_counter() - self._start)

    def summary(self) -> dict[str, float]:
        full = self.pauses[2]
        return {'full_collections': len(full), 'full_max_ms': 1e3 * max(full, default=0.0),
                'all_total_s': sum(sum(p) for p in self.pauses.values())}

    def close(self) -> None:
        gc.callbacks.remove(self)


def feed(live: LiveCalibrator, bag: Path, offset_ns: int = 0,
         until: Callable[[], bool] | None = None) -> dict[str, list[float]]:
    """Hand every message to its handler, timing each call; stop early when ``until()``."""
    costs: dict[str, list[float]] = {name: [] for name in _HANDLERS.values()}
    handlers = {msgtype: getattr(live, name) for msgtype, name in _HANDLERS.items()}
    for batch in bag_messages(bag):
        if until is not None and until():
            break
        if offset_ns:
            batch = [(msgtype, shift(msg, offset_ns)) for msgtype, msg in batch]
        for msgtype, msg in batch:
            handler = handlers[msgtype]
            start = time.perf_counter()
            handler(msg)
            costs[_HANDLERS[msgtype]].append(time.perf_counter() - start)
    return costs


def stats_us(values: list[float]) -> dict[str, float]:
    a = np.asarray(values) * 1e6
    if a.size == 0:
        return {'n': 0}
    return {'n': int(a.size), 'mean_us': float(a.mean()), 'p50_us': float(np.median(a)),
            'p99_us': float(np.percentile(a, 99)), 'max_us': float(a.max())}


def synthetic_500(live: LiveCalibrator, frames: int = 2000) -> dict[str, float]:
    store = msgs.get_typestore()
    rng = np.random.default_rng(0)
    t0 = 1_900_000_000 * 10**9
    messages = [msgs.encode_pointcloud(store, t0 + i * 66_666_667, 'radar',
                                       rng.uniform([1, -60, -10], [150, 60, 10], (500, 3)),
                                       rng.normal(0, 8, 500))
                for i in range(frames)]
    costs = []
    for message in messages:
        start = time.perf_counter()
        live.on_radar(message)
        costs.append(time.perf_counter() - start)
    return stats_us(costs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--duration', type=float, default=900.0)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--scenario', default='baseline')
    parser.add_argument('--bag', type=Path, help='use this recording instead of simulating')
    parser.add_argument('--no-calibrate', action='store_true')
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix='bench_node_'))
    bag = args.bag
    if bag is None:
        from radar_calib_ros.sim import simulate

        bag = work / 'drive'
        start = time.perf_counter()
        simulate(bag, seed=args.seed, duration_s=args.duration, scenario=args.scenario)
        print(f'simulated {args.duration:.0f} s of {args.scenario!r} in '
              f'{time.perf_counter() - start:.0f} s')
    config = CalibConfig.from_mapping({'output.path': str(work / 'result.yaml'),
                                       'buffer.max_duration': 3600.0,
                                       'buffer.max_memory_mb': 8192.0})
    log_lines: list[str] = []
    live = LiveCalibrator(config, log=lambda severity, text: log_lines.append(text))

    gc.collect()
    gc.freeze()  # as the node's main() does after start
    rss_before = rss_mib()
    pauses = GcPauses()
    costs = feed(live, bag)
    pauses.close()
    first = live.buffer_stats()
    report: dict[str, Any] = {
        'recording_s': first['span_s'],
        'radar_frames': first['radar_frames'],
        'targets_per_frame': first['targets'] / max(first['radar_frames'], 1),
        'radar_frame': stats_us(costs['on_radar']),
        'navsatfix': stats_us(costs['on_navsat']),
        'odometry': stats_us(costs['on_odometry']),
        'gc_during_feed': pauses.summary(),
    }
    if not args.no_calibrate:
        start = time.perf_counter()
        outcome = live.calibrate()
        report['trigger_to_result_s'] = time.perf_counter() - start
        report['calibration'] = outcome.message
        # again, while messages keep arriving (the node's subscriptions run meanwhile): the
        # same recording shifted by its span is fed during the calibration
        span_ns = int(round(first['span_s'] * 1e9)) + 66_666_667
        done: dict[str, float] = {}

        def trigger(calibrator: LiveCalibrator = live) -> None:
            begin = time.perf_counter()
            calibrator.calibrate()
            done['s'] = time.perf_counter() - begin

        worker = threading.Thread(target=trigger)
        worker.start()
        during = feed(live, bag, offset_ns=span_ns, until=lambda: 's' in done)
        worker.join()
        report['trigger_to_result_while_feeding_s'] = done['s']
        report['radar_frame_during_calibration'] = stats_us(during['on_radar'])

    del live
    gc.collect()
    # a fresh buffer of 30 minutes, traced: the recording, then again shifted by its span
    span_ns = int(round(first['span_s'] * 1e9)) + 66_666_667
    tracemalloc.start()
    live = LiveCalibrator(config, log=lambda severity, text: log_lines.append(text))
    feed(live, bag)
    feed(live, bag, offset_ns=span_ns)
    gc.collect()
    traced, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    full = live.buffer_stats()
    report['buffer_span_s'] = full['span_s']
    report['buffer_traced_mib'] = traced / 2**20
    report['buffer_estimate_mib'] = full['memory_mib']
    report['rss_growth_mib'] = rss_mib() - rss_before
    del live
    gc.collect()

    bench_live = LiveCalibrator(CalibConfig.from_mapping({'output.path': str(work / 'b.yaml')}),
                                log=lambda severity, text: None)
    report['synthetic_500_target_frame'] = synthetic_500(bench_live)

    r = report
    print(f"recording: {r['recording_s']:.0f} s, {r['radar_frames']} radar frames, "
          f"{r['targets_per_frame']:.0f} targets per frame")
    for key in ('radar_frame', 'synthetic_500_target_frame', 'navsatfix', 'odometry',
                'radar_frame_during_calibration'):
        if key not in r:
            continue
        s = r[key]
        print(f"{key:>27}: mean {s['mean_us']:7.1f} us, p50 {s['p50_us']:7.1f} us, "
              f"p99 {s['p99_us']:7.1f} us, max {s['max_us']:8.1f} us  (n={s['n']})")
    print(f"buffer of {r['buffer_span_s']:.0f} s: {r['buffer_traced_mib']:.0f} MiB measured, "
          f"{r['buffer_estimate_mib']:.0f} MiB by its own estimate (process RSS grew "
          f"{r['rss_growth_mib']:.0f} MiB)")
    g = r['gc_during_feed']
    print(f"garbage collections while feeding: {g['full_collections']} full ones, longest "
          f"{g['full_max_ms']:.0f} ms, {g['all_total_s']:.1f} s in all (the max above)")
    if 'trigger_to_result_s' in r:
        print(f"trigger to result on {r['recording_s']:.0f} s: {r['trigger_to_result_s']:.1f} s"
              f" -> {r['calibration']}")
        print('trigger to result while messages keep arriving: '
              f"{r['trigger_to_result_while_feeding_s']:.1f} s")
    OUT.mkdir(exist_ok=True)
    (OUT / 'bench_node.json').write_text(json.dumps(report, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
