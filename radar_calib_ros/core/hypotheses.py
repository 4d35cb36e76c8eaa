"""Stage 6: calibration hypotheses, one per track, and the filter that accepts one cluster.

Every smoothed track is paired in time with the calibration vehicle's poses; a closed-form
rigid fit per track gives a hypothesis (levelled sensor frame -> world). Tracks of the
calibration vehicle give hypotheses that agree; other road users give transforms that fit
badly (dropped by their RMS) or scatter. The hypotheses are clustered by translation
(DBSCAN) and the cluster whose rotations agree best is accepted.

References
----------
Method paper, section "Hypothesis Generation and Filtering".
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from sklearn.cluster import DBSCAN

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import registration
from radar_calib_ros.core.vehicle import box_limits
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.types import (
    F64, I64, Extrinsics, GroundPlane, Hypothesis, HypothesisSelection, PoseSamples,
    SmoothedTrack, VehicleTrack)

_LOG = logging.getLogger(__name__)
_STAGE = 'hypotheses'


@dataclass(frozen=True, slots=True)
class Correspondences:
    """Track positions paired in time with the vehicle's reflection centre.

    source_m : (k, 3) levelled sensor frame (x, y, height); target_m : (k, 3) world;
    stamps_ns : (k,) radar stamps (without any offset).
    """

    track_id: int
    source_m: F64
    target_m: F64
    stamps_ns: I64


def pose_stamps_ns(stamps_ns: I64, time_offset_s: float) -> I64:
    """Radar stamps shifted by a clock offset [s] onto the pose clock."""
    return np.asarray(stamps_ns, np.int64) + np.int64(round(time_offset_s * 1e9))


def nearest_pose_gap_s(vehicle: VehicleTrack, stamps_ns: I64) -> F64:
    """(n,) time from each stamp to the nearest vehicle pose sample [s]."""
    idx = np.clip(np.searchsorted(vehicle.stamps_ns, stamps_ns), 1, len(vehicle) - 1)
    gap = np.minimum(np.abs(vehicle.stamps_ns[idx] - stamps_ns),
                     np.abs(vehicle.stamps_ns[idx - 1] - stamps_ns))
    gap_s: F64 = gap * 1e-9
    return gap_s


def reflection_centre_world(poses: PoseSamples, config: CalibConfig) -> F64:
    """(n, 3) where the radar is assumed to see the vehicle, in the world.

    The radar sees the centre of the car's reflections, not the localisation reference
    point (often the rear axle, metres from the middle of the car): without knowing where
    the car reflects, the centre of its footprint is the unbiased guess horizontally, and
    ``hypotheses.reflection_height_m`` above the road vertically.
    """
    x0, x1, _, _ = box_limits(config.vehicle)
    forward = 0.5 * (x0 + x1)
    c, s = np.cos(poses.yaw_rad), np.sin(poses.yaw_rad)
    z = (poses.positions_m[:, 2] - config.vehicle.ref_height
         + config.hypotheses.reflection_height_m)
    return np.column_stack([poses.positions_m[:, 0] + c * forward,
                            poses.positions_m[:, 1] + s * forward, z])


def track_correspondences(tracks: Sequence[SmoothedTrack], recording: Recording,
                          config: CalibConfig) -> list[Correspondences]:
    """Correspondences of every track long enough to make a hypothesis.

    Poses are interpolated to the radar stamps plus ``sync.time_offset`` (never the nearest
    sample: at 15 m/s, 10 ms is 15 cm). Correspondences whose pose is invalid (outside the
    pose stream, across a gap) or farther than ``hypotheses.max_time_gap_s`` from a pose
    sample are dropped; a track is skipped when fewer than ``min_track_frames`` remain or
    it travelled less than ``min_track_length_m``.
    """
    cfg = config.hypotheses
    kept = [t for t in tracks if t.stamps_ns.size >= cfg.min_track_frames
            and _path_length_m(t.positions_m) >= cfg.min_track_length_m]
    if not kept:
        return []
    # one interpolation over all tracks: a per-track call re-reads the whole pose stream
    stamps = np.concatenate([t.stamps_ns for t in kept])
    query = pose_stamps_ns(stamps, config.sync.time_offset)
    poses = interpolate_poses(recording.vehicle, query, config.sync.max_pose_gap)
    valid = poses.valid & (nearest_pose_gap_s(recording.vehicle, query) <= cfg.max_time_gap_s)
    centre = reflection_centre_world(poses, config)
    out: list[Correspondences] = []
    start = 0
    for t in kept:
        sl = slice(start, start + t.stamps_ns.size)
        start = sl.stop
        ok = valid[sl]
        if ok.sum() < cfg.min_track_frames:
            continue
        source = np.column_stack([t.positions_m, t.heights_m])[ok]
        out.append(Correspondences(int(t.track_id), source, centre[sl][ok], t.stamps_ns[ok]))
    return out


def generate_hypotheses(tracks: tuple[SmoothedTrack, ...], recording: Recording,
                        ground: GroundPlane, config: CalibConfig) -> list[Hypothesis]:
    """One calibration hypothesis per usable track.

    Parameters
    ----------
    tracks : tuple of SmoothedTrack
        Stage 5 output, levelled bird's-eye view.
    recording : Recording
        For the vehicle poses.
    ground : GroundPlane
        Unused here (the tracks are already levelled); kept for a uniform stage signature.
    config : CalibConfig
        Uses ``hypotheses``, ``sync`` and ``vehicle``.

    Returns
    -------
    list of Hypothesis
        Levelled sensor frame -> world, rotation about z only; hypotheses whose horizontal
        RMS exceeds ``hypotheses.max_rms_m`` are dropped.
    """
    del ground
    hyps: list[Hypothesis] = []
    for corr in track_correspondences(tracks, recording, config):
        fit = registration.fit_yaw_translation(corr.source_m, corr.target_m)
        if fit.rms_m <= config.hypotheses.max_rms_m:
            hyps.append(Hypothesis(corr.track_id, fit.rotation, fit.translation_m,
                                   int(corr.stamps_ns.size), fit.rms_m))
    _LOG.debug('%d hypotheses from %d tracks', len(hyps), len(tracks))
    return hyps


def merge_intervals_ns(intervals_ns: I64, gap_s: float) -> I64:
    """(p, 2) distinct passes from (n, 2) [start, end] intervals.

    Intervals that overlap or lie within ``gap_s`` of each other are one pass: a track can
    be cut into fragments by the association, and the fragments of one drive through the
    view are one observation, not several.
    """
    intervals_ns = np.asarray(intervals_ns, np.int64).reshape(-1, 2)
    if intervals_ns.shape[0] == 0:
        return intervals_ns.copy()
    order = np.argsort(intervals_ns[:, 0], kind='stable')
    starts, ends = intervals_ns[order, 0], intervals_ns[order, 1]
    reach = np.maximum.accumulate(ends)
    new_pass = np.ones(starts.size, bool)
    new_pass[1:] = starts[1:] - reach[:-1] > round(gap_s * 1e9)
    group = np.cumsum(new_pass) - 1
    merged_end = np.full(group[-1] + 1, np.iinfo(np.int64).min, np.int64)
    np.maximum.at(merged_end, group, ends)
    return np.column_stack([starts[new_pass], merged_end])


def _path_length_m(positions_m: F64) -> float:
    if positions_m.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(positions_m, axis=0), axis=1).sum())


@dataclass(frozen=True, slots=True)
class _ClusterSummary:
    label: int
    members: I64
    mean_angle_deg: float
    passes: I64
    median_rms_m: float


def prune_hypotheses(hyps: Sequence[Hypothesis], tracks: tuple[SmoothedTrack, ...],
                     recording: Recording, ground: GroundPlane,
                     config: CalibConfig) -> HypothesisSelection:
    """Accept the cluster of hypotheses that agree and re-estimate the calibration.

    Hypotheses are clustered by translation (DBSCAN, ``eps_m``, ``min_samples``). A
    cluster is eligible when its tracks cover at least ``min_passes`` distinct passes:
    fragments of a single pass of another car agree with each other perfectly, so
    agreement only counts across passes. Among eligible clusters the lowest mean pairwise
    rotation angle wins (the paper's rule); clusters within ``angle_tie_deg`` of it tie,
    and the tie goes to the cluster seen in more passes, then to the one whose tracks
    follow the vehicle's poses more closely in time (lower median RMS): a car that drove
    a similar path at another moment, or beside the vehicle, matches the poses worse and
    not on every pass. The transform is then re-fitted on the merged correspondences of
    the accepted tracks and concatenated with the ground plane's R_αβ.

    Raises
    ------
    InsufficientDataError
        No hypothesis (vehicle never seen), fewer than ``min_passes`` passes, or no
        cluster of agreeing hypotheses.
    """
    cfg = config.hypotheses
    if not hyps:
        raise InsufficientDataError(
            _STAGE, f'the calibration vehicle was never seen: none of {len(tracks)} tracks '
            f'follows its poses (registration RMS <= {cfg.max_rms_m:g} m over at least '
            f'{cfg.min_track_frames} frames)')
    by_id = {int(t.track_id): t for t in tracks}
    intervals = np.array([[by_id[h.track_id].stamps_ns[0], by_id[h.track_id].stamps_ns[-1]]
                          for h in hyps], np.int64)
    all_passes = merge_intervals_ns(intervals, cfg.pass_gap_s).shape[0]
    if all_passes < cfg.min_passes:
        raise InsufficientDataError(
            _STAGE, f'calibration vehicle seen in {_n_passes(all_passes)}, need at least '
            f'{cfg.min_passes}')
    translations = np.array([h.translation_m for h in hyps])
    labels = DBSCAN(eps=cfg.eps_m, min_samples=cfg.min_samples).fit_predict(translations)
    labels = labels.astype(np.int64)
    rotations = np.array([h.rotation for h in hyps])
    rms = np.array([h.rms_m for h in hyps])
    summaries = []
    for label in np.unique(labels[labels >= 0]):
        members = np.flatnonzero(labels == label)
        summaries.append(_ClusterSummary(
            int(label), members, _mean_pairwise_angle_deg(rotations[members]),
            merge_intervals_ns(intervals[members], cfg.pass_gap_s),
            float(np.median(rms[members]))))
    mean_angles = {s.label: s.mean_angle_deg for s in summaries}
    eligible = [s for s in summaries if s.passes.shape[0] >= cfg.min_passes]
    if not eligible:
        largest = max((s.passes.shape[0] for s in summaries), default=0)
        raise InsufficientDataError(
            _STAGE, f'hypotheses do not agree: {len(hyps)} hypotheses from '
            f'{_n_passes(all_passes)} form no cluster (translations within '
            f'{cfg.eps_m:g} m) spanning {cfg.min_passes} passes; the largest spans '
            f'{_n_passes(largest)}')
    best_angle = min(s.mean_angle_deg for s in eligible)
    tied = [s for s in eligible if s.mean_angle_deg <= best_angle + cfg.angle_tie_deg]
    accepted = min(tied, key=lambda s: (-s.passes.shape[0], s.median_rms_m,
                                        s.mean_angle_deg))
    if accepted.mean_angle_deg > cfg.max_mean_angle_deg:
        raise InsufficientDataError(
            _STAGE, f'hypotheses do not agree: the best cluster ({accepted.members.size} '
            f'tracks, {_n_passes(accepted.passes.shape[0])}) has a mean pairwise rotation '
            f'of {accepted.mean_angle_deg:.2f} deg > {cfg.max_mean_angle_deg:g} deg')
    accepted_ids = tuple(int(hyps[i].track_id) for i in accepted.members)
    corrs = track_correspondences([by_id[i] for i in accepted_ids], recording, config)
    source = np.concatenate([c.source_m for c in corrs])
    target = np.concatenate([c.target_m for c in corrs])
    fit = registration.fit_yaw_translation(source, target)
    extrinsics = Extrinsics(fit.rotation @ ground.rotation_level, fit.translation_m, 0.0)
    _LOG.debug('accepted cluster %d: %d tracks, %d passes, mean angle %.3f deg, rms %.3f m',
               accepted.label, len(accepted_ids), accepted.passes.shape[0],
               accepted.mean_angle_deg, fit.rms_m)
    return HypothesisSelection(tuple(hyps), labels, accepted.label, mean_angles, accepted_ids,
                               extrinsics, int(source.shape[0]), accepted.passes)


def _mean_pairwise_angle_deg(rotations: F64) -> float:
    """Mean angle of R_j^T R_i over distinct pairs; 0 for a single hypothesis."""
    n = rotations.shape[0]
    if n < 2:
        return 0.0
    angles = registration.pairwise_rotation_angles_deg(rotations)
    return float(angles[np.triu_indices(n, k=1)].mean())


def _n_passes(n: int) -> str:
    return f'{n} pass' if n == 1 else f'{n} passes'
