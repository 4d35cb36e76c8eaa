"""The calibration vehicle's bird's-eye-view box, shared by refinement, quality and
evaluation.

The vehicle frame is REP-103 (x forward, y left, z up) with its origin at the
localisation reference point; the box spans x in [-rear_overhang, length - rear_overhang],
y in [-width/2, width/2], z in [-ref_height, height - ref_height].
"""
from __future__ import annotations

import numpy as np

from radar_calib_ros.config import VehicleConfig
from radar_calib_ros.types import F64


def box_limits(vehicle: VehicleConfig) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the footprint in the vehicle frame [m]."""
    return (-vehicle.rear_overhang, vehicle.length - vehicle.rear_overhang,
            -0.5 * vehicle.width, 0.5 * vehicle.width)


def world_to_vehicle(points_world: F64, positions_m: F64, yaw_rad: F64) -> F64:
    """Points (n, >=2) into each one's vehicle pose (n, 2): BEV only, x forward, y left."""
    d = points_world[:, :2] - positions_m[:, :2]
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def vehicle_to_world(points_vehicle: F64, positions_m: F64, yaw_rad: F64) -> F64:
    """Inverse of :func:`world_to_vehicle` (n, 2) -> (n, 2)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    x, y = points_vehicle[:, 0], points_vehicle[:, 1]
    return np.column_stack([positions_m[:, 0] + c * x - s * y, positions_m[:, 1] + s * x + c * y])


def box_distance(points_vehicle: F64, vehicle: VehicleConfig) -> F64:
    """(n,) Euclidean distance of vehicle-frame BEV points to the footprint; 0 inside."""
    x0, x1, y0, y1 = box_limits(vehicle)
    dx = np.maximum(np.maximum(x0 - points_vehicle[:, 0], points_vehicle[:, 0] - x1), 0.0)
    dy = np.maximum(np.maximum(y0 - points_vehicle[:, 1], points_vehicle[:, 1] - y1), 0.0)
    return np.hypot(dx, dy)


def inside_box(points_vehicle: F64, vehicle: VehicleConfig) -> np.ndarray:
    """(n,) True where a vehicle-frame BEV point lies in the footprint (edges included)."""
    x0, x1, y0, y1 = box_limits(vehicle)
    return ((points_vehicle[:, 0] >= x0) & (points_vehicle[:, 0] <= x1)
            & (points_vehicle[:, 1] >= y0) & (points_vehicle[:, 1] <= y1))


def box_corners_world(positions_m: F64, yaw_rad: F64, vehicle: VehicleConfig) -> F64:
    """(n, 4, 2) footprint corners in the world, counter-clockwise from rear right."""
    x0, x1, y0, y1 = box_limits(vehicle)
    local = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    c, s = np.cos(yaw_rad)[:, None], np.sin(yaw_rad)[:, None]
    wx = positions_m[:, None, 0] + c * local[None, :, 0] - s * local[None, :, 1]
    wy = positions_m[:, None, 1] + s * local[None, :, 0] + c * local[None, :, 1]
    return np.stack([wx, wy], axis=-1)
