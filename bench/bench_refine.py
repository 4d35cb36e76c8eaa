#!/usr/bin/env python3
"""Stage 8 alone on the simulator: accuracy and calibrated uncertainty of the final refinement.

The association is taken from the simulator's truth (which targets are the calibration
vehicle's, the other road users' object ids as tracks) and the start is the true
calibration moved by 0.3 m and 1 deg of yaw with an unknown clock offset, so the numbers
measure the refinement (and its reported 1-sigma), not stages 1-7. Prints per run the
horizontal / vertical / rotation / clock-offset errors and the reported sigmas, then per
scatter model the medians, maxima and the 2-sigma coverage (target 90-98 %).

    .venv/bin/python bench/bench_refine.py [--models interior skin mixed]
        [--scenarios ...] [--seeds 1 2 3] [--duration 600]

Bags are cached under bench/out/ (delete to regenerate).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path(__file__).resolve().parent / 'out'
SCENARIOS = ('baseline', 'dense_traffic_steep_pitch', 'low_mount', 'navsat_only',
             'clock_offset', 'mid_block', 'skewed_junction', 'southern_t_junction',
             'far_from_meridian')


def run_one(scenario: str, model: str, seed: int, duration: float) -> dict[str, Any]:
    from scipy.spatial.transform import Rotation

    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.core import refine
    from radar_calib_ros.groundtruth import load_ground_truth
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.result import utm_to_extrinsics
    from radar_calib_ros.sim import simulate
    from radar_calib_ros.types import Extrinsics, HypothesisSelection, TrackedTargets

    bag = OUT / f'{scenario}_{model}_s{seed}_{int(duration)}'
    if not (bag / 'ground_truth.json').is_file():
        simulate(bag, seed=seed, duration_s=duration, scenario=scenario, scatter_model=model)
    config = CalibConfig.from_file(bag / 'params.yaml')
    recording = read_recording(bag, config)
    truth = load_ground_truth(bag)
    assert truth is not None
    targets = np.load(bag / 'ground_truth_targets.npz')
    true = utm_to_extrinsics(Rotation.from_quat(truth['quaternion_xyzw']).as_matrix(),
                             np.asarray(truth['translation']), recording.frame)
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=3)
    direction[2] *= 0.3
    direction /= np.linalg.norm(direction)
    start = Extrinsics(Rotation.from_euler('z', float(rng.choice([-1.0, 1.0])),
                                           degrees=True).as_matrix() @ true.rotation,
                       true.translation_m + 0.3 * direction, 0.0)
    moving = np.flatnonzero(np.abs(recording.targets.radial_velocity_mps) > 0.1 / 3.6)
    object_id = targets['object_id'][moving].astype(np.int64)
    calib_id = int(np.unique(targets['object_id'][targets['is_calibration_vehicle']])[0])
    tracked = TrackedTargets(moving.astype(np.int64), np.where(object_id >= 0, object_id, -1))
    selection = HypothesisSelection((), np.zeros(0, np.int64), 0, {}, (calib_id,), start, 0)
    t0 = time.perf_counter()
    ref = refine.refine_extrinsics(start, recording, tracked, selection, config)
    elapsed = time.perf_counter() - t0
    est = ref.extrinsics
    d = est.translation_m - true.translation_m
    rot = float(np.degrees(Rotation.from_matrix(true.rotation.T @ est.rotation).magnitude()))
    diag = ref.diagnostics
    err = {'horizontal': float(np.hypot(d[0], d[1])), 'vertical': float(abs(d[2])),
           'rotation': rot, 'time': abs(est.time_offset_s + config.sync.time_offset
                                        - float(truth['time_offset_s']))}
    sig = {'horizontal': diag['sigma_horizontal_m'], 'vertical': diag['sigma_vertical_m'],
           'rotation': diag['sigma_rotation_deg'], 'time': diag['sigma_time_offset_s'],
           'along': diag['sigma_along_boresight_m'],
           'across': diag['sigma_across_boresight_m']}
    return {'scenario': scenario, 'model': model, 'seed': seed, 'err': err, 'sigma': sig,
            'passes': ref.n_passes, 'targets': ref.n_targets, 'time_s': elapsed,
            'advice': len(diag['advice'])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--models', nargs='+', default=['interior', 'skin', 'mixed'])
    parser.add_argument('--scenarios', nargs='+', default=list(SCENARIOS))
    parser.add_argument('--seeds', nargs='+', type=int, default=[1])
    parser.add_argument('--duration', type=float, default=600.0)
    args = parser.parse_args()
    rows = []
    print(f'{"scenario":28s} {"model":8s} seed | horiz cm (2sig) | vert cm (2sig) | '
          'rot deg (2sig) | clock ms | along/across 1sig cm | passes  time')
    for model in args.models:
        for seed in args.seeds:
            for scenario in args.scenarios:
                row = run_one(scenario, model, seed, args.duration)
                rows.append(row)
                e, s = row['err'], row['sigma']
                print(f'{scenario:28s} {model:8s} {seed:4d} | {100 * e["horizontal"]:5.1f} '
                      f'({200 * s["horizontal"]:5.1f}) | {100 * e["vertical"]:5.1f} '
                      f'({200 * s["vertical"]:5.1f}) | {e["rotation"]:.3f} '
                      f'({2 * s["rotation"]:.3f}) | {1000 * e["time"]:5.1f} | '
                      f'{100 * s["along"]:5.1f} / {100 * s["across"]:4.1f} | '
                      f'{row["passes"]:3d} {row["time_s"]:5.1f}s', flush=True)
    print()
    print(f'{"model":8s} runs | horizontal med/max cm | vertical med/max cm | '
          'rotation med/max deg | coverage 2sig h / v / rot / clock')
    for model in args.models:
        sub = [r for r in rows if r['model'] == model]
        if not sub:
            continue

        def col(key: str, sub: list[dict[str, Any]] = sub) -> list[float]:
            return [r['err'][key] for r in sub]

        def cover(key: str, sub: list[dict[str, Any]] = sub) -> float:
            return 100.0 * statistics.mean(r['err'][key] <= 2.0 * r['sigma'][key]
                                           for r in sub)

        med_h, med_v = statistics.median(col('horizontal')), statistics.median(col('vertical'))
        print(f'{model:8s} {len(sub):4d} | {100 * med_h:6.1f} / '
              f'{100 * max(col("horizontal")):5.1f} | {100 * med_v:6.1f}'
              f' / {100 * max(col("vertical")):5.1f} | {statistics.median(col("rotation")):.3f} / '
              f'{max(col("rotation")):.3f} | {cover("horizontal"):5.1f} / {cover("vertical"):5.1f}'
              f' / {cover("rotation"):5.1f} / {cover("time"):5.1f} %')


if __name__ == '__main__':
    main()
