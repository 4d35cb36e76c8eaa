"""Stage 8 (beyond the paper): joint robust refinement of the six degrees of freedom, the
radar/GNSS clock offset and the vehicle's reflection profile over every target the current
calibration places on or near the calibration vehicle.

The paper stops at decimetres (delta_op 0.26-0.39 m) because it fits cluster centres and
then a polygon loss that is biased when most targets lie inside the footprint. Here every
target counts, through two kinds of residuals:

* Radial velocity. For a rigid car v_r = (v_ref + omega x r) . u, u the unit line of sight,
  whatever point reflected. It depends on the rotation and the clock offset, not on the
  radar's position (to first order) and not on where on the car the target lies: it pins
  the yaw and the clock offset free of any reflection model. (Its line of sight takes the
  target's height from the model, not from the 1-2 deg elevation noise: used inside the
  nonlinear model that noise biases the pitch by ~0.1-0.5 deg; a corrected-score version
  was tried and carried too little pitch information to be worth it. Pitch and roll come
  from the heights.) Wheels break rigidity (micro-Doppler), hence a robust loss.
* Position. The target in the vehicle frame minus the reflection profile m(alpha), the mean
  offset of the targets as a function of the aspect angle (``core/reflection.py``),
  estimated jointly. Residuals are whitened per target by the radar's spherical noise
  (range ~0.15 m, azimuth ~0.3 deg, elevation ~1.5 deg: the cross-range and vertical parts
  grow with range) plus the scatter of the reflectors around their mean; the scatter is
  re-estimated every gate round.

Gauge and priors (the least we can defend):
* Left-right symmetry of the car (m_x even, m_y odd in alpha, one mean height) fixes the
  lateral profile; the depth along the line of sight stays free (and may drift linearly
  with range, one more coefficient) and is resolved only by seeing an aspect from several
  bearings. Its trade-off with the radar's position along the boresight is reported, not
  hidden. The low orders of the profile also change as 1 / range (perspective: the car
  spans L / r of the view, and its nearer, squarer parts show more), with a prior of a
  twentieth of the vehicle's length. Two smoothed steps let the near face switch from
  front to rear and from one side to the other (``core/reflection.py``): smoothed by the
  Fourier terms, that switch pinned the near side's offset, and with it the position,
  where the views do not.
* The mean reflection height cannot be told from the radar's altitude by the vehicle alone
  (both shift every target's height equally). A stated prior fixes it:
  ``refine.reflection_height_m`` above the road, +- ``refine.reflection_height_sigma_m``;
  the road is the vehicle's reference point minus ``vehicle.ref_height``. It is the mean of
  ALL the vehicle's targets, multipath images below the road included: direct returns
  average about 0.5 m (wheels, underbody, engine, sills), while the road ghosts and the
  multi-bounce returns of the wheel houses and underbody (15-30 % of the targets) sit about
  as far below the road, hence 0.35 +- 0.3 m for a car 1.5 m tall, scaled with
  ``vehicle.height`` for others (``reflection_height_prior``). (Measured on the simulator at
  the true pose: 0.17-0.38 m interior, 0.15-0.68 m skin. Independent simulators' cars
  averaged 0.48-1.15 m without road ghosts: a twenty-third probe's panel cars at 0.84-0.93 m
  put the radar 0.54-0.75 m low at a reported 0.3, 29 of 38 outside 2 sigma with +- 0.2.)
  The ghosts' mirror symmetry about the road does in principle show the road itself; a
  mirror-mixture fit was tried and, at 1-2 deg of elevation noise, scattered by 5-50 cm:
  not better than the prior, so not used.
* Where the elevation field of view (found from all targets' elevations) cuts off the lower
  part of the car, what remains is higher on average, and more so at short range; a pitch
  error would follow it. Those frames give no height information (``_inside_elevation_view``).
* Weak bounds keep the profile on the car (coefficients within about a car length), the
  clock offset within ``sync.max_time_offset`` and the horizontal translation within half a
  metre of the paper's estimate; they only matter when the data say nothing, and then they
  are what the reported uncertainty shows. The altitude has no such bound: only the height
  prior above may decide it (``_ALTITUDE_START_SIGMA_M``).
* On a grade the car is pitched with the road (``_road_grades``): the profile's offsets
  ahead of the reference point are raised by the grade.

Information, not frame count: a car crawling in a queue gives hundreds of near-identical
frames from one place and one aspect. Frames are binned by (vehicle position, aspect) and
the frames of a bin share the weight of ``refine.cell_frames`` frames.

The uncertainty comes from agreement across passes and across range bands
(``core/uncertainty.py``), never from the per-target fit or from r_i.

This module holds the stage: the gate rounds, the model check and a 2-D radar's tilt
probes, the rescan along the boresight, the clock offset's second start and the clock
refits around them, and the road plane's own uncertainty. Its parts live next to it: the
poses at float times, the model, the solver and the priors in
``refine_model.py``; which targets a fit takes and how much each counts in
``refine_targets.py``; the noise the residuals show in ``refine_noise.py``; the clock
offset's start, drift and steps in ``refine_clock.py``; the divergence checks and the
covariance's consider terms in ``refine_covariance.py``; the diagnostics and drive advice's
candidates in ``refine_diagnostics.py``.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, reflection, uncertainty
from radar_calib_ros.core.refine_clock import (_clock_drift, _clock_step, _mid_recording_s,
                                               _pass_time_offsets, _radar_clock_s,
                                               _rescan_time_offset, _scan_time_offset)
from radar_calib_ros.core.refine_covariance import (
    _VELOCITY_SUSPECTS, _check_not_diverged, _Diverged, _halves_disagreement, _halves_geometry,
    _halves_shift, _height_difference_shift, _height_shift, _jackknife_groups, _lane_separation,
    _line_axis, _pose_block, _position_spread, _range_bands, _start_term, _turn_between_passes,
    _yaw_rate_shift, _yaw_step_between_passes, along_boresight_share, start_error_m)
from radar_calib_ros.core.refine_diagnostics import _diagnostics
from radar_calib_ros.core.refine_model import (
    _START_SIGMA_M, ClockDrift, _anchor, _change, _Fit, _Model, _parameter_sigma, _Poses,
    _priors, _road_up, _robust, _rotation_between, _Selected, _solve, _Times, _vehicle_poses,
    n_range_terms, range_columns, reflection_height_prior)
from radar_calib_ros.core.refine_noise import (_azimuth_bias, _azimuth_noise_deg,
                                               _elevation_noise_deg, _noisy_azimuth,
                                               _noisy_elevation, _scatter)
from radar_calib_ros.core.refine_targets import (_MIN_PASS_TARGETS, _MIN_TARGETS, _corridor,
                                                 _gate, _in_passes, _occluded, _select,
                                                 _track_sizes, with_static_targets)
from radar_calib_ros.core.vehicle import box_limits
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import (
    F64, I64, Extrinsics, HypothesisSelection, Refinement, TrackedTargets)

__all__ = ['ClockDrift', 'Diverged', 'n_range_terms', 'range_columns',
           'reflection_height_prior', 'refine_extrinsics']

#: The final fit ran farther from the paper's stages than they can be off: raised by
#: ``refine_extrinsics`` (a subclass of InsufficientDataError, with ``shift_m`` and
#: ``turn_deg``) for the pipeline to start it elsewhere.
Diverged = _Diverged

_LOG = logging.getLogger(__name__)

#: What a 2-D radar leaves of roll and pitch (1 sigma each), held level where its mount's
#: were not measured: a roadside radar's roll is within a few degrees of level, but its
#: pitch is what aims it at the road, 3-15 deg down on a pole (a sixty-ninth probe's pitched
#: 13.8-15 deg were reported level at 5 deg, 1 sigma, outside two). Its altitude comes
#: from the dip of the radial velocities' line of sight, which the reflection heights and
#: the held tilt blur (a fifth probe's 2-D radars: 23-39 cm below the truth, with 17 cm
#: from the heights).
_PLANAR_ROLL_SIGMA_DEG = 3.0
_PLANAR_PITCH_SIGMA_DEG = 8.0

#: Relative 1-sigma of a yaw rate from fixes alone (``vehicle_track._course_over_ground``):
#: the course differentiated read turns 20 % low on our simulator and 7-14 % low on
#: independent probes', with 0.04-0.09 rad/s of noise besides, the local quadratic that
#: replaced it 6-12 % low on a fifty-fifth probe's corners entered within a fraction of a
#: second; what the fit makes of it is an effective few per cent (the errors above over
#: the linearised shift of ``_yaw_rate_shift``: 3-6 %).
_FIX_YAW_RATE_SIGMA = 0.05
_PLANAR_HEIGHT_SIGMA_M = 0.3
#: Prior sigma that holds a 2-D radar's roll and pitch at the start [rad].
_PLANAR_HOLD_RAD = 1e-5
#: Gate rounds fit at most about this many targets; the final fit takes them all. An
#: imaging radar puts 100+ targets on the car in every frame (120 000 in five minutes at
#: 20 Hz), and each LM step costs in proportion; the gate and the scatter need far fewer.
_ROUND_TARGETS = 40_000
#: ... and the final fit at most about this many: a 4D imaging radar gives 300 000 targets
#: on the car in ten minutes (100+ per frame, each frame's nearly the same reflectors), and
#: the Jacobian of the fit of all of them held 1.2 GB; every second of them carries the
#: same views and the same agreement across passes. Our simulator's fits hold 3 000-25 000.
_FINAL_TARGETS = 150_000
#: Fitted azimuth scale errors from this size (and three sigma) are named.
_AZIMUTH_SCALE_NOTE = 0.005
#: At most this many refits for a drift, stopped once what is left of it is below this
#: fraction of the rate found.
_DRIFT_REFITS = 3
_DRIFT_SETTLED = 0.1
#: Clock offsets the first round leaves more uncertain than this are not estimated [s]:
#: normal drives pin it to 2-4 ms; where the vehicle keeps one speed through the view an
#: offset only moves it along its own travel, as a longer or shorter car would (the
#: profile's constant), and the fit slid 0.73 s to where other cars' targets were (an
#: independent recording of four straight passes: refused). Sigma of the hold [s].
_TAU_HOLD_SIGMA_S = 0.01
_TAU_HOLD_S = 1e-6
#: 1-sigma of the tilt prior from the road plane [deg]: the plane of the road users'
#: reflections is 0.1-0.5 deg off the road's (where a vehicle reflects changes with the
#: look-down angle), a cross slope adds up to 1; normal views pin the tilt to 0.05-0.2 deg
#: and are not moved by it.
_TILT_PRIOR_DEG = 1.0
#: How far the fit may tilt the radar from the road plane [deg], and across how much spread
#: of its targets about one road [m] (1 sigma) the vehicle's views count as one road, before
#: the tilt is held at the plane's (``_HELD_TILT_DEG``; see ``_refine_checked``). Junction
#: views spread 11-21 m and their fits stay within 0.93 deg of the plane (the bench's 33
#: drives); one road seen by a narrow beam spreads 3-4 m, one lane 0.6 m.
_TILT_MOVED_DEG = 0.75
_LINE_SPREAD_M = 5.0
_HELD_TILT_DEG = 0.1
#: Least separation [m] of the two directions' lanes the held plane's roll is judged over
#: (two lanes of one carriageway a car's width apart at the least).
_MIN_LANE_SEPARATION_M = 2.0


# --- the stage --------------------------------------------------------------------------

def refine_extrinsics(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
                      selection: HypothesisSelection, config: CalibConfig, *,
                      ground_normal: F64 | None = None,
                      plane_sigma_deg: float = 0.0) -> Refinement:
    """Final robust refinement of rotation, translation, clock offset and reflection profile.

    Parameters
    ----------
    initial : Extrinsics
        Estimate after the paper's stages (decimetres, about a degree off; clock offset
        unknown within ``sync.max_time_offset``).
    recording : Recording
    tracked : TrackedTargets
        Moving targets with track ids; seeds the selection. The targets stage 1 took for
        static are added near the vehicle while it moves (``with_static_targets``).
    selection : HypothesisSelection
        Its accepted tracks are always admitted to the gate.
    config : CalibConfig
        Uses ``refine``, ``sync``, ``vehicle``, ``hypotheses.pass_gap_s`` and
        ``quality.max_boresight_sigma_m``.
    ground_normal : ndarray of shape (3,), optional
        The road plane's normal in the sensor frame (stage 4): a weak prior on the tilt
        (``_TILT_PRIOR_DEG``) where the vehicle's views leave it undetermined.
    plane_sigma_deg : float
        How uncertain stage 4's plane is (``GroundPlane.tilt_sigma_deg``): where the
        vehicle was seen along one road only, the tilt about it is the plane's, and this
        joins the covariance (``_plane_swing``).

    Returns
    -------
    Refinement
        ``extrinsics`` (clock offset on top of ``sync.time_offset``), the 7x7 covariance over
        [rotation vector (world, left perturbation), translation, time offset] from a
        jackknife over passes, the reflection profile (``core/reflection.py`` layout) and
        diagnostics: sigmas, advice, coverage, per-pass summaries and residual arrays.

    Raises
    ------
    InsufficientDataError
        Fewer than a handful of targets near the vehicle.

    References
    ----------
    method-paper.tex, Sec. "Result Refinement" (what this stage goes beyond).
    """
    # The products here are tall and skinny (tens of thousands of rows, ~20 columns):
    # memory-bound, and multi-threaded BLAS only spins on a busy machine (measured 10x
    # slower with 2 cores shared). One thread is as fast when idle and far faster when not.
    if not recording.has_elevation:
        initial = _above_the_road(_with_mount_tilt(initial, config), recording, config)
    # every fit knows how sure stage 4's plane is (where it is no surer than the fit, the
    # tilt is not held at it: see ``_refine_checked``)
    _checked = functools.partial(_refine_checked, plane_sigma_deg=plane_sigma_deg)
    with threadpool_limits(limits=1, user_api='blas'):
        tracked = with_static_targets(initial, recording, tracked, config)
        start_sigma = _START_SIGMA_M
        held_note: _Diverged | None = None
        try:
            refinement = _checked(initial, recording, tracked, selection, config,
                                  ground_normal, None)
        except _Diverged as err:
            # Every drive runs towards or away from the radar: the position along the
            # boresight is a flat valley that the reflection depth trades along, and the
            # half-metre prior did not hold the fit in it (a twenty-second probe's straight
            # drives: 9 of 17 ran 5-9 m off and were refused as radial velocities gone
            # wrong, which they were not). There the position is held at the paper's
            # estimate, whose error the uncertainty reports (a car length, ``_start_term``).
            if not _drives_along_boresight(initial, recording, tracked, selection, config):
                raise
            start_sigma = _HELD_START_SIGMA_M
            try:
                refinement = _checked(initial, recording, tracked, selection, config,
                                      ground_normal, None, start_sigma)
            except InsufficientDataError:
                raise err from None
            held_note = err
        # Drives along one road leave the position along the boresight open by up to a car
        # length, and a drive across the view that would close it then lies that far from
        # the box, outside the gate: seen from a place it was never fitted at (see
        # ``_rescan_along_boresight``), it is fitted from there and kept where it agrees.
        rescan = _rescan_along_boresight(refinement, recording, tracked, config)
        other = None if rescan is None else _kept_restart(
            rescan, refinement, _rescan_better, 'rescan_shift_m', lambda start: _checked(
                start, recording, tracked, selection, config, ground_normal, None))
        if rescan is not None and other is not None:
            _LOG.info('started again %.2f m along the boresight: %d passes (%d before), '
                      'along-boresight sigma %.2f m (%.2f before)',
                      float(np.linalg.norm(other.diagnostics['rescan_shift_m'])),
                      other.n_passes, refinement.n_passes,
                      other.diagnostics['sigma_along_boresight_m'],
                      refinement.diagnostics['sigma_along_boresight_m'])
            initial, refinement = rescan, other
        # A bus or a truck shows the radar its flat front when it comes and its rear when it
        # goes, metres from where its other targets lie: the fit can settle with the box
        # slid along the road, keeping the targets of one face and leaving the rest outside
        # the gate (see ``_rescan_along_the_road``).
        road = (_rescan_along_the_road(refinement, recording, tracked, config)
                if hypotheses.long_vehicle(config) else None)
        other = None if road is None else _kept_restart(
            road, refinement, _road_refit_better, 'road_shift_m', lambda start: _checked(
                start, recording, tracked, selection, config, ground_normal, None,
                start_sigma))
        if road is not None and other is not None:
            _LOG.info('started again %.2f m along the road: %d targets (%d before)',
                      float(np.linalg.norm(other.diagnostics['road_shift_m'])),
                      other.n_targets, refinement.n_targets)
            initial, refinement = road, other
        # The clock offset's start is scanned at the paper's stages' position, decimetres
        # to metres off along the road, and the offset that puts the most targets on the
        # box there makes up for that: along a road driven at one speed a clock offset and
        # a shift along it look alike, and the fit can settle where it started (a
        # sixty-second probe's on-ramp: started 1.9 m off, scanned +0.23 s for +0.157,
        # fitted +0.225 at 12 ms, 0.42 m off with exit 0; started at +0.15 or +0.21, it
        # fitted +0.153, 0.10 m off). Scanned again at the fitted position, an offset far
        # from the fitted one starts a second fit from there, and the fit that explains its
        # targets better (lower robust cost per target, not fewer of them) is kept.
        initial, refinement = _clock_restarted(
            initial, refinement, lambda started: _checked(
                started, recording, tracked, selection, config, ground_normal, None,
                start_sigma, scan_clock=False))
        # Where the offsets the passes show change steadily with time, the fit is run again
        # with the radar's stamps on a clock of that rate (see ``_clock_drift``). The
        # passes' offsets are taken at a fit that has partly followed the drift with its
        # other parameters (the position, where the directions driven change over time), so
        # they show less of it than there is: what they still show is added, a few times.
        # A clock that stepped between two passes (``_clock_step``) is tested first: a
        # straight line drawn through a step misplaces every pass but the middle ones.
        drift: ClockDrift | None = None
        reference_s = _mid_recording_s(recording, config)
        for _ in range(_DRIFT_REFITS):
            # once a drift or step is found, what is left of it is estimated, not tested
            # for again
            offsets = refinement.diagnostics.get('pass_time_offsets', [])
            if drift is None:
                more = (_clock_step(offsets) or _clock_drift(offsets, reference_s))
            elif drift.step_s:
                more = _clock_step(offsets, at_s=drift.step_at_s)
            else:
                more = _clock_drift(offsets, reference_s, found=True)
            if more is None or (drift is not None
                                and more.size < _DRIFT_SETTLED * drift.size):
                break
            drift = more if drift is None else drift.plus(more)
            try:
                refinement = _checked(initial, recording, tracked, selection, config,
                                      ground_normal, drift, start_sigma)
            except InsufficientDataError:
                break
            _LOG.info('radar clock drift %.0f +- %.0f ppm, step %.0f ms: refitted',
                      1e6 * drift.rate, 1e6 * drift.sigma, 1e3 * drift.step_s)
        if held_note is not None:
            sigma = refinement.diagnostics['sigma_along_boresight_m']
            refinement.diagnostics['advice'] = [
                'Every drive ran towards or away from the radar, which leaves its position '
                'along the boresight to where the paper\'s stages put it: the fit, left free, '
                f'ran {held_note.shift_m:.1f} m (and {held_note.turn_deg:.1f} deg) off along '
                'that open direction. The horizontal position was held at the paper\'s '
                f'estimate, uncertain by about a car length ({sigma:.1f} m along the '
                'boresight, 1 sigma): cross the view or turn through it to measure it.',
                *refinement.diagnostics['advice']]
            _LOG.info('%s', refinement.diagnostics['advice'][0])
        return _plane_swing(refinement, plane_sigma_deg)


def _plane_swing(refinement: Refinement, plane_sigma_deg: float) -> Refinement:
    """The refinement with the road plane's own uncertainty in its covariance, where the
    vehicle was seen along one road only (``_LINE_SPREAD_M``): a turn about that road
    through its targets, which moves them by nothing and the radar by its distance from
    them times the angle, is then decided by the plane (the fit's prior, or held there),
    and is as uncertain as the plane is."""
    diagnostics = refinement.diagnostics
    axis = diagnostics.get('line_axis')
    offset = diagnostics.get('target_offset_m')
    if (plane_sigma_deg <= 0.0 or axis is None or offset is None
            or diagnostics.get('line_spread_m', math.inf) >= _LINE_SPREAD_M):
        return refinement
    swing = np.concatenate([axis, -np.cross(axis, offset), [0.0]])
    covariance = refinement.covariance + math.radians(plane_sigma_deg) ** 2 * np.outer(
        swing, swing)
    diagnostics = dict(diagnostics)
    diagnostics.update(uncertainty.sigma_summary(covariance, refinement.extrinsics.rotation))
    diagnostics['plane_sigma_deg'] = float(plane_sigma_deg)
    return dataclasses.replace(refinement, covariance=covariance, diagnostics=diagnostics)


#: Width of the prior that holds the horizontal position at the paper's estimate where
#: every drive runs along the boresight and the fit ran off along it [m].
_HELD_START_SIGMA_M = 0.05
#: The drives all run along the boresight (``uncertainty.near_axis``) when this share of
#: the accepted tracks' targets are seen so.
_ALONG_BORESIGHT_SHARE = 0.9


def _with_mount_tilt(initial: Extrinsics, config: CalibConfig) -> Extrinsics:
    """A 2-D radar's start with the roll and pitch measured at its mount (``radar.mount_*``),
    its yaw kept; unchanged where none was measured. The fit then holds them there, as it
    holds them level otherwise."""
    if config.radar.mount_tilt_sigma_deg <= 0.0:
        return initial
    _, _, yaw = Rotation.from_matrix(initial.rotation).as_euler('xyz')
    rotation = Rotation.from_euler('xyz', [math.radians(config.radar.mount_roll_deg),
                                           math.radians(config.radar.mount_pitch_deg), yaw])
    return Extrinsics(rotation.as_matrix(), np.asarray(initial.translation_m, float),
                      float(initial.time_offset_s))


#: Least height [m] above the vehicle's reflections a 2-D radar's altitude starts at.
_PLANAR_START_ABOVE_M = 3.0


def _above_the_road(initial: Extrinsics, recording: Recording,
                    config: CalibConfig) -> Extrinsics:
    """A 2-D radar's start raised to at least ``_PLANAR_START_ABOVE_M`` above the
    vehicle's reflections (the road under its median pose plus the reflection-height
    prior), where it was lower.

    Why: without elevations the altitude comes from the dip of the radial velocities'
    line of sight and the slant ranges, both the same for a radar as far below the
    reflections as above them, and the paper's stages start it at the vehicle's: the fit
    went either way. A seventy-first probe's 2-D radars seen with vans, minibuses and buses
    (vehicle.height above about 2.1 m, which raises the reflections' prior above the start)
    were put 11-18 m low, under the road, at a reported 0.7-1 m; a radar looks down on the
    road from a pole or a gantry, and from above the fit finds that root."""
    road = float(np.median(recording.vehicle.positions_m[:, 2])) - config.vehicle.ref_height
    floor = road + reflection_height_prior(config)[0] + _PLANAR_START_ABOVE_M
    if initial.translation_m[2] >= floor:
        return initial
    translation = np.array(initial.translation_m, float, copy=True)
    translation[2] = floor
    return Extrinsics(initial.rotation, translation, float(initial.time_offset_s))


def _planar_tilt_sigmas_deg(config: CalibConfig) -> tuple[float, float]:
    """1-sigma of a 2-D radar's held roll and pitch: as measured at its mount, or
    ``_PLANAR_ROLL_SIGMA_DEG`` and ``_PLANAR_PITCH_SIGMA_DEG`` where they were not."""
    given = config.radar.mount_tilt_sigma_deg
    return (given, given) if given > 0.0 else (_PLANAR_ROLL_SIGMA_DEG, _PLANAR_PITCH_SIGMA_DEG)


def _drives_along_boresight(est: Extrinsics, recording: Recording, tracked: TrackedTargets,
                            selection: HypothesisSelection, config: CalibConfig) -> bool:
    """Whether the vehicle heads towards or away from the radar (``uncertainty.near_axis``
    of its boresight) wherever the accepted tracks see it."""
    index = np.asarray(tracked.target_index, np.int64)[np.isin(
        tracked.track_id, np.asarray(selection.accepted_track_ids, np.int64))]
    if index.size == 0:
        return False
    poses, times = _vehicle_poses(recording, index, config)
    valid = times.valid(poses, est.time_offset_s)
    if not valid.any():
        return False
    _, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    boresight = math.atan2(est.rotation[1, 0], est.rotation[0, 0])
    return float(np.mean(uncertainty.near_axis(yaw[valid], boresight))) >= _ALONG_BORESIGHT_SHARE


#: Shifts along the boresight are searched for left-out drives only where the fit leaves the
#: position open by at least this much (3 sigma) [m]: nearer, the gate sees them already.
_RESCAN_MIN_HALF_WIDTH_M = 1.0
#: ... at most this many vehicle lengths either way, in steps of [m].
_RESCAN_MAX_LENGTHS = 1.5
_RESCAN_STEP_M = 0.25
#: Left-out drives join only with at least this share of the fitted targets (and a pass's
#: worth): a few stray targets of other road users do not move the start.
_RESCAN_MIN_SHARE = 0.1


def _rescan_along_boresight(refinement: Refinement, recording: Recording,
                            tracked: TrackedTargets, config: CalibConfig) -> Extrinsics | None:
    """A start shifted along the boresight at which drives the fit left out join it.

    Straight drives along one road (a radar mid-block) show the car head-on and tail-on
    only: its reflection depth trades off exactly against the radar's distance, and the
    paper's stages leave the radar up to a car length off along the boresight (a twentieth
    probe: 1-4 m). A drive across the view would show the sides and settle it, but from
    that start its targets lie metres beside the box and the gate leaves them out: two such
    drives were reported "without targets" while the fit stayed 3.5 and 4.3 m off. So the
    open direction is searched, within 3 sigma of it (at most ``_RESCAN_MAX_LENGTHS``
    vehicle lengths), for the shift that brings the most targets of the left-out drives
    into the gate, their radial velocities matching the vehicle's; the centre of that
    stretch is the new start (the caller keeps the fit from there only where it takes in
    more passes and narrows the open direction).
    """
    est = refinement.extrinsics
    sigma = float(refinement.diagnostics.get('sigma_along_boresight_m', 0.0))
    half = min(3.0 * sigma, _RESCAN_MAX_LENGTHS * config.vehicle.length)
    boresight = np.array([est.rotation[0, 0], est.rotation[1, 0], 0.0])
    norm = float(np.linalg.norm(boresight))
    if half < _RESCAN_MIN_HALF_WIDTH_M or norm < 1e-6:
        return None
    boresight /= norm
    candidates = np.asarray(tracked.target_index, np.int64)
    track_ids = np.asarray(tracked.track_id, np.int64)
    track_size = _track_sizes(track_ids)
    poses, times = _vehicle_poses(recording, candidates, config)
    fitted = np.asarray(refinement.diagnostics['residuals']['target_index'], np.int64)
    fitted_t = np.sort(times.t_s[np.isin(candidates, fitted)])
    if fitted_t.size == 0:
        return None
    # the targets of drives with no fitted target (none within a pass gap in time)
    after = np.clip(np.searchsorted(fitted_t, times.t_s), 0, fitted_t.size - 1)
    before = np.maximum(after - 1, 0)
    gap = np.minimum(np.abs(times.t_s - fitted_t[after]), np.abs(times.t_s - fitted_t[before]))
    unused = gap > config.hypotheses.pass_gap_s
    if not unused.any():
        return None
    candidates, track_ids, track_size = (candidates[unused], track_ids[unused],
                                         track_size[unused])
    times = times.subset(unused)
    shifts = np.arange(-half, half + 1e-9, _RESCAN_STEP_M)
    counts = _gate_counts_along(est, boresight, shifts, candidates, track_ids, track_size,
                                times, recording, poses, config)
    if counts.max() < max(_MIN_PASS_TARGETS, _RESCAN_MIN_SHARE * fitted.size):
        return None
    # the gate is a stretch as wide as the car and the gate: its centre, not its edge
    shift = _stretch_centre(shifts, counts, 0.5)
    return Extrinsics(est.rotation, est.translation_m + shift * boresight, est.time_offset_s)


def _gate_counts_along(est: Extrinsics, direction: F64, shifts: F64, candidates: I64,
                       track_ids: I64, track_size: I64, times: _Times, recording: Recording,
                       poses: _Poses, config: CalibConfig) -> F64:
    """(len(shifts),) targets among ``candidates`` that the gate takes in, within passes,
    with the radar moved by each shift [m] along ``direction`` (unit, world)."""
    view = recording.radar_view()
    counts = np.zeros(shifts.size)
    for i, shift in enumerate(shifts):
        moved = Extrinsics(est.rotation, est.translation_m + shift * direction,
                           est.time_offset_s)
        keep = _gate(moved, candidates, track_ids, track_size, np.zeros(0, np.int64), times,
                     recording, poses, config, first_round=False, view=view)
        if keep.any():
            keep[keep] = _in_passes(times.subset(keep).t_s, config.hypotheses.pass_gap_s)
        counts[i] = keep.sum()
    return counts


def _stretch_centre(shifts: F64, counts: F64, share: float) -> float:
    """The count-weighted centre of the stretch of shifts around the most counted one
    whose counts stay at ``share`` of the most or above."""
    best = int(np.argmax(counts))
    lo = hi = best
    while lo > 0 and counts[lo - 1] >= share * counts[best]:
        lo -= 1
    while hi < shifts.size - 1 and counts[hi + 1] >= share * counts[best]:
        hi += 1
    return float(np.average(shifts[lo:hi + 1], weights=counts[lo:hi + 1]))


def _kept_restart(start: Extrinsics, first: Refinement,
                  better: Callable[[Refinement, Refinement], bool], shift_key: str,
                  refit: Callable[[Extrinsics], Refinement]) -> Refinement | None:
    """``refit`` from ``start`` where it succeeds and is ``better`` than ``first``, with
    the start's shift from ``first``'s estimate [m] in its diagnostics under ``shift_key``;
    else None (the rescans along the boresight and along the road)."""
    try:
        other = refit(start)
    except InsufficientDataError:
        return None
    if not better(other, first):
        return None
    other.diagnostics[shift_key] = [
        float(v) for v in start.translation_m - first.extrinsics.translation_m]
    return other


def _rescan_better(other: Refinement, first: Refinement) -> bool:
    """The fit from a rescanned start is kept where it takes in more passes and narrows
    the position along the boresight: the drives it added agree with the others."""
    return (other.n_passes > first.n_passes
            and other.diagnostics['sigma_along_boresight_m']
            < first.diagnostics['sigma_along_boresight_m'])


#: A long vehicle's box is searched along the road it drove this far either way, in vehicle
#: lengths, in steps of [m].
_ROAD_SCAN_LENGTHS = 1.0
_ROAD_SCAN_STEP_M = 0.5
#: A shift along the road starts a second fit where it brings this many times the targets
#: into the gate that the fitted estimate does ...
_ROAD_SCAN_GAIN = 1.2
#: ... and that fit is kept where it keeps this many times the first's targets, at a robust
#: cost per target at most this many times the first's.
_ROAD_REFIT_TARGETS = 1.1
_ROAD_REFIT_COST = 1.05


def _rescan_along_the_road(refinement: Refinement, recording: Recording,
                           tracked: TrackedTargets, config: CalibConfig) -> Extrinsics | None:
    """A start shifted along the road driven at which the gate takes in far more targets.

    A long vehicle's strongest returns are its near face (the flat front of a bus or a box
    truck when it comes, its rear when it goes), up to half its length from the targets of
    its sides, wheels and underbody. A fit that puts the box over the one face keeps those
    targets in its gate and leaves the others out, at a robust cost per target no better
    than the right one's: a seventieth probe's 9.5-12 m buses and trucks on straight roads
    were placed 2-7 m along the road at exit 0, each fit keeping 1.1-2.2 times fewer of
    the vehicle's targets than a fit started at the truth, whose cost per target was about
    the same (0.93-1.03 times) or far lower (0.25-0.76 times). So the box is slid along
    the road (the mean axis of the headings driven) by up to a vehicle length either way,
    and the gate's count, the radial velocities matching the vehicle's, says where most of
    the vehicle lies; the centre of the stretch at 90 % of the most is the new start.
    """
    est = refinement.extrinsics
    candidates = np.asarray(tracked.target_index, np.int64)
    track_ids = np.asarray(tracked.track_id, np.int64)
    fitted = np.asarray(refinement.diagnostics['residuals']['target_index'], np.int64)
    if candidates.size == 0 or fitted.size == 0:
        return None
    track_size = _track_sizes(track_ids)
    poses, times = _vehicle_poses(recording, candidates, config)
    valid = times.valid(poses, est.time_offset_s)
    _, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    on_box = np.isin(candidates, fitted) & valid
    if not on_box.any():
        return None
    # the axis of the headings (doubled angles: a road driven both ways is one axis)
    axis = 0.5 * math.atan2(float(np.mean(np.sin(2.0 * yaw[on_box]))),
                            float(np.mean(np.cos(2.0 * yaw[on_box]))))
    along = np.array([math.cos(axis), math.sin(axis), 0.0])
    half = _ROAD_SCAN_LENGTHS * config.vehicle.length
    shifts = np.union1d(np.arange(-half, half + 1e-9, _ROAD_SCAN_STEP_M), [0.0])
    counts = _gate_counts_along(est, along, shifts, candidates, track_ids, track_size, times,
                                recording, poses, config)
    here = float(counts[np.searchsorted(shifts, 0.0)])
    if counts.max() < max(_MIN_PASS_TARGETS, _ROAD_SCAN_GAIN * here):
        return None
    shift = _stretch_centre(shifts, counts, 0.9)
    return Extrinsics(est.rotation, est.translation_m + shift * along, est.time_offset_s)


def _road_refit_better(other: Refinement, first: Refinement) -> bool:
    """The fit from a start along the road is kept where it explains far more of the
    vehicle's targets at about the same robust cost per target (``_ROAD_REFIT_*``)."""
    return (other.n_targets >= _ROAD_REFIT_TARGETS * first.n_targets
            and other.diagnostics['cost_per_target']
            <= _ROAD_REFIT_COST * first.diagnostics['cost_per_target'])


#: A clock offset scanned at the fitted position this far from the fitted one starts a
#: second fit [s]: two steps of the scan's grid.
_CLOCK_RESTART_S = 0.04
#: The second fit must keep this share of the first one's targets at least.
_RESTART_TARGET_SHARE = 0.98


def fits_better(other: Refinement, first: Refinement, *, held_counts: bool = False) -> bool:
    """Whether a fit from another start (or of corrected targets) explains the vehicle's
    targets better: a lower robust cost per target (priors included) over at least about
    as many targets. Both gates are drawn by the same rule around their own estimate, so a
    fit that is off sees its targets further from the box and keeps fewer of them. A fit
    that held the clock offset at its start (``_TAU_HOLD_SIGMA_S``) has not fitted it, and
    does not count, unless ``held_counts`` (the same start, other targets)."""
    return ((held_counts or 'time_offset_held_sigma_s' not in other.diagnostics)
            and other.diagnostics['cost_per_target'] < first.diagnostics['cost_per_target']
            and other.n_targets >= _RESTART_TARGET_SHARE * first.n_targets)


def _clock_sigma_capped(covariance: F64, cap_s: float) -> F64:
    """``covariance`` (7x7) with the clock offset's sigma at most ``cap_s`` [s], its row and
    column scaled alike (the correlations kept, the pose block untouched).

    Why: with few passes the clock may be fixed only by all of them together (drives one
    way and the other tell a clock from a position along the road), and a pass left out
    leaves it free: the linearised jackknife then steps seconds away. A sixty-sixth
    probe's three-pass drive had the clock to 0.6 ms and reported it at +-3.3 s (+-4.1 s
    with the offset it advised). No fit is less sure of the clock than the range searched
    for it (``sync.max_time_offset``, or the offset found beyond it)."""
    variance = float(covariance[6, 6])
    if not variance > cap_s ** 2:
        return covariance
    scale = cap_s / math.sqrt(variance)
    out = np.array(covariance, float, copy=True)
    out[6, :] *= scale
    out[:, 6] *= scale
    return out


def _held_clock_shift(velocity_mps: F64, weight: F64) -> F64:
    """(7, 7) outer product of how the pose moves per second of a held clock offset (its
    own entry 1): against the vehicles' mean velocity over the fitted targets.

    Why: where the drives do not show the clock offset (one direction, one speed), it is
    held at stage 6's value, and whatever it is off by, stage 6 placed the radar off along
    the road by the vehicle's speed times that, where the fit's half-metre prior around it
    keeps it (the fit can move the vehicle's reflections along it as readily). The
    jackknife, with the offset held in every replicate, sees none of it: a sixty-fifth
    probe's one-way roads were 1.5-5.2 m off along the road at a reported 0.9 m, the clock
    0.15-0.3 s off at a reported 0.03-0.17 s. Drives both ways cancel in the mean, as they
    do in stage 6's agreement. The offset held is a guess within the searched range,
    uniform there at best (its sigma at least sync.max_time_offset / sqrt(3)).
    """
    mean = np.average(np.asarray(velocity_mps, float)[:, :2], axis=0, weights=weight)
    shift = np.zeros(7)
    shift[3:5] = -mean
    shift[6] = 1.0
    return np.outer(shift, shift)


def _clock_restarted(initial: Extrinsics, refinement: Refinement,
                     refit: Callable[[Extrinsics], Refinement]
                     ) -> tuple[Extrinsics, Refinement]:
    """The start and fit to keep: ``refit`` from the clock offset the scan finds at the
    fitted position (``clock_rescan_s``) where that lies beyond ``_CLOCK_RESTART_S`` of the
    fitted offset, kept where it ``fits_better``; else the given ones. (The scan finds no
    peak at the end of its range: a sixty-second probe's on-ramp had one at -0.25 s, where
    the refit held the offset and was 1.7 m off.)"""
    restart = refinement.diagnostics.get('clock_rescan_s')
    fitted = float(refinement.extrinsics.time_offset_s)
    if restart is None or abs(restart - fitted) <= _CLOCK_RESTART_S:
        return initial, refinement
    started = Extrinsics(initial.rotation, initial.translation_m, float(restart))
    try:
        other = refit(started)
    except (InsufficientDataError, _Diverged):
        return initial, refinement
    if not fits_better(other, refinement):
        _LOG.info('clock offset started again at %+.3f s: fitted %+.3f s, kept %+.3f s',
                  restart, other.extrinsics.time_offset_s, fitted)
        return initial, refinement
    _LOG.info('clock offset started again at %+.3f s: fitted %+.3f s (%+.3f s before)',
              restart, other.extrinsics.time_offset_s, fitted)
    other.diagnostics['clock_restart_s'] = [fitted, float(restart)]
    return started, other


def _refine_checked(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
                    selection: HypothesisSelection, config: CalibConfig,
                    ground_normal: F64 | None, drift: ClockDrift | None,
                    start_sigma_m: float = _START_SIGMA_M, scan_clock: bool = True,
                    plane_sigma_deg: float = 0.0) -> Refinement:
    """``_refine`` with the model check and a 2-D radar's tilt probes (below)."""
    alternative = None
    if config.refine.model_check:
        # The reflection model is the largest error left, and neither jackknife sees the
        # part every pass shares. The same fit under another range law of the profile
        # (perspective -> depth only; depth <-> full) shows how much the position depends
        # on that choice; the squared difference enters the reported covariance along its
        # direction, capped at this fit's own variance there (at most sqrt(2) wider):
        # a difference far beyond the data's precision says the alternative, with its
        # many more range terms, is ill-determined in that geometry (seen: 2 m apart
        # where this fit erred by 11 cm), not that this fit is off by that much.
        # Measured over 106 simulated ten-minute runs (with the 2 cm along-boresight
        # term): the 2-sigma ellipse covered 97 / 100 / 82 % of the interior / mixed /
        # skin horizontal errors without it, 97 / 100 / 97 % with it, for one more fit.
        other = 'full' if config.refine.profile_range_terms == 'depth' else 'depth'
        alt_config = dataclasses.replace(config, refine=dataclasses.replace(
            config.refine, profile_range_terms=other, model_check=False))
        try:
            alternative = _refine(initial, recording, tracked, selection, alt_config,
                                  None, ground_normal=ground_normal, drift=drift,
                                  start_sigma_m=start_sigma_m,
                                  scan_clock=scan_clock).extrinsics.translation_m
        except InsufficientDataError:
            alternative = None
    tilted: list[F64 | None] = []
    if not recording.has_elevation:
        # A 2-D radar's roll and pitch are held level (nothing measures them), yet they
        # still move its position: a tilted plane maps azimuth to bearing differently
        # off the boresight (a fifth probe's radar pitched 7 deg: 45 cm along the
        # boresight, reported at 18). The fit is run again with each held at its sigma
        # (the pitch downwards, as mounts are), and what that moves joins the covariance.
        # At the sigma, not extrapolated from a small tilt: what the pitch moves grows
        # with its square (the slant range's dip), and a sixty-ninth probe's radars
        # pitched 4-15 deg down were all placed 0.55-1.83 m back along the boresight,
        # where 2 deg had moved them 0.05 m.
        single = dataclasses.replace(config, refine=dataclasses.replace(
            config.refine, model_check=False))
        for axis, sigma_deg in zip(np.eye(3)[:2], _planar_tilt_sigmas_deg(config)):
            turn = Rotation.from_rotvec(math.radians(sigma_deg) * axis)
            start = Extrinsics(np.asarray(initial.rotation, float) @ turn.as_matrix(),
                               np.asarray(initial.translation_m, float),
                               float(initial.time_offset_s))
            try:
                tilted.append(_refine(start, recording, tracked, selection, single,
                                      None, drift=drift, start_sigma_m=start_sigma_m,
                                      scan_clock=scan_clock).extrinsics.translation_m)
            except InsufficientDataError:
                tilted.append(None)
    refinement = _refine(initial, recording, tracked, selection, config, alternative,
                         tilted, ground_normal=ground_normal, drift=drift,
                         start_sigma_m=start_sigma_m, scan_clock=scan_clock)
    moved = refinement.diagnostics.get('tilt_from_plane_deg', 0.0)
    spread = refinement.diagnostics.get('line_spread_m', math.inf)
    if moved <= _TILT_MOVED_DEG or spread >= _LINE_SPREAD_M or moved <= 2.0 * plane_sigma_deg:
        # (nor where the fit lies within two sigma of stage 4's plane as stage 4 knows it:
        # two planes it could not tell apart, that far apart. A sixty-fourth probe's slow car
        # park: the road users' plane, taken over a clutter-tilted one 5.8 deg from it, held
        # the tilt 4.4 deg off in pitch, 2.2 m in height; the free fit was 0.18 deg off)
        return refinement
    # Every target lies along one road (one lane of a one-way street; a narrow beam
    # across a road far away): a tilt about that road, with the altitude, moves them by
    # the road's width times the angle, i.e. centimetres per degree, and what decides it
    # then is how the reflections' height differs from the model (the near and far side
    # of the car, front and rear), not the radar's tilt. An eighteenth probe: 1.0-3.4 deg
    # and 0.5-2 m of altitude off at a reported 0.4-0.6 deg, where the road plane (stage
    # 4) had the tilt to 0.1 deg. Such a fit is run again with the tilt held at the road
    # plane's, and the difference between the two joins the covariance as its 1 sigma:
    # which of the two is nearer the truth the data cannot say, and the plane of other road
    # users' reflections can be as far off on the other side (a sixty-third probe's old-town
    # street: the plane 3.2 deg off in roll, the fit 1.7 deg from it, reported at 0.8 deg
    # with the difference as 2 sigma).
    try:
        held = _refine(initial, recording, tracked, selection, config, alternative,
                       tilted, ground_normal=ground_normal, drift=drift,
                       tilt_prior_deg=_HELD_TILT_DEG, start_sigma_m=start_sigma_m,
                       scan_clock=scan_clock)
    except InsufficientDataError:
        return refinement
    free, kept = refinement.extrinsics, held.extrinsics
    difference = np.concatenate([
        Rotation.from_matrix(free.rotation @ kept.rotation.T).as_rotvec(),
        free.translation_m - kept.translation_m, [free.time_offset_s - kept.time_offset_s]])
    covariance = held.covariance + np.outer(difference, difference)
    # The road plane is no surer of that tilt where the road carries traffic both ways: the
    # road users' reflections lie in it at heights that differ from lane to lane (traffic
    # comes towards the radar on one side of the road showing its front, goes away on the
    # other showing its rear), and that height difference over the lanes' separation is its
    # roll about the road. A twenty-fourth probe's radars beside a two-way road: the plane
    # 3 deg off in roll (8 of 8 runs), reported at 1.0-1.8; an eighteenth probe's one-way
    # streets had it to 0.2 deg. Held there, the fit's altitude and position follow that
    # roll (targets metres below and beside the radar swing with it): a consider term of the
    # vehicle's front/rear height difference (``refine.model_sigma_height_difference_m``)
    # over the separation of the two directions' lanes, rotating about the road through the
    # radar.
    axis = held.diagnostics.get('line_axis')
    offset = held.diagnostics.get('target_offset_m')
    lanes = held.diagnostics.get('lane_separation_m')
    if axis is not None and offset is not None and lanes is not None:
        roll = math.atan2(config.refine.model_sigma_height_difference_m,
                          max(lanes, _MIN_LANE_SEPARATION_M))
        swing = np.concatenate([axis, -np.cross(axis, offset), [0.0]])
        covariance = covariance + roll ** 2 * np.outer(swing, swing)
    diagnostics = dict(held.diagnostics)
    diagnostics.update(uncertainty.sigma_summary(covariance, kept.rotation))
    diagnostics['tilt_held'] = {'moved_deg': moved, 'line_spread_m': spread,
                                'altitude_change_m': float(-difference[5])}
    diagnostics['advice'] = [
        # 1 sigma, said as such: a forty-fifth probe read '4.8 m' on a road whose four lanes
        # span 12.5 m as one lane's worth
        f'The vehicle was seen along one road only (its targets spread {spread:.1f} m across '
        f'it, 1 sigma: lanes side by side on one road), which cannot show the radar\'s roll '
        f'and pitch about that road: the fit tilted the radar {moved:.1f} deg from the road '
        'plane of the moving targets (other road users, or with none clutter that passed as '
        'moving), following the vehicle\'s reflection heights instead. The tilt was held at '
        f'that plane (the altitude moved {-difference[5]:+.2f} m with it) and the uncertainty '
        'widened. '
        'Drive through the view on a second road, or turn through it, to measure the tilt.',
        *diagnostics['advice']]
    _LOG.info('%s', diagnostics['advice'][0])
    return dataclasses.replace(held, covariance=covariance, diagnostics=diagnostics)


def _refine(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
            selection: HypothesisSelection, config: CalibConfig,
            alternative_translation: F64 | None,
            tilted_translations: list[F64 | None] | None = None, *,
            ground_normal: F64 | None = None, drift: ClockDrift | None = None,
            tilt_prior_deg: float | None = None,
            start_sigma_m: float = _START_SIGMA_M, scan_clock: bool = True) -> Refinement:
    cfg = config.refine
    candidates = np.asarray(tracked.target_index, np.int64)
    track_ids = np.asarray(tracked.track_id, np.int64)
    accepted = np.asarray(selection.accepted_track_ids, np.int64)
    poses, times = _vehicle_poses(recording, candidates, config, drift)
    estimate_tau = bool(config.sync.estimate_time_offset) and config.sync.max_time_offset > 0
    est = Extrinsics(np.asarray(initial.rotation, float),
                     np.asarray(initial.translation_m, float), float(initial.time_offset_s))
    # Every later step looks only at targets that could come near the box: a generous
    # corridor around the initial estimate (its decimetres and ~1 deg, the largest clock
    # offset at the vehicle's speed) cuts a busy junction's moving targets ten-fold.
    # Track sizes are counted before, so the track rule of the gate keeps its meaning.
    track_size = _track_sizes(track_ids)
    view = recording.radar_view()
    fov = view.elevation_rad

    def linearised_at(data: _Selected, est: Extrinsics, profile: F64,
                      stride: int = 1) -> tuple[_Model, F64]:
        """The model linearised at ``est`` and the parameter vector of that point (each
        round's start, and the final point for the covariance). A fit of every
        ``stride``-th target weighs its priors down by as much: they keep their say
        against the data, while the data's robust loss sees the same residuals."""
        model = _Model(data, poses, est.rotation, est.translation_m,
                       None if estimate_tau else est.time_offset_s, harmonics,
                       cfg.velocity_sigma_mps, _anchor(prior_mean, start, est, tilt_anchor),
                       prior_sigma * math.sqrt(stride), centre_x, cfg.profile_range_terms,
                       cfg.azimuth_scale_sigma > 0)
        x = np.zeros(model.n_par)
        if estimate_tau:
            x[6] = est.time_offset_s
        x[model.i_prof:] = profile
        return model, x
    # every tracked moving target, what may hide the car (but not the vehicle's own tracks)
    road_users, road_user_tracks = candidates.copy(), track_ids.copy()
    corridor = _corridor(est, candidates, times, recording, poses, config)
    candidates, track_ids = candidates[corridor], track_ids[corridor]
    times = times.subset(corridor)
    track_size = track_size[corridor]
    if estimate_tau and scan_clock:
        tau0 = _scan_time_offset(est, candidates, times, recording, poses, config)
        est = Extrinsics(est.rotation, est.translation_m, tau0)
    harmonics = cfg.profile_harmonics
    x_lo, x_hi, _, _ = box_limits(config.vehicle)
    centre_x = 0.5 * (x_lo + x_hi)
    prior_mean, prior_sigma = _priors(config, harmonics, estimate_tau, start_sigma_m)
    if not recording.has_elevation:
        # A 2-D radar (z = 0 for every target) measures no height, so its targets hold no
        # roll or pitch: left free, the fit tilts the radar's plane until it passes through
        # the car (a fifth probe's six such recordings ran 8-22 deg off and were refused).
        # They stay where the paper's stages put them (level), and the covariance says how
        # little that is worth. The altitude is left to the radial velocities, which the
        # line of sight's dip shrinks (see ``_slant_to_height``).
        prior_mean[:2], prior_sigma[:2] = 0.0, _PLANAR_HOLD_RAD
    start = est
    tilt_anchor = start.rotation
    if recording.has_elevation and ground_normal is not None:
        # The road plane of every road user (stage 4) holds the tilt where the vehicle's
        # own views cannot: seen only along one direction (a single road at the edge of the
        # view, a narrow long-range beam), the rotation about that direction moves its
        # targets by millimetres, and the fit wandered 2-3 deg off while the plane had it
        # to 0.1 (an independent recording: 3.6 deg, reported at 1.1). The plane is the
        # road's, not level: the road's own tilt comes from the vehicle's RTK altitude.
        up = start.rotation @ np.asarray(ground_normal, float)
        tilt_anchor = _rotation_between(up, _road_up(poses, start, recording.fix_sigma_m)
                                        ) @ start.rotation
        prior_mean[:2] = 0.0
        prior_sigma[:2] = math.radians(_TILT_PRIOR_DEG if tilt_prior_deg is None
                                       else tilt_prior_deg)
    profile = np.nan_to_num(prior_mean[(7 if estimate_tau else 6):])
    scatter = np.full(3, cfg.position_sigma_m)
    previous: I64 | None = None
    plane_moved: tuple[float, float] | None = None
    tau_held: float | None = None
    data: _Selected | None = None
    model: _Model | None = None
    fit: _Fit | None = None
    rounds = 0
    stride = 1
    noise_config = config
    azimuth_noise = 0.0
    elevation_noise = 0.0
    hidden_targets = 0

    def fit_round(keep: np.ndarray, every: int) -> tuple[float, float, float]:
        """Fit the gated targets (every ``every``-th by target number) from ``est``;
        returns how far it moved."""
        nonlocal data, model, fit, est, profile, scatter, noise_config, azimuth_noise
        nonlocal elevation_noise
        if every > 1:
            keep = keep & (candidates % every == 0)
        data = _select(candidates[keep], times.subset(keep), est, recording, poses, scatter,
                       noise_config, fov)
        model, x0 = linearised_at(data, est, profile, every)
        fit = _solve(model, x0)
        rot, trans, tau, profile = model.unpack(fit.x)
        moved = _change(est, rot, trans, tau)
        est = Extrinsics(rot, trans, tau)
        # the next round whitens with the azimuth noise the radar shows where that is far
        # above the configured one (each round anew: the first, gated wide, shows more)
        geometry = model.geometry(fit.x, jacobian=False)
        azimuth_noise = _azimuth_noise_deg(geometry, data)
        elevation_noise = _elevation_noise_deg(geometry, data)
        measured = {}
        if _noisy_azimuth(azimuth_noise, cfg.azimuth_sigma_deg):
            measured['azimuth_sigma_deg'] = azimuth_noise
        if _noisy_elevation(elevation_noise, cfg.elevation_sigma_deg):
            measured['elevation_sigma_deg'] = elevation_noise
        noise_config = (dataclasses.replace(config, refine=dataclasses.replace(cfg, **measured))
                        if measured else config)
        scatter = _scatter(geometry, cfg.position_sigma_m, noise_config)
        _LOG.debug('refine round %d: %d targets (every %d), %d iterations, moved %s', rounds,
                   data.index.size, every, fit.iterations, moved)
        return moved

    for rounds in range(1, cfg.max_iterations + 1):
        keep = _gate(est, candidates, track_ids, track_size, accepted, times, recording, poses,
                     config, first_round=rounds == 1, view=view)
        if rounds > 1 and keep.any():
            # not from the paper's estimate: a box metres off takes the vehicle's own
            # targets for something in front of it (a fourteenth probe's van: 0.1 -> 3 m)
            others = road_users[(road_user_tracks >= 0)
                                & ~np.isin(road_user_tracks, track_ids[keep])]
            hidden = _occluded(est, candidates[keep], times.subset(keep), recording, poses,
                               others, config)
            hidden_targets = int(hidden.sum())
            keep[keep] = ~hidden
        keep[keep] = _in_passes(times.subset(keep).t_s, config.hypotheses.pass_gap_s)
        index = candidates[keep]
        if index.size < _MIN_TARGETS:
            # Said with where the estimate came from: in the first round it is the paper's
            # stages', and a vehicle with nothing near it there means those stages agreed
            # on something else (a fourth probe's radar folded a third of the car's radial
            # velocities, and the bare count told the user nothing).
            if rounds == 1:
                where = ('where the paper\'s stages put it: they agreed on tracks that were '
                         'not the vehicle\'s (other road users by chance, or a radar whose '
                         'radial velocities fold at its unambiguous limit); check the drive '
                         'and the radar\'s velocity range')
            else:
                unchecked = config if cfg.velocity_gate_mps <= 0 else dataclasses.replace(
                    config, refine=dataclasses.replace(cfg, velocity_gate_mps=0.0))
                near = int(_gate(est, candidates, track_ids, track_size, accepted, times,
                                 recording, poses, unchecked, first_round=False,
                                 view=view).sum())
                angle, shift, clock = _change(start, est.rotation, est.translation_m,
                                              est.time_offset_s)
                why = f'radial velocities off the vehicle\'s motion: {_VELOCITY_SUSPECTS}'
                if clock > 0.05:
                    # the vehicle moved along its travel by its speed times that
                    why = ('a clock offset the drives cannot pin down (set sync.time_offset '
                           'and sync.estimate_time_offset: false if it is known), or ' + why)
                where = (f'moving as the vehicle does ({near} lie near it, but with {why})'
                         if near >= _MIN_TARGETS else
                         f'after the first round moved the estimate {shift:.1f} m, '
                         f'{math.degrees(angle):.1f} deg and the clock offset by {clock:.2f} s '
                         f'from the paper\'s stages\' (what pulls it away is most likely '
                         f'{why})')
            reason = (f'only {index.size} targets within {cfg.gate_m} m of the vehicle '
                      f'box {where}, need at least {_MIN_TARGETS}')
            if rounds == 1:
                raise InsufficientDataError('refine', reason)
            # the first round took the estimate away from the vehicle
            raise _Diverged('refine', reason, shift, math.degrees(angle))
        # Targets are numbered frame by frame, so every k-th number thins each frame evenly
        # and picks the same targets again when the gate barely changes.
        stride = max(1, index.size // _ROUND_TARGETS)
        moved = fit_round(keep, stride)
        if rounds == 1 and estimate_tau and tau_held is None:
            assert model is not None and fit is not None
            tau_sigma = _parameter_sigma(model, fit.x, 6, stride)
            if tau_sigma > _TAU_HOLD_SIGMA_S:
                # the drives cannot show the clock offset: hold it where the paper's stages
                # had it and fit this round again from their estimate. What it is uncertain
                # by counts how far the free round put it from there too: a nineteenth
                # probe's held offsets were 35 ms off at a first-round sigma of 10-13 ms.
                tau_held = math.hypot(tau_sigma, est.time_offset_s - initial.time_offset_s)
                _LOG.info('the clock offset is not observable here (sigma %.3f s after the '
                          'first round, which moved it %+.3f s): held at %+.3f s', tau_sigma,
                          est.time_offset_s - start.time_offset_s, initial.time_offset_s)
                prior_mean[6], prior_sigma[6] = float(initial.time_offset_s), _TAU_HOLD_S
                est = Extrinsics(start.rotation, start.translation_m,
                                 float(initial.time_offset_s))
                profile = np.nan_to_num(prior_mean[7:])
                scatter = np.full(3, cfg.position_sigma_m)
                moved = fit_round(keep, stride)
        plane_moved = _check_not_diverged(start, est, planar=not recording.has_elevation)
        same = previous is not None and np.array_equal(previous, index)
        previous = index
        if same and moved[0] < 1e-4 and moved[1] < 1e-3 and moved[2] < 1e-4:
            break
    final_stride = max(1, -(-int(keep.sum()) // _FINAL_TARGETS))
    if stride > final_stride:
        fit_round(keep, final_stride)
        stride = final_stride
    assert data is not None and model is not None and fit is not None
    # Covariance at the final solution, re-based so w = 0 is the reported rotation.
    # A thinned final fit stands in for all its targets: each row counts ``stride`` times
    # against the priors at full strength (as in the fit, where the priors were weighed
    # down instead), or the prior-held directions (the height) would widen by sqrt(stride).
    model, x_hat = linearised_at(data, est, profile)
    r, j, rp, jp = model.residuals(x_hat, jac=True)
    assert j is not None and jp is not None
    w = np.sqrt(_robust(r, data.index.size)[0] * stride)
    row_pass = np.concatenate([np.repeat(data.pass_id, 3), data.pass_id])
    pc = uncertainty.pass_jackknife_covariance(j * w[:, None], r * w, row_pass, jp.T @ jp)
    band = _range_bands(data)
    row_band = np.concatenate([np.repeat(band, 3), band])
    pb = uncertainty.pass_jackknife_covariance(j * w[:, None], r * w, row_band, jp.T @ jp,
                                               prior_term=False)
    halves_shift = _halves_shift(pc, jp.T @ jp)
    _, heading, velocity, _, _ = (v[data.times.inverse] for v in poses.at(
        data.times.frame_t + est.time_offset_s))
    # the agreement the covariance measures: across passes, or the headings of one or two
    # (the passes themselves stay what the halves, clock and mount checks compare). The
    # headings of one drive share its errors (its clock, how the car reflected that day),
    # so they count as no more than the passes they come from: the variance is raised by
    # their ratio, the design effect of groups correlated within a pass (without it a
    # sixty-fourth probe's two ten-metre-per-second loops were 11-16 cm off at a reported
    # 6 cm).
    groups = _jackknife_groups(data.pass_id, heading)
    pg = pc
    if not np.array_equal(groups, data.pass_id):
        pg = uncertainty.pass_jackknife_covariance(
            j * w[:, None], r * w, np.concatenate([np.repeat(groups, 3), groups]), jp.T @ jp)
        pg = dataclasses.replace(pg, covariance=pg.covariance * (pg.n_passes / pc.n_passes))
    along_share = along_boresight_share(heading, data.sqrt_weight ** 2, math.atan2(
        est.rotation[1, 0], est.rotation[0, 0]))
    # a position held at the paper's estimate (every drive along the boresight) may be the
    # whole car length off, whatever the share
    start_error = (config.vehicle.length if start_sigma_m < _START_SIGMA_M
                   else start_error_m(along_share, config))
    start_term = _start_term(pg, jp.T @ jp, config, start_sigma_m, start_error)
    covariance = uncertainty.shrink_correlations(uncertainty.combined_covariance(pg, pb),
                                                 pg.n_passes) + start_term
    cov7 = uncertainty.add_along_boresight(_pose_block(covariance, estimate_tau), est.rotation,
                                           cfg.model_sigma_along_m)
    cov7 = uncertainty.add_tilt(cov7, math.radians(cfg.model_sigma_tilt_deg))
    height_shift = _height_difference_shift(model, x_hat, j, w, jp)
    cov7 += _pose_block(np.outer(height_shift, height_shift), estimate_tau) * (
        cfg.model_sigma_height_difference_m ** 2)
    # The vehicle's mean reflection height changes with range (the roof seen from near and
    # above, road-multipath images merging far away): on our simulator by -0.17 to +0.48 m
    # from the median range to twice it, on an independent mesh car with 20 % road
    # ghosts by about 0.35 m. The fit cannot tell that from a pitch (a height growing with
    # range is a pitch wherever the targets lie ahead) or, where range follows azimuth (one
    # bend through the view), from a roll: it tilted that mesh car's radar by 0.55-1.15
    # deg at a reported 0.24 (all 11 such drives outside 2 sigma). A consider term of
    # ``refine.model_sigma_height_range_m`` per unit of relative range says so: about 2
    # deg of tilt per metre, i.e. 0.3-0.4 deg at 0.2 m.
    if recording.counters.get('yaw_rate_from_fixes'):
        # With fixes alone the yaw rate is the course over ground differentiated, and the
        # fit leans on it (``_yaw_rate_shift``): a forty-fourth probe's NavSatFix-only
        # drives sat 7-13 cm further back along the boresight than the same drives with
        # their Odometry's gyro rate (one at 2.4 sigma), and our bench's drives read
        # without their Odometry were up to 44 cm off (far_from_meridian, reported at 18).
        # The linearised move per unit of relative rate error was 0.8-7.5 m over those
        # drives (a refit with the rate 5 % high agrees with it); scaled by
        # ``_FIX_YAW_RATE_SIGMA`` every one of them lies within 1.1 sigma. With Odometry
        # the result is unchanged.
        rate_shift = _yaw_rate_shift(model, x_hat, j, w, jp)
        _LOG.debug('a yaw rate 1 %% off moves the radar by %s m',
                   np.round(0.01 * rate_shift[3:6], 3))
        cov7 += _pose_block(np.outer(rate_shift, rate_shift), estimate_tau) * (
            _FIX_YAW_RATE_SIGMA ** 2)
    rho = model.geometry(x_hat, jacobian=False)['rho']
    range_shift = _height_shift(model, x_hat, j, w, jp, rho)
    cov7 += _pose_block(np.outer(range_shift, range_shift), estimate_tau) * (
        cfg.model_sigma_height_range_m ** 2)
    if not recording.has_elevation:
        # A 2-D radar (z = 0 for every target) measures no height: its targets carry no
        # roll, pitch or altitude (the field of view found from the data is zero wide, so
        # no target gives height information above), and those come from the start and
        # second-order effects only. Say so in the covariance rather than report the
        # jackknife's agreement on values nothing measured.
        roll_sigma_deg, pitch_sigma_deg = _planar_tilt_sigmas_deg(config)
        cov7 = uncertainty.add_roll_pitch(cov7, est.rotation, math.radians(roll_sigma_deg),
                                          math.radians(pitch_sigma_deg))
        cov7[5, 5] += _PLANAR_HEIGHT_SIGMA_M ** 2
        for moved, sigma_deg in zip(tilted_translations or [],
                                    (roll_sigma_deg, pitch_sigma_deg)):
            if moved is None:
                continue
            shift = np.asarray(moved, float) - est.translation_m
            _LOG.debug('2-D radar: %.1f deg of held tilt moves the position by %s m',
                       sigma_deg, np.round(shift, 3))
            cov7[3:6, 3:6] += np.outer(shift, shift)
    model_difference = (np.zeros(3) if alternative_translation is None
                        else np.asarray(alternative_translation, float) - est.translation_m)
    cov7[3:6, 3:6] += uncertainty.model_term(model_difference, cov7[3:6, 3:6])
    # The vehicle's own position error passes one to one into the radar's, and a GNSS
    # error drifts over minutes, so the passes share it: the fixes' declared 1-sigma
    # (median over the drive; assumed from their status where they declare none) joins
    # the translation (RTK: ~2 cm, nothing; a standalone fix: metres, which the fit
    # cannot see).
    sigma_h, sigma_v = recording.pose_sigma_m
    cov7[3:6, 3:6] += np.diag([sigma_h ** 2, sigma_h ** 2, sigma_v ** 2])
    # The same error tilts and turns the fit where it differs along the drive: heights
    # off by sigma_v at one end of the vehicle positions and not at the other tilt the
    # radar by about sigma_v over their spread (RTK: 2 cm over 25 m, 0.05 deg; a
    # standalone fix's metres of wander: degrees, which the jackknife of a few passes
    # missed by half on an independent recording, 6.4 deg off at 2.9 deg 1 sigma).
    spread = _position_spread(data, poses, est.time_offset_s)
    cov7 = uncertainty.add_tilt(cov7, sigma_v / spread)
    cov7[2, 2] += (sigma_h / spread) ** 2
    halves = _halves_disagreement(halves_shift, cov7, _halves_geometry(pc, jp.T @ jp))
    if halves is not None and halves_shift is not None:
        # The result is a blend of two different poses: either could be the radar's, so the
        # whole difference joins the covariance (a fourth probe's pole turned 1.5 deg halfway
        # through: 227 cm and 0.79 deg off, reported at 44 cm and 0.18 deg).
        cov7[:6, :6] += np.outer(halves_shift[:6], halves_shift[:6])
    if tau_held is not None:
        tau_held = max(tau_held, config.sync.max_time_offset / math.sqrt(3.0))
        cov7 += tau_held ** 2 * _held_clock_shift(velocity, data.sqrt_weight ** 2)
    cov7 = _clock_sigma_capped(cov7, max(config.sync.max_time_offset,
                                         abs(est.time_offset_s)))
    diagnostics = _diagnostics(model, x_hat, r, data, pc, cov7, est, recording, poses,
                               config, fit, rounds, scatter)
    if plane_moved is not None:
        # the start's tilt and height were off (stage 4's plane): named by the pipeline
        diagnostics['plane_moved'] = {'tilt_deg': plane_moved[0],
                                      'vertical_m': plane_moved[1]}
    turn = (_turn_between_passes(pc, jp.T @ jp, cov7, data, recording, est, config)
            if halves is not None else None)
    if turn is None:
        turn = _yaw_step_between_passes(j * w[:, None], r * w, jp, rp, data, pc.n_passes,
                                        recording, est, config)
    if turn is not None:
        diagnostics['mount_turn'] = turn
    if halves is not None:
        diagnostics['halves_rotation_deg'], diagnostics['halves_translation_m'] = halves
        diagnostics['advice'] = [
            f'The first and the second half of the drives disagree by {halves[0]:.2f} deg and '
            f'{100 * halves[1]:.0f} cm, far beyond their uncertainty: the radar may have moved '
            'during the recording (a bumped or loose mount), or its clock drifted. The '
            'uncertainty includes the difference; calibrate each half on its own (cut the '
            'recording) to see which holds.', *diagnostics['advice']]
    if tau_held is not None:
        diagnostics['time_offset_held_sigma_s'] = tau_held
    elif estimate_tau:
        diagnostics['pass_time_offsets'] = _pass_time_offsets(pc, data, est.time_offset_s)
        # the clock scan again, now at the fitted rotation and position (see ``refine``)
        rescan = _rescan_time_offset(est, candidates, times, recording, poses, config)
        if rescan is not None:
            diagnostics['clock_rescan_s'] = rescan
    diagnostics['cost_per_target'] = float(
        (_robust(r, data.index.size)[1] + float(rp @ rp)) / max(data.index.size, 1))
    if drift is not None and drift.step_s:
        first_s = _radar_clock_s(recording, config, int(recording.frame_stamps_ns[0]))
        diagnostics['clock_step_ms'] = 1e3 * drift.step_s
        diagnostics['clock_step_sigma_ms'] = 1e3 * drift.sigma
        diagnostics['clock_step_at_s'] = drift.step_at_s - first_s
        before = est.time_offset_s - drift.step_s * float(drift.reference_s >= drift.step_at_s)
        diagnostics['advice'] = [
            f'The radar\'s clock offset against the vehicle\'s stepped by '
            f'{1000 * drift.step_s:+.0f} ms (+-{1000 * drift.sigma:.0f}) between two passes, '
            f'about {drift.step_at_s - first_s:.0f} s after the radar\'s first frame: '
            f'{1000 * before:+.0f} ms before, {1000 * (before + drift.step_s):+.0f} ms after '
            '(a clock set by NTP or after a reboot, or a driver restarted to stamp otherwise). '
            'The fit took both (the clock offset reported is the one of the side with the '
            'more passes). Synchronise the radar\'s clock (PTP or NTP) before recording.',
            *diagnostics['advice']]
    elif drift is not None:
        diagnostics['clock_drift_ppm'] = 1e6 * drift.rate
        diagnostics['clock_drift_sigma_ppm'] = 1e6 * drift.sigma
        span = [est.time_offset_s + drift.rate * (_radar_clock_s(recording, config, stamp)
                                                  - drift.reference_s)
                for stamp in recording.frame_stamps_ns[[0, -1]]]
        diagnostics['time_offset_span_s'] = span
        diagnostics['advice'] = [
            f'The radar\'s clock drifts {1e6 * drift.rate:+.0f} ppm against the vehicle\'s '
            f'(+-{1e6 * drift.sigma:.0f}): its offset went from {1000 * span[0]:+.0f} ms at '
            f'the start of the recording to {1000 * span[1]:+.0f} ms at the end, pass by '
            'pass, and the fit followed it as a straight line (the clock offset reported is '
            'the one at the middle). Synchronise the radar\'s clock (PTP or NTP), or stamp '
            'its scans with a synchronised host clock.', *diagnostics['advice']]
    # the vehicle's targets near its box the last round left out as hidden (``_occluded``)
    diagnostics['hidden_targets'] = hidden_targets
    if cfg.azimuth_scale_sigma == 0.0 and recording.has_elevation:
        # (where the user fits a scale of the azimuths, that is theirs to judge; a 2-D
        # radar's unknown pitch turns its lines of sight by the pitch times the sine of
        # their azimuth, an odd error of the same shape: a forty-ninth probe's, pitched 7.8
        # deg and held level, read -0.44 deg at the edges)
        diagnostics['azimuth_bias'] = _azimuth_bias(model.geometry(x_hat, jacobian=False),
                                                    data)
    if recording.has_elevation and ground_normal is not None:
        diagnostics['tilt_from_plane_deg'] = math.degrees(float(np.linalg.norm(
            Rotation.from_matrix(tilt_anchor @ est.rotation.T).as_rotvec()[:2])))
        geometry = model.geometry(x_hat, jacobian=False)
        world = geometry['world']
        axis, centre, diagnostics['line_spread_m'] = _line_axis(world, data)
        diagnostics['line_axis'] = axis
        diagnostics['target_offset_m'] = centre - est.translation_m
        diagnostics['lane_separation_m'] = _lane_separation(world, geometry['vel'], axis, data)
    if _noisy_azimuth(azimuth_noise, cfg.azimuth_sigma_deg):
        diagnostics['azimuth_noise_deg'] = azimuth_noise
        diagnostics['advice'] = [
            f'The radial velocities show about {azimuth_noise:.1f} deg of azimuth noise '
            f'(refine.azimuth_sigma_deg is {cfg.azimuth_sigma_deg:g}); the fit used it. At '
            'that noise the lines of sight the radial velocities are predicted along are '
            'noisy too, which biases the position along the boresight by decimetres '
            '(measured on independent generators: 0.3-0.7 m forward at 2 deg and 0.1-0.3 m '
            'at 1 deg on one, 0.2-0.5 m back at 1.5-2 deg on another, within the reported '
            'uncertainty about as often as not). '
            'Set refine.azimuth_sigma_deg to what the radar\'s datasheet says; where it is '
            'this noisy, trust the position along the boresight less than its sigma says.',
            *diagnostics['advice']]
    if _noisy_elevation(elevation_noise, cfg.elevation_sigma_deg):
        diagnostics['elevation_noise_deg'] = elevation_noise
        diagnostics['advice'] = [
            f'The heights of the vehicle\'s targets show about {elevation_noise:.1f} deg of '
            f'elevation noise (refine.elevation_sigma_deg is {cfg.elevation_sigma_deg:g}): '
            'their scatter grows with range as that noise does. The fit weighed the heights '
            'by it; at the configured noise it had trusted the far targets\' heights too much '
            'and put the radar decimetres low (an independent generator at 2.5-3 deg: '
            '0.5-0.7 m, outside its uncertainty). Set refine.elevation_sigma_deg to what the '
            'radar\'s datasheet says.', *diagnostics['advice']]
    if model.n_par > model.i_end:
        scale = float(x_hat[model.i_end])
        scale_sigma = float(math.sqrt(max(pc.covariance[model.i_end, model.i_end], 0.0)))
        diagnostics['azimuth_scale'] = scale
        diagnostics['azimuth_scale_sigma'] = scale_sigma
        if abs(scale) >= _AZIMUTH_SCALE_NOTE and abs(scale) >= 3.0 * scale_sigma:
            diagnostics['advice'] = [
                f'The radar\'s azimuths are {"stretched" if scale > 0 else "compressed"} by '
                f'{100 * abs(scale):.1f} % (+-{100 * scale_sigma:.2f}): '
                f'{math.degrees(abs(scale) * math.radians(45.0)):.2f} deg at 45 deg, an error '
                'of its own angle calibration (or of its mount on the pole)? The fit took it out '
                '(unmodelled, it moves the radar along its boresight by about that share of the '
                'range). Check the radar\'s angle calibration.', *diagnostics['advice']]
    diagnostics.update({
        'range_slopes_m': [float(v) for v in profile[
            reflection.n_coefficients(harmonics):model.i_end - model.i_prof]],
        'depth_reference_range_m': model.r_ref,
        'elevation_view_deg': [math.degrees(fov[0]), math.degrees(fov[1])],
        'height_used_fraction': float(np.mean(data.vertical_ok)),
        'reflection_height_prior_m': list(reflection_height_prior(config)),
        'range_band_t_scale': pb.t_scale,
        # position under the other range law of the profile minus this one (zero unchecked)
        'model_difference_m': [float(v) for v in model_difference],
        # the two jackknifes behind the reported covariance (7x7 blocks, as cov7)
        'covariance_passes': _pose_block(pc.covariance, estimate_tau),
        'covariance_bands': _pose_block(pb.covariance, estimate_tau),
        # the passes' disagreement alone, without the priors (``evaluate``'s agreement)
        'covariance_pass_scatter': _pose_block(uncertainty.pass_scatter(pc), estimate_tau),
        # what the start's own error adds where the data leave the position to it
        'covariance_start_term': _pose_block(start_term, estimate_tau),
    })
    return Refinement(extrinsics=est, covariance=cov7, n_targets=int(data.index.size),
                      n_passes=pc.n_passes,
                      reflection_profile=np.asarray(profile[:reflection.n_coefficients(harmonics)],
                                                    float),
                      diagnostics=diagnostics)
