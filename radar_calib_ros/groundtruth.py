"""Comparison of a calibration with the simulator's ground truth.

Only the demo, the benches and ``evaluate`` read ground truth; the calibration never does.
Both sides are in the contract's result layout (UTM), so they compare directly.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

GROUND_TRUTH_FILE = 'ground_truth.json'


def load_ground_truth(bag_dir: str | Path, radar_frame: str | None = None,
                      ) -> dict[str, Any] | None:
    """The simulator's ground truth inside a bag directory, or None.

    ``ground_truth.json``; in a recording of several radars, ``radar_frame`` picks that
    radar's ``ground_truth_<frame>.json`` (None when the recording has no such radar).
    """
    path = Path(bag_dir) / GROUND_TRUTH_FILE
    if radar_frame is not None and (Path(bag_dir) / f'ground_truth_{radar_frame}.json').is_file():
        path = Path(bag_dir) / f'ground_truth_{radar_frame}.json'
    if not path.is_file():
        return None
    with path.open(encoding='utf-8') as fh:
        truth: dict[str, Any] = json.load(fh)
    if radar_frame is not None and 'radars' in truth and truth.get('radar_frame') != radar_frame:
        return None  # a multi-radar recording without that radar
    return truth


def calibration_errors(estimate: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, float]:
    """Errors of an estimate against the truth, both in the contract's result layout.

    Returns horizontal_m, vertical_m, rotation_deg (angle of R_est^T R_true), yaw_deg,
    along_boresight_m / across_boresight_m (the horizontal error split along the true
    boresight) and time_offset_s (estimate - truth, when both carry one).
    """
    if int(estimate['epsg']) != int(truth['epsg']):
        raise ValueError(f'estimate in EPSG {estimate["epsg"]}, truth in {truth["epsg"]}')
    d = np.asarray(estimate['translation'], float) - np.asarray(truth['translation'], float)
    r_est = Rotation.from_quat(estimate['quaternion_xyzw'])
    r_true = Rotation.from_quat(truth['quaternion_xyzw'])
    boresight = r_true.as_matrix()[:2, 0]
    boresight = boresight / max(float(np.linalg.norm(boresight)), 1e-12)
    along = float(d[:2] @ boresight)
    across = float(d[0] * -boresight[1] + d[1] * boresight[0])
    yaw_err = (r_est.as_euler('xyz', degrees=True)[2] - r_true.as_euler('xyz', degrees=True)[2]
               + 180.0) % 360.0 - 180.0
    out = {
        'horizontal_m': float(np.hypot(d[0], d[1])),
        'vertical_m': float(abs(d[2])),
        'rotation_deg': float(np.degrees((r_true.inv() * r_est).magnitude())),
        'yaw_deg': float(yaw_err),
        'along_boresight_m': along,
        'across_boresight_m': across,
    }
    est_dt = (estimate.get('quality') or {}).get('time_offset_s')
    true_dt = truth.get('time_offset_s')
    if est_dt is not None and true_dt is not None:
        out['time_offset_s'] = float(est_dt) - float(true_dt)
    return out
