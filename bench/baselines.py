"""The methods ``bench/compare.py`` sets against ours, on the same recording.

Bench code, not package code: none of this is offered to users.

* :func:`naive_fit`, a naive baseline: one least-squares rigid fit of all moving targets
  time-matched to the vehicle within a gate; no clustering, tracking or hypothesis
  filtering. A naive user has no initial guess, so the gate comes from iterated closest
  points (ICP in time) from twelve starts: level, at headings 30 deg apart, each placed so
  that the centroid of the moving targets falls on the centroid of the vehicle's
  trajectory (at their stamps). Each start alternates gating (moving targets whose
  transformed position lies within a shrinking horizontal gate, 15 m down to 3 m, of where
  the vehicle was at that target's stamp) and one 3-D Kabsch fit of the gated targets (sensor
  frame) to the vehicle's footprint centre at ``hypotheses.reflection_height_m`` above the
  road (the same vehicle knowledge our stage 6 uses). The starts run on a sample of 10^5
  moving targets; the start that ends with the most of them inside the last gate wins, and
  the final fit takes every moving target inside that gate. Clock offset: none (0).
* :func:`gmm_peer`, a 2-D peer in the manner of Li et al. 2023 ("Globally optimal robust
  radar calibration in intelligent transportation systems", IEEE T-ITS): yaw and 2-D
  translation maximising a robust Gaussian-mixture likelihood of the moving targets under
  the vehicle's footprint (six Gaussians on a 3 x 2 grid over the box, widened by the
  radar's noise, plus a uniform outlier floor). Their branch and bound is replaced by an
  exhaustive global search at 2 deg / 1 m resolution (every 2 deg of yaw, a Hough vote of
  (target, component) pairs over translation in 1 m bins, smoothed), then the best five
  candidates polished by Nelder-Mead on the likelihood itself. Roll, pitch and height
  are not estimated: the sensor's x, y are taken as horizontal (roll = pitch = 0) and the
  height is a nominal 6 m above the road (the road = the vehicle's reference point minus
  ``vehicle.ref_height``); errors are reported against what it outputs. Clock offset: 0.
* :func:`oracle_refinement`, an oracle told which targets came from the calibration vehicle
  (``ground_truth_targets.npz``): our final refinement (``core.refine.refine_extrinsics``)
  on exactly those targets, moving or not, started at the true calibration; the best our
  estimator can do on that data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import moving, refine
from radar_calib_ros.core.hypotheses import reflection_centre_world
from radar_calib_ros.core.registration import fit_rigid, yaw_rotation
from radar_calib_ros.core.vehicle import box_limits
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.types import (
    F64, Extrinsics, HypothesisSelection, PoseSamples, Refinement, TrackedTargets)

#: ICP starts of the naive baseline: headings 30 deg apart.
NAIVE_STARTS = 12
#: Horizontal gates of the naive baseline's ICP [m], three iterations each.
NAIVE_GATES_M = (15.0, 10.0, 6.0, 4.0, 3.0)
#: Moving targets the naive baseline's ICP starts are searched on.
NAIVE_SAMPLE = 100_000
#: Nominal mounting height the 2-D peer reports [m above the road].
PEER_NOMINAL_HEIGHT_M = 6.0


@dataclass(frozen=True)
class MatchedTargets:
    """Moving targets with a valid vehicle pose at their stamp.

    sensor_m : (n, 3) sensor frame; poses : the vehicle's poses at their stamps
    (``sync.time_offset`` applied); centres_m : (n, 3) the vehicle's footprint centre at
    reflection height, in the world.
    """

    index: np.ndarray
    sensor_m: F64
    poses: PoseSamples
    centres_m: F64


def matched_moving_targets(recording: Recording, config: CalibConfig) -> MatchedTargets:
    """Stage 1's moving targets, each time-matched (interpolated) to the vehicle's pose."""
    targets = recording.targets
    index = np.flatnonzero(moving.filter_moving_targets(targets.radial_velocity_mps,
                                                        config.moving))
    stamps = recording.target_stamps_ns[index] + np.int64(round(config.sync.time_offset * 1e9))
    poses = interpolate_poses(recording.vehicle, stamps, config.sync.max_pose_gap)
    keep = poses.valid
    poses = PoseSamples(poses.positions_m[keep], poses.yaw_rad[keep],
                        poses.velocities_mps[keep], poses.yaw_rate_rps[keep], poses.valid[keep])
    index = index[keep]
    return MatchedTargets(index, targets.positions_m[index], poses,
                          reflection_centre_world(poses, config))


# --- (b) naive least squares ---------------------------------------------------------------

def naive_fit(recording: Recording, config: CalibConfig, *,
              rng: np.random.Generator | None = None) -> Extrinsics:
    """One least-squares rigid fit of all moving targets within a gate of the vehicle.

    See the module docstring for how the gate is found without an initial guess.
    """
    m = matched_moving_targets(recording, config)
    rng = rng if rng is not None else np.random.default_rng(0)
    # The starts are searched on a sample (a 10-minute drive has ~10^6 moving targets);
    # the final fit takes every target in the last gate.
    sample = rng.choice(m.index.size, size=min(m.index.size, NAIVE_SAMPLE), replace=False)
    src, dst = m.sensor_m[sample], m.centres_m[sample]
    start_t = np.array([np.mean(dst[:, 0]), np.mean(dst[:, 1]), np.mean(dst[:, 2])])
    best: tuple[int, Extrinsics] | None = None
    for k in range(NAIVE_STARTS):
        rot = yaw_rotation(2.0 * math.pi * k / NAIVE_STARTS)
        trans = start_t - rot @ np.mean(src, axis=0)
        n_in = 0
        for gate in NAIVE_GATES_M:
            for _ in range(3):
                world = src @ rot.T + trans
                inside = np.hypot(world[:, 0] - dst[:, 0], world[:, 1] - dst[:, 1]) <= gate
                n_in = int(np.count_nonzero(inside))
                if n_in < 10:
                    break
                fit = fit_rigid(src[inside], dst[inside])
                rot, trans = fit.rotation, fit.translation_m
            if n_in < 10:
                break
        if n_in >= 10 and (best is None or n_in > best[0]):
            best = (n_in, Extrinsics(rot, trans, 0.0))
    if best is None:
        raise RuntimeError('naive baseline: no start kept 10 targets in its gate')
    rot, trans = best[1].rotation, best[1].translation_m
    for _ in range(3):
        world = m.sensor_m @ rot.T + trans
        inside = np.hypot(world[:, 0] - m.centres_m[:, 0],
                          world[:, 1] - m.centres_m[:, 1]) <= NAIVE_GATES_M[-1]
        fit = fit_rigid(m.sensor_m[inside], m.centres_m[inside])
        rot, trans = fit.rotation, fit.translation_m
    return Extrinsics(rot, trans, 0.0)


# --- (c) 2-D Gaussian-mixture peer --------------------------------------------------------

def _footprint_mixture(config: CalibConfig) -> tuple[F64, F64]:
    """(means (6, 2), variances (6, 2)) of the footprint mixture in the vehicle frame."""
    x0, x1, y0, y1 = box_limits(config.vehicle)
    length, width = x1 - x0, y1 - y0
    xs = x0 + length * np.array([1.0, 3.0, 5.0]) / 6.0
    ys = y0 + width * np.array([1.0, 3.0]) / 4.0
    means = np.array([[x, y] for x in xs for y in ys])
    # a component covers its cell (uniform variance cell^2 / 12) plus the radar's noise
    noise2 = 0.3 ** 2
    var = np.array([(length / 3.0) ** 2 / 12.0 + noise2, (width / 2.0) ** 2 / 12.0 + noise2])
    return means, np.tile(var, (means.shape[0], 1))


def _peer_log_likelihood(params: F64, src_xy: F64, pos_xy: F64, cos_yaw: F64, sin_yaw: F64,
                         means: F64, var: F64, floor: float) -> float:
    theta, tx, ty = params
    c, s = math.cos(theta), math.sin(theta)
    wx = c * src_xy[:, 0] - s * src_xy[:, 1] + tx - pos_xy[:, 0]
    wy = s * src_xy[:, 0] + c * src_xy[:, 1] + ty - pos_xy[:, 1]
    lx = cos_yaw * wx + sin_yaw * wy
    ly = -sin_yaw * wx + cos_yaw * wy
    dx = lx[:, None] - means[None, :, 0]
    dy = ly[:, None] - means[None, :, 1]
    norm = 1.0 / (2.0 * math.pi * np.sqrt(var[:, 0] * var[:, 1]) * means.shape[0])
    dens = np.exp(-0.5 * (dx ** 2 / var[:, 0] + dy ** 2 / var[:, 1])) @ norm
    return float(np.sum(np.log(floor + dens)))


def gmm_peer(recording: Recording, config: CalibConfig, *,
             rng: np.random.Generator | None = None) -> Extrinsics:
    """Yaw and 2-D translation by aligning the footprint mixture to the moving targets.

    Roll and pitch are zero and the height nominal (module docstring).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    m = matched_moving_targets(recording, config)
    means, var = _footprint_mixture(config)
    pos = m.poses.positions_m
    yaw = m.poses.yaw_rad
    n = m.index.size
    # the vote uses a sample of targets; the likelihood polish a larger one
    vote = rng.choice(n, size=min(n, 30000), replace=False)
    polish = rng.choice(n, size=min(n, 80000), replace=False)
    src = m.sensor_m[:, :2]
    lo = pos[:, :2].min(axis=0) - 60.0
    hi = pos[:, :2].max(axis=0) + 60.0
    shape = np.ceil(hi - lo).astype(int)
    c_v, s_v = np.cos(yaw[vote]), np.sin(yaw[vote])
    comp_world = np.stack([
        pos[vote, 0, None] + c_v[:, None] * means[None, :, 0] - s_v[:, None] * means[None, :, 1],
        pos[vote, 1, None] + s_v[:, None] * means[None, :, 0] + c_v[:, None] * means[None, :, 1],
    ], axis=-1)                                                  # (n_vote, 6, 2)
    kernel = np.exp(-0.5 * (np.arange(-3, 4) / 1.5) ** 2)
    candidates: list[tuple[float, float, float, float]] = []
    for theta in np.radians(np.arange(0.0, 360.0, 2.0)):
        c, s = math.cos(theta), math.sin(theta)
        rs = np.column_stack([c * src[vote, 0] - s * src[vote, 1],
                              s * src[vote, 0] + c * src[vote, 1]])
        t = comp_world - rs[:, None, :]
        cell = np.floor(t.reshape(-1, 2) - lo).astype(int)
        ok = (cell >= 0).all(axis=1) & (cell < shape).all(axis=1)
        hist = np.bincount(cell[ok, 0] * shape[1] + cell[ok, 1],
                           minlength=shape[0] * shape[1]).reshape(shape).astype(float)
        # separable Gaussian smoothing (sigma 1.5 m) of the vote map
        hist = np.apply_along_axis(np.convolve, 0, hist, kernel, mode='same')
        hist = np.apply_along_axis(np.convolve, 1, hist, kernel, mode='same')
        i = int(np.argmax(hist))
        ix, iy = divmod(i, shape[1])
        candidates.append((float(hist.flat[i]), float(theta), lo[0] + ix + 0.5,
                           lo[1] + iy + 0.5))
    candidates.sort(reverse=True)
    args = (src[polish], pos[polish, :2], np.cos(yaw[polish]), np.sin(yaw[polish]), means, var,
            1e-4)
    best: tuple[float, F64] | None = None
    for _, theta, tx, ty in candidates[:5]:
        res = minimize(lambda p: -_peer_log_likelihood(p, *args), np.array([theta, tx, ty]),
                       method='Nelder-Mead', options={'xatol': 1e-4, 'fatol': 1e-3,
                                                      'maxiter': 2000})
        if best is None or res.fun < best[0]:
            best = (float(res.fun), res.x)
    assert best is not None
    theta, tx, ty = best[1]
    road = float(np.median(pos[:, 2])) - config.vehicle.ref_height
    return Extrinsics(yaw_rotation(float(theta)),
                      np.array([tx, ty, road + PEER_NOMINAL_HEIGHT_M]), 0.0)


# --- (e) oracle ------------------------------------------------------------------------------

def truth_vehicle_mask(bag: str | Path, recording: Recording) -> np.ndarray:
    """(n,) True for each recording target that the simulator says came from the calibration
    vehicle (``ground_truth_targets.npz``), after checking both hold the same targets."""
    with np.load(Path(bag) / 'ground_truth_targets.npz') as npz:
        label = np.asarray(npz['is_calibration_vehicle'], bool)
        sensor = np.asarray(npz['position_sensor_m'], float)
        frame = np.asarray(npz['frame_index'], np.int64)
        stamps = np.asarray(npz['frame_stamp_ns'], np.int64)
    targets = recording.targets
    if len(targets) != label.size:
        raise ValueError(f'the bag holds {len(targets)} targets, the truth {label.size}')
    same_frames = np.array_equal(recording.frame_stamps_ns[targets.frame_index], stamps[frame])
    # positions go through float32 in the bag (and the spherical layout through trigonometry)
    if not same_frames or np.max(np.abs(targets.positions_m - sensor)) > 1e-3:
        raise ValueError('the bag and ground_truth_targets.npz list different targets')
    return label


def oracle_refinement(recording: Recording, config: CalibConfig, vehicle_mask: np.ndarray,
                      truth: Extrinsics) -> Refinement:
    """Our final refinement on exactly the calibration vehicle's targets, started at the truth.

    The vehicle's targets form one track that is always accepted by the refinement's gate;
    the gate still drops targets more than ``refine.gate_m`` from the box (wall ghosts).
    """
    index = np.flatnonzero(vehicle_mask).astype(np.int64)
    tracked = TrackedTargets(index, np.zeros(index.size, np.int64))
    selection = HypothesisSelection(
        hypotheses=(), labels=np.zeros(0, np.int64), accepted_label=0, mean_angles_deg={},
        accepted_track_ids=(0,), extrinsics=truth, n_correspondences=0)
    return refine.refine_extrinsics(truth, recording, tracked, selection, config)
