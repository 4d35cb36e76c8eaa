"""The paper's quality metrics of a calibration: r_i, delta_op and delta_p.

Given the calibration vehicle's radar targets, its poses and a calibration, every target
is placed in the world and compared with the vehicle's bird's-eye-view box at the
target's own stamp (poses interpolated, clock offsets applied):

- r_i (``inlier_ratio``): the fraction of the targets inside the box;
- delta_op (``outlier_distance_m``): the mean distance of the outside targets to the box;
- delta_p (``closest_target_offset_m``): per radar frame, the target closest to the sensor
  against the box corner closest to the sensor, averaged over frames.

Used by the quality stage on the calibration recording and by ``evaluate`` on a second
one. A high r_i does not prove a calibration right: most real reflections come from
inside the footprint, so a box slid towards the radar can swallow more of them than the
true one; these figures describe the fit, the uncertainty comes from elsewhere.

References
----------
Method paper, section "Evaluation" (protocol, Table I).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import vehicle as vehicle_box
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.types import F64, I64, Extrinsics, TrackedTargets, VehicleTrack, _freeze

#: Tracks whose targets lie farther than this from the vehicle on average are not the
#: vehicle's (the paper's evaluation protocol) [m].
PAPER_MAX_MEAN_OFFSET_M = 5.0


@dataclass(frozen=True, slots=True)
class PaperMetrics:
    """The paper's metrics and the per-target numbers behind them (for figures).

    distance_m : (n,) BEV distance of each used target to the box, 0 inside;
    range_m : (n,) horizontal distance of each used target from the sensor;
    closest_offset_m : (f,) per frame, closest target to the nearest box corner;
    closest_range_m : (f,) per frame, horizontal distance from the sensor to that corner.
    Metrics are NaN when there is nothing to average.
    """

    inlier_ratio: float
    outlier_distance_m: float
    closest_target_offset_m: float
    n_targets: int
    n_outside: int
    n_frames: int
    distance_m: F64 = field(default_factory=lambda: np.zeros(0))
    range_m: F64 = field(default_factory=lambda: np.zeros(0))
    closest_offset_m: F64 = field(default_factory=lambda: np.zeros(0))
    closest_range_m: F64 = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        _freeze(self)


def paper_metrics(positions_sensor_m: F64, stamps_ns: I64, vehicle: VehicleTrack,
                  extrinsics: Extrinsics, config: CalibConfig) -> PaperMetrics:
    """r_i, delta_op and delta_p of the calibration vehicle's targets.

    Parameters
    ----------
    positions_sensor_m : ndarray of shape (n, 3)
        The calibration vehicle's targets in the sensor frame [m].
    stamps_ns : ndarray of shape (n,)
        Radar header stamp of each target's frame (no offset applied); targets sharing a
        stamp are one frame for delta_p.
    vehicle : VehicleTrack
        The vehicle's poses (the recording's local frame, like ``extrinsics``).
    extrinsics : Extrinsics
        The calibration under test; its ``time_offset_s`` is added to the radar stamps on
        top of ``sync.time_offset``.
    config : CalibConfig
        Uses ``vehicle`` (the box) and ``sync``.

    Returns
    -------
    PaperMetrics
        Targets whose stamp has no valid pose are left out.

    Notes
    -----
    Vectorised: one pose interpolation and one sort; ~100k targets take a few tens of
    milliseconds.
    """
    positions_sensor_m = np.asarray(positions_sensor_m, np.float64).reshape(-1, 3)
    stamps_ns = np.asarray(stamps_ns, np.int64)
    offset_s = config.sync.time_offset + extrinsics.time_offset_s
    poses = interpolate_poses(vehicle, stamps_ns + np.int64(round(offset_s * 1e9)),
                              config.sync.max_pose_gap)
    ok = poses.valid
    world = extrinsics.apply(positions_sensor_m[ok])
    positions, yaw, stamps = poses.positions_m[ok], poses.yaw_rad[ok], stamps_ns[ok]
    n = world.shape[0]
    if n == 0:
        nan = float('nan')
        return PaperMetrics(nan, nan, nan, 0, 0, 0)
    local = vehicle_box.world_to_vehicle(world, positions, yaw)
    distance = vehicle_box.box_distance(local, config.vehicle)
    outside = distance > 0.0
    sensor_xy = np.asarray(extrinsics.translation_m, np.float64)[:2]
    range_m = np.hypot(world[:, 0] - sensor_xy[0], world[:, 1] - sensor_xy[1])
    # closest target per frame: sort by (stamp, range), the first of each stamp wins
    order = np.lexsort((range_m, stamps))
    first = order[np.unique(stamps[order], return_index=True)[1]]
    corners = vehicle_box.box_corners_world(positions[first], yaw[first], config.vehicle)
    corner_range = np.hypot(corners[..., 0] - sensor_xy[0], corners[..., 1] - sensor_xy[1])
    nearest = np.argmin(corner_range, axis=1)
    corner = corners[np.arange(first.size), nearest]
    closest_offset = np.hypot(world[first, 0] - corner[:, 0], world[first, 1] - corner[:, 1])
    n_outside = int(outside.sum())
    return PaperMetrics(
        inlier_ratio=float(1.0 - n_outside / n),
        outlier_distance_m=float(distance[outside].mean()) if n_outside else 0.0,
        closest_target_offset_m=float(closest_offset.mean()),
        n_targets=n, n_outside=n_outside, n_frames=int(first.size),
        distance_m=distance, range_m=range_m, closest_offset_m=closest_offset,
        closest_range_m=corner_range[np.arange(first.size), nearest])


def track_target_index(tracked: TrackedTargets, track_ids: I64 | tuple[int, ...]) -> I64:
    """Indices into ``Recording.targets`` of the targets of the given tracks."""
    mask = np.isin(tracked.track_id, np.asarray(track_ids, np.int64))
    return tracked.target_index[mask]


def vehicle_track_ids(recording: Recording, tracked: TrackedTargets, extrinsics: Extrinsics,
                      config: CalibConfig,
                      max_mean_offset_m: float = PAPER_MAX_MEAN_OFFSET_M) -> I64:
    """Tracks that belong to the calibration vehicle under a calibration (paper protocol).

    A track is kept when its targets, placed in the world by ``extrinsics``, lie on average
    within ``max_mean_offset_m`` of the centre of the vehicle's box at their stamps;
    targets without a valid pose do not count.
    """
    track_id = tracked.track_id
    keep = track_id >= 0
    index, track_id = tracked.target_index[keep], track_id[keep]
    if index.size == 0:
        return np.zeros(0, np.int64)
    stamps = recording.stamps_of(index)
    offset_s = config.sync.time_offset + extrinsics.time_offset_s
    poses = interpolate_poses(recording.vehicle, stamps + np.int64(round(offset_s * 1e9)),
                              config.sync.max_pose_gap)
    ok = poses.valid
    world = extrinsics.apply(recording.targets.positions_m[index[ok]])
    x0, x1, _, _ = vehicle_box.box_limits(config.vehicle)
    local = vehicle_box.world_to_vehicle(world, poses.positions_m[ok], poses.yaw_rad[ok])
    offset = np.hypot(local[:, 0] - 0.5 * (x0 + x1), local[:, 1])
    ids, inverse = np.unique(track_id[ok], return_inverse=True)
    mean = np.bincount(inverse, weights=offset) / np.bincount(inverse)
    return ids[mean <= max_mean_offset_m].astype(np.int64)


#: Radial velocity off the vehicle's [m/s] beyond which a target of its tracks moves unlike
#: it: another road user merged into its clusters, or a wheel's micro-Doppler.
MOTION_MISMATCH_MPS = 0.5


def moving_unlike_vehicle(recording: Recording, target_index: I64, extrinsics: Extrinsics,
                          config: CalibConfig) -> np.ndarray:
    """(n,) True for the given targets whose radial velocity differs from the one the
    vehicle's motion gives them under a calibration by more than ``MOTION_MISMATCH_MPS``
    (its yaw rate neglected); False where there is no pose."""
    target_index = np.asarray(target_index, np.int64)
    offset_s = config.sync.time_offset + extrinsics.time_offset_s
    poses = interpolate_poses(recording.vehicle, recording.stamps_of(target_index)
                              + np.int64(round(offset_s * 1e9)), config.sync.max_pose_gap)
    world = extrinsics.apply(recording.targets.positions_m[target_index])
    predicted = rigid_radial_velocity(world, extrinsics, poses.velocities_mps)
    measured = recording.targets.radial_velocity_mps[target_index]
    unlike: np.ndarray = poses.valid & (np.abs(measured - predicted) > MOTION_MISMATCH_MPS)
    return unlike


def rigid_radial_velocity(world: F64, extrinsics: Extrinsics, velocities: F64) -> F64:
    """(n,) radial velocity (range rate) the radar at ``extrinsics`` sees of targets at
    ``world`` on a vehicle moving at ``velocities`` (its yaw rate neglected)."""
    rays = world - np.asarray(extrinsics.translation_m, np.float64)
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-9)[:, None]
    return np.asarray(np.sum(velocities * rays, axis=1), np.float64)


def recording_metrics(recording: Recording, target_index: I64, extrinsics: Extrinsics,
                      config: CalibConfig) -> PaperMetrics:
    """:func:`paper_metrics` of the given targets of a recording."""
    target_index = np.asarray(target_index, np.int64)
    return paper_metrics(recording.targets.positions_m[target_index],
                         recording.stamps_of(target_index), recording.vehicle,
                         extrinsics, config)
