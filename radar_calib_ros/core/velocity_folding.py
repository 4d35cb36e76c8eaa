"""Radial velocities folded at the radar's unambiguous limit: found on the vehicle, unfolded.

A radar's chirp sequence resolves Doppler only within an interval of width P (its
unambiguous velocity is P / 2 each way for the usual symmetric interval); a reflector whose
radial speed lies beyond it is reported wrapped into the interval, off by a whole multiple
of P. Radars tuned for range at a roadside, whose cars pass at 50 km/h, fold: a fourth
probe's did at +-15 m/s, with 37 % of the vehicle's targets folded on a road driven at
14-19 m/s. The paper's stages barely notice (clusters split by velocity still track the
vehicle's position), but the final fit reads the folded velocities as a turned radar and
runs off (120 m and 173 deg there; on our simulator at +-5 m/s, 54 % folded, 6 m and 10 deg).

The contract has no parameter for the interval, and none is needed: near the vehicle, where
the paper's stages put it within decimetres and a degree, its known motion predicts every
target's radial velocity to a fraction of a metre per second, and folded targets differ
from it by the same P. A sharp peak of |measured - predicted| at one value, with every
reported velocity confined to an interval of that width, is the fold (wheel micro-Doppler
and other road users spread their differences instead); the vehicle's targets are then
unfolded by its motion: the multiple of P that brings each nearest to its prediction.

Runs after :func:`quality.radial_velocity_convention` (a flipped sign gives differences of
twice the prediction, which spread, so it must be put right first) and before the final fit.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses
from radar_calib_ros.core.vehicle import box_distance, world_to_vehicle
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.types import Extrinsics

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_LOG = logging.getLogger(__name__)

#: Smallest fold period believed [m/s]: the differences of wheels and rounding stay below it.
_MIN_PERIOD_MPS = 4.0
#: Width of the window the peak of |difference| is counted in, and of the rings beside it
#: that measure the background [m/s] (the vehicle's predicted v_r, without its yaw rate
#: and with the paper's stages' degree of rotation error, is good to a few tenths).
_PEAK_HALF_WIDTH_MPS = 0.5
_RING_MPS = 2.0
#: The peak must hold at least this many targets, this share of those near the vehicle,
#: and this many times the background density beside it.
_MIN_FOLDED = 20
_MIN_FOLDED_SHARE = 0.03
_MIN_CONTRAST = 5.0
#: Share of the peak's targets that a fold explains: moved towards the other end of the
#: interval (a speed beyond +V comes back near -V), so their difference has the opposite
#: sign of their prediction.
_MIN_FOLDED_BACK_SHARE = 0.8
#: Largest difference between the peak and the reported velocities' span, and slack on
#: the vehicle's distance from the box for the unfolding [m/s, m].
_SPAN_SLACK_MPS = 1.0
_UNFOLD_MARGIN_M = 1.0
#: Below this speed the vehicle's radial velocities cannot fold [m/s].
_MIN_SPEED_MPS = 1.0


@dataclass(frozen=True)
class VelocityFolding:
    """A fold found on the vehicle: the interval's width and the evidence."""

    period_mps: float      # P: width of the unambiguous interval (twice +-V)
    n_near: int            # targets near the vehicle, moving, that were judged
    n_folded: int          # of them, those off their prediction by about P
    n_unfolded: int = 0    # targets whose velocity was unfolded


def _near_vehicle(extrinsics: Extrinsics, recording: Recording, index: I64,
                  config: CalibConfig, gate_m: float) -> tuple[I64, F64]:
    """The targets of ``index`` within ``gate_m`` of the vehicle's box under
    ``extrinsics`` while it moves, and their predicted radial velocity."""
    targets = recording.targets
    frames = targets.frame_index[index]
    stamps = hypotheses.pose_stamps_ns(recording.frame_stamps_ns,
                                       config.sync.time_offset + extrinsics.time_offset_s)
    poses = interpolate_poses(recording.vehicle, stamps, config.sync.max_pose_gap)
    speed = np.hypot(poses.velocities_mps[:, 0], poses.velocities_mps[:, 1])
    ok = (poses.valid & (speed > _MIN_SPEED_MPS))[frames]
    index, frames = index[ok], frames[ok]
    world = extrinsics.apply(targets.positions_m[index])
    near = box_distance(world_to_vehicle(world, poses.positions_m[frames],
                                         poses.yaw_rad[frames]), config.vehicle) <= gate_m
    index, frames, world = index[near], frames[near], world[near]
    rays = world - extrinsics.translation_m
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-9)[:, None]
    predicted: F64 = np.einsum('ij,ij->i', poses.velocities_mps[frames], rays)
    return index, predicted


def detect_folding(extrinsics: Extrinsics, recording: Recording, candidates: I64,
                   config: CalibConfig) -> VelocityFolding | None:
    """The fold period of the radar's radial velocities, judged on the vehicle's targets
    among ``candidates`` (the moving ones) under the paper's stages' ``extrinsics``; None
    when they show none."""
    index, predicted = _near_vehicle(extrinsics, recording, np.asarray(candidates, np.int64),
                                     config, config.refine.gate_m)
    if index.size < _MIN_FOLDED:
        return None
    measured = recording.targets.radial_velocity_mps[index]
    off = np.abs(measured - predicted)
    far = off[off > _MIN_PERIOD_MPS - _PEAK_HALF_WIDTH_MPS]
    if far.size < _MIN_FOLDED:
        return None
    # the densest window of |difference|: a sort and a sliding count, no histogram bins to
    # straddle
    far.sort()
    upper = np.searchsorted(far, far + 2.0 * _PEAK_HALF_WIDTH_MPS, side='right')
    start = int(np.argmax(upper - np.arange(far.size)))
    period = float(np.median(far[start:upper[start]]))
    in_peak = np.abs(off - period) <= _PEAK_HALF_WIDTH_MPS
    n_peak = int(in_peak.sum())
    ring = (np.abs(off - period) > _PEAK_HALF_WIDTH_MPS) & (
        np.abs(off - period) <= _PEAK_HALF_WIDTH_MPS + _RING_MPS)
    background = ring.sum() * _PEAK_HALF_WIDTH_MPS / _RING_MPS
    # Every velocity the radar reports lies within its interval, so over a whole
    # recording (clutter, traffic both ways) the reported span fills it to a few cm/s: it
    # must match the peak, and it is the sharper value of the two (the peak's median sits
    # low: targets just beyond the limit fold only where their error carried them over).
    span = float(np.ptp(recording.targets.radial_velocity_mps))
    back = float(np.mean((measured - predicted)[in_peak] * predicted[in_peak] < 0.0))
    _LOG.debug('velocity folding: %d near the vehicle, peak of %d at %.2f m/s over a '
               'background of %.1f, reported span %.2f m/s, %.0f %% folded back',
               index.size, n_peak, period, background, span, 100 * back)
    if (period < _MIN_PERIOD_MPS or n_peak < max(_MIN_FOLDED, _MIN_FOLDED_SHARE * index.size)
            or n_peak < _MIN_CONTRAST * max(background, 1.0)
            or abs(span - period) > _SPAN_SLACK_MPS or back < _MIN_FOLDED_BACK_SHARE):
        return None
    return VelocityFolding(span, int(index.size), n_peak)


def unfold_radial_velocities(recording: Recording, extrinsics: Extrinsics, candidates: I64,
                             folding: VelocityFolding, config: CalibConfig
                             ) -> tuple[Recording, VelocityFolding]:
    """The recording with the vehicle's targets among ``candidates`` unfolded: each moved by
    the multiple of the period that brings it nearest to the vehicle's predicted radial
    velocity (within a metre beyond the refinement's gate, which the final fit never
    leaves). Other targets keep their measurement: nothing predicts theirs."""
    index, predicted = _near_vehicle(extrinsics, recording, np.asarray(candidates, np.int64),
                                     config, config.refine.gate_m + _UNFOLD_MARGIN_M)
    velocities = recording.targets.radial_velocity_mps
    turns = np.round((predicted - velocities[index]) / folding.period_mps)
    moved = turns != 0
    unfolded = velocities.copy()
    unfolded[index[moved]] += turns[moved] * folding.period_mps
    recording = replace(recording, targets=replace(recording.targets,
                                                   radial_velocity_mps=unfolded))
    return recording, replace(folding, n_unfolded=int(moved.sum()))
