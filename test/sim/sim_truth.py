"""Helpers for the simulator tests: the paper's metrics at the true calibration.

r_i, delta_op and delta_p (method paper, "Evaluation", Table I) of the calibration
vehicle's targets, placed in the world with the TRUE extrinsics and compared with the
vehicle's TRUE box at each frame's true measurement time (``ground_truth_targets.npz``),
using the box helpers of ``core/vehicle.py``. ``is_calibration_vehicle`` leaves out the
vehicle's wall ghosts: they appear behind buildings, far from the vehicle, and no track of
the vehicle would contain them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radar_calib_ros.config import VehicleConfig
from radar_calib_ros.core import vehicle as vehicle_box


@dataclass(frozen=True)
class TruthMetrics:
    inlier_ratio: float
    outlier_distance_m: float
    closest_target_offset_m: float
    n_targets: int
    n_frames: int


def load(bag: Path) -> tuple[dict, dict[str, np.ndarray]]:
    with (bag / 'ground_truth.json').open(encoding='utf-8') as fh:
        truth = json.load(fh)
    with np.load(bag / 'ground_truth_targets.npz') as z:
        arrays = {k: z[k] for k in z.files}
    return truth, arrays


def vehicle_config(truth: dict) -> VehicleConfig:
    v = truth['vehicle']
    return VehicleConfig(length=v['length'], width=v['width'], height=v['height'],
                         rear_overhang=v['rear_overhang'], ref_height=v['ref_height'])


def metrics_at_truth(bag: Path, *, measured: bool = True) -> TruthMetrics:
    """The paper's metrics of the calibration vehicle's targets at the true calibration."""
    truth, z = load(bag)
    sel = z['is_calibration_vehicle']
    frame = z['frame_index'][sel]
    key = 'position_sensor_m' if measured else 'position_true_sensor_m'
    rotation, translation = z['radar_rotation'], z['radar_translation_m']
    world = z[key][sel].astype(np.float64) @ rotation.T + translation
    positions, yaw = z['vehicle_position_m'][frame], z['vehicle_yaw_rad'][frame]
    box = vehicle_config(truth)
    local = vehicle_box.world_to_vehicle(world, positions, yaw)
    distance = vehicle_box.box_distance(local, box)
    outside = distance > 0.0
    radar_xy = translation[:2]
    range_m = np.hypot(world[:, 0] - radar_xy[0], world[:, 1] - radar_xy[1])
    order = np.lexsort((range_m, frame))
    first = order[np.unique(frame[order], return_index=True)[1]]
    corners = vehicle_box.box_corners_world(positions[first], yaw[first], box)
    corner_range = np.hypot(corners[..., 0] - radar_xy[0], corners[..., 1] - radar_xy[1])
    nearest = corners[np.arange(first.size), np.argmin(corner_range, axis=1)]
    offset = np.hypot(world[first, 0] - nearest[:, 0], world[first, 1] - nearest[:, 1])
    return TruthMetrics(float(1.0 - outside.mean()), float(distance[outside].mean()),
                        float(offset.mean()), int(sel.sum()), int(first.size))
