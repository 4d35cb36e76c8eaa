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
from radar_calib_ros.core import hypotheses
from radar_calib_ros.core import vehicle as vehicle_box
from radar_calib_ros.core.refine_noise import tilt_slopes
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


#: Radial velocities further than this off the calibration's prediction never count in a
#: pass's yaw [m/s]: a 6 deg turn of the mount at 15 m/s (and other road users beyond).
_PASS_YAW_GATE_MPS = 2.0
#: Fastest the vehicle may turn where its targets count in a pass's yaw [rad/s]: the
#: rotation's share of a target's velocity rests on where the calibration puts it (a yaw
#: error of 0.5 deg misplaces a target 40 m out by 0.35 m: 0.1 m/s at 0.3 rad/s), and the
#: heading's rate is noisy where the car is slow.
_PASS_YAW_MAX_YAW_RATE_RPS = 0.15
#: Least |v . (z x ray)| of the targets that seed a pass's yaw (``_robust_yaw``) [m/s].
_PASS_YAW_SEED_SLOPE_MPS = 1.0


def _robust_yaw(slope: F64, residual: F64) -> tuple[float, np.ndarray, float] | None:
    """One pass's yaw [rad] from ``residual = yaw * slope`` (+ outliers): seeded by the
    median ratio of its well-conditioned targets, then least squares within 3 robust
    standard deviations of the fit, three times; with the mask kept and the residual
    spread [m/s] (at least 0.05). None where nothing seeds it."""
    seed = np.abs(slope) >= _PASS_YAW_SEED_SLOPE_MPS
    if np.count_nonzero(seed) < 3:
        return None
    yaw = float(np.median(residual[seed] / slope[seed]))
    kept = np.ones(slope.size, bool)
    spread = 0.05
    for _ in range(3):
        error = residual - yaw * slope
        mad = float(np.median(np.abs(error - np.median(error))))
        spread = max(1.4826 * mad, 0.05)
        kept = np.abs(error) <= 3.0 * spread
        hessian = float(np.sum(slope[kept] ** 2))
        if hessian <= 0.0:
            return None
        yaw = float(np.sum(slope[kept] * residual[kept])) / hessian
    return yaw, kept, spread


@dataclass(frozen=True, slots=True)
class PassYaws:
    """Each vehicle pass's yaw relative to a calibration, from its radial velocities
    (:func:`pass_yaw_offsets`)."""

    yaw_rad: F64          # (G,)
    weight: F64           # (G,) inverse variances [1/rad^2]
    spans_ns: I64         # (G, 2) first and last stamps
    #: (G, 2) change of each pass's yaw per radian of error of the calibration's roll and
    #: pitch: a tilt the calibration has wrong reads as a different yaw in each view
    tilt_shift: F64


def pass_yaw_offsets(recording: Recording, target_index: I64, extrinsics: Extrinsics,
                     config: CalibConfig) -> PassYaws:
    """Each vehicle pass's yaw [rad] relative to a calibration, from the radial velocities of
    the given targets alone, its weight (inverse variance) and its [start, end] stamps.

    Why: the radial velocity a calibration predicts for a target of the moving vehicle is
    the vehicle's velocity on the ray ``R p`` to the target, which depends on the rotation
    (and the clock) only: neither on where the radar stands nor on where on the car the
    target lies. Turning the radar by a yaw d adds d * v . (z x ray), so each pass measures
    the yaw on its own, and a mount knocked between passes shows as a step (a thirty-sixth
    probe's 3 deg knock, which a fit over the whole recording blended to 1 deg). Only the
    car's turning needs the position (its points' speed about the reference point). Targets
    off the pass's own robust fit (wheels, other road users) are left out (``_robust_yaw``:
    a fixed gate about the calibration's prediction would keep a knocked mount's passes
    only in part and bias them towards it); the weight counts frames, not targets (a
    frame's targets share the vehicle's velocity and the clock).

    Each pass's yaw holds the calibration's roll and pitch, and an error of theirs shifts
    it by as much as the pass's rays mix roll or pitch into their horizontal turn
    (``tilt_shift``): a forty-eighth probe's edge-of-view crossings at 59 deg azimuth read
    1.8 deg off the head-on passes under a fit 3.4 deg off in roll, and a mount turn was
    declared for a radar that had not moved.

    Passes (``hypotheses.drive_passes``) with fewer than 3 usable frames are left out.
    """
    target_index = np.asarray(target_index, np.int64)
    stamps = recording.stamps_of(target_index)
    order = np.argsort(stamps, kind='stable')
    target_index, stamps = target_index[order], stamps[order]
    offset_s = config.sync.time_offset + extrinsics.time_offset_s
    poses = interpolate_poses(recording.vehicle, stamps + np.int64(round(offset_s * 1e9)),
                              config.sync.max_pose_gap)
    local = recording.targets.positions_m[target_index]
    rays = local @ np.asarray(extrinsics.rotation, np.float64).T
    # a turning car's points move with its yaw rate about the reference point too (2 m off
    # it at 0.3 rad/s: 0.6 m/s): without it a pass through a turn read 0.3 deg off
    lever = rays + np.asarray(extrinsics.translation_m, np.float64) - poses.positions_m
    velocity = poses.velocities_mps.copy()
    velocity[:, 0] -= poses.yaw_rate_rps * lever[:, 1]
    velocity[:, 1] += poses.yaw_rate_rps * lever[:, 0]
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-9)[:, None]
    residual = (recording.targets.radial_velocity_mps[target_index]
                - np.sum(velocity * rays, axis=1))
    slope = velocity[:, 1] * rays[:, 0] - velocity[:, 0] * rays[:, 1]   # v . (z x ray)
    # the same for a turn about the radar's own x (roll) and y (pitch) axes
    tilt = tilt_slopes(local, extrinsics.rotation, velocity)
    # one pass per drive through the view, as the calibration's (a stop in view is none)
    t_s = (stamps + np.int64(round(offset_s * 1e9)) - recording.vehicle.stamps_ns[0]) * 1e-9
    pass_id = hypotheses.drive_passes(t_s, recording.vehicle, config.hypotheses.pass_gap_s)
    frames = recording.targets.frame_index[target_index]
    usable = (poses.valid & (np.abs(residual) <= _PASS_YAW_GATE_MPS)
              & (np.abs(poses.yaw_rate_rps) <= _PASS_YAW_MAX_YAW_RATE_RPS))
    yaws, weights, spans, shifts = [], [], [], []
    for p in range(int(pass_id.max()) + 1 if pass_id.size else 0):
        in_pass = usable & (pass_id == p)
        fitted = _robust_yaw(slope[in_pass], residual[in_pass])
        if fitted is None:
            continue
        yaw, kept, spread = fitted
        n_frames = np.unique(frames[in_pass][kept]).size
        if n_frames < 3:
            continue
        yaws.append(yaw)
        hessian = float(np.sum(slope[in_pass][kept] ** 2))
        weights.append(hessian / spread ** 2 * n_frames / int(kept.sum()))
        shifts.append(slope[in_pass][kept] @ tilt[in_pass][kept] / hessian)
        pass_stamps = stamps[pass_id == p]
        spans.append((int(pass_stamps[0]), int(pass_stamps[-1])))
    return PassYaws(np.asarray(yaws, np.float64), np.asarray(weights, np.float64),
                    np.asarray(spans, np.int64).reshape(-1, 2),
                    np.asarray(shifts, np.float64).reshape(-1, 2))


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
