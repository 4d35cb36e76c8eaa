#!/usr/bin/env python3
"""Speed and memory of a calibration: a 15-minute, 15 Hz recording with ~200 targets per
frame. Prints the time merely to read the bag, the time per stage, the total wall time and
the peak RSS (targets: <= 30 s, <= 1.5 GB on 2 cores).

    .venv/bin/python bench/bench_speed.py [--duration 900] [--scenario baseline]
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / 'out'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=900.0)
    parser.add_argument('--scenario', default='baseline')
    parser.add_argument('--seed', type=int, default=7)
    args = parser.parse_args()
    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.pipeline import run_calibration
    from radar_calib_ros.sim import simulate

    bag = OUT / f'speed_{args.scenario}_s{args.seed}_{int(args.duration)}'
    if not (bag / 'ground_truth.json').is_file():
        start = time.perf_counter()
        simulate(bag, seed=args.seed, duration_s=args.duration, scenario=args.scenario)
        print(f'simulated {args.duration:.0f} s in {time.perf_counter() - start:.1f} s')
    config = CalibConfig.from_file(bag / 'params.yaml')
    start = time.perf_counter()
    recording = read_recording(bag, config)
    read_s = time.perf_counter() - start
    result = run_calibration(recording, config)
    total_s = time.perf_counter() - start
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    n_frames = recording.frame_stamps_ns.size
    print(f'recording: {n_frames} radar frames, {len(recording.targets)} targets '
          f'({len(recording.targets) / max(n_frames, 1):.0f} per frame), '
          f'{len(recording.vehicle)} vehicle poses, {recording.duration_s:.0f} s')
    print(f'read bag        {read_s:7.2f} s')
    for name, seconds in result.stage_times_s.items():
        print(f'  {name:<14}{seconds:7.2f} s')
    print(f'total (read + calibrate) {total_s:.2f} s wall; peak RSS {rss_mb:.0f} MB')
    return 0


if __name__ == '__main__':
    sys.exit(main())
