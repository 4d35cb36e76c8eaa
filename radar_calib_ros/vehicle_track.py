"""The calibration vehicle's track from its fixes and odometry, and the checks of that stream.

``build_vehicle_track`` turns the NavSatFixes and Odometry a recording holds into the
``VehicleTrack`` (positions in the local metric frame, heading, velocity, yaw rate) that
every pipeline stage pairs the radar with. Most of its work is judging the pose stream
before trusting it: fixes that lag the Odometry or scatter along the travel, RTK lost for
float without a word, orientations and twists in the wrong convention or frame, a heading
that is offset or wanders, a speed off by a scale, a vehicle that reverses. Each check
names what it found in the recording's counters.

Kept apart from ``recording.py`` because none of it concerns how samples are stored,
copied or dropped: it takes plain arrays and returns the track, and it is by far the
larger part of turning messages into a ``Recording``.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import interpolate, ndimage
from scipy.spatial.transform import Rotation

from radar_calib_ros.core._angles import circular_mean, interp_angle, wrap_angle
from radar_calib_ros.errors import ConfigError, InsufficientDataError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.types import F64, I64, OdomSample, VehicleTrack

_LOG = logging.getLogger(__name__)

#: Largest median horizontal 1-sigma [m] that fixes which all say NavSatStatus 0 may declare
#: to be taken as RTK (see ``Recording.fix_status_unreported``): RTK fixed declares 1-3 cm,
#: float a decimetre or more, a standalone receiver metres.
RTK_DECLARED_SIGMA_M = 0.1


def build_vehicle_track(fix_stamps_ns: I64, fix_rows: F64, odometry: Sequence[OdomSample], *,
                        epsg: int, odom_is_utm: bool, min_heading_speed: float,
                        counters: Counter[str]) -> tuple[LocalFrame, VehicleTrack]:
    """The local metric frame and the vehicle's track in it, from the fixes where there are
    any, else from Odometry positions in UTM (``odom_is_utm``).

    Parameters
    ----------
    fix_stamps_ns : (n,) int64 header stamps of the kept fixes, in the order received
    fix_rows : (n, 7) the same fixes as (stamp, lat, lon, alt, status, sigma horizontal,
        sigma vertical), float64
    odometry : the Odometry samples, sorted by stamp
    epsg, odom_is_utm, min_heading_speed : ``world.epsg``, ``vehicle.odom_is_utm``,
        ``vehicle.min_heading_speed``
    counters : the recording's counters: read for what the fixes' intake dropped, and
        given what the checks of the pose stream find

    Raises
    ------
    InsufficientDataError
        No usable vehicle pose.
    ConfigError
        ``odom_is_utm`` without ``epsg``, or Odometry positions that cannot be UTM.
    """
    has_fixes = fix_stamps_ns.size > 0
    odoms = list(odometry)
    status_rtk = False
    if has_fixes:
        # Of fixes sharing a stamp the first received is kept (a stable sort by stamp
        # alone): a receiver at 20 Hz whose stamps have 0.1 s resolution gives pairs
        # 0.05 s apart under one stamp, and sorted by latitude as well, the later of a
        # pair was kept on every pass heading south or west, a lag that turned with the
        # heading (an eleventh probe: 25-30 cm along the boresight, outside 2 sigma).
        stamps = np.asarray(fix_stamps_ns, np.int64)
        order = np.argsort(stamps, kind='stable')
        fixes = fix_rows[order]
        stamps, unique = np.unique(stamps[order], return_index=True)
        shared = _shared_stamps(fixes, unique)
        if shared:
            counters['fixes_stamp_shared'] = shared
        fixes = fixes[unique]
        counters.update(_unaugmented_stretches(stamps, fixes[:, 4]))
        degraded = _degraded_fixes(fixes[:, 4], fixes[:, 5])
        if degraded.any():
            counters['fixes_degraded_dropped'] = int(degraded.sum())
            counters['fixes_unaugmented_dropped'] = int(
                np.count_nonzero(degraded & (fixes[:, 4] == 0)))
            counters['fixes_sbas_dropped'] = int(
                np.count_nonzero(degraded & (fixes[:, 4] == 1)))
            stamps, fixes = stamps[~degraded], fixes[~degraded]
        stale = _stale_repeats(stamps, fixes)
        if stale.any():
            counters['fixes_stale_dropped'] = int(stale.sum())
            stamps, fixes = stamps[~stale], fixes[~stale]
        declared = fixes[np.isfinite(fixes[:, 5]), 5]
        status_rtk = bool(np.mean(fixes[:, 4] >= 2) > 0.5 or (
            np.all(fixes[:, 4] == 0) and declared.size > 0
            and np.median(declared) <= RTK_DECLARED_SIGMA_M))
        lat, lon, alt = fixes[:, 1], fixes[:, 2], fixes[:, 3]
        frame = LocalFrame.at(lat[0], lon[0], epsg)
        positions = frame.geodetic_to_local(lat, lon, alt)
        lattice = _lattice_m(lat, lon)
        if lattice is not None:
            counters['fix_lattice_east_mm'] = round(1000.0 * lattice[0])
            counters['fix_lattice_north_mm'] = round(1000.0 * lattice[1])
            if not odoms:
                # each fix off by up to half a step, uniformly (1/sqrt(12) of it, 1 sigma);
                # with an Odometry its twist and yaw carry the motion between the steps (a
                # sixty-first probe: 0.02-0.18 m with one, 0.2-1.6 m without)
                counters['fix_lattice_sigma_mm'] = round(
                    1000.0 * math.hypot(*lattice) / math.sqrt(12.0))
    elif odoms and odom_is_utm:
        if not epsg:
            raise ConfigError('vehicle.odom_is_utm needs world.epsg (the UTM zone of the '
                              'Odometry positions)')
        stamps, unique = np.unique(np.array([o.stamp_ns for o in odoms], np.int64),
                                   return_index=True)
        utm = np.array([odoms[i].position_m for i in unique], np.float64)
        _check_utm(utm, epsg)
        probe = LocalFrame(0.0, 0.0, epsg)
        lat0, lon0, _ = probe.utm_to_geodetic(utm[:1])
        frame = LocalFrame(float(lat0[0]), float(lon0[0]), epsg)
        positions = frame.utm_to_local(utm)
        lat, lon, _ = frame.utm_to_geodetic(utm)
    else:
        no_altitude = counters.get('fixes_altitude_nan', 0)
        no_fix = counters.get('fixes_no_fix', 0)
        reason = 'no valid NavSatFix'
        if no_altitude:
            reason += (f' ({no_altitude} of {counters["fixes"]} have a latitude and '
                       'longitude but no altitude (NaN): the radar\'s height needs the '
                       'vehicle\'s)')
        if no_fix and no_fix == counters.get('fixes', 0):
            reason += (f' (all {no_fix} report no fix, status -1: the receiver had no '
                       'solution during the whole recording)')
        if odoms:
            reason += ' (Odometry positions are used only with vehicle.odom_is_utm)'
        raise InsufficientDataError('read', f'no vehicle pose: {reason}')
    if stamps.size < 2:
        raise InsufficientDataError('read', f'only {stamps.size} vehicle pose(s)')
    t = (stamps - stamps[0]) * 1e-9
    raw_positions = positions
    if has_fixes and status_rtk:
        jitter = _stamp_jitter(t, positions)
        if jitter is not None:
            positions, along_m, spread_s = jitter
            counters['fix_stamp_jitter_ms'] = int(round(1000.0 * spread_s))
            counters['fix_stamp_jitter_cm'] = int(round(100.0 * along_m))
            _LOG.warning('the fixes scatter by %.0f cm along their travel only (%.0f ms of '
                         'their stamps): smoothed', 100.0 * along_m, 1000.0 * spread_s)
    if odoms:
        # A twist no road vehicle drives is a driver's glitch, not a velocity: a sixtieth
        # probe's -13 500 m/s once a pass (8 of 17 784 samples) read as a twist speed 26 %
        # off, 'rescaled' every twist, and the calibration was refused for radial velocities
        # that were not the vehicle's.
        glitch = [not math.hypot(*o.velocity_body_mps[:2]) <= TWIST_MAX_MPS for o in odoms]
        if any(glitch):
            counters['odometry_twist_glitches'] = sum(glitch)
            _LOG.warning('%d Odometry samples carry a twist beyond %.0f m/s: left out',
                         sum(glitch), TWIST_MAX_MPS)
            odoms = [o for o, bad in zip(odoms, glitch) if not bad]
    o_stamps = np.array([o.stamp_ns for o in odoms], np.int64)
    if odoms and has_fixes:
        if o_stamps.max() < stamps[0] or o_stamps.min() > stamps[-1]:
            # Not one Odometry stamp within the fixes' span: the two are on different
            # clocks (a node without use_sim_time stamps wall-clock time beside a sim's),
            # and interpolated at the fixes' times the Odometry is its first or last
            # sample throughout. Left out, and said.
            apart_s = float(np.median(o_stamps) - np.median(stamps)) * 1e-9
            counters['odometry_other_clock_s'] = int(round(apart_s))
            _LOG.warning('the Odometry stamps lie %.1f s from the NavSatFix stamps and '
                         'never overlap them: the Odometry is left out', apart_s)
            odoms = []
    if odoms:
        q = np.array([o.quaternion_xyzw for o in odoms], np.float64)
        yaw_true = np.arctan2(2.0 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]),
                              1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2))
        v_body = np.array([o.velocity_body_mps for o in odoms], np.float64)
        v_level = _level_twist(q, yaw_true, v_body)
        rate = np.array([o.yaw_rate_rps for o in odoms], np.float64)
        to = (o_stamps - stamps[0]) * 1e-9
        # over +-0.2 s; unchanged by a lag correction, which moves every fix alike
        measured = _position_velocities(t, positions)
        if has_fixes:
            offset_s = _stream_offset(t, np.hypot(measured[:, 0], measured[:, 1]), to,
                                      np.hypot(v_level[:, 0], v_level[:, 1]))
            if offset_s is not None:
                # onto the Odometry's clock, as a lag below: one clock for the poses, and
                # the radar's against it is the fit's (or, whole seconds off, named there)
                counters['fix_stream_offset_ds'] = int(round(10.0 * offset_s))
                _LOG.warning('the NavSatFix stamps lie %+.1f s from the Odometry\'s: the '
                             'fixes are taken on the Odometry\'s clock', offset_s)
                stamps = stamps - int(round(offset_s * 1e9))
                to = to + offset_s
            against = _fix_lag(t, measured[:, :2], to, yaw_true, v_level, rate)
            lag_s = against.lag_s
            if against.lever_arm_m is not None:
                forward, left = against.lever_arm_m
                counters['fix_lever_arm_forward_cm'] = int(round(100.0 * forward))
                counters['fix_lever_arm_left_cm'] = int(round(100.0 * left))
                _LOG.warning('the NavSatFix positions describe a point %+.2f m forward and '
                             '%+.2f m left of the Odometry\'s', forward, left)
                # The vehicle is placed by the fixes: its velocity must be that of their
                # point, which in a turn moves by omega x l against the Odometry's (0.7 m/s
                # for a roof antenna 1.5 m ahead at 0.47 rad/s: radial velocities that far
                # off in every turn)
                v_level = v_level.copy()
                v_level[:, 0] -= rate * left
                v_level[:, 1] += rate * forward
            if lag_s or offset_s is not None:
                # the fix stamped t shows where the vehicle was at t - lag (the whole lag,
                # the stream offset's included: a radar on the fixes' clock is -lag away)
                counters['fix_lag_ms'] = int(round(1000.0 * (lag_s + (offset_s or 0.0))))
            if lag_s:
                _LOG.warning('the NavSatFix stamps lag the Odometry\'s by %.0f ms: the '
                             'fixes are taken at their stamp minus that', 1000.0 * lag_s)
                stamps = stamps - int(round(lag_s * 1e9))
                to = to + lag_s
        yaw_true_at = interp_angle(t, to, yaw_true)
        # The checks differentiate over +-1 s, not the +-0.2 s the velocities use: a
        # standalone fix (metres of noise, 10 Hz) gives ~7 m/s of noise over 0.4 s and
        # would condemn a good twist, ~1.4 m/s over 2 s; a zero or mis-framed twist, or a
        # wrong heading, still misses by the speed.
        coarse = _position_velocities(t, positions[:, :2], _TWIST_CHECK_SPAN_S)
        vx = np.interp(t, to, v_level[:, 0])
        vy = np.interp(t, to, v_level[:, 1])
        yaw, offset = _checked_orientation(t, coarse, measured, positions, yaw_true_at, lat,
                                           lon, frame, min_heading_speed,
                                           counters, vx, rtk=status_rtk)
        tilt_known = _tilted(q)
        if tilt_known and counters.get('odometry_orientation_replaced'):
            # An orientation that does not describe the travel (an INS's ECEF attitude,
            # another frame's) does not describe the tilt either: turned by it, the twist
            # lost 13 % of its speed into the vertical and was 'rescaled' (a tenth probe:
            # 2.8 m and 5 deg off). The body twist is taken as level, graded by the fixes.
            tilt_known = False
            v_level = v_body
            vx = np.interp(t, to, v_level[:, 0])
            vy = np.interp(t, to, v_level[:, 1])
        if not tilt_known:
            # a heading-only orientation on a grade: the fixes' climb tells the tilt
            level = _grade_cosine(t, positions, np.hypot(vx, vy), declared_fix_sigma(fix_rows))
            vx, vy = vx * level, vy * level
        yaw_rate = np.interp(t, to, rate)
        twist_world = _turned(np.column_stack([vx, vy]), yaw)
        twist_turn = 0.0
        if offset:
            # an INS turned on its mount gives its twist in its own frame too: then the
            # heading as given turns it into the world, not the corrected one
            own_frame = _turned(np.column_stack([vx, vy]), yaw + offset)
            if _twist_mismatch(own_frame, coarse) < _twist_mismatch(twist_world, coarse):
                twist_world, twist_turn = own_frame, offset
        velocities = _checked_twist(t, positions, measured, coarse, twist_world,
                                    np.column_stack([vx, vy]), counters, yaw_rate)
        if _slow_fixes(t, to):
            held = offset
            if counters.get('odometry_heading_wander_cdeg'):
                # the wander followed at the fixes, at the Odometry's own stamps
                wander = wrap_angle(frame.true_yaw_to_local(yaw_true_at, lat, lon)
                                    - offset - yaw)
                held = offset + np.interp(to, t, wander)
            dense = _odometry_between_fixes(
                t, positions, yaw, velocities, yaw_rate, to,
                _odometry_heading(frame, yaw_true, np.interp(to, t, lat),
                                  np.interp(to, t, lon), held, counters, t, to,
                                  positions, v_level),
                v_level, rate, twist_turn, counters)
            if dense is not None:
                t_dense, positions, yaw, velocities, yaw_rate = dense
                stamps = stamps[0] + np.round(t_dense * 1e9).astype(np.int64)
    else:
        velocities = _fix_velocities(t, positions)
        yaw, yaw_rate = _course_over_ground(t, velocities, min_heading_speed,
                                            counters, positions)
        # the rate is then the course differentiated: the final fit's covariance allows for
        # its error (``core/refine.py``, ``_FIX_YAW_RATE_SIGMA``)
        counters['yaw_rate_from_fixes'] = 1
    # Positions from the Odometry alone (vehicle.odom_is_utm) come from the same GNSS
    # behind an INS: an RTK fix lost for float and regained moves them as it moves fixes
    # (a fifteenth probe: 0.30-0.87 m off against 0.01-0.09 m with the same jumps in
    # NavSatFix, where they were found), so they are searched alike.
    from_odometry = not has_fixes and bool(odoms)
    jittered = bool(counters.get('fix_stamp_jitter_ms'))
    if (status_rtk or from_odometry) and stamps.size == t.size:
        # (not where the Odometry's samples were added between slow fixes)
        twist = (velocities if odoms and not counters.get('odometry_twist_replaced')
                 else None)
        # jittered fixes are smoothed by now: the jumps are searched in the fixes
        # as stamped, across the travel only
        steps = _fix_steps(t, raw_positions if jittered else positions, twist,
                           across_only=jittered)
        if steps.times_s.size and from_odometry:
            counters['fix_jumps_in_odometry'] = 1
        if steps.times_s.size:
            counters['fix_jumps'] = int(steps.times_s.size)
            counters['fix_jump_max_cm'] = int(round(100.0 * steps.sizes_m.max()))
            counters['fix_jump_median_cm'] = int(round(
                100.0 * np.median(steps.sizes_m)))
            counters['fix_jumps_first_s'] = int(steps.times_s[0])
            counters['fix_jumps_last_s'] = int(steps.times_s[-1])
        if steps.dropped.any():
            keep = ~steps.dropped
            counters['odometry_silent_float_dropped' if from_odometry else
                     'fixes_silent_float_dropped'] = int(steps.dropped.sum())
            if steps.by_noise:
                counters['silent_float_by_noise'] = 1
                if not steps.times_s.size:
                    counters['fix_noisy_first_s'] = int(t[steps.dropped][0])
                    counters['fix_noisy_last_s'] = int(t[steps.dropped][-1])
            stamps, positions, yaw = stamps[keep], positions[keep], np.asarray(yaw)[keep]
            velocities, yaw_rate = velocities[keep], np.asarray(yaw_rate)[keep]
    if has_fixes and not odoms:
        # after the search for RTK-float jumps, which needs the fixes as they came
        splined = _spline_between_fixes((stamps - stamps[0]) * 1e-9, positions, counters)
        if splined is not None:
            t_dense, positions, velocities = splined
            stamps = stamps[0] + np.round(t_dense * 1e9).astype(np.int64)
            # (what the course finds of slow and stopped stretches was counted at the fixes)
            yaw, yaw_rate = _course_over_ground(t_dense, velocities, min_heading_speed,
                                                Counter(), positions)
    vehicle = VehicleTrack(stamps, positions, np.asarray(yaw, float), velocities,
                           np.asarray(yaw_rate, float))
    return frame, vehicle


def on_centre_line(vehicle: VehicleTrack, ref_left_m: float) -> VehicleTrack:
    """The track of the point of the vehicle's centre line beside its reference point, where
    that lies ``ref_left_m`` to the left of it (``vehicle.ref_left``); unchanged at 0.

    Why: the box, the reflection profile's mirror symmetry and the paper's figures all
    take the reference point on the centre line; a GNSS antenna 0.2-0.4 m off it (a
    fifty-third probe's) moved the radar 0.4-1.1 m, and no parameter could say so. The
    velocity is the rigid body's at that point (the yaw rate times the offset, along the
    heading)."""
    if ref_left_m == 0.0:
        return vehicle
    c, s = np.cos(vehicle.yaw_rad), np.sin(vehicle.yaw_rad)
    zero = np.zeros_like(c)
    positions = vehicle.positions_m - ref_left_m * np.column_stack([-s, c, zero])
    velocities = vehicle.velocities_mps + (ref_left_m * vehicle.yaw_rate_rps)[:, None] * (
        np.column_stack([c, s, zero]))
    return VehicleTrack(vehicle.stamps_ns, positions, vehicle.yaw_rad, velocities,
                        vehicle.yaw_rate_rps)


def declared_fix_sigma(fix_rows: F64) -> tuple[float, float] | None:
    """Median declared 1-sigma of the fixes ``fix_rows`` (as ``build_vehicle_track`` takes
    them; horizontal, vertical), None if none; the degraded ones the track leaves out
    (``_degraded_fixes``) not counted."""
    if fix_rows.shape[0] == 0:
        return None
    sigma = np.array(fix_rows[:, 5:7], np.float64)
    status = np.array(fix_rows[:, 4], np.float64)
    known = np.all(np.isfinite(sigma), axis=1) & ~_degraded_fixes(status, sigma[:, 0])
    if not known.any():
        return None
    h, v = np.median(sigma[known], axis=0)
    return float(h), float(v)


#: Fixes slower than this (median interval) [s] are bridged by the Odometry's motion between
#: them; intervals longer than ``_BRIDGED_INTERVAL_S`` are not (an outage stays a gap).
_SLOW_FIX_INTERVAL_S = 0.3
_BRIDGED_INTERVAL_S = 2.5


#: Least jump of RTK fix positions between consecutive fixes taken as a fix lost or regained
#: [m], and in robust sigmas of the jump estimates (they scatter by ~1 cm at 20 Hz).
_FIX_STEP_MIN_M = 0.1
_FIX_STEP_SIGMAS = 6.0
#: Largest misfit of a window's parabola [m], or in medians of all windows', that still
#: measures a jump (a fix's noise is 1-2 cm).
_FIX_STEP_MISFIT_M = 0.03
_FIX_STEP_MISFIT_RATIO = 3.0
#: Largest misfit [m] of a window paired with one that fits for a jump to be measured
#: (RTK float's 5-10 cm of noise; a window bent by a stop of a simulated car, more).
_FIX_STEP_NOISY_M = 0.2
#: Largest change of velocity across a jump [m/s] (its two sides' parabolas at its middle):
#: a car brakes by less within a fix interval, a dead stop of a simulated one by more.
_FIX_STEP_RATE_MPS = 1.5
#: Fixes on each side of an interval its jump is measured from: at least this many, over
#: at least this span [s]; fixes slower than ``_FIX_STEP_MAX_INTERVAL_S`` are not searched
#: (a vehicle's own motion over seconds is no straight line).
_FIX_STEP_MIN_FIXES = 4
_FIX_STEP_MAX_FIXES = 16
_FIX_STEP_SPAN_S = 0.5
_FIX_STEP_MAX_INTERVAL_S = 0.2
#: Fixes this close to a jump [s] are left out with a float stretch (their velocities,
#: differenced over +-0.2 s, straddle the jump).
_FIX_STEP_MARGIN_S = 0.5
#: Largest share of the drive taken as RTK float between jumps: more, and which side of the
#: jumps is the fixed one is no longer clear.
_SILENT_FLOAT_MAX_SHARE = 0.4


@dataclass(frozen=True)
class FixSteps:
    """Jumps of the fix positions that the vehicle's motion does not explain.

    times_s : (j,) midpoints of the intervals where they happen [s, the fixes' time];
    sizes_m : (j,) horizontal size [m]; dropped : (n,) fixes taken as RTK float and left out;
    by_noise : whether those were told by their noise rather than by the jumps' alternation.
    """

    times_s: F64
    sizes_m: F64
    dropped: np.ndarray
    by_noise: bool = False


def _fix_steps(t: F64, positions: F64, twist: F64 | None,
               across_only: bool = False) -> FixSteps:
    """The jumps of fixes (n,) sorted by time, and the stretches between them taken as RTK
    float.

    Why: a receiver that loses its RTK fix for RTK float wanders by decimetres and jumps
    back when the fix returns; some drivers say so in neither the status nor the
    covariance (an eleventh probe: 23 cm along the boresight, no word). The jumps show: a
    parabola fitted to the fixes just before an interval and one fitted just after disagree
    at its middle by the jump, against ~1 cm of noise. With the Odometry's twist the
    vehicle's travel is taken out first (``twist``, world frame), so that only the jump and
    the twist's slow drift remain. The stretches between jumps alternate fixed and float;
    the float ones are taken as those that make the shorter share of the drive, and are
    dropped only while that share is clearly the smaller (``_SILENT_FLOAT_MAX_SHARE``). A
    jump missed (a float stretch that began where its error was small) flips the
    alternation after it; where that leaves no clearly smaller share, nothing is dropped,
    only said (on the eleventh probe's recordings about 97 % of the dropped fixes were
    float). Float noisier than the fix is told by its noise instead (``_noisy_runs``).
    ``across_only``: fixes whose stamps scatter (``_stamp_jitter``) scatter along
    the travel by decimetres, which would hide any jump there; across it they stay exact,
    so only the jumps' part across the travel is measured (a false fix of 0.7-1 m over a
    pass, missed in a sixteenth probe's jittered fixes: 0.13-0.78 m off).
    """
    none = FixSteps(np.empty(0), np.empty(0), np.zeros(t.size, bool))
    if t.size < 2:
        return none
    interval = float(np.median(np.diff(t)))
    if interval <= 0.0 or interval > _FIX_STEP_MAX_INTERVAL_S:
        return none
    # (capped: a 100 Hz stream's half-second windows would cost memory, not accuracy)
    k = min(max(_FIX_STEP_MIN_FIXES, math.ceil(_FIX_STEP_SPAN_S / interval)),
            _FIX_STEP_MAX_FIXES)
    if t.size < 2 * k + 1:
        return none
    q = positions[:, :2] if twist is None else positions[:, :2] - _travelled(t, twist)
    # a parabola through each window: constant acceleration (braking, a turn) leaves none
    # of itself in the jump, as a line would (4-5 cm at 3-8 m/s^2)
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    t_mean = tw.mean(axis=1)
    qw, design, coef = _window_quadratics(t, q, k, t_mean)
    misfit = np.sqrt(np.mean(np.sum((qw - design @ coef) ** 2, axis=2), axis=1))
    if across_only:
        # the travel's direction in each window from the fixes themselves (their scatter
        # is along it); what is measured is what lies across it
        _, _, path = _window_quadratics(t, positions[:, :2], k, t_mean)
        normal, _ = _across_travel(path[:, 1])
        misfit = np.sqrt(np.mean(np.einsum('wkd,wd->wk', qw - design @ coef, normal) ** 2,
                                 axis=1))
    # interval i (fixes i, i+1): the window ending at fix i against the one starting at i+1
    i = np.arange(k - 1, t.size - k)
    before, after = i - k + 1, i + 1
    mid = 0.5 * (t[i] + t[i + 1])

    def at_mid(w: I64) -> F64:
        d = (mid - t_mean[w])[:, None]
        return coef[w, 0] + coef[w, 1] * d + coef[w, 2] * d ** 2

    def rate_at_mid(w: I64) -> F64:
        return coef[w, 1] + 2.0 * coef[w, 2] * (mid - t_mean[w])[:, None]

    jump = at_mid(after) - at_mid(before)
    rate_change = rate_at_mid(after) - rate_at_mid(before)
    if across_only:
        across = normal[before] + normal[after]
        across /= np.maximum(np.hypot(across[:, 0], across[:, 1]), 1e-9)[:, None]
        jump = across * np.einsum('ij,ij->i', jump, across)[:, None]
        rate_change = across * np.einsum('ij,ij->i', rate_change, across)[:, None]
    # a jump of the position leaves the velocity as it was
    steady = np.hypot(*rate_change.T) <= _FIX_STEP_RATE_MPS
    # A window across a gap (an outage, fixes already left out) measures no jump, nor one
    # that no parabola fits, nor a pair whose velocities differ: a step of the velocity (a
    # simulator's car stopping dead) bends the windows that straddle it, while either side
    # of a jump is smooth and at the same speed.
    span = 2.0 * k * interval
    compact = tw[:, -1] - tw[:, 0] <= span
    fits = misfit <= max(_FIX_STEP_MISFIT_M, _FIX_STEP_MISFIT_RATIO * float(np.median(misfit)))
    # RTK float is noisier than the fix (5-10 cm), so the windows inside it fit no parabola
    # to the fixed stretches' standard, and its edges went unmeasured: a thirty-third
    # probe's 1 m float stretches, 5-10 cm noisy, went unnoticed in 5 of 6 drives (0.13-0.21
    # deg, 8-39 cm). A window that fits paired with one that fits within
    # ``_FIX_STEP_NOISY_M`` measures the jump too, against a limit raised to as many of its
    # misfits as the fixed ones' spread counts.
    noisy = misfit <= _FIX_STEP_NOISY_M
    edge = (fits[before] & noisy[after]) | (noisy[before] & fits[after])
    whole = (compact[before] & compact[after]
             & (t[i + 1] - t[i] <= 3.0 * interval) & steady)
    clean = whole & fits[before] & fits[after]
    whole &= edge
    if clean.sum() < 10:
        return none
    size = np.where(whole, np.hypot(jump[:, 0], jump[:, 1]), 0.0)
    spread = 1.4826 * np.median(np.abs(jump[clean] - np.median(jump[clean], axis=0)), axis=0)
    # Stamp jitter too small for _stamp_jitter to smooth (a few ms) still places each fix
    # off along the travel by speed x jitter, so the jumps' noise grows with speed; one
    # limit from the whole drive's spread (set by its slow and stopped stretches) took the
    # fastest stretch's scatter for a jump (a thirty-third probe: 3-4 ms of jitter, 21-27
    # cm 'jumps' at 12 m/s in 3 of 7 drives, a third of each dropped as RTK float). The
    # speed-proportional part of the spread along the travel is added at each interval's
    # speed: none without jitter, and an RTK float step (decimetres to metres) still shows.
    velocity = (rate_at_mid(before) + rate_at_mid(after)) * 0.5 if twist is None else (
        0.5 * (twist[i, :2] + twist[i + 1, :2]))
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    limit = _FIX_STEP_SIGMAS * np.sqrt(float(spread @ spread)
                                       + (speed * _jump_jitter_s(jump, velocity, speed,
                                                                 clean)) ** 2)
    limit = np.maximum(_FIX_STEP_MIN_M, limit)
    limit = np.where(clean, limit, np.maximum(
        limit, _FIX_STEP_SIGMAS * np.maximum(misfit[before], misfit[after])))
    # one jump shows in the k intervals on either side too: its own is the largest
    peak = ndimage.maximum_filter1d(size, 2 * k + 1, mode='constant') == size
    at = np.flatnonzero((size > limit) & peak)
    if at.size == 0:
        # Float can begin and end where its wander is small, with no jump to find, and
        # still scatter by decimetres in between (a seventy-second probe: 20 s stretches
        # 10 cm noisy and 0.4 m wandering, reported as RTK fixed, tilted a radar by 3-5 deg
        # through the vehicle's height, unflagged). Its noise alone tells it then.
        noisy = _noisy_without_jumps(t, tw, compact, positions, interval)
        if noisy.any() and noisy.mean() <= _SILENT_FLOAT_MAX_SHARE:
            return FixSteps(np.empty(0), np.empty(0), noisy, by_noise=True)
        return none
    times, sizes = mid[at], size[at]
    near = np.abs(t[:, None] - times[None, :]).min(axis=1) <= _FIX_STEP_MARGIN_S
    # Float that is noisy shows as such too: runs of windows no parabola fits. Where there
    # are any, they are the float, not the alternation below (a jump missed at one end of
    # a 10 cm noisy stretch flipped it: the drive before it was dropped instead); a
    # receiver's float is noisy throughout or not at all.
    noisy_float = _noisy_runs(t, tw, ~fits & compact, k)
    # stretches between jumps, alternately fixed and float: the float ones the shorter share
    bounds = np.concatenate([[t[0]], times, [t[-1]]])
    lengths = np.diff(bounds)
    odd = lengths[1::2].sum()
    parity = 1 if odd <= lengths[0::2].sum() else 0
    share = lengths[parity::2].sum() / max(t[-1] - t[0], 1e-9)
    dropped = (np.searchsorted(times, t) % 2) == parity
    by_noise = bool(noisy_float.any())
    if by_noise:
        dropped, share = noisy_float, float(noisy_float.mean())
    if share > _SILENT_FLOAT_MAX_SHARE:
        return FixSteps(times, sizes, np.zeros(t.size, bool))
    return FixSteps(times, sizes, dropped | near, by_noise)


#: Shortest run of windows no parabola fits taken as RTK float by its noise [s].
_NOISY_FLOAT_MIN_S = 3.0


#: Least scatter [m] of a window's fixes about their parabola, across the travel and in
#: height, taken as RTK float by its noise where no jump was found (an RTK fix scatters by
#: 1-2 cm horizontally and 2-3 cm in height; float by 5-30 cm), and in medians of the
#: drive's windows (``_FIX_STEP_MISFIT_RATIO``).
_NOISY_FLOAT_MIN_M = 0.06
#: Least speed [m/s] at which a window's travel gives the direction across it.
_NOISY_FLOAT_MOVING_MPS = 0.5
#: Span [s] over which the windows' scatter is averaged.
_NOISY_FLOAT_SMOOTH_S = 1.0


def _noisy_without_jumps(t: F64, tw: F64, compact: np.ndarray, positions: F64,
                         interval: float) -> np.ndarray:
    """(n,) the fixes in runs of ``_NOISY_FLOAT_MIN_S`` or more whose windows (``tw``, (w, k)
    times; ``compact``: those spanning no gap, as ``_fix_steps`` takes them) scatter about
    a parabola by ``_NOISY_FLOAT_MIN_M`` and ``_FIX_STEP_MISFIT_RATIO`` times the drive's
    median; ``interval`` the fixes' [s].

    Why across the travel and in height only: stamps a few milliseconds off scatter fixes
    along the travel by speed times that (a thirty-third probe's 3-4 ms: 4-5 cm at 12 m/s,
    more than the drive's median), and neither across it nor in height, where float is as
    noisy as anywhere (more in height)."""
    if positions.shape[1] < 3 or not compact.any():
        return np.zeros(t.size, bool)
    k = tw.shape[1]
    vw, design, coef = _window_quadratics(t, positions[:, :3], k, tw.mean(axis=1))
    residual = vw - design @ coef
    normal, speed = _across_travel(coef[:, 1, :2])
    across = np.where((speed >= _NOISY_FLOAT_MOVING_MPS)[:, None],
                      np.einsum('wkd,wd->wk', residual[..., :2], normal),
                      np.hypot(residual[..., 0], residual[..., 1]) / math.sqrt(2.0))
    # over a second of windows: one window's handful of fixes scatters by chance, and 10 cm
    # float let a fifth of them fit, splitting its runs
    spread = ndimage.uniform_filter1d(np.mean(across ** 2 + residual[..., 2] ** 2, axis=1),
                                      max(1, round(_NOISY_FLOAT_SMOOTH_S / interval)),
                                      mode='nearest')
    misfit = np.sqrt(np.maximum(spread, 0.0))
    limit = max(_NOISY_FLOAT_MIN_M, _FIX_STEP_MISFIT_RATIO * float(np.median(misfit[compact])))
    noisy = _noisy_runs(t, tw, (misfit > limit) & compact, k)
    # the second's average blurs a stretch's edges by half of it either way
    margin = round(_FIX_STEP_MARGIN_S / interval)
    return ndimage.binary_dilation(noisy, np.ones(2 * margin + 1, bool)) if noisy.any() else noisy


def _across_travel(rate: F64) -> tuple[F64, F64]:
    """((w, 2) unit horizontal normals to windows' travel, (w,) their speeds [m/s]) from
    the rates (w, 2) of their parabolas (``_window_quadratics``)."""
    speed = np.hypot(rate[:, 0], rate[:, 1])
    return rate[:, ::-1] * np.array([-1.0, 1.0]) / np.maximum(speed, 1e-9)[:, None], speed


def _noisy_runs(t: F64, tw: F64, unfit: np.ndarray, k: int) -> np.ndarray:
    """(n,) the fixes inside runs of consecutive windows (``unfit``, (w,)) that last at
    least ``_NOISY_FLOAT_MIN_S``: fixes noisier than the rest for seconds."""
    out = np.zeros(t.size, bool)
    if not unfit.any():
        return out
    # (a float window that happens to fit does not split its run)
    unfit = ndimage.binary_closing(unfit, structure=np.ones(k, bool))
    edges = np.flatnonzero(np.diff(np.concatenate([[0], unfit.view(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2]):
        if tw[stop - 1, -1] - tw[start, 0] >= _NOISY_FLOAT_MIN_S:
            out[start:stop - 1 + k] = True
    return out


#: Fixes are smoothed when their scatter from a quadratic over +-``_JITTER_HALF_SPAN_S``
#: along the travel (moving faster than ``_JITTER_MIN_SPEED_MPS``) is at least
#: ``_JITTER_ANISOTROPY`` times that across it, and amounts to ``_JITTER_MIN_S`` of their
#: stamps (1 sigma, robust). (At 10 ms a sixteenth probe's 20-40 ms delays, 7 ms of
#: spread, went unnamed, and their 20-30 cm of scatter along the travel were taken for
#: 144 RTK-float jumps; over 917 bench and probe recordings, 5 ms fires on none that 10
#: ms did not, but on these.)
_JITTER_HALF_SPAN_S = 1.0
#: (at most this many fixes either side: a 100 Hz stream's 201-fix windows cost seconds,
#: and 41 fixes average its scatter as well as 41 over +-1 s at 20 Hz)
_JITTER_MAX_HALF_FIXES = 20
_JITTER_MIN_SPEED_MPS = 3.0
_JITTER_ANISOTROPY = 3.0
_JITTER_MIN_S = 0.005
_JITTER_MIN_SAMPLES = 50


def _jump_jitter_s(jump: F64, velocity: F64, speed: F64, whole: np.ndarray) -> float:
    """The part of the jumps' (w, 2) scatter along the travel that grows with the speed
    (``velocity`` (w, 2), ``speed`` (w,)), as a time [s]: the robust spread of the jump
    along the travel per unit speed, less that across it (the fixes' own noise, alike in
    every direction); 0 where too few intervals are moving."""
    moving = whole & (speed > _JITTER_MIN_SPEED_MPS)
    if int(moving.sum()) < _JITTER_MIN_SAMPLES:
        return 0.0
    along, across = _along_across(jump[moving], velocity[moving] / speed[moving, None])
    along, across = along / speed[moving], across / speed[moving]
    return math.sqrt(max(0.0, _robust_sigma(along) ** 2 - _robust_sigma(across) ** 2))


def _along_across(vectors: F64, unit: F64) -> tuple[F64, F64]:
    """Horizontal ``vectors`` (n, 2) split along the unit directions ``unit`` (n, 2) of the
    travel and across them (positive to the left)."""
    along = np.einsum('ij,ij->i', vectors, unit)
    across = vectors[:, 1] * unit[:, 0] - vectors[:, 0] * unit[:, 1]
    return along, across


def _robust_sigma(x: F64) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _stamp_jitter(t: F64, positions: F64) -> tuple[F64, float, float] | None:
    """(positions smoothed, scatter along the travel [m], its spread in time [s]) where the
    fixes' stamps scatter, else None.

    Why: a driver that stamps each fix when it arrives rather than at the receiver's epoch
    (nmea_navsat_driver's default) adds the serial link's varying delay to every stamp. The
    positions are exact but each is placed up to a metre along the travel from where the
    vehicle was at its stamp (0.15 s at 12 m/s), while across the travel they lie on a
    smooth path to the millimetre; RTK float or a standalone fix errs in every direction
    alike. A fifteenth probe's fixes stamped 20-150 ms late: the radar 0.31-0.47 m off
    along its boresight with the Odometry, and with fixes alone 1-2 m high and 1.6-3.2 deg
    pitched (2.6 sigma), the vehicle recognised in 40 % of its frames, and the only word a
    wrong one (RTK float). A quadratic in time over +-``_JITTER_HALF_SPAN_S`` around each
    fix (the travel's constant acceleration; a turn's cubic term leaves the centre value
    alone in a symmetric window) gives the path; where the scatter is along it only, the
    fixes are replaced by it. The delay's mean is a latency like any other, found against
    the Odometry (``_fix_lag``) or by the final fit's clock offset.
    """
    n = t.size
    if n < 2:
        return None
    interval = float(np.median(np.diff(t)))
    if interval <= 0.0 or interval > _FIX_STEP_MAX_INTERVAL_S:
        return None
    m = min(max(2, int(round(_JITTER_HALF_SPAN_S / interval))), _JITTER_MAX_HALF_FIXES)
    k = 2 * m + 1
    if n < 4 * k:
        return None
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    _, _, coef = _window_quadratics(t, positions, k, tw[:, m])
    centre = np.arange(m, n - m)
    # a window across an outage measures nothing
    whole = tw[:, -1] - tw[:, 0] <= 2.0 * (k - 1) * interval
    value, rate = coef[:, 0, :], coef[:, 1, :2]
    speed = np.hypot(rate[:, 0], rate[:, 1])
    moving = whole & (speed > _JITTER_MIN_SPEED_MPS)
    if int(moving.sum()) < _JITTER_MIN_SAMPLES:
        return None
    heading = rate[moving] / speed[moving, None]
    residual = positions[centre[moving], :2] - value[moving, :2]
    along, across = _along_across(residual, heading)
    sigma_along, sigma_across = _robust_sigma(along), _robust_sigma(across)
    spread_s = _robust_sigma(along / speed[moving])
    if spread_s < _JITTER_MIN_S or sigma_along < _JITTER_ANISOTROPY * sigma_across:
        return None
    smoothed = np.array(positions, float, copy=True)
    smoothed[centre[whole]] = value[whole]
    return smoothed, sigma_along, spread_s


def _window_quadratics(t: F64, values: F64, k: int, origin: F64
                       ) -> tuple[F64, F64, F64]:
    """A quadratic in time fitted (least squares) to each run of ``k`` consecutive samples
    of ``values`` (n, d) at times ``t`` (n,), time counted from the window's ``origin``
    (n - k + 1,): the windows' values (w, k, d), design (w, k, 3) and coefficients
    (w, 3, d) (value, rate, half the acceleration at the origin)."""
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    vw = np.lib.stride_tricks.sliding_window_view(values, k, axis=0).transpose(0, 2, 1)
    dt = tw - origin[:, None]
    design = np.stack([np.ones_like(dt), dt, dt ** 2], axis=2)
    gram = np.einsum('wki,wkj->wij', design, design)
    # a window of samples at fewer than three times fits no quadratic (a stream whose
    # stamps were moved onto one instant): the identity keeps it solvable
    gram[(np.diff(tw, axis=1) != 0.0).sum(axis=1) < 2] += np.eye(3)
    coef = np.linalg.solve(gram, np.einsum('wki,wkd->wid', design, vw))
    return vw, design, coef


#: A run of fixes repeating one position that spans less than this [s] is a slower
#: receiver's position republished (5 Hz positions in 20 Hz messages); a longer one is the
#: vehicle standing (a receiver's static hold), kept.
_STALE_RUN_S = 1.0


#: A lattice of the fixes' latitudes or longitudes at least this far apart on the ground
#: [m] is named (``_lattice_m``); rounded decimals tried, from the coarsest.
_LATTICE_MIN_M = 0.05
_LATTICE_DECIMALS = (4, 5, 6)
#: metres of a degree of latitude (and of longitude at the equator), for a step's size
_M_PER_DEG = 111_320.0


def _lattice_step_deg(values: F64) -> float:
    """The step [deg] of the lattice ``values`` lie on, 0 for none: every one a 32-bit
    float (the step: the spacing of 32-bit floats at the largest), or every one rounded to
    4, 5 or 6 decimals. Only these: a receiver's noise puts fixes on neither, and a
    noise-free simulated drive at one speed, its fixes evenly spaced, is no lattice."""
    distinct = np.unique(values[np.isfinite(values)])
    # (values apart by less than a step lie on no lattice of it: a drive along a parallel
    # has its latitudes within 1e-11 deg of one value, which 4 decimals 'round')
    if distinct.size < 3:
        return 0.0
    gap = float(np.diff(distinct).min())
    if np.array_equal(distinct.astype(np.float32).astype(np.float64), distinct):
        return float(np.spacing(np.float32(np.max(np.abs(distinct)))))
    for decimals in _LATTICE_DECIMALS:
        scaled = distinct * 10.0 ** decimals
        if gap >= 0.5 * 10.0 ** -decimals and np.all(np.abs(scaled - np.round(scaled)) < 1e-4):
            return 10.0 ** -decimals
    return 0.0


def _lattice_m(lat: F64, lon: F64) -> tuple[float, float] | None:
    """The steps (east, north) [m] of the lattice the fixes' longitudes and latitudes lie
    on (``_lattice_step_deg``), where either is ``_LATTICE_MIN_M`` or more, else None.

    Why: latitude and longitude passed through 32-bit floats on the way (a bridge, a
    message type of its own) or rounded to a few decimals (a CSV, a log) lie on a lattice:
    at 151.2 E a float32 longitude steps by 1.41 m. A sixty-first probe's NavSatFix-only
    drives at Sydney and Singapore, 124 distinct longitudes in 11 145 fixes, came out
    0.2-1.6 m and up to 2.6 deg off, three of eight outside 2 sigma (8 sigma at worst),
    with not a word; the same drives unrounded, 0.02-0.16 m."""
    east = _lattice_step_deg(lon) * _M_PER_DEG * math.cos(math.radians(float(np.median(lat))))
    north = _lattice_step_deg(lat) * _M_PER_DEG
    if max(east, north) < _LATTICE_MIN_M:
        return None
    return east, north


def _stale_repeats(stamps: I64, fixes: F64) -> np.ndarray:
    """(n,) fixes (sorted by stamp) that repeat the position of the fix before them to the
    digit, within a run shorter than ``_STALE_RUN_S``.

    Why: a driver that republishes a receiver's last position at its own, faster rate
    stamps each copy anew, so the vehicle seems to stand, then leap, four times a fifth
    of a second: a thirty-third probe's were smoothed as fixes stamped on arrival (78 ms
    of 'jitter') and a 72 ms lag was found that was not there. The first of each run
    holds the position at its stamp; the copies are left out."""
    if stamps.size < 2:
        return np.zeros(stamps.size, bool)
    same = np.all(fixes[1:, 1:4] == fixes[:-1, 1:4], axis=1)
    repeat = np.concatenate([[False], same])
    # each run of copies with the fix it copies: its first and last stamps
    run = np.cumsum(~repeat) - 1
    first = np.flatnonzero(~repeat)
    last = np.append(first[1:], stamps.size) - 1
    span_s = (stamps[last] - stamps[first]) * 1e-9
    return repeat & (span_s[run] < _STALE_RUN_S)


def _shared_stamps(fixes: F64, first: I64) -> int:
    """How many fixes (rows sorted by stamp, ``first`` the first row of each stamp) share
    their stamp with an earlier fix of another position (over 1 mm apart: a copy of the
    same fix, a topic recorded twice, is no loss)."""
    owner = np.repeat(first, np.diff(np.append(first, len(fixes))))
    moved = np.abs(fixes[:, 1:3] - fixes[owner, 1:3]).max(axis=1) > 1e-8
    return int(np.count_nonzero(moved))


def _slow_fixes(t: F64, to: F64) -> bool:
    """True when the fixes come slower than ``_SLOW_FIX_INTERVAL_S`` and the Odometry at
    least twice as fast within their span."""
    if t.size < 3:
        return False
    interval = float(np.median(np.diff(t)))
    inside = to[(to > t[0]) & (to < t[-1])]
    return (interval >= _SLOW_FIX_INTERVAL_S and inside.size >= 2 * t.size
            and float(np.median(np.diff(inside))) <= 0.5 * interval)


#: Largest median turn of a replaced Odometry heading from the course over ground, once its
#: constant offset is taken off, for it still to give the heading between fixes [rad].
_TURNED_MAP_SPREAD_RAD = math.radians(3.0)


def _dead_reckoned(times: F64, to: F64, twist: F64) -> tuple[F64, F64]:
    """(velocity, path from the first of ``times``): the world twist (sampled at ``to``) at
    ``times`` and its integral by trapezoids."""
    v = np.column_stack([np.interp(times, to, twist[:, i]) for i in range(2)])
    return v, _travelled(times, v)


def _travelled(times: F64, v: F64) -> F64:
    """(n, 2) path from the first of ``times``: horizontal velocities ``v`` at ``times``
    integrated by trapezoids."""
    return np.vstack([np.zeros((1, 2)), np.cumsum(
        0.5 * (v[1:, :2] + v[:-1, :2]) * np.diff(times)[:, None], axis=0)])


def _odometry_heading(frame: LocalFrame, yaw_true: F64, lat: F64, lon: F64,
                      offset: float | F64,
                      counters: Counter[str], t: F64, to: F64, positions: F64, v_level: F64
                      ) -> F64 | None:
    """The Odometry's heading at its own stamps as ``_checked_orientation`` read it (local
    grid, its offset taken off); where that replaced it by the course over ground, the
    Odometry's heading turned by the constant turn of its map frame when the fixes'
    ``positions`` (at ``t``) show one, else None.

    Why the second: a map frame turned against east (an HD map's, or a simulator's) is
    further off than ``_checked_orientation`` takes for an offset, but between fixes a
    second apart its turns are all there is (a probe's Odometry in a map frame turned 37 deg,
    beside 1 Hz fixes)."""
    if counters.get('odometry_orientation_compass'):
        return frame.true_yaw_to_local(np.pi / 2.0 - yaw_true, lat, lon)
    local = frame.true_yaw_to_local(yaw_true, lat, lon)
    if not counters.get('odometry_orientation_replaced'):
        return local - offset
    # the turn of the map frame: between consecutive fixes, the direction of their chord
    # against that of the twist integrated with the heading as given (exact for any path;
    # the course over ground at slow fixes is not the heading where the curvature changes)
    twist = _turned(v_level, local)
    times = np.union1d(t, to[(to > t[0]) & (to < t[-1])])
    _, travelled = _dead_reckoned(times, to, twist)
    reckoned = np.diff(travelled[np.searchsorted(times, t)], axis=0)
    chord = np.diff(positions[:, :2], axis=0)
    used = ((np.diff(t) <= _BRIDGED_INTERVAL_S)
            & (np.hypot(*chord.T) > _TWIST_CHECK_SPEED_MPS * np.diff(t)))
    if int(used.sum()) < _ORIENTATION_SAMPLES:
        return None
    turn = wrap_angle(np.arctan2(reckoned[used, 1], reckoned[used, 0])
                      - np.arctan2(chord[used, 1], chord[used, 0]))
    offset = float(circular_mean(turn))
    if float(np.median(np.abs(wrap_angle(turn - offset)))) > _TURNED_MAP_SPREAD_RAD:
        return None
    return local - offset


def _odometry_between_fixes(t: F64, positions: F64, yaw: F64, velocities: F64, yaw_rate: F64,
                            to: F64, heading: F64 | None, v_level: F64, rate: F64,
                            twist_turn: float, counters: Counter[str]
                            ) -> tuple[F64, F64, F64, F64, F64] | None:
    """(t, positions, yaw, velocities, yaw_rate) with the Odometry's samples added between
    fixes no more than ``_BRIDGED_INTERVAL_S`` apart, or None where its heading or twist
    was found unusable.

    Why: GNSS receivers give 1-2 Hz by default beside a 50-100 Hz INS. Linear between 1 Hz
    fixes, a car turning at 0.3 rad/s and 10 m/s is off its arc by up to 37 cm, and a gap
    of a second is more than ``sync.max_pose_gap`` allows (a probe's 1 Hz fixes were
    refused, and with the gap raised gave 19 cm against 11 cm at 10 Hz). Between two fixes
    the path is the Odometry's twist integrated from the first, its misclosure at the
    second spread linearly over the interval: the fixes stay exact, and a twist off by a
    scale, a grade or a small turn errs only by how much that error varies within one
    interval. Height is interpolated between the fixes (the twist's is not trusted).
    """
    if heading is None or counters.get('odometry_twist_replaced'):
        return None
    if counters.get('odometry_twist_in_parent_frame'):
        twist = v_level[:, :2]
    else:
        twist = _turned(v_level, heading + twist_turn)
    interval = np.diff(t)
    k = np.searchsorted(t, to, side='right') - 1
    inside = (k >= 0) & (k < t.size - 1)
    inside[inside] &= (to[inside] > t[k[inside]]) & (interval[k[inside]] <= _BRIDGED_INTERVAL_S)
    if not inside.any():
        return None
    added = np.flatnonzero(inside)
    times = np.concatenate([t, to[added]])
    order = np.argsort(times, kind='stable')
    times = times[order]
    is_fix = order < t.size
    v, travelled = _dead_reckoned(times, to, twist)
    misclosure = positions[:, :2] - travelled[is_fix]
    seg = np.clip(np.searchsorted(t, times, side='right') - 1, 0, t.size - 2)
    share = (times - t[seg]) / interval[seg]
    slope = (misclosure[seg + 1] - misclosure[seg]) / interval[seg][:, None]
    xy = travelled + misclosure[seg] + share[:, None] * (misclosure[seg + 1] - misclosure[seg])
    z = positions[seg, 2] + share * (positions[seg + 1, 2] - positions[seg, 2])
    vz = (positions[seg + 1, 2] - positions[seg, 2]) / interval[seg]
    out_positions = np.column_stack([xy, z])
    out_velocities = np.column_stack([v + slope, vz])
    out_yaw = np.empty(times.size)
    out_rate = np.empty(times.size)
    odom = ~is_fix
    out_yaw[odom] = heading[added]
    out_rate[odom] = rate[added]
    # at a fix the Odometry's heading too (a course over ground it replaced errs most at
    # the ends of the drive); one with no bridged interval on either side keeps what the
    # fixes alone gave
    bridged = np.zeros(t.size + 1, bool)
    bridged[1:-1] = interval <= _BRIDGED_INTERVAL_S
    alone = ~(bridged[:-1] | bridged[1:])
    fix_rows = np.flatnonzero(is_fix)
    out_yaw[is_fix] = np.where(alone, yaw, interp_angle(t, to, heading))
    out_rate[is_fix] = np.where(alone, yaw_rate, np.interp(t, to, rate))
    out_positions[fix_rows] = positions
    # at a fix the misclosure's slope of a bridged interval beside it (an outage's one
    # trapezoid over seconds is no velocity)
    fix_seg = np.where(bridged[1:], np.arange(t.size), np.arange(t.size) - 1)[~alone]
    out_velocities[fix_rows[~alone], :2] = (
        v[fix_rows[~alone]] + (misclosure[fix_seg + 1] - misclosure[fix_seg])
        / interval[fix_seg][:, None])
    out_velocities[fix_rows[~alone], 2] = ((positions[fix_seg + 1, 2] - positions[fix_seg, 2])
                                           / interval[fix_seg])
    out_velocities[fix_rows[alone]] = velocities[alone]
    # sample stamps equal to a fix's would be duplicates once rounded to nanoseconds
    keep = np.ones(times.size, bool)
    keep[1:] = np.diff(np.round(times * 1e9)) > 0
    counters['poses_bridged_by_odometry'] = int(added.size)
    _LOG.info('the fixes come every %.2f s: the Odometry\'s %d samples between them give the '
              'path there', float(np.median(interval)), added.size)
    return (times[keep], out_positions[keep], out_yaw[keep], out_velocities[keep],
            out_rate[keep])


#: Fixes alone slower than ``_SLOW_FIX_INTERVAL_S`` get samples this far apart [s] between
#: them on a cubic spline through every run of at least ``_SPLINE_MIN_FIXES`` fixes no more
#: than ``_BRIDGED_INTERVAL_S`` apart (see ``_spline_between_fixes``).
_SPLINE_STEP_S = 0.1
_SPLINE_MIN_FIXES = 4


def _spline_between_fixes(t: F64, positions: F64, counters: Counter[str]
                          ) -> tuple[F64, F64, F64] | None:
    """(t, positions, velocities) of slow fixes alone (no Odometry) with samples every
    ``_SPLINE_STEP_S`` between them on a cubic spline through each run of fixes no more than
    ``_BRIDGED_INTERVAL_S`` apart, the velocities its derivative; None where the fixes come
    faster than ``_SLOW_FIX_INTERVAL_S`` or no run is long enough.

    Why: many rovers give 1 Hz by default. Linear between them, a car turning on a 14 m
    radius at 10 m/s cuts the arc by up to 0.9 m (R omega^2 dt^2 / 8), and its velocity,
    differenced over the two seconds either side, by as much; a forty-sixth probe's 1 Hz
    fixes alone, with sync.max_pose_gap raised as the refusal advised, came out 40-89 cm off
    along the boresight, where 5 Hz gave 3 cm. A cubic spline through the same fixes errs by
    about (5/384) R omega^4 dt^4 on such an arc: 4 cm. It passes through every fix (RTK's
    centimetres over a second are a few cm/s of velocity), and a run of fewer fixes, or a
    longer gap (an outage), is left as it is.
    """
    if t.size < _SPLINE_MIN_FIXES:
        return None
    interval = np.diff(t)
    if float(np.median(interval)) < _SLOW_FIX_INTERVAL_S:
        return None
    breaks = np.flatnonzero(interval > _BRIDGED_INTERVAL_S) + 1
    times, out_positions, out_velocities = [], [], []
    added = 0
    for run in np.split(np.arange(t.size), breaks):
        if run.size < _SPLINE_MIN_FIXES:
            times.append(t[run])
            out_positions.append(positions[run])
            out_velocities.append(_fix_velocities(t[run], positions[run])
                                  if run.size > 1 else np.zeros((run.size, 3)))
            continue
        spline = interpolate.CubicSpline(t[run], positions[run], axis=0)
        # the fixes' own times and a sample every step between them, none within a
        # hundredth of a step of a fix (a duplicate once rounded to nanoseconds)
        between = np.arange(t[run[0]], t[run[-1]], _SPLINE_STEP_S)
        after = np.clip(np.searchsorted(t[run], between), 1, run.size - 1)
        nearest = np.minimum(np.abs(between - t[run][after - 1]),
                             np.abs(t[run][after] - between))
        between = between[nearest > 0.01 * _SPLINE_STEP_S]
        grid = np.sort(np.concatenate([t[run], between]))
        added += between.size
        times.append(grid)
        out_positions.append(spline(grid))
        out_velocities.append(spline(grid, 1))
    if not added:
        return None
    counters['poses_splined_between_fixes'] = added
    counters['fix_interval_ms'] = int(round(1000.0 * float(np.median(interval))))
    _LOG.info('the fixes come every %.2f s with no Odometry: %d samples between them on a '
              'cubic spline', float(np.median(interval)), added)
    return (np.concatenate(times), np.concatenate(out_positions),
            np.concatenate(out_velocities))


#: Where UTM coordinates can lie [m]: eastings within a zone (166-834 km at the equator,
#: the zone's overlap allowed for), northings from the equator (or its false northing).
_UTM_EASTING_M = (100_000.0, 900_000.0)
_UTM_NORTHING_M = (0.0, 10_000_000.0)


def _check_utm(utm: F64, epsg: int) -> None:
    """Raise ConfigError when Odometry positions taken as UTM (``vehicle.odom_is_utm``)
    cannot be: a local map frame's metres (Autoware's map is one MGRS grid square's, 0-100
    km) were placed 5000 km off at exit 0 with an 8 cm sigma (a tenth probe)."""
    east, north = np.median(utm[:, 0]), np.median(utm[:, 1])
    if not (_UTM_EASTING_M[0] <= east <= _UTM_EASTING_M[1]
            and _UTM_NORTHING_M[0] <= north <= _UTM_NORTHING_M[1]):
        raise ConfigError(
            f'vehicle.odom_is_utm: the Odometry positions (median E {east:.1f} m, N '
            f'{north:.1f} m) cannot be UTM coordinates of EPSG:{epsg} (eastings lie within '
            '100-900 km, northings within 0-10 000 km): they are in a local map frame (an '
            'MGRS grid square\'s, as Autoware\'s map is?). Record the NavSatFix, or publish '
            'the Odometry in UTM.')


def _turned(vectors: F64, angle_rad: F64 | float) -> F64:
    """(n, 2): the horizontal part of ``vectors`` (n, >=2) turned counter-clockwise by
    ``angle_rad`` (one angle, or one per row): a body-frame twist into the world by the
    heading."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.column_stack([c * vectors[:, 0] - s * vectors[:, 1],
                            s * vectors[:, 0] + c * vectors[:, 1]])


def _unaugmented_stretches(stamps_ns: I64, status: F64) -> dict[str, int]:
    """Runs of consecutive standalone fixes (status 0) among fixes sorted by stamp: how
    many, and the longest [ms]. An RTK receiver that drops to a float or standalone
    solution for a while gives such runs; their error reaches the calibration unseen by
    the fit."""
    edges = np.diff(np.concatenate([[0], (status == 0).astype(np.int64), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    if starts.size == 0:
        return {}
    longest = int(np.max(stamps_ns[ends] - stamps_ns[starts])) // 1_000_000
    return {'fixes_unaugmented_stretches': int(starts.size),
            'fixes_unaugmented_longest_ms': longest}


#: A fix declaring more than this many times the horizontal sigma of the drive's best
#: quarter (and more than _DEGRADED_SIGMA_M) is degraded.
_DEGRADED_SIGMA_RATIO = 5.0
_DEGRADED_SIGMA_M = 0.1


#: Share of RTK fixes from which the others are left out. Not half: a drive 57 % in RTK
#: float (status 1) kept every fix, reported at SBAS's 0.6 m, 1.2 m and 4 deg for a
#: 0.33 m result (an eleventh probe), where the 43 % in RTK fixed held four minutes of
#: passes. A quarter of a calibration drive is still minutes; a drive with less RTK is
#: calibrated on what it has, and says so.
_DEGRADED_MIN_SHARE = 0.25


def _degraded_fixes(status: F64, sigma_h: F64) -> np.ndarray:
    """(n,) True for the fixes of a mostly-RTK drive where the receiver lost its solution:
    status 0 (no augmentation) while at least a quarter of the fixes are augmented, or a
    declared horizontal sigma far above that of the drive's best quarter. Their decimetres
    to metres would pass into the radar's position one to one (an independent recording
    with three 20 s RTK dropouts: 2.4 -> 15.4 cm); left out, their radar frames have no pose
    and wait for the passes with a good one. A drive with less than a quarter in RTK keeps
    everything (and a note says so): nothing better is there."""
    # SBAS (status 1) is decimetres to a metre as well: in an RTK drive it is a lost
    # solution too (or RTK float); in a drive mostly without RTK only the standalone fixes
    # are worse
    rtk = status >= 2
    augmented = status > 0
    if rtk.mean() >= _DEGRADED_MIN_SHARE:
        degraded = ~rtk
    elif augmented.mean() >= _DEGRADED_MIN_SHARE:
        degraded = ~augmented
    else:
        return np.zeros(status.size, bool)
    known = np.isfinite(sigma_h)
    if known.sum() >= 2:
        best = float(np.quantile(sigma_h[known], _DEGRADED_MIN_SHARE))
        limit = max(_DEGRADED_SIGMA_M, _DEGRADED_SIGMA_RATIO * best)
        degraded |= known & (sigma_h > limit)
    # at least two fixes must stay
    return degraded if (~degraded).sum() >= 2 else np.zeros(status.size, bool)


#: Median disagreement of the Odometry heading with the course over ground above which the
#: orientation is not the vehicle's [rad], and the least moving samples to judge it on.
_ORIENTATION_TOLERANCE_RAD = math.radians(20.0)
_ORIENTATION_SAMPLES = 10
#: Forward speed of the twist below which the vehicle is taken to reverse [m/s].
_REVERSE_TWIST_MPS = 0.5


def _checked_orientation(t: F64, coarse: F64, measured: F64, positions: F64, yaw_true: F64,
                         lat: F64, lon: F64, frame: LocalFrame, min_speed: float,
                         counters: Counter[str], forward_mps: F64 | None = None,
                         rtk: bool = False) -> tuple[F64, float]:
    """(n,) local-grid heading from the Odometry orientation where it describes the
    vehicle's travel (less its constant offset, returned too: ``_heading_offset``), else
    from a compass-convention reading of it, else from the course over ground.

    Why: the heading turns the vehicle's box and its body-frame twist. Drivers in the field
    write a compass heading (clockwise from north) into the quaternion, or leave it the
    identity; both were taken at their word, the twist then failed its check and was blamed
    (fourth probe: 22 cm and a 66 cm sigma). Where the vehicle moves (speed above
    ``min_speed``, over +-1 s) the course over ground is its heading: forwards, or backwards
    where the twist's forward speed ``forward_mps`` says the vehicle reversed (a shuttle
    that backs through the view half the time had its right orientation condemned and
    faced the wrong way: 3 m off, an independent probe). The orientation is judged against
    both readings of the course, with and without those reversals (a twist in the wrong
    frame has no meaningful sign), and the better one counts. ``coarse`` and ``measured``
    are the positions' velocities over +-1 s and +-0.2 s. With ``rtk`` fixes, whose course
    is good to a tenth of a degree, a slowly wandering offset is followed too
    (``_heading_wander``).
    """
    yaw = frame.true_yaw_to_local(yaw_true, lat, lon)
    moving = np.hypot(coarse[:, 0], coarse[:, 1]) > max(min_speed, 2.0)
    if int(moving.sum()) < _ORIENTATION_SAMPLES:
        return yaw, 0.0
    course = np.arctan2(coarse[moving, 1], coarse[moving, 0])
    courses = [course]
    if forward_mps is not None:
        backwards = np.asarray(forward_mps, float)[moving] < -_REVERSE_TWIST_MPS
        if backwards.any():
            courses.append(course + np.pi * backwards)

    def disagreement(heading: F64) -> float:
        return min(_median_turn(heading[moving], c) for c in courses)

    as_given = disagreement(yaw)
    if as_given <= _ORIENTATION_TOLERANCE_RAD:
        # straight stretches only where it matters: turning, a reference point ahead of the
        # rear axle moves off the car's heading (1-3 deg at the centre of a car in a
        # junction turn)
        # the heading's change over +-0.5 s, not between samples: an INS heading with
        # 0.1-0.2 deg of noise at 100 Hz turns by tens of degrees a second from one sample
        # to the next, every sample read as turning and no straight stretch left (a
        # seventy-second and a seventy-third probe's 0.3-1.0 deg heading biases were then
        # judged over turns, from 1 deg, and went into the radar's yaw at 2.4-8.9 sigma)
        rate = _finite_difference(t, np.unwrap(yaw), _STRAIGHT_RATE_HALF_SPAN_S)
        speed = np.hypot(coarse[moving, 0], coarse[moving, 1])
        turning = ((np.abs(rate[moving]) >= _STRAIGHT_RATE_RPS)
                   | (np.abs(rate[moving]) >= _STRAIGHT_CURVATURE_PER_M * speed))
        # the course is taken over +-_TWIST_CHECK_SPAN_S: straight where all of it is
        t_moving = t[moving]
        if t_moving.size > 1:
            step = float(np.median(np.diff(t_moving)))
            width = 2 * int(math.ceil(_TWIST_CHECK_SPAN_S / max(step, 1e-3))) + 1
            turning = ndimage.maximum_filter1d(turning.astype(np.int8), width) > 0
        straight = ~turning
        best = min(courses, key=lambda c: _median_turn(yaw[moving], c))
        settled = (_heading_settled(t[moving][straight],
                                    wrap_angle(yaw[moving] - best)[straight]) if rtk else None)
        steady = straight
        if settled is not None:
            # the offset is the INS's alignment once it has converged: the start-up's tail
            # would be taken for one (0.4 deg 'throughout' of a 15 deg start)
            counters['odometry_heading_settled_s'] = max(1, int(round(settled - t[0])))
            steady = straight & (t[moving] >= settled)
        offset = _heading_offset(yaw[moving], courses, counters, t[moving], steady)
        _warn_heading_offset(offset, frame, lat, lon)
        wander = (_heading_wander(t[moving][straight],
                                  wrap_angle(yaw[moving] - offset - best)[straight], t,
                                  counters) if rtk else None)
        if wander is not None:
            return yaw - offset - wander, offset
        return yaw - offset, offset
    compass = frame.true_yaw_to_local(np.pi / 2.0 - yaw_true, lat, lon)
    if disagreement(compass) <= _ORIENTATION_TOLERANCE_RAD:
        counters['odometry_orientation_compass'] = 1
        _LOG.warning('the Odometry orientation reads as a compass heading (clockwise from '
                     'north), not as REP-103 yaw (counter-clockwise from east): used so')
        return compass, 0.0
    counters['odometry_orientation_replaced'] = 1
    _LOG.warning('the Odometry orientation does not describe the vehicle\'s travel (median '
                 '%.0f deg off its course over ground): the heading is taken from the course '
                 'over ground instead', math.degrees(as_given))
    return _course_over_ground(t, measured, min_speed, counters, positions)[0], 0.0


def _median_turn(heading: F64, course: F64) -> float:
    """Median absolute angle between a heading and a course [rad]."""
    return float(np.median(np.abs(wrap_angle(heading - course))))


#: A constant heading offset of the Odometry against the course over ground smaller than
#: this is left alone [rad] where it can only be measured over turns as well (a reference
#: point ahead of the rear axle leaves the heading by a degree or more there).
_HEADING_OFFSET_MIN_RAD = math.radians(1.0)
#: Where straight stretches show it (``_HEADING_WANDER_BIN_S`` bins of at least
#: ``_HEADING_WANDER_MIN_SAMPLES`` straight moving samples, ``_HEADING_OFFSET_MIN_BINS`` of
#: them), an offset is taken off from this size [rad], or from ``_HEADING_OFFSET_SE``
#: standard errors of the bins' median if that is more.
_HEADING_OFFSET_STRAIGHT_MIN_RAD = math.radians(0.1)
_HEADING_OFFSET_MIN_BINS = 3
_HEADING_OFFSET_SE = 3.0


def _heading_offset(heading: F64, courses: list[F64], counters: Counter[str],
                    t: F64 | None = None, straight: np.ndarray | None = None) -> float:
    """The Odometry heading's constant offset from the vehicle's travel [rad], 0 where it
    is too small to be told from the course's own error.

    Why: an INS whose yaw is not aligned with the car (mounted turned, or the heading of
    ``imu_link`` rather than the vehicle) turns the vehicle's box and its twist by that
    angle; 12-20 deg went unnoticed below the 20 deg check and put an independent probe's
    radar 0.5 m off at twice its sigma. A car drives where it faces (no crab angle), so the
    median of heading minus course over the moving samples is the offset; of the two
    readings of the course (with and without reversals) the one the heading agrees with.
    On straight stretches (``straight``, at times ``t``) the course is the heading to a
    few hundredths of a degree with RTK, and there even a fraction of a degree counts: a
    fifteenth probe's INS turned by 0.7-1.0 deg, measured at 0.9-1.0 deg over all samples
    and left alone below the 1 deg that turns need, put the radar 0.22-0.40 m off across
    its boresight (2.2-2.8 sigma) and its yaw 0.55 deg, with no word (about 0.35 m and
    0.55 deg per degree). Straight, the offset is the median of 10 s bins' medians, and it
    is taken off where it exceeds both 0.1 deg and three standard errors of that median
    (the bins' spread: a standalone fix's course, or an INS that wanders, widens it).
    """
    best = min(courses, key=lambda c: _median_turn(heading, c))
    residual = wrap_angle(heading - best)
    offset, threshold = float(np.median(residual)), _HEADING_OFFSET_MIN_RAD
    if t is not None and straight is not None and straight.any():
        medians, _ = _heading_bins(t[straight], residual[straight])
        if medians.size >= _HEADING_OFFSET_MIN_BINS:
            offset = float(np.median(medians))
            # standard error of a median: 1.25 sigma / sqrt(n), sigma from the bins' MAD
            threshold = max(_HEADING_OFFSET_STRAIGHT_MIN_RAD, _HEADING_OFFSET_SE * 1.2533
                            * _robust_sigma(medians) / math.sqrt(medians.size))
    if abs(offset) < threshold:
        return 0.0
    counters['odometry_heading_offset_cdeg'] = int(round(100.0 * math.degrees(offset)))
    return offset


#: An Odometry heading offset within this of the site's meridian convergence is taken
#: for a yaw against the UTM grid's north [deg] (the offset is measured to 0.01-0.05 deg);
#: only where the convergence is itself no smaller than it.
_GRID_HEADING_TOLERANCE_DEG = 0.1


def heading_offset_is_grid(offset_deg: float, convergence_deg: float) -> bool:
    """Whether an Odometry heading offset is the site's meridian convergence: a yaw
    against the UTM grid's north rather than true north.

    Why: a thirty-fifth probe's, a forty-seventh's (0.13 deg, warned of as a turned INS
    with no word in the result) and two generators' Odometry yaw came from UTM easting and
    northing; the contract's REP-103 yaw is against true north.
    """
    return (abs(convergence_deg) >= _GRID_HEADING_TOLERANCE_DEG
            and abs(abs(offset_deg) - abs(convergence_deg)) <= _GRID_HEADING_TOLERANCE_DEG)


def _warn_heading_offset(offset: float, frame: LocalFrame, lat: F64, lon: F64) -> None:
    """Say on stderr what a heading offset taken off most likely is."""
    if not offset:
        return
    convergence = math.degrees(float(np.ravel(frame.utm_convergence_rad(
        float(np.median(lat)), float(np.median(lon))))[0]))
    if heading_offset_is_grid(math.degrees(offset), convergence):
        _LOG.warning('the Odometry heading is %.2f deg off the vehicle\'s course over ground '
                     'throughout, the meridian convergence here (%.2f deg): a yaw against '
                     'the UTM grid\'s north, not true north; taken off', math.degrees(offset),
                     abs(convergence))
    else:
        _LOG.warning('the Odometry heading is %.2f deg off the vehicle\'s course over ground '
                     'throughout: taken off', math.degrees(offset))


#: The Odometry heading's offset from the course over ground, in medians over bins of this
#: length [s] with at least this many straight moving samples, is taken as varying (and
#: followed) when those medians span more than ``_HEADING_WANDER_MIN_RAD`` (medians beyond
#: ``_HEADING_WANDER_MAX_RAD`` left out); straight is below ``_STRAIGHT_RATE_RPS`` of yaw
#: rate.
_HEADING_WANDER_BIN_S = 10.0
_HEADING_WANDER_MIN_SAMPLES = 20
_HEADING_WANDER_MIN_RAD = math.radians(0.6)
#: (20 deg: a single-antenna INS converging after start-up is 8-15 deg off for its first
#: minute; with 5 deg a thirty-third probe's first passes kept 2-7 deg of it, 0.13-0.18 deg
#: of rotation and up to 20 cm off -> 0.03-0.11 deg, 3-7 cm.)
_HEADING_WANDER_MAX_RAD = math.radians(20.0)
_STRAIGHT_RATE_RPS = 0.05
#: ... and below this curvature [1/m] (yaw rate over speed): a bend driven slowly turns
#: slower than the rate above, while its course still leaves the heading by the reference
#: point's distance ahead of the rear axle over the radius (1.2 deg on a 70 m bend: a
#: seventeenth probe's exact Odometry on a bend was called wandering by 0.3-0.6 deg). At
#: 200 m, 1.5 m ahead is 0.4 deg, under ``_HEADING_WANDER_MIN_RAD``.
_STRAIGHT_CURVATURE_PER_M = 1.0 / 200.0


#: Half span [s] over which the yaw rate that tells straight from turning is taken.
_STRAIGHT_RATE_HALF_SPAN_S = 0.5


def _heading_bins(t_straight: F64, residual: F64) -> tuple[F64, F64]:
    """(medians of ``residual``, mean times) over the ``_HEADING_WANDER_BIN_S`` bins of the
    straight moving samples ``t_straight`` that hold ``_HEADING_WANDER_MIN_SAMPLES`` or
    more (empty where none does)."""
    label = np.floor((t_straight - t_straight[0]) / _HEADING_WANDER_BIN_S).astype(np.int64)
    used = np.flatnonzero(np.bincount(label) >= _HEADING_WANDER_MIN_SAMPLES)
    if used.size == 0:
        return np.zeros(0), np.zeros(0)
    return (np.asarray(ndimage.median(residual, labels=label, index=used), float),
            np.asarray(ndimage.mean(t_straight, labels=label, index=used), float))


def _heading_settled(t_straight: F64, residual: F64) -> float | None:
    """The time [s] by which an Odometry heading that started far off the course over
    ground had settled, or None where it did not start so.

    Why: a single-antenna INS aligns its heading by driving, starting 8-15 deg off and
    converging over a minute (a thirty-third probe: called a wander of 2-4 deg, the first
    bins beyond the wander's old 5 deg limit left out, 0.13-0.18 deg of rotation against
    0.02-0.06). Its ``_HEADING_WANDER_BIN_S`` medians of heading minus course
    (``residual`` at the straight moving samples ``t_straight``) are furthest from their
    final level in the first bin, by more than ``_HEADING_SETTLE_MIN_RAD``; settled is the
    first bin within a third of that.
    """
    if t_straight.size < 2 * _HEADING_WANDER_MIN_SAMPLES:
        return None
    medians, centres = _heading_bins(t_straight, residual)
    if medians.size < 4:
        return None
    medians = ndimage.median_filter(medians, size=3, mode='nearest')
    level = float(np.median(medians[medians.size // 2:]))
    size = np.abs(medians - level)
    if (int(np.argmax(size)) != 0 or size[0] < _HEADING_SETTLE_MIN_RAD
            or size[0] > _HEADING_WANDER_MAX_RAD):
        return None
    within = size < size[0] / 3.0
    if not within.any():
        return None
    return float(centres[int(np.argmax(within))])


#: Least start-up offset of the heading that ``_heading_settled`` names [rad].
_HEADING_SETTLE_MIN_RAD = math.radians(2.0)


def _heading_wander(t_straight: F64, residual: F64, t: F64, counters: Counter[str]
                    ) -> F64 | None:
    """(n,) the slowly varying part of the Odometry heading's offset from the course over
    ground at ``t``, or None where it does not vary.

    Why: an INS without a second antenna holds its heading by its gyro between manoeuvres,
    and it wanders by a degree or two over minutes (a twelfth probe: +-2 deg over 300 s put
    the radar 1 m too high and its pitch 1.9 deg off, far outside 2 sigma, with no word; a
    constant offset is taken off by ``_heading_offset``). The heading turns the vehicle's
    box and its twist, whose direction the radial velocities read against the radar's
    rotation. A car drives where it faces, so on straight stretches the course over ground
    (RTK, +-1 s) shows the heading's error to a tenth of a degree; its medians over
    ``_HEADING_WANDER_BIN_S`` are interpolated between (turns, stops) and held beyond the
    ends. ``residual`` is heading minus course (the constant offset already off) at the
    straight moving samples ``t_straight``.
    """
    if t_straight.size < 2 * _HEADING_WANDER_MIN_SAMPLES:
        return None
    medians, centres = _heading_bins(t_straight, residual)
    if medians.size < 2:
        return None
    # a heading further off is no drift or start-up but a broken orientation (an INS still
    # aligning writes the identity): what judges the orientation as a whole sees to it
    small = np.abs(medians) <= _HEADING_WANDER_MAX_RAD
    if small.sum() < 3:
        return None
    # a drift over minutes, not one bin's (the edge of a stretch where the orientation was
    # the identity, or the wrong way round)
    medians = ndimage.median_filter(medians[small], size=3, mode='mirror')
    centres = centres[small]
    if float(medians.max() - medians.min()) < _HEADING_WANDER_MIN_RAD:
        return None
    counters['odometry_heading_wander_cdeg'] = int(round(100.0 * math.degrees(
        float(np.max(np.abs(medians))))))
    if counters.get('odometry_heading_settled_s'):
        _LOG.warning('the Odometry heading starts %.1f deg off the vehicle\'s course over '
                     'ground and settles within %d s: followed',
                     math.degrees(float(np.max(np.abs(medians)))),
                     counters['odometry_heading_settled_s'])
    else:
        _LOG.warning('the Odometry heading wanders by up to %.1f deg from the vehicle\'s '
                     'course over ground: followed', math.degrees(float(np.max(np.abs(medians)))))
    return np.interp(t, centres, medians)


def _level_twist(quaternion_xyzw: F64, yaw: F64, v_body: F64) -> F64:
    """(n, 3) body-frame twists turned into the level frame that shares the vehicle's
    heading: rotated by the full orientation, then back by its yaw.

    Why: REP-105's twist is along the vehicle's own axes, so on a grade its x is the speed
    along the slope, and the horizontal speed is shorter by the cosine of the pitch (0.18 %
    at 6 %). The final refinement takes the speed at its word, and a speed that much too
    high was absorbed by the dip of the radial velocities' line of sight: an independent
    recording on a 6 % road along a mid-block view came out 50 cm high and 30-45 cm off
    across the boresight, well outside its sigma. A level orientation changes nothing.
    """
    rot = Rotation.from_quat(quaternion_xyzw)
    return Rotation.from_euler('z', -yaw[:, None]).apply(rot.apply(v_body))


#: Orientation tilt [rad] above which the quaternions are taken to carry pitch and roll
#: (an INS's attitude); a heading-only orientation is level to rounding.
_TILT_CARRIED_RAD = math.radians(0.05)
#: Vertical sigma of the fixes [m] up to which their climb is trusted for the grade
#: (RTK: 2-5 cm; a standalone fix's metres would invent grades), and the largest grade
#: taken from it (a steeper one is the noise of a slow vehicle's altitude).
_GRADE_FIX_SIGMA_M = 0.1
_GRADE_MAX = 0.15


def _tilted(quaternion_xyzw: F64) -> bool:
    """True when any orientation is tilted out of the level (pitch or roll carried)."""
    z_axis = Rotation.from_quat(quaternion_xyzw).apply([0.0, 0.0, 1.0])
    return bool(np.any(np.arccos(np.clip(z_axis[:, 2], -1.0, 1.0)) > _TILT_CARRIED_RAD))


def _grade_cosine(t: F64, positions: F64, speed: F64,
                  fix_sigma: tuple[float, float] | None) -> F64:
    """(n,) cosine of the vehicle's pitch on the road's grade, from the fixes' climb over
    +-1 s against the twist's speed along the slope, for a twist whose orientation is
    heading-only; ones where the fixes are too coarse to say (no declared sigma, or a
    vertical sigma above ``_GRADE_FIX_SIGMA_M``)."""
    if fix_sigma is None or not fix_sigma[1] <= _GRADE_FIX_SIGMA_M:
        return np.ones(t.size)
    climb = _finite_difference(t, positions[:, 2], _TWIST_CHECK_SPAN_S)
    sine = np.clip(climb / np.maximum(speed, 1e-9), -_GRADE_MAX, _GRADE_MAX)
    sine[speed < _TWIST_CHECK_SPEED_MPS] = 0.0
    return np.sqrt(1.0 - sine ** 2)


#: The Odometry twist is trusted where it agrees with the motion of the positions to within
#: this (m/s) or this fraction of the median speed, whichever is larger (RTK positions
#: differentiated over 0.4 s: ~0.1 m/s; a standalone fix at 1 Hz: ~1 m/s).
_TWIST_TOLERANCE_MPS = 0.5
_TWIST_TOLERANCE_FRACTION = 0.2
#: Half span of the positions' differences the twist is judged against [s].
_TWIST_CHECK_SPAN_S = 1.0
#: Fewest samples of a moving vehicle (above this speed, m/s) to judge the twist on.
_TWIST_CHECK_SPEED_MPS = 2.0
#: A twist speed beyond this [m/s] (360 km/h) is no road vehicle's: the sample is left out.
TWIST_MAX_MPS = 100.0
_TWIST_CHECK_SAMPLES = 10


#: Velocity noise [m/s] the span of the fixes' local quadratic is chosen for, and the
#: bounds of its half span [s] (see ``_fix_velocities``).
_FIX_VELOCITY_NOISE_MPS = 0.03
_FIX_VELOCITY_HALF_SPAN_S = (0.2, 0.5)


def _fix_velocity_half_span(t: F64, positions: F64) -> float:
    """Half span [s] of the local quadratic that leaves ``_FIX_VELOCITY_NOISE_MPS`` of
    velocity noise from the fixes' own white noise, within ``_FIX_VELOCITY_HALF_SPAN_S``.

    The noise is read from third differences of evenly spaced fixes (a steady acceleration
    or a turn cancels in them, 20 sigma^2 of white noise does not); a quadratic's slope over
    +-h from samples dt apart has sigma^2 3 dt / (2 h^3) of it. Why not one span for all: a
    wide span costs speed in tight turns (a forty-fourth probe's U-turns, with 8 mm of
    white noise, moved 6 cm further along the boresight at +-0.4 s), a narrow one leaves
    2 cm of white noise at 0.07-0.14 m/s."""
    lo, hi = _FIX_VELOCITY_HALF_SPAN_S
    if t.size < 8:
        return lo
    dt = np.diff(t)
    step = float(np.median(dt))
    even = np.abs(dt - step) <= 0.05 * step
    run = even[:-2] & even[1:-1] & even[2:]
    if step <= 0.0 or run.sum() < 5:
        return lo
    third = (positions[3:, :2] - 3.0 * positions[2:-1, :2] + 3.0 * positions[1:-2, :2]
             - positions[:-3, :2])[run]
    sigma = 1.4826 * float(np.median(np.abs(third))) / math.sqrt(20.0)
    span = (3.0 * step * sigma ** 2 / (2.0 * _FIX_VELOCITY_NOISE_MPS ** 2)) ** (1.0 / 3.0)
    return float(np.clip(span, lo, hi))


def _fix_velocities(t: F64, positions: F64, half_span_s: float | None = None) -> F64:
    """(n, k) velocities of fixes alone: the slope at each sample of a quadratic fitted by
    least squares to the samples within +-``half_span_s`` (by default as the fixes' noise
    needs, ``_fix_velocity_half_span``).

    Why not the +-0.2 s central difference the Odometry's checks use: with fixes alone this
    velocity is the vehicle's, and every radial velocity of a frame is compared with it. RTK's
    2 cm over 0.2-0.4 s is 0.07-0.14 m/s of noise (and 13 m/s at 0.3 deg of course), shared
    by all the frame's targets and by the frames around it, which the fit reads as signal: a
    forty-second probe's straight drives with fixes alone put the clock offset +41 ms off on
    average (4 of 10 within 2 sigma; with Odometry +2 ms, 9 of 10), one 85 ms and 0.6 m along
    the boresight with hardly any radar noise. The slope of a quadratic over +-0.4 s has a
    fifth of that noise (0.026 m/s at 10 Hz), carries no lag where the window is one-sided
    (the ends of a pass) and none under a steady acceleration; a lane change's curvature
    costs about 4 % of its lateral speed, a tight turn's about 2 % of its speed, so the span
    is as wide as the fixes' noise needs and no wider. Where the span holds fewer than three
    samples it takes one either side, as ``_finite_difference`` does, and three samples'
    exact slope.
    """
    n = t.size
    if n < 3:
        return _position_velocities(t, positions)
    if half_span_s is None:
        half_span_s = _fix_velocity_half_span(t, positions)
    index = np.arange(n)
    # one-sided where the span is (the ends of a pass: a sample across the gap between
    # passes, seconds away, would bend the quadratic); at least one either side only where
    # the span holds fewer than three samples (fixes at 1-2 Hz)
    lo, hi = _window(t, half_span_s, either_side=False)
    sparse = hi - lo < 2
    forced_lo, forced_hi = _window(t, half_span_s)
    lo, hi = np.where(sparse, forced_lo, lo), np.where(sparse, forced_hi, hi)
    reach = int(max(np.max(index - lo), np.max(hi - index)))
    # sums of dt^p (p = 0..4) and dx dt^p (p = 0..2) over each window, offsets from the
    # centre sample (a loop over the window's width, vectorised over the samples)
    moments = np.zeros((5, n))
    weighted = np.zeros((3, n, positions.shape[1]))
    for k in range(-reach, reach + 1):
        j = index + k
        inside = (j >= lo) & (j <= hi)
        jj = np.clip(j, 0, n - 1)
        dt = np.where(inside, t[jj] - t, 0.0)
        dx = np.where(inside[:, None], positions[jj] - positions, 0.0)
        power = inside.astype(float)
        for p in range(5):
            moments[p] += power
            if p < 3:
                weighted[p] += dx * power[:, None]
            power = power * dt
    normal = np.stack([moments[0:3], moments[1:4], moments[2:5]], axis=1).transpose(2, 0, 1)
    rhs = weighted.transpose(1, 0, 2)
    # the centre sample's own offset is zero: with dx measured from it, the intercept is
    # that sample's noise, left free so that it does not tilt the slope
    solvable = np.abs(np.linalg.det(normal)) > 1e-18
    velocities = _position_velocities(t, positions)
    if solvable.any():
        coefficients = np.linalg.solve(normal[solvable], rhs[solvable])
        velocities[solvable] = coefficients[:, 1]
    return velocities


def _window(t: F64, half_span_s: float, either_side: bool = True) -> tuple[I64, I64]:
    """First and last index of the samples within +-``half_span_s`` of each sample, and
    (``either_side``) at least one either side (one-sided only at the ends).

    The span is widened by a microsecond: stamps rounded to the nanosecond put a 10 Hz
    fix 0.2 s away a few nanoseconds beyond +-0.2 s as often as within it, and the window
    fell to +-0.1 s for 60 % of the samples (twice the noise)."""
    index = np.arange(t.size)
    lo = np.searchsorted(t, t - half_span_s - _SPAN_TOLERANCE_S, side='left')
    hi = np.searchsorted(t, t + half_span_s + _SPAN_TOLERANCE_S, side='right') - 1
    if either_side:
        lo = np.minimum(lo, np.maximum(index - 1, 0))
        hi = np.maximum(hi, np.minimum(index + 1, t.size - 1))
    return lo, hi


#: Widening of a difference's span against stamps rounded to the nanosecond [s].
_SPAN_TOLERANCE_S = 1e-6


def _position_velocities(t: F64, positions: F64, half_span_s: float = 0.2) -> F64:
    """(n, k) velocities of positions (n, k) by central differences (``_finite_difference``)."""
    return np.column_stack([_finite_difference(t, positions[:, i], half_span_s)
                            for i in range(positions.shape[1])])


#: Latency of the fixes against the Odometry looked for [s] (a receiver at 1 Hz that stamps
#: on output, or an Odometry stamped as late: a ninth probe's 1 s), its grid step [s], the
#: smallest worth correcting [s] (a few centimetres of travel at urban speed), and how many
#: standard errors it must stand clear of zero.
_FIX_LAG_MAX_S = 1.2
_FIX_LAG_STEP_S = 0.01
_FIX_LAG_MIN_S = 0.02
_FIX_LAG_SIGMAS = 5.0
#: Fix velocities beyond this rate [Hz] add nothing to the lag's search (see ``_fix_lag``).
_FIX_LAG_RATE_HZ = 10.0
#: Half the span [s] of the Odometry's velocity means whose difference is the acceleration
#: a lag's standard error counts (``_sustained_acceleration``: over a second either side).
_FIX_LAG_ACCEL_HALF_S = 0.5
#: Grid steps between the lags searched first (see ``_fix_lag``).
_FIX_LAG_COARSE = 4
#: A lag found with a lever arm is taken only where the speeds' misfit along the travel
#: (no arm) falls from no lag to it by at least this share of what the accelerations
#: predict (see ``_fix_lag``).
_FIX_LAG_SHOWN = 0.5


#: Offsets between the fixes' and the Odometry's clocks searched beyond ``_FIX_LAG_MAX_S``
#: [s] (GPS, UTC and TAI differ by 18, 19 and 37 s), on a grid of this step [s]; taken when
#: the speeds agree to ``_STREAM_OFFSET_MATCH`` of their misfit at the lag ``_fix_lag``
#: searches, over at least ``_STREAM_OFFSET_OVERLAP`` of the fixes' span.
_STREAM_OFFSET_MAX_S = 60.0
_STREAM_OFFSET_STEP_S = 0.1
_STREAM_OFFSET_MATCH = 0.25
_STREAM_OFFSET_OVERLAP = 0.5


def _stream_offset(t: F64, speed_fix: F64, to: F64, speed_odom: F64) -> float | None:
    """Seconds by which the fixes' stamps lag the Odometry's where that is more than
    ``_fix_lag`` searches (``_FIX_LAG_MAX_S``) and the speeds show it clearly, else None.

    Why: a driver that stamps one stream in GPS time and the other in UTC puts them 18 s
    apart (a thirty-third probe). Within the ~1 s ``_fix_lag`` searches the two then never
    agree, and the Odometry's orientation and twist were condemned as another frame's and
    replaced (0.24-0.30 m off, with advice about azimuth noise and the vehicle's size);
    fixes 18 s late were refused with the radar's clock blamed. The speeds (not the
    velocities: they need no heading, right or wrong) are compared on a grid of offsets:
    the drive's stops and starts make one offset fit far better than every other.
    """
    if t.size < 50 or to.size < 50:
        return None
    step = _STREAM_OFFSET_STEP_S
    grid = np.arange(t[0], t[-1], step)
    fix = np.interp(grid, t, speed_fix)
    order = np.argsort(to, kind='stable')
    shifts = int(round(_STREAM_OFFSET_MAX_S / step))
    lags = np.arange(-shifts, shifts + 1) * step
    # the Odometry's speed on the fixes' grid extended by the largest lag either way (NaN
    # outside its span): each lag is then a shift by whole steps, not an interpolation
    # (0.3 s of a fifteen-minute recording's read, interpolated per lag)
    wide = t[0] + np.arange(-shifts, grid.size + shifts) * step
    odom = np.interp(wide, to[order], speed_odom[order], left=np.nan, right=np.nan)
    misfit = np.full(lags.size, np.inf)
    for k in range(lags.size):
        # the fix stamped t shows the vehicle at Odometry time t - lag
        diff = fix - odom[2 * shifts - k:2 * shifts - k + grid.size]
        inside = np.isfinite(diff)
        if inside.sum() < _STREAM_OFFSET_OVERLAP * grid.size:
            continue
        misfit[k] = float(np.sqrt(np.mean(diff[inside] ** 2)))
    near = np.abs(lags) <= _FIX_LAG_MAX_S
    far = ~near & np.isfinite(misfit)
    if not far.any() or not np.isfinite(misfit[near]).any():
        return None
    best = int(np.flatnonzero(far)[np.argmin(misfit[far])])
    tolerance = max(_TWIST_TOLERANCE_MPS, _TWIST_TOLERANCE_FRACTION * float(np.median(fix)))
    if (misfit[best] > tolerance
            or misfit[best] > _STREAM_OFFSET_MATCH * float(np.min(misfit[near]))):
        return None
    return float(lags[best])


def _sustained_acceleration(to: F64, velocity: F64, tq: F64, half_s: float) -> F64:
    """(m, 2): the acceleration at ``tq`` (m,) of velocities (n, 2) at sorted times ``to``
    (n,), as the difference of their means over the ``2 half_s`` after and before each
    time, over ``2 half_s`` (the mean of a velocity is its integral's change over the
    span); zero where that reaches past the samples or into a gap between them.

    Why not the velocities differenced sample by sample: an INS heading with 0.16 deg of
    white noise per 50 Hz sample turns an 11 m/s twist by 0.03 m/s from one sample to the
    next, 0.2 m/s^2 of acceleration that no car makes. Counted as information, it gave a
    lag searched on a fifty-seventh probe's straight passes at constant speed (fixes and
    Odometry stamped alike) a standard error of 15 ms, and the noise's best lag, -1.19 s,
    was taken: the radar went 4-13 m along the road. Means over a second take that noise
    down fivefold and keep a braking or a turn, which last seconds.
    """
    span = 2.0 * half_s
    step = np.diff(to)[:, None]
    travelled = np.vstack([np.zeros((1, velocity.shape[1])),
                           np.cumsum(0.5 * (velocity[1:] + velocity[:-1]) * step, axis=0)])

    def at(tx: F64) -> F64:
        return np.column_stack([np.interp(tx, to, travelled[:, i])
                                for i in range(velocity.shape[1])])

    acc = (at(tq + span) - 2.0 * at(tq) + at(tq - span)) / span ** 2
    inside = (tq - span >= to[0]) & (tq + span <= to[-1])
    for start, end in _gaps(to):
        inside &= (tq + span < start) | (tq - span > end)
    return np.where(inside[:, None], acc, 0.0)


@dataclass(frozen=True)
class FixAgainstOdometry:
    """What the fixes' motion shows against the Odometry's (``_fix_lag``): the lag of their
    stamps [s] (0.0 when not clear), and the horizontal lever arm of the fixes' point from
    the Odometry's in the vehicle frame [m] (forward, left; None when not clear)."""

    lag_s: float = 0.0
    lever_arm_m: tuple[float, float] | None = None


#: A lever arm between the fixes' point and the Odometry's is reported when at least this
#: long [m] (a roof antenna above the rear axle: 1-2 m) and this many standard errors.
_LEVER_ARM_MIN_M = 0.3
_LEVER_ARM_SIGMAS = 5.0


def _lever_columns(rate: F64, heading: F64) -> F64:
    """(n, 2, 2): d(world velocity of a point)/d(lever arm forward, left) of a vehicle
    turning at ``rate`` [rad/s] on ``heading``: omega x l, turned into the world."""
    c, s = np.cos(heading), np.sin(heading)
    cols = np.empty((rate.size, 2, 2))
    cols[:, 0, 0], cols[:, 0, 1] = -rate * s, -rate * c
    cols[:, 1, 0], cols[:, 1, 1] = rate * c, -rate * s
    return cols


#: An interval between two poses of one stream is a gap when longer than this many times the
#: stream's median interval and ``_LAG_GAP_MIN_S`` [s] (see ``_clear_of_gaps``).
_LAG_GAP_INTERVALS = 3.0
_LAG_GAP_MIN_S = 0.5


def _gaps(times: F64) -> F64:
    """(g, 2) start and end [s] of the gaps in a stream of sorted ``times``."""
    if times.size < 2:
        return np.empty((0, 2))
    step = np.diff(times)
    gap = step > max(_LAG_GAP_MIN_S, _LAG_GAP_INTERVALS * float(np.median(step)))
    return np.column_stack([times[:-1][gap], times[1:][gap]])


def _clear_of_gaps(t: F64, to: F64, margin_s: float) -> np.ndarray:
    """(n,) fixes at ``t`` whose velocity over +-0.2 s spans no gap between fixes, and
    whose Odometry within +-``margin_s`` (the lags searched) spans none of the Odometry's.

    Why: a recording paused between passes, or one whose poses stop while the vehicle
    turns round out of view, puts seconds between two poses of different passes. The fixes'
    difference across it is no velocity (50 m/s across a forty-sixth probe's 6 s jumps
    between passes), nor is the Odometry's interpolated over it; 8 such samples of 1857
    made the residual's variance that of metres per second, and a 200 ms lag of the fixes
    (5 standard errors needed) went untaken at 225 +- 76 ms, leaving the twin with a perfect
    Odometry 20-30 cm off where the fixes alone were 4 cm.
    """
    clear = np.ones(t.size, bool)
    for stream, reach in ((t, 0.2 + _SPAN_TOLERANCE_S), (to, margin_s)):
        for start, end in _gaps(stream):
            # (the fixes either side of a gap are within reach of it: their difference, one
            # neighbour either side at least, ``_window``, spans it)
            clear &= (t < start - reach) | (t > end + reach)
    return clear


#: An Odometry turning faster than this lateral acceleration [m/s^2] (yaw rate times
#: speed; a car's tyres hold ~8, a calibration drive stays below 4) is no drive.
_JOLT_LATERAL_MPS2 = 8.0


def _clear_of_jolts(t: F64, to: F64, rate: F64, speed: F64, margin_s: float) -> np.ndarray:
    """(n,) fixes at ``t`` with no Odometry sample within +-``margin_s`` (the lags searched
    and the fixes' velocity span) whose yaw rate no car could drive at its speed.

    Why: a heading that jumps (a path joined at a corner, an INS resetting its yaw) puts
    a yaw rate of 10-16 rad/s in the twist for one sample. The lever arm's velocity
    (omega x l) is fitted to those few samples like to any turn: a fifty-third probe's
    fixes and Odometry of one point, stamped alike, read as an arm of 0.2 m (too short
    to be taken) and then a lag of -28 ms, 20 standard errors clear, on every recording
    of one seed, with advice to check the receiver's stamping.
    """
    jolt = np.abs(rate) * speed > _JOLT_LATERAL_MPS2
    clear = np.ones(t.size, bool)
    if not jolt.any():
        return clear
    at = np.sort(to[jolt])
    # the jolt nearest each fix, before and after it
    k = np.searchsorted(at, t)
    before = np.abs(t - at[np.maximum(k - 1, 0)])
    after = np.abs(at[np.minimum(k, at.size - 1)] - t)
    return np.minimum(before, after) > margin_s


def _fix_lag(t: F64, v_fix: F64, to: F64, yaw: F64, v_level: F64,
             rate: F64 | None = None) -> FixAgainstOdometry:
    """Seconds by which the fixes' stamps lag the Odometry's, and the lever arm between
    the points the two describe, where the data show them clearly.

    Why the lag: a GNSS receiver that stamps a fix when it outputs it, not at its epoch, is
    50-200 ms late, while the INS beside it is on time. The fixes then place the vehicle
    that far behind itself along its path, an offset that turns with every pass and that
    no radar clock offset can take up (an independent recording: 0.73 m along the
    boresight, reported at 0.17 m, where the same data on one clock gave 0.34 m). The lag
    shows wherever the vehicle accelerates or turns: the fixes' velocity follows the
    Odometry's that much later. It is found on a grid of lags by least squares, refined by
    a parabola, and taken when it is at least ``_FIX_LAG_MIN_S`` and ``_FIX_LAG_SIGMAS``
    standard errors (the fixes' velocities over +-0.2 s are correlated over that span,
    which the error counts). A twist that does not describe the motion at all (zero,
    another frame, a compass heading) shows no clear minimum and is left to
    ``_checked_twist``.

    Why the lever arm: a NavSatFix of the roof antenna beside an Odometry of the rear axle
    (a tenth probe) moves faster on the outside of every turn (omega x l). Unmodelled, a
    lever arm 1 m forward passed for a fix lag of -46 ms and was 'corrected' in time. It
    is fitted with the lag (``rate``, the Odometry's yaw rate, makes it observable) and
    reported: the contract takes the fixes' point as the vehicle's reference point, and
    whether ``vehicle.*`` describes that point only the user knows.
    """
    if t.size < 50 or to.size < 50:
        return FixAgainstOdometry()
    v_odom = _turned(v_level, yaw)
    margin = _FIX_LAG_MAX_S + 0.2
    rate = np.zeros(to.size) if rate is None else rate
    use = ((np.hypot(v_fix[:, 0], v_fix[:, 1]) > _TWIST_CHECK_SPEED_MPS)
           & (t - margin > to[0]) & (t + margin < to[-1]) & _clear_of_gaps(t, to, margin)
           & _clear_of_jolts(t, to, rate, np.hypot(v_level[:, 0], v_level[:, 1]), margin))
    if int(use.sum()) < 50:
        return FixAgainstOdometry()
    # Velocities over +-0.2 s are correlated over that span: every fifth of a 50 Hz drive
    # says as much and makes the two grid searches below five times cheaper (2.4 s of a
    # fifteen-minute recording's read otherwise)
    use = np.flatnonzero(use)
    use = use[::max(1, int(use.size / max(float(t[use[-1]] - t[use[0]]), 1e-9)
                           / _FIX_LAG_RATE_HZ))]
    tu, vu = t[use], v_fix[use]
    unwrapped = np.unwrap(yaw)
    rate_hz = (tu.size - 1) / max(float(tu[-1] - tu[0]), 1e-9)
    correlated = max(1.0, 0.4 * rate_hz)

    def odom_at(tq: F64) -> F64:
        return np.column_stack([np.interp(tq, to, v_odom[:, i]) for i in range(2)])

    def matched_at(lag: float, with_arm: bool) -> tuple[F64, tuple[F64, F64] | None]:
        """The Odometry's velocity at the fixes' times minus ``lag``, turned by the angle
        that fits the fixes' best (an INS heading offset, ``_heading_offset``, must not
        pass for a lag: on a steady turn the two are one), plus (``with_arm``) the lever
        arm that fits best; also that lever arm and the (3, 3) normal matrix of the last
        turn and the arm (None without one, or where the turns do not determine it)."""
        v = odom_at(tu - lag)
        angle = math.atan2(float(np.sum(v[:, 0] * vu[:, 1] - v[:, 1] * vu[:, 0])),
                           float(np.sum(v[:, 0] * vu[:, 0] + v[:, 1] * vu[:, 1])))
        v = _turned(v, angle)
        if not with_arm:
            return v, None
        cols = _lever_columns(np.interp(tu - lag, to, rate),
                              np.interp(tu - lag, to, unwrapped) + angle)
        # the arm with a last turn of the velocities, together: where the drive turns
        # more one way than the other, a turn found first takes up part of the arm's
        # sideways velocity (a thirty-first probe: 0.29 deg, and the arm 1.42 m for 1.5)
        both = np.concatenate([np.column_stack([-v[:, 1], v[:, 0]])[:, :, None], cols],
                              axis=2)
        normal = np.einsum('nki,nkj->ij', both, both)
        if np.linalg.cond(normal) > 1e8:
            return v, None
        solved = np.linalg.solve(normal, np.einsum('nki,nk->i', both, vu - v))
        return v + both @ solved, (solved[1:], normal)

    lags = np.arange(-_FIX_LAG_MAX_S, _FIX_LAG_MAX_S + 1e-9, _FIX_LAG_STEP_S)
    speed = float(np.median(np.hypot(vu[:, 0], vu[:, 1])))
    tolerance = max(_TWIST_TOLERANCE_MPS, _TWIST_TOLERANCE_FRACTION * speed)

    def best_lag(with_arm: bool) -> float | None:
        """The lag of least misfit (a parabola through the grid's best three), None without
        a clear minimum. The grid is searched every ``_FIX_LAG_COARSE`` steps first, then
        step by step around the best of those (the misfit is smooth over a tenth of a
        second: a turn or a braking takes longer)."""
        def misfit(lag: float) -> float:
            matched = matched_at(lag, with_arm)[0]
            if not with_arm:
                return float(np.mean((vu - matched) ** 2))
            # Along the travel only: across it, in a turn, a lag moves the velocity as a
            # lever arm ahead does (by the speed times the lag, for the arm by the yaw rate
            # times its length), and on turns all driven at one speed the two are one.
            # There the fixes' finite-difference velocities decided, and a thirty-first
            # probe's exactly stamped antenna fixes 1.5 m ahead of a rear-axle Odometry
            # read as a -39 ms lag plus a 0.93 m arm; a braking or speeding up shows the
            # lag alone.
            heading = matched / np.maximum(np.linalg.norm(matched, axis=1), 1e-9)[:, None]
            return float(np.mean(np.sum((vu - matched) * heading, axis=1) ** 2))

        coarse = np.arange(0, lags.size, _FIX_LAG_COARSE)
        best = int(coarse[np.argmin([misfit(lags[i]) for i in coarse])])
        near = np.arange(max(best - _FIX_LAG_COARSE, 0),
                         min(best + _FIX_LAG_COARSE, lags.size - 1) + 1)
        cost = np.full(lags.size, np.inf)
        cost[near] = [misfit(lags[i]) for i in near]
        k = int(np.argmin(cost))
        while 0 < k < lags.size - 1:
            # on to the nearest local minimum should the search's edge hold the best
            for i in (k - 1, k + 1):
                if not np.isfinite(cost[i]):
                    cost[i] = misfit(lags[i])
            step = int(np.argmin(cost[k - 1:k + 2])) - 1
            if step == 0:
                break
            k += step
        if k in (0, lags.size - 1) or cost[k] > tolerance ** 2:
            return None
        curvature = cost[k - 1] - 2.0 * cost[k] + cost[k + 1]
        if curvature <= 0.0:
            return None
        return float(lags[k] + 0.5 * _FIX_LAG_STEP_S * (cost[k - 1] - cost[k + 1]) / curvature)

    def significant_arm(lag: float) -> tuple[float, float] | None:
        """The lever arm fitted at ``lag`` where it is long and clear enough, else None."""
        matched, fitted = matched_at(lag, True)
        if fitted is None:
            return None
        arm, normal = fitted
        variance = float(np.mean((vu - matched) ** 2))
        arm_se = np.sqrt(np.diag(np.linalg.inv(normal))[1:] * variance * correlated)
        length = float(np.hypot(*arm))
        _LOG.debug('lever arm of the fixes from the Odometry at %.0f ms: %s +- %s m',
                   1e3 * lag, np.round(arm, 3), np.round(arm_se, 3))
        if length >= _LEVER_ARM_MIN_M and length >= _LEVER_ARM_SIGMAS * float(
                np.hypot(*arm_se)):
            return float(arm[0]), float(arm[1])
        return None

    def along_misfit(lag: float) -> float:
        """The misfit along the travel without an arm: what a change of speed says."""
        matched = matched_at(lag, False)[0]
        heading = matched / np.maximum(np.linalg.norm(matched, axis=1), 1e-9)[:, None]
        return float(np.mean(np.sum((vu - matched) * heading, axis=1) ** 2))

    # with a lever arm first; where none shows, the lag alone (a free lever arm of a few
    # centimetres moved the slow_gnss scenario's lag from 118 to 127 ms; the truth is 120)
    lag = best_lag(True)
    lever_arm = None if lag is None else significant_arm(lag)
    if lever_arm is None:
        lag = best_lag(False)
        if lag is None:
            return FixAgainstOdometry()
    matched = matched_at(lag, lever_arm is not None)[0]
    raw = odom_at(tu - lag)
    residual = vu - matched
    variance = float(np.mean(residual ** 2))
    # standard error of a one-parameter least squares: residual variance over the summed
    # squared sensitivity (the Odometry's acceleration, sustained over a second: its
    # heading's noise is none), with samples 0.4 s apart independent
    turn = math.atan2(float(np.sum(matched[:, 1] * raw[:, 0] - matched[:, 0] * raw[:, 1])),
                      float(np.sum(raw[:, 0] * matched[:, 0] + raw[:, 1] * matched[:, 1])))
    acc = _turned(_sustained_acceleration(to, v_odom, tu - lag, _FIX_LAG_ACCEL_HALF_S), turn)
    heading = matched / np.maximum(np.linalg.norm(matched, axis=1), 1e-9)[:, None]
    if lever_arm is not None:
        # with an arm the lag was searched along the travel only (see ``misfit``): only a
        # change of speed tells it. Counted across as well, a forty-sixth probe's weaving
        # at one steady speed on straight passes took a 481 ms lag with a 2.8 m arm, both
        # from nothing.
        along = np.sum(acc * heading, axis=1) ** 2
        information = float(np.sum(along)) / correlated
        # and the speeds must say so: without the arm (which moves the velocity across the
        # travel, but for a sideways arm little along it) the misfit along the travel
        # falls from no lag to this one by about the lag's squared times the
        # accelerations' mean square. A sixtieth probe's fixes and Odometry stamped alike,
        # driven straight through at steady speeds, took -1157 +- 37 ms with an arm of
        # -0.93 m while the speeds fitted alike at both (a fall of 8e-7 against 4e-3
        # expected), and the radar was put 2.1 m off.
        fall = along_misfit(0.0) - along_misfit(lag)
        if fall < _FIX_LAG_SHOWN * lag ** 2 * float(np.mean(along)):
            _LOG.debug('fix lag %.0f ms with an arm: the speeds do not show it', 1e3 * lag)
            information = 0.0
    else:
        # the part of the lag's sensitivity that the turn's angle cannot take up: on a
        # steady circle the acceleration lies along the turn's (perpendicular to the
        # velocity) and a lag says nothing
        # (over the samples whose acceleration is known: a zero beside a gap is none)
        perp = np.column_stack([-matched[:, 1], matched[:, 0]]) * np.any(acc != 0.0, axis=1,
                                                                         keepdims=True)
        along_turn = float(np.sum(acc * perp)) ** 2 / max(float(np.sum(perp ** 2)), 1e-12)
        information = max(float(np.sum(acc ** 2)) - along_turn, 0.0) / correlated
    se = math.sqrt(variance / information) if information > 0.0 else math.inf
    if abs(lag) < _FIX_LAG_MIN_S or abs(lag) < _FIX_LAG_SIGMAS * se:
        _LOG.debug('fix lag against the Odometry %.1f +- %.1f ms: not taken', 1e3 * lag,
                   1e3 * se)
        # the arm as it fits at no lag (it moves by the speed times the lag, 14 mm per ms
        # at 14 m/s), and only where it is still clear there
        return FixAgainstOdometry(0.0, None if lever_arm is None else significant_arm(0.0))
    _LOG.debug('fix lag against the Odometry %.1f +- %.1f ms', 1e3 * lag, 1e3 * se)
    return FixAgainstOdometry(lag, lever_arm)


#: A twist this many times the positions' speed is in km/h, give or take the tolerance.
_KMH_PER_MPS = 3.6
_KMH_TOLERANCE = 0.25


def _speed_ratio(twist_world: F64, velocities: F64, moving: np.ndarray) -> float:
    """Median ratio of a world twist's speed to the positions' ``velocities`` (over +-0.2 s:
    the +-1 s ones cut the corners of a turn) where moving (0 if never)."""
    speed = np.hypot(velocities[:, 0], velocities[:, 1])
    moving = moving & (speed > 0.0)
    if not moving.any():
        return 0.0
    return float(np.median(np.hypot(twist_world[moving, 0], twist_world[moving, 1])
                           / speed[moving]))


def _twist_mismatch(twist_world: F64, coarse: F64) -> float:
    """Median distance of a world twist from the positions' velocities where moving."""
    moving = np.hypot(coarse[:, 0], coarse[:, 1]) > _TWIST_CHECK_SPEED_MPS
    if not moving.any():
        return 0.0
    return float(np.median(np.linalg.norm(twist_world[moving] - coarse[moving], axis=1)))


def _checked_twist(t: F64, positions: F64, measured: F64, coarse: F64, twist_world: F64,
                   twist_as_given: F64, counters: Counter[str], yaw_rate: F64) -> F64:
    """(n, 3) vehicle velocities: the Odometry twist where it describes the motion of the
    positions, else what does; a twist speed clearly off the positions' is rescaled to them
    (``_speed_scale``).

    The radial-velocity constraint of the final refinement takes the vehicle's velocity at
    its word, so a twist that is not the vehicle's body-frame velocity would turn the
    radar's yaw. Drivers in the field get this wrong in two ways: the twist is left zero,
    or it is published in the parent (ENU) frame instead of ``child_frame_id`` as REP-105
    asks. Both are told from the positions' own motion; what matches is used (the ENU
    reading as it is, else the positions' central differences) and a warning says so.
    ``measured`` and ``coarse`` are the positions' velocities over +-0.2 s (3-D) and +-1 s
    (horizontal, the check's: see ``build_vehicle_track``).
    """
    speed = np.hypot(coarse[:, 0], coarse[:, 1])
    moving = speed > _TWIST_CHECK_SPEED_MPS
    if int(moving.sum()) < _TWIST_CHECK_SAMPLES:
        return np.column_stack([twist_world, measured[:, 2]])
    tolerance = max(_TWIST_TOLERANCE_MPS,
                    _TWIST_TOLERANCE_FRACTION * float(np.median(speed[moving])))

    body, enu = _twist_mismatch(twist_world, coarse), _twist_mismatch(twist_as_given, coarse)
    if body <= tolerance:
        scale = _speed_scale(t, positions, twist_world, moving, yaw_rate)
        if scale != 1.0:
            counters['odometry_speed_scale_permille'] = int(round(1000.0 * (scale - 1.0)))
            _LOG.warning('the Odometry twist speed is %.1f %% off the positions\' on straight '
                         'driving: rescaled to them', 100.0 * (1.0 / scale - 1.0))
        return np.column_stack([scale * twist_world, measured[:, 2]])
    kmh = twist_world / _KMH_PER_MPS
    if (abs(_speed_ratio(twist_world, measured[:, :2], moving) - _KMH_PER_MPS) <= _KMH_TOLERANCE
            and _twist_mismatch(kmh, coarse) <= tolerance):
        # a driver that writes km/h (a tenth probe's): 3.6 times the fixes' speed, and
        # right once divided; better than the positions' differences, and said
        counters['odometry_twist_kmh'] = 1
        _LOG.warning('the Odometry twist is 3.6 times the positions\' speed: read as km/h')
        scale = _speed_scale(t, positions, kmh, moving, yaw_rate)
        return np.column_stack([scale * kmh, measured[:, 2]])
    if enu <= tolerance:
        counters['odometry_twist_in_parent_frame'] = 1
        _LOG.warning('the Odometry twist describes the vehicle\'s motion only read in the '
                     'parent (ENU) frame (median mismatch %.2f m/s, as the child frame %.2f '
                     'm/s): it is used so; REP-105 puts it in child_frame_id', enu, body)
        return np.column_stack([twist_as_given, measured[:, 2]])
    counters['odometry_twist_replaced'] = 1
    _LOG.warning('the Odometry twist does not describe the vehicle\'s motion (median mismatch '
                 '%.2f m/s against the positions, tolerance %.2f m/s): the velocity is taken '
                 'from the positions instead', body, tolerance)
    return measured


#: Straight driving for the speed-scale check [rad/s]; shortest straight stretch [s]; the
#: distance driven on such stretches needed to judge [m]; smallest correction.
_SCALE_STRAIGHT_RPS = 0.05
_SCALE_STRETCH_S = 5.0
_SCALE_DISTANCE_M = 100.0
_SCALE_MIN = 0.003
#: A gap between fixes this long ends a straight stretch [s] (fixes come at 1-50 Hz).
_SCALE_GAP_S = 2.5


def _speed_scale(t: F64, positions: F64, twist_world: F64, moving: np.ndarray,
                 yaw_rate: F64) -> float:
    """Factor that brings the twist's speed to the fixes' (1.0 when they agree).

    Why: the final refinement's radial-velocity fit takes the vehicle's speed at its word,
    and a speed 1 % off (wheel odometry) tilts the fitted pitch by about half a degree
    (seen on an independent recording), 0.3 % by about 0.15 deg. On every straight stretch
    of at least ``_SCALE_STRETCH_S`` the distance the fixes travelled (their path sampled
    once a second: 2 cm of RTK noise over 10 m steps adds nothing) is compared with the
    twist's speed integrated over the same time; the ratio of the sums is the scale, and
    the spread of the stretches' ratios its standard error. (A median of instantaneous
    speed ratios, used before, was itself 0.3 % off on our simulator's exact twist when
    the speed varied, and could only judge errors of 0.6 % and more; this estimate reads
    0.01-0.13 % there.) Corrected when off by ``_SCALE_MIN`` and three standard errors:
    standalone fixes are too noisy to say.
    """
    speed_twist = np.hypot(twist_world[:, 0], twist_world[:, 1])
    use = moving & (np.abs(yaw_rate) < _SCALE_STRAIGHT_RPS) & (speed_twist > 0.5)
    # A stretch ends where the fixes stop: across an outage the vehicle drove on unseen
    # (turned, looped) and the chord from the last fix to the next says nothing of its
    # path; a twenty-third probe's 4-8 s outages between passes read an exact twist as
    # 11-16 % off, 'rescaled' it, and failed the calibration.
    after_gap = np.concatenate([[True], np.diff(t) > _SCALE_GAP_S])
    start = use & (after_gap | ~np.concatenate([[False], use[:-1]]))
    end = use & np.concatenate([start[1:] | ~use[1:], [True]])
    paths, integrals = [], []
    for a, b in zip(np.flatnonzero(start), np.flatnonzero(end)):
        if t[b] - t[a] < _SCALE_STRETCH_S:
            continue
        idx = np.unique(np.concatenate([np.searchsorted(t, np.arange(t[a], t[b], 1.0)),
                                        [b]]))
        # pieces of about 10 s: their spread gives the standard error even on one stretch
        for piece in np.array_split(idx, max(1, round((t[b] - t[a]) / (2 * _SCALE_STRETCH_S)))):
            if piece.size < 2:
                continue
            step = np.diff(positions[piece, :2], axis=0)
            paths.append(float(np.sum(np.hypot(step[:, 0], step[:, 1]))))
            lo, hi = int(piece[0]), int(piece[-1]) + 1
            integrals.append(float(np.sum(0.5 * (speed_twist[lo + 1:hi]
                                                 + speed_twist[lo:hi - 1]) * np.diff(t[lo:hi]))))
    path, integral = np.array(paths), np.array(integrals)
    if path.size < 2 or integral.sum() < _SCALE_DISTANCE_M:
        return 1.0
    scale = float(path.sum() / integral.sum())
    # weighted spread of the stretches' ratios -> standard error of the ratio of sums
    ratio = path / integral
    weight = integral / integral.sum()
    spread = math.sqrt(float(np.sum(weight * (ratio - scale) ** 2)) / (1.0 - np.sum(weight ** 2)))
    se = spread * math.sqrt(float(np.sum(weight ** 2)))
    if abs(scale - 1.0) > max(_SCALE_MIN, 3.0 * se):
        return scale
    return 1.0


def _finite_difference(t: F64, x: F64, half_span_s: float = 0.2) -> F64:
    """Central difference over about +-half_span_s: RTK noise (~2 cm) differentiated over
    one 20 ms step would be ~1.4 m/s of noise; over 0.4 s it is ~0.07 m/s, while the lag
    on a 10 m/s, 15 m radius turn stays a few centimetres per second.

    Always at least one sample either side (one-sided only at the ends): with samples
    sparser than the span (fixes at 1-4 Hz) a forward difference is the velocity half an
    interval later, which the fix-lag check read as fixes 125-500 ms early and 'corrected'
    (a ninth probe: 0.66-1.1 m off along the boresight)."""
    if t.size < 2:
        return np.zeros_like(x)
    lo, hi = _window(t, half_span_s)
    dt = t[hi] - t[lo]
    with np.errstate(divide='ignore', invalid='ignore'):
        v = np.where(dt > 0, (x[hi] - x[lo]) / dt, 0.0)
    return v


#: The course over ground is summed over the time the vehicle takes for this distance
#: [m] either side, within these bounds [s] (see ``_course_over_ground``).
_COURSE_SPAN_M = 2.0
_COURSE_HALF_SPAN_S = (0.2, 0.5)
#: Half span [s] of the local quadratic whose slope is the yaw rate of fixes alone.
_COURSE_RATE_HALF_SPAN_S = 0.2


def _course_over_ground(t: F64, velocities: F64, min_speed: float,
                        counters: Counter[str], positions: F64) -> tuple[F64, F64]:
    """Heading from the course over ground where the speed allows it, held (interpolated
    on the circle) across slow and stopped stretches where the course is noise.

    The course is the direction of the speed-weighted sum of the velocities of the usable
    samples within +-``_COURSE_SPAN_M`` of travel (+-0.2 to 0.5 s): right where the vehicle
    slows through ``min_speed`` a single 0.4 s difference spans only ~0.4 m, so 2 cm of RTK
    noise turns it by ~4 deg; the weighted sum leans on the faster neighbours instead. At
    speed the window shrinks: a car weaving in its lane (+-0.5 m over 25 m) turns its
    heading by +-7 deg within 2.5 s, which +-0.5 s flattened by a quarter (a twelfth
    probe's NavSatFix-only weaving: 21-35 cm along the boresight). A symmetric window adds
    no lag on a steady turn.
    """
    speed = np.hypot(velocities[:, 0], velocities[:, 1])
    good = speed >= min_speed
    weighted = np.where(good[:, None], velocities[:, :2] * speed[:, None], 0.0)
    sums = np.vstack([np.zeros((1, 2)), np.cumsum(weighted, axis=0)])
    half_span_s = np.clip(_COURSE_SPAN_M / np.maximum(speed, 1e-6), *_COURSE_HALF_SPAN_S)
    lo = np.searchsorted(t, t - half_span_s, side='left')
    hi = np.searchsorted(t, t + half_span_s, side='right')
    smoothed = sums[hi] - sums[lo]
    course = np.arctan2(smoothed[:, 1], smoothed[:, 0])
    course = course + np.pi * _reversing(t, course, good, speed, positions, counters)
    if good.sum() >= 2:
        yaw = interp_angle(t, t[good], course[good])
    elif good.any():
        yaw = np.full_like(t, course[good][0])
    else:
        yaw = np.zeros_like(t)
    yaw_rate = _finite_difference(t, np.unwrap(yaw))
    # The rate where the vehicle moves: a local quadratic's slope of each velocity's own
    # direction over +-``_COURSE_RATE_HALF_SPAN_S``, not the smoothed course differenced.
    # The course's window and the difference's each flatten a turn's peak: a fifty-fifth
    # probe's 10 Hz fixes read its turns 10 % slow (0.90 of its INS's rate, 0.043 rad/s of
    # noise), and with the rate's lever arm in every radial velocity the radar went 0.36 m
    # along the boresight where its Odometry's rate gave 0.15; the quadratic reads 0.95
    # (0.038 rad/s), 0.23 m. A quadratic has no lag on a turn that tightens steadily.
    raw = np.unwrap(np.arctan2(velocities[:, 1], velocities[:, 0]))
    fitted = _fix_velocities(t, raw[:, None], _COURSE_RATE_HALF_SPAN_S)[:, 0]
    # only where every sample within reach moves (the direction of a stop is noise)
    slow = np.concatenate([[0], np.cumsum(~good)])
    lo = np.searchsorted(t, t - 1.5 * _COURSE_RATE_HALF_SPAN_S, side='left')
    hi = np.searchsorted(t, t + 1.5 * _COURSE_RATE_HALF_SPAN_S, side='right')
    moving = (slow[hi] - slow[lo] == 0) & np.isfinite(fitted)
    yaw_rate = np.where(moving, fitted, yaw_rate)
    return yaw, yaw_rate


#: A stop across which the course turns by more than this is a change of gear (a car cannot
#: turn while standing) [rad]; the most the vehicle may move during such a stop [m].
_REVERSE_FLIP_RAD = math.radians(135.0)
_REVERSE_STOP_MOVE_M = 3.0


def _reversing(t: F64, course: F64, good: np.ndarray, speed: F64, positions: F64,
               counters: Counter[str]) -> np.ndarray:
    """(n,) True where the vehicle, by its course over ground alone, drove backwards.

    Why: with fixes alone the heading is the course over ground, which points backwards
    while the vehicle reverses, and its box then faces the wrong way (a shuttle that backed
    through the view: 1.7-1.9 m off, outside 2 sigma, an independent probe). A car cannot
    turn while it stands, so a stop (or a slowing below ``min_speed``) across which the
    course turns by more than ``_REVERSE_FLIP_RAD`` while the vehicle stays within
    ``_REVERSE_STOP_MOVE_M`` is a change of gear: the runs of driving on either side face
    the same way, one of them backwards. Which one is told by distance driven: a calibration
    vehicle drives forwards most of the way (on a tie, the faster runs are the forward
    ones). Runs joined by no such stop keep their course.
    """
    reverse = np.zeros(t.size, bool)
    idx = np.flatnonzero(good)
    if idx.size < 2:
        return reverse
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    if starts.size < 2:
        return reverse
    turn = np.abs(wrap_angle(course[starts[1:]] - course[ends[:-1]]))
    moved = np.linalg.norm(positions[starts[1:], :2] - positions[ends[:-1], :2], axis=1)
    flip = (turn > _REVERSE_FLIP_RAD) & (moved < _REVERSE_STOP_MOVE_M)
    if not flip.any():
        return reverse
    # direction of each run within chains of runs joined by gear changes; a chain is broken
    # where the stop between runs says nothing (the vehicle moved, or the course went on)
    gear_change = np.concatenate([[False], flip])
    chain = np.cumsum(~gear_change)
    parity = np.cumsum(gear_change) % 2
    dt = np.gradient(t)
    distance = np.array([float(np.sum(speed[a:b + 1] * dt[a:b + 1]))
                         for a, b in zip(starts, ends)])
    duration = np.array([float(np.sum(dt[a:b + 1])) for a, b in zip(starts, ends)])
    backwards_run = np.zeros(starts.size, bool)
    for c in np.unique(chain[gear_change]):
        runs = np.flatnonzero(chain == c)
        odd = parity[runs] == 1
        d_odd, d_even = distance[runs][odd].sum(), distance[runs][~odd].sum()
        if math.isclose(d_odd, d_even, rel_tol=0.1):
            v_odd = d_odd / max(duration[runs][odd].sum(), 1e-9)
            v_even = d_even / max(duration[runs][~odd].sum(), 1e-9)
            odd_forward = v_odd > v_even
            counters['vehicle_reversed_ambiguous'] += 1
        else:
            odd_forward = d_odd > d_even
        backwards_run[runs] = odd != odd_forward
    for k in np.flatnonzero(backwards_run):
        reverse[starts[k]:ends[k] + 1] = True
    counters['vehicle_reversed_stretches'] += int(backwards_run.sum())
    counters['vehicle_reversed_m'] += int(round(float(distance[backwards_run].sum())))
    return reverse
