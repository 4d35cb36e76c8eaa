"""Stage 7: the paper's refinement (closest target, then a 2D offset on the polygon loss).

With the accepted calibration the radar's position is known well enough to say which part
of the vehicle faces it. In each radar frame, the vehicle's target closest to the sensor is
paired with the point of the vehicle's box closest to the sensor and the bird's-eye-view
transform is re-estimated on these pairs; then a 2D offset is found by Nelder-Mead that
pulls the targets into the vehicle's footprint (the paper's polygon loss).

Both steps assume something about where the car reflects: the first that the closest
target lies on the box's closest corner or edge, the second that targets outside the box
are errors. Issue 7 measures both as biased by decimetres on realistic cars; stage 8
(``refine``) is the model-independent estimate. This stage stays as the paper's method and
for comparison.

References
----------
Method paper, section "Result Refinement".
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import registration
from radar_calib_ros.core import vehicle as vehicle_box
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.types import (
    F64, I64, Extrinsics, HypothesisSelection, TrackedTargets)

_LOG = logging.getLogger(__name__)
_STAGE = 'polygon'

#: Huber threshold of the closest-target fit, in robust standard deviations (the usual
#: 95 %-efficiency constant).
_HUBER_K = 1.345
#: Most pair-and-fit rounds of the closest-target step (each moves the sensor, which moves
#: the box point it is paired with; a few rounds settle it to below a nanometre).
_MAX_PAIRINGS = 10


@dataclass(frozen=True, slots=True)
class VehicleTargets:
    """The calibration vehicle's targets under a calibration, with their poses.

    target_index : (n,) into ``Recording.targets``; stamps_ns : (n,) radar stamps (no
    offset); world_m : (n, 3) placed by the calibration; positions_m, yaw_rad : (n, 3),
    (n,) the vehicle pose at each target's stamp.
    """

    target_index: I64
    stamps_ns: I64
    world_m: F64
    positions_m: F64
    yaw_rad: F64


@dataclass(frozen=True, slots=True)
class ClosestTargets:
    """Per radar frame, the vehicle's target closest to the sensor and the box point
    closest to the sensor (both world, BEV), and the frame's stamp."""

    target_xy_m: F64
    box_xy_m: F64
    stamps_ns: I64


def vehicle_targets(extrinsics: Extrinsics, recording: Recording, tracked: TrackedTargets,
                    track_ids: tuple[int, ...], config: CalibConfig) -> VehicleTargets:
    """The targets of the given tracks with a valid pose, placed in the world."""
    mask = np.isin(tracked.track_id, np.asarray(track_ids, np.int64))
    index = tracked.target_index[mask]
    stamps = recording.stamps_of(index)
    offset_s = config.sync.time_offset + extrinsics.time_offset_s
    poses = interpolate_poses(recording.vehicle, stamps + np.int64(round(offset_s * 1e9)),
                              config.sync.max_pose_gap)
    ok = poses.valid
    index = index[ok]
    world = extrinsics.apply(recording.targets.positions_m[index])
    return VehicleTargets(index, stamps[ok], world, poses.positions_m[ok], poses.yaw_rad[ok])


def closest_targets(targets: VehicleTargets, sensor_xy_m: F64,
                    config: CalibConfig) -> ClosestTargets:
    """Per frame, the target closest to the sensor and the box point closest to it.

    The box point is the sensor's position clamped to the footprint in the vehicle frame:
    the corner when the sensor looks at the car diagonally, a point on the nearest edge
    when it faces a side square-on.
    """
    sensor_xy_m = np.asarray(sensor_xy_m, np.float64)[:2]
    range_m = np.hypot(targets.world_m[:, 0] - sensor_xy_m[0],
                       targets.world_m[:, 1] - sensor_xy_m[1])
    order = np.lexsort((range_m, targets.stamps_ns))
    first = order[np.unique(targets.stamps_ns[order], return_index=True)[1]]
    positions, yaw = targets.positions_m[first], targets.yaw_rad[first]
    sensor_local = vehicle_box.world_to_vehicle(
        np.broadcast_to(sensor_xy_m, (first.size, 2)), positions, yaw)
    x0, x1, y0, y1 = vehicle_box.box_limits(config.vehicle)
    clamped = np.column_stack([np.clip(sensor_local[:, 0], x0, x1),
                               np.clip(sensor_local[:, 1], y0, y1)])
    box_xy = vehicle_box.vehicle_to_world(clamped, positions, yaw)
    return ClosestTargets(targets.world_m[first, :2], box_xy, targets.stamps_ns[first])


def apply_bev_correction(extrinsics: Extrinsics, rotation_2d: F64,
                         translation_xy_m: F64) -> Extrinsics:
    """Compose a world-frame BEV correction ``x' = R2 x + t2`` after a calibration.

    The levelled frame's z is the world's, so a rotation about world z changes only the
    yaw and leaves the ground plane's roll and pitch alone; the height is kept.
    """
    r3 = np.eye(3)
    r3[:2, :2] = rotation_2d
    t = r3 @ np.asarray(extrinsics.translation_m, np.float64)
    t[:2] += translation_xy_m
    return Extrinsics(r3 @ extrinsics.rotation, t, extrinsics.time_offset_s)


def robust_bev_fit(source_xy: F64, target_xy: F64,
                   iterations: int = 10) -> registration.RigidFit:
    """2D rigid fit with Huber weights (iteratively reweighted least squares).

    The closest target is sometimes clutter or a wheel's micro-Doppler return metres off;
    a Huber weight keeps such frames from dragging the fit while leaving the bulk
    least-squares.
    """
    weights = np.ones(source_xy.shape[0])
    fit = registration.fit_rigid(source_xy, target_xy, weights)
    for _ in range(iterations):
        residual = np.linalg.norm(source_xy @ fit.rotation.T + fit.translation_m - target_xy,
                                  axis=1)
        scale = 1.4826 * np.median(residual) + 1e-9
        weights = np.minimum(1.0, _HUBER_K * scale / np.maximum(residual, 1e-12))
        fit = registration.fit_rigid(source_xy, target_xy, weights)
    return fit


def polygon_loss(offset_xy_m: F64, world_xy_m: F64, positions_m: F64, yaw_rad: F64,
                 config: CalibConfig) -> float:
    """Mean polygon loss of targets shifted by a world-frame offset.

    The paper writes L(p) = min_i |a_i - p| "if p in a, 0 else", which would reward targets
    for leaving the box and measures to the vertices only. The meaningful version, used
    here: a target inside the footprint costs nothing, one outside costs its distance to
    the footprint (nearest edge or corner).
    """
    local = vehicle_box.world_to_vehicle(world_xy_m + offset_xy_m, positions_m, yaw_rad)
    return float(vehicle_box.box_distance(local, config.vehicle).mean())


def refine_polygon(extrinsics: Extrinsics, recording: Recording, tracked: TrackedTargets,
                   selection: HypothesisSelection, config: CalibConfig) -> Extrinsics:
    """The paper's refinement of the accepted calibration.

    1. Closest-target re-estimate: in each frame in which the accepted tracks are seen,
       the target closest to the sensor is paired with the box point closest to the
       sensor; a robust 2D rigid fit of the pairs corrects yaw and x, y. The paper re-runs
       its tracker on these targets; the tracker there only averages frame-to-frame
       scatter, which the least-squares fit over every frame of every pass does as well,
       so the pairs are fitted directly (with Huber weights for the tracker's outlier
       suppression). Measured on simulated junctions, smoothing them per pass with the
       stage-5 UKF/RTS first changed the result by 1-6 cm, never for the better.
    2. Polygon offset: Nelder-Mead finds the 2D world offset minimising the polygon loss
       (:func:`polygon_loss`) over all targets of the accepted tracks within
       2 x ``refine.gate_m`` of the box (a target metres away is another object merged
       into the cluster, and the loss, linear in distance, would let it pull).

    Raises
    ------
    InsufficientDataError
        The accepted tracks have fewer than 3 frames with a valid pose.
    """
    return refine_polygon_steps(extrinsics, recording, tracked, selection, config)[1]


def refine_polygon_steps(extrinsics: Extrinsics, recording: Recording, tracked: TrackedTargets,
                         selection: HypothesisSelection, config: CalibConfig
                         ) -> tuple[Extrinsics, Extrinsics]:
    """:func:`refine_polygon`'s two results: after step 1, and after step 2 from there (the
    final fit may start between them: :func:`bracketed_start`)."""
    closest = closest_target_fit(extrinsics, recording, tracked, selection, config)
    return closest, polygon_offset(closest, recording, tracked, selection, config)


def closest_target_fit(extrinsics: Extrinsics, recording: Recording, tracked: TrackedTargets,
                       selection: HypothesisSelection, config: CalibConfig) -> Extrinsics:
    """Step 1 of :func:`refine_polygon`: the closest-target re-estimate."""
    current = extrinsics
    for _ in range(_MAX_PAIRINGS):
        targets = vehicle_targets(current, recording, tracked, selection.accepted_track_ids,
                                  config)
        closest = closest_targets(targets, current.translation_m, config)
        if closest.stamps_ns.size < 3:
            raise InsufficientDataError(
                _STAGE, f'the accepted tracks have {closest.stamps_ns.size} frames with a '
                'valid vehicle pose, need at least 3')
        fit = robust_bev_fit(closest.target_xy_m, closest.box_xy_m)
        previous = current
        current = apply_bev_correction(current, fit.rotation, fit.translation_m)
        # the box point depends on where the sensor is: pair again until it stops moving
        if np.linalg.norm(current.translation_m - previous.translation_m) < 1e-9:
            break
    _LOG.debug('closest-target fit over %d frames: rms %.3f m', closest.stamps_ns.size,
               fit.rms_m)

    return current


def polygon_offset(extrinsics: Extrinsics, recording: Recording, tracked: TrackedTargets,
                   selection: HypothesisSelection, config: CalibConfig) -> Extrinsics:
    """Step 2 of :func:`refine_polygon`: the 2D offset on the polygon loss."""
    current = extrinsics
    targets = vehicle_targets(current, recording, tracked, selection.accepted_track_ids,
                              config)
    local = vehicle_box.world_to_vehicle(targets.world_m, targets.positions_m, targets.yaw_rad)
    near = vehicle_box.box_distance(local, config.vehicle) <= 2.0 * config.refine.gate_m
    world_xy = targets.world_m[near, :2]
    positions, yaw = targets.positions_m[near], targets.yaw_rad[near]
    if world_xy.shape[0] == 0:
        return current
    result = minimize(polygon_loss, np.zeros(2), args=(world_xy, positions, yaw, config),
                      method='Nelder-Mead',
                      options={'xatol': 1e-4, 'fatol': 1e-7, 'maxiter': 2000,
                               'initial_simplex': np.array([[0.0, 0.0], [0.5, 0.0],
                                                            [0.0, 0.5]])})
    offset = np.asarray(result.x, np.float64)
    _LOG.debug('polygon offset (%.3f, %.3f) m, loss %.4f -> %.4f m over %d targets',
               offset[0], offset[1], polygon_loss(np.zeros(2), world_xy, positions, yaw,
                                                  config), result.fun, world_xy.shape[0])
    t = np.asarray(current.translation_m, np.float64).copy()
    t[:2] += offset
    return Extrinsics(current.rotation, t, current.time_offset_s)


def bracketed_start(closest: Extrinsics, polygon: Extrinsics) -> Extrinsics:
    """The final refinement's start: midway between the two steps' positions.

    Where the views pin the position, stage 8 moves from either to the same place. Where
    they do not (a car seen only head-on and tail-on: its reflection depth trades exactly
    against the radar's distance along the boresight), the start is what the result keeps,
    and each step errs to its own side: the closest-target step puts the nearest target on
    the box's outline, a radar too far out where the car reflects from inside its footprint
    (a twentieth probe's interior cars: 1.1 m back); the polygon loss draws the box over the
    targets until most lie inside it, sliding it by up to a car length where they sit on
    the outline with noise outside it (its skin-like cars: 0.9-3.8 m forward). Direct
    returns lie inside the footprint and no nearer than its outline, so the truth lies
    about between (noise aside), and halfway errs by at most about half their distance (on
    those recordings 0.1-2.2 m against 0.02-3.8 from the polygon). The pipeline starts the
    final fit here where the position along the boresight comes out of it open. Rotation
    and clock offset are the polygon's.
    """
    midway = 0.5 * (np.asarray(closest.translation_m, np.float64)
                    + np.asarray(polygon.translation_m, np.float64))
    return Extrinsics(polygon.rotation, midway, polygon.time_offset_s)
