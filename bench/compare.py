#!/usr/bin/env python3
"""Side-by-side comparison on the same data: ours, two baselines, the paper, an oracle.

Per simulated 10-minute scenario (every scenario in which the calibration vehicle is seen;
bags cached under bench/out/, shared with bench_accuracy.py), one recording is read once
and handed to

  ours    run_calibration with the defaults (stages 1-9)
  paper   the paper's method alone: refine.final = False (stages 1-7)
  naive   one least-squares rigid fit of all moving targets time-matched to the vehicle
          within a gate found by ICP from the trajectory's centroid (bench/baselines.py)
  peer2d  a 2-D Gaussian-mixture peer in the manner of Li et al. 2023: yaw + 2-D
          translation; roll = pitch = 0 and a nominal 6 m height, scored as output
  oracle  our final refinement on exactly the calibration vehicle's targets (from
          ground_truth_targets.npz), moving or not, started at the truth: the best
          achievable on that data
  orc_mv  the same oracle on the vehicle's moving targets only (what stage 1 passes on):
          separates what our target selection costs from what the moving filter costs

It prints horizontal / vertical / rotation error and run time (the method alone, the
shared bag read excluded) per scenario, the ratio of our error to the oracle's, medians,
and checks the issue's targets: ours beats every baseline (naive, peer2d, paper) on every
scenario, per axis group, and stays within 1.5x of the oracle.

    .venv/bin/python bench/compare.py [--scenarios ...] [--seed 1] [--duration 600]
        [--jobs 2] [--json out.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
OUT = HERE / 'out'
METHODS = ('ours', 'paper', 'naive', 'peer2d', 'oracle', 'orc_mv')
BASELINES = ('paper', 'naive', 'peer2d')
AXES = ('horizontal_m', 'vertical_m', 'rotation_deg')
#: ours / oracle allowed per axis group
ORACLE_RATIO = 1.5


def bag_path(scenario: str, seed: int, duration: float) -> Path:
    """The cached bag of a scenario (bench_accuracy.py's naming, default scatter model)."""
    from radar_calib_ros.sim import DEFAULT_SCATTER_MODEL, simulate
    bag = OUT / f'{scenario}_{DEFAULT_SCATTER_MODEL}_s{seed}_{int(duration)}'
    if not (bag / 'ground_truth.json').is_file():
        simulate(bag, seed=seed, duration_s=duration, scenario=scenario)
    return bag


def run_one(scenario: str, seed: int, duration: float) -> dict[str, Any]:
    sys.path.insert(0, str(HERE))
    import numpy as np
    from baselines import gmm_peer, naive_fit, oracle_refinement, truth_vehicle_mask
    from scipy.spatial.transform import Rotation

    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.core.moving import filter_moving_targets
    from radar_calib_ros.errors import CalibrationError
    from radar_calib_ros.groundtruth import calibration_errors, load_ground_truth
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.pipeline import run_calibration
    from radar_calib_ros.result import calibration_dict, utm_to_extrinsics

    bag = bag_path(scenario, seed, duration)
    truth = load_ground_truth(bag)
    assert truth is not None
    config = CalibConfig.from_file(bag / 'params.yaml')
    start = time.perf_counter()
    recording = read_recording(bag, config)
    row: dict[str, Any] = {'scenario': scenario, 'seed': seed,
                           'read_s': time.perf_counter() - start,
                           'n_targets': len(recording.targets)}

    def errors(ext: Any) -> dict[str, float]:
        return calibration_errors(calibration_dict(ext, recording.frame), truth)

    def timed(name: str, fn: Any) -> None:
        t0 = time.perf_counter()
        try:
            ext, extra = fn()
        except CalibrationError as err:
            row[name] = {'status': f'exit 1: {err}', 'time_s': time.perf_counter() - t0}
            return
        row[name] = {'status': 'ok', 'time_s': time.perf_counter() - t0, **extra,
                     'errors': errors(ext)}

    def ours() -> tuple[Any, dict[str, Any]]:
        result = run_calibration(recording, config)
        cal = result.calibration(config)
        extra = {'sigma': cal['quality']['sigma'], 'passes': cal['quality']['passes']}
        if result.refinement is not None:
            # how clean the final refinement's target set is, against the truth labels
            used = np.asarray(result.refinement.diagnostics['residuals']['target_index'])
            extra.update(n_used=int(used.size), precision=float(mask[used].mean()),
                         recall=float(mask[used].sum() / max(int(moving_mask[mask].sum()), 1)))
        return result.extrinsics, extra

    def paper() -> tuple[Any, dict[str, Any]]:
        cfg = dataclasses.replace(config, refine=dataclasses.replace(config.refine,
                                                                     final=False))
        return run_calibration(recording, cfg).extrinsics, {}

    truth_ext = utm_to_extrinsics(Rotation.from_quat(truth['quaternion_xyzw']).as_matrix(),
                                  np.asarray(truth['translation'], float), recording.frame,
                                  float(truth.get('time_offset_s', 0.0)))
    mask = truth_vehicle_mask(bag, recording)
    moving_mask = filter_moving_targets(recording.targets.radial_velocity_mps, config.moving)
    row['n_vehicle_targets'] = int(mask.sum())
    row['n_vehicle_moving'] = int((mask & moving_mask).sum())

    def oracle(labels: Any) -> Any:
        def run() -> tuple[Any, dict[str, Any]]:
            ref = oracle_refinement(recording, config, labels, truth_ext)
            return ref.extrinsics, {'n_used': ref.n_targets}
        return run

    timed('ours', ours)
    timed('paper', paper)
    timed('naive', lambda: (naive_fit(recording, config), {}))
    timed('peer2d', lambda: (gmm_peer(recording, config), {}))
    timed('oracle', oracle(mask))
    timed('orc_mv', oracle(mask & moving_mask))
    return row


def main() -> int:
    from radar_calib_ros.sim import SCENARIOS
    default = [s for s in SCENARIOS if s != 'vehicle_never_in_view' and 'radars' not in s]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenarios', nargs='+', default=default)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--duration', type=float, default=600.0)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--json', help='write all rows here')
    parser.add_argument('--from-json', help='print the table of an earlier --json instead')
    args = parser.parse_args()
    if args.from_json:
        rows = json.loads(Path(args.from_json).read_text())
    else:
        OUT.mkdir(parents=True, exist_ok=True)
        n = len(args.scenarios)
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            rows = list(pool.map(run_one, args.scenarios, [args.seed] * n,
                                 [args.duration] * n))
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0 if print_table(rows) else 1


_W = 27


def _cell(entry: dict[str, Any] | None) -> str:
    if not entry or entry.get('status') != 'ok':
        return f'{"failed":>{_W}}'
    e = entry['errors']
    return _fmt(e['horizontal_m'], e['vertical_m'], e['rotation_deg'], entry['time_s'])


def _fmt(h_m: float, v_m: float, rot_deg: float, time_s: float) -> str:
    return f'{100 * h_m:8.1f}{100 * v_m:7.1f}{rot_deg:7.2f}{time_s:5.0f}'


def _sigma(entry: dict[str, Any], axis: str) -> float:
    """Our reported 1-sigma for an axis group (same units as the errors)."""
    s = entry.get('sigma') or {}
    if axis == 'horizontal_m':
        return math.hypot(s.get('along_boresight_m', math.nan),
                          s.get('across_boresight_m', math.nan))
    return float(s.get(axis, math.nan))


def print_table(rows: list[dict[str, Any]]) -> bool:
    """Print the comparison; True when every target of the issue is met."""
    print('per method: horizontal [cm], vertical [cm], rotation [deg], run time [s] '
          '(bag read excluded)')
    print(f'{"scenario":<26}' + ''.join(f'{m + " h v rot t":>{_W}}' for m in METHODS)
          + f'{"ours/oracle h v rot":>22}')
    ok = True
    ratios: dict[str, list[float]] = {a: [] for a in AXES}
    misses: list[str] = []
    for r in rows:
        line = f'{r["scenario"]:<26}' + ''.join(_cell(r.get(m)) for m in METHODS)
        ours, oracle = r.get('ours'), r.get('oracle')
        if ours and oracle and ours['status'] == oracle['status'] == 'ok':
            rs = [ours['errors'][a] / max(oracle['errors'][a], 1e-9) for a in AXES]
            for a, v in zip(AXES, rs):
                ratios[a].append(v)
            line += f'{rs[0]:8.2f}{rs[1]:7.2f}{rs[2]:7.2f}'
            for a, v in zip(AXES, rs):
                if v > ORACLE_RATIO:
                    misses.append(f'{r["scenario"]}: ours/oracle {a} {v:.2f} > {ORACLE_RATIO} '
                                  f'(ours {ours["errors"][a]:.3f}, oracle '
                                  f'{oracle["errors"][a]:.3f}, ours 1-sigma '
                                  f'{_sigma(ours, a):.3f})')
        print(line)
        if not ours or ours['status'] != 'ok':
            misses.append(f'{r["scenario"]}: ours {ours["status"] if ours else "missing"}')
            continue
        for b in BASELINES:
            entry = r.get(b)
            if not entry or entry['status'] != 'ok':
                continue
            for a in AXES:
                if ours['errors'][a] >= entry['errors'][a]:
                    misses.append(f'{r["scenario"]}: {b} {a} {entry["errors"][a]:.3f} <= ours '
                                  f'{ours["errors"][a]:.3f} (ours 1-sigma {_sigma(ours, a):.3f})')
    print(f'{"median":<26}', end='')
    for m in METHODS:
        good = [r[m] for r in rows if r.get(m) and r[m]['status'] == 'ok']
        if not good:
            print(f'{"-":>{_W}}', end='')
            continue
        med = [statistics.median(g['errors'][a] for g in good) for a in AXES]
        print(_fmt(*med, statistics.median(g['time_s'] for g in good)), end='')
    if ratios['horizontal_m']:
        print(''.join(f'{statistics.median(ratios[a]):7.2f}' for a in AXES), end='')
    print()
    print('\nours: targets of the final refinement against the truth labels (precision = '
          "share from the calibration vehicle; recall = share of the vehicle's moving targets "
          'used)')
    for r in rows:
        o = r.get('ours') or {}
        if 'precision' in o:
            print(f'  {r["scenario"]:<26}{o["n_used"]:7d} used  precision {o["precision"]:.3f}  '
                  f'recall {o["recall"]:.3f}  passes {o.get("passes")}')
    reads = [r['read_s'] for r in rows]
    print(f'bag read (shared, excluded above): median {statistics.median(reads):.1f} s; '
          f'{len(rows)} scenarios')
    if misses:
        ok = False
        print('targets missed (ours beats every baseline per axis group, within '
              f'{ORACLE_RATIO}x of the oracle):')
        for miss in misses:
            print('  ' + miss)
    else:
        print(f'all targets met: ours beats every baseline on every scenario and stays within '
              f'{ORACLE_RATIO}x of the oracle')
    return ok


if __name__ == '__main__':
    sys.exit(main())
