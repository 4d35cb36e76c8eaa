#!/usr/bin/env python3
"""Accuracy suite: simulate 10-minute scenarios, calibrate them, compare with the truth.

Prints, per scenario and scatter model: horizontal / vertical / rotation error after
stage 6 (hypotheses), 7 (the paper's polygon refinement) and 8 (our final refinement),
the clock-offset error, the reported 1-sigma (along / across the boresight), whether the
2-sigma covers the error, and the run time; then medians and maxima per model against
the issue's targets. Bags are cached under bench/out/ (delete to regenerate).

    .venv/bin/python bench/bench_accuracy.py [--models skin interior mixed]
        [--scenarios ...] [--seeds 1] [--duration 600] [--jobs 2] [--json FILE]
        [--set refine.KEY=VALUE ...]   (an experiment's parameters over every scenario's)
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import yaml

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import ConfigError

OUT = Path(__file__).resolve().parent / 'out'


def _overridden(config: CalibConfig, overrides: tuple[str, ...]) -> CalibConfig:
    """--set KEY=VALUE: an experiment's parameters (YAML values) over the scenario's own."""
    if not overrides:
        return config
    return config.replaced({key: yaml.safe_load(value) for key, _, value in
                            (item.partition('=') for item in overrides)})


def run_one(scenario: str, model: str, seed: int, duration: float,
            overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    from radar_calib_ros.cli import calibrate_bag
    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.errors import CalibrationError
    from radar_calib_ros.groundtruth import calibration_errors, load_ground_truth
    from radar_calib_ros.result import calibration_dict
    from radar_calib_ros.sim import simulate

    bag = OUT / f'{scenario}_{model}_s{seed}_{int(duration)}'
    if not (bag / 'ground_truth.json').is_file():
        simulate(bag, seed=seed, duration_s=duration, scenario=scenario, scatter_model=model)
    truth = load_ground_truth(bag)
    assert truth is not None
    config = CalibConfig.from_file(bag / 'params.yaml')
    config = _overridden(config, overrides)
    row: dict[str, Any] = {'scenario': scenario, 'model': model, 'seed': seed}
    start = time.perf_counter()
    try:
        result, read_s = calibrate_bag(bag, config)
    except CalibrationError as err:
        row.update(status=f'exit: {err}', time_s=time.perf_counter() - start)
        return row
    row['time_s'] = time.perf_counter() - start
    row['read_s'] = read_s
    cal = result.calibration(config)
    row['status'] = 'ok'
    row['final'] = calibration_errors(cal, truth)
    for stage, ext in result.stage_extrinsics.items():
        row[stage] = calibration_errors(calibration_dict(ext, result.recording.frame), truth)
    sigma = cal['quality']['sigma']
    row['sigma'] = sigma
    row['passes'] = cal['quality'].get('passes')
    row['headings_deg'] = cal['quality'].get('pass_headings_deg') or []
    row['advice'] = cal['quality'].get('advice')
    f = row['final']
    row['covered'] = {
        'horizontal': f['horizontal_m'] <= 2 * (sigma['along_boresight_m'] ** 2
                                                + sigma['across_boresight_m'] ** 2) ** 0.5,
        'vertical': f['vertical_m'] <= 2 * sigma['vertical_m'],
        'rotation': f['rotation_deg'] <= 2 * sigma['rotation_deg'],
    }
    return row


def main() -> int:
    from radar_calib_ros.sim import SCATTER_MODELS, SCENARIOS
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--models', nargs='+', default=list(SCATTER_MODELS))
    # a recording of several radars is calibrated by `calibrate --all-radars`, not here
    parser.add_argument('--scenarios', nargs='+',
                        default=[s for s in SCENARIOS if 'radars' not in s])
    parser.add_argument('--seeds', type=int, default=1)
    parser.add_argument('--duration', type=float, default=600.0)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--json', help='write all rows here')
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help='a parameter over every scenario\'s own (e.g. '
                        'refine.max_iterations=3), for experiments')
    args = parser.parse_args()
    try:   # a mistyped --set fails here, not in every worker
        _overridden(CalibConfig(), tuple(args.set))
    except ConfigError as err:
        parser.error(str(err))
    OUT.mkdir(parents=True, exist_ok=True)
    jobs = [(s, m, seed, args.duration, tuple(args.set)) for m in args.models
            for s in args.scenarios for seed in range(1, args.seeds + 1)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(run_one, *zip(*jobs)))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    _print(rows)
    return 0


def _cm(row: dict[str, Any], stage: str) -> str:
    e = row.get(stage)
    if not e:
        return f'{"-":>17}'
    return f'{100 * e["horizontal_m"]:6.1f}{100 * e["vertical_m"]:6.1f}{e["rotation_deg"]:5.2f}'


def _headings(row: dict[str, Any]) -> str:
    """The passes' directions of travel as compass initials (N, SE, ...), each once."""
    from radar_calib_ros.core.uncertainty import compass_name
    names = sorted({''.join(w[0].upper() for w in compass_name(math.radians(90.0 - h)).split('-'))
                    for h in row.get('headings_deg') or []})
    return ','.join(names) or '-'


def _print(rows: list[dict[str, Any]]) -> None:
    print(f'{"scenario":<28}{"model":<9}{"stage6 h/v cm, rot":>18}{"stage7":>17}'
          f'{"final":>17}{"dt ms":>7}{"sig al/ac cm":>14}{"cov":>5}{"pass":>5}{"time s":>8}'
          '  headings')
    for r in rows:
        if r['status'] != 'ok':
            print(f'{r["scenario"]:<28}{r["model"]:<9}{r["status"]}')
            continue
        s = r['sigma']
        cov = ''.join('y' if v else 'n' for v in r['covered'].values())
        dt = r['final'].get('time_offset_s')
        print(f'{r["scenario"]:<28}{r["model"]:<9}{_cm(r, "hypotheses")}{_cm(r, "polygon")}'
              f'{_cm(r, "final")}{"" if dt is None else f"{1000 * dt:7.1f}"}'
              f'{100 * s["along_boresight_m"]:7.1f}{100 * s["across_boresight_m"]:7.1f}'
              f'{cov:>5}{r["passes"]!s:>5}{r["time_s"]:8.1f}  {_headings(r)}')
    print()
    print('per model (final): horizontal median/max [cm], vertical max [cm], rotation '
          'median/max [deg], 2-sigma coverage h/v/rot; targets: h median <= 5, max <= 10, '
          'v max <= 20, rot median <= 0.15, max <= 0.3')
    for model in sorted({r['model'] for r in rows}):
        ok = [r for r in rows if r['model'] == model and r['status'] == 'ok']
        if not ok:
            continue
        h = [100 * r['final']['horizontal_m'] for r in ok]
        v = [100 * r['final']['vertical_m'] for r in ok]
        rot = [r['final']['rotation_deg'] for r in ok]
        cov = {k: sum(r['covered'][k] for r in ok) / len(ok) for k in ok[0]['covered']}
        for stage in ('hypotheses', 'polygon'):
            hs = [100 * r[stage]['horizontal_m'] for r in ok if stage in r]
            if hs:
                print(f'  {model:<9}{stage:<11} h median {statistics.median(hs):6.1f} '
                      f'max {max(hs):6.1f}')
        print(f'  {model:<9}{"final":<11} h median {statistics.median(h):6.1f} max '
              f'{max(h):6.1f}  v max {max(v):6.1f}  rot median {statistics.median(rot):.3f} '
              f'max {max(rot):.3f}  coverage {cov["horizontal"]:.0%}/{cov["vertical"]:.0%}/'
              f'{cov["rotation"]:.0%}  ({len(ok)} runs)')
        sig_al = [100 * r['sigma']['along_boresight_m'] for r in ok]
        sig_ac = [100 * r['sigma']['across_boresight_m'] for r in ok]
        print(f'  {model:<9}{"":<11} v median {statistics.median(v):6.1f}  reported 1-sigma '
              f'along / across the boresight median {statistics.median(sig_al):.1f} / '
              f'{statistics.median(sig_ac):.1f} cm, max {max(sig_al):.1f} / {max(sig_ac):.1f}; '
              f'passes median {statistics.median(r["passes"] or 0 for r in ok):g}')


if __name__ == '__main__':
    sys.exit(main())
