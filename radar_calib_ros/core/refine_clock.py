"""The radar's clock in the final refinement (stage 8, ``core/refine.py``): the clock
offset's starting value, the refinement's time axis, and a drifting or stepped clock.

``_scan_time_offset`` gives the fit a coarse start for the offset; ``_pass_time_offsets``
estimates each pass's own offset at the joint fit; ``_clock_step`` and ``_clock_drift`` test
those offsets for a clock that stepped between two passes or runs at a rate of its own, and
return the ``ClockDrift`` the stage refits with. Separate because it is a question about the
radar's stamps that the stage asks between fits, not part of any one fit.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from scipy import stats

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import uncertainty
from radar_calib_ros.core.refine_model import ClockDrift, _Poses, _Selected, _Times
from radar_calib_ros.core.refine_targets import _vehicle_frame
from radar_calib_ros.core.vehicle import box_distance
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, I64, Extrinsics

_LOG = logging.getLogger(__name__)


# --- the clock offset's starting value --------------------------------------------------

def _time_offset_scores(est: Extrinsics, candidates: I64, times: _Times,
                        recording: Recording, poses: _Poses, config: CalibConfig
                        ) -> tuple[F64, F64]:
    """Clock offsets (sorted) and the soft count of moving targets near the box at each,
    for ``est``'s rotation and position."""
    max_off = config.sync.max_time_offset
    # around the bound's centre, and around where stage 6 found agreement (beyond the bound
    # when the fixes' and the Odometry's stamps disagree: ``pipeline._hypotheses``)
    grid = np.union1d(np.arange(-max_off, max_off + 1e-9, 0.02),
                      est.time_offset_s + np.arange(-0.1, 0.1 + 1e-9, 0.02))
    world = est.apply(recording.targets.positions_m[candidates])
    gate = config.refine.gate_m
    scores = np.empty(grid.size)
    for i, tau in enumerate(grid):   # a few dozen offsets, each vectorised over targets
        pos, yaw, _, _, _ = times.poses(poses, tau)
        dist = box_distance(_vehicle_frame(world, pos, yaw)[:, :2], config.vehicle)
        scores[i] = np.sum(np.clip(1.0 - dist / gate, 0.0, 1.0) * times.valid(poses, tau))
    return grid, scores


def _scan_peak(est: Extrinsics, candidates: I64, times: _Times, recording: Recording,
               poses: _Poses, config: CalibConfig) -> tuple[F64, int] | None:
    """The scanned offsets and the index of the best, None where nothing was scanned or
    the score is flat (no better than at ``est``'s own offset)."""
    if config.sync.max_time_offset <= 0.0 or candidates.size == 0:
        return None
    grid, scores = _time_offset_scores(est, candidates, times, recording, poses, config)
    best = int(np.argmax(scores))
    if scores[best] <= 1.001 * scores[int(np.argmin(np.abs(grid - est.time_offset_s)))]:
        return None
    return grid, best


def _scan_time_offset(est: Extrinsics, candidates: I64, times: _Times, recording: Recording,
                      poses: _Poses, config: CalibConfig) -> float:
    """Coarse start for the clock offset: the offset that puts the most moving targets near
    the box (soft count). The fit itself refines it; the scan only keeps a large offset
    (vehicle displaced by metres) from starving the gate. A flat score keeps the given
    offset."""
    peak = _scan_peak(est, candidates, times, recording, poses, config)
    return est.time_offset_s if peak is None else float(peak[0][peak[1]])


def _rescan_time_offset(est: Extrinsics, candidates: I64, times: _Times,
                        recording: Recording, poses: _Poses, config: CalibConfig
                        ) -> float | None:
    """The scan's offset at a fitted rotation and position (``refine._clock_restarted``);
    None where it is no peak: a flat score, or the end of the scanned range."""
    peak = _scan_peak(est, candidates, times, recording, poses, config)
    if peak is None or peak[1] in (0, peak[0].size - 1):
        return None
    return float(peak[0][peak[1]])


# --- clock drift and steps --------------------------------------------------------------

def _radar_clock_s(recording: Recording, config: CalibConfig, stamp_ns: int) -> float:
    """A radar stamp on the refinement's time axis (``_Times``): seconds since the first
    vehicle pose, plus ``sync.time_offset``."""
    return float((int(stamp_ns) - int(recording.vehicle.stamps_ns[0])) * 1e-9
                 + config.sync.time_offset)


def _mid_recording_s(recording: Recording, config: CalibConfig) -> float:
    """The middle of the radar's frames on the refinement's time axis: where a drifting
    clock's offset is reported (``ClockDrift.reference_s``)."""
    stamps = recording.frame_stamps_ns
    return _radar_clock_s(recording, config, int(stamps[0] + (stamps[-1] - stamps[0]) // 2))


def _pass_time_offsets(pc: uncertainty.PassCovariance, data: _Selected,
                       tau: float) -> list[list[float]]:
    """(time [s], clock offset [s], information [1/s^2]) of each pass: the one-step
    estimate of the offset from that pass's targets alone, everything else held at the
    joint fit (its own gradient and curvature along the offset)."""
    t_s = data.times.t_s
    out = []
    for p in range(pc.n_passes):
        m = data.pass_id == p
        information = float(pc.hessians[p, 6, 6])
        if not m.any() or information <= 0.0:
            continue
        out.append([float(np.median(t_s[m])), tau - float(pc.gradients[p, 6]) / information,
                    information])
    return out


#: Clock drift: the fewest passes it is judged on, the two-sided false-alarm rate of its
#: t-test (the offsets' scatter about the line, not their formal precision, sets its
#: error: reflection-model errors move a pass's offset more than its noise), and the least
#: rate worth a second fit (20 ppm: 12 ms over ten minutes, 18 cm at 15 m/s at the ends,
#: half of which the fit's constant offset takes).
_DRIFT_MIN_PASSES = 5
_DRIFT_FALSE_ALARM = 0.001
_DRIFT_MIN_RATE = 20e-6
#: No pass weighs more than this many times the median pass in the line: a
#: turn gives one pass ten times the information of a straight one, which the model error
#: does not share; a fifty-eighth probe's 1000 ppm over six minutes, plain in 16 passes'
#: offsets, was refused at 3.8 sigma for two turning passes that held the line flat (4.5
#: with this cap, 5.3 with equal weights).
_WEIGHT_CAP = 2.0


def _capped_weights(information: F64) -> F64:
    """The passes' weights in the line through their offsets, summing to 1."""
    w = np.minimum(information, _WEIGHT_CAP * float(np.median(information)))
    return w / w.sum()


#: Clock step: the fewest passes on either side of it, its least size worth a refit [s],
#: and how much less scatter than a straight line it must leave (a drift is a line).
_STEP_MIN_SIDE = 2
_STEP_MIN_S = 0.02
_STEP_BETTER = 0.5


def _clock_step(offsets: list[list[float]], at_s: float | None = None) -> ClockDrift | None:
    """A step of the radar clock's offset between two passes, from the passes' clock
    offsets, or None when they show none clearly (or, with ``at_s``, what is left of a
    step found there before, taken when two standard errors clear of zero).

    Why: a radar whose clock is set by NTP mid-recording, or reboots, or whose driver is
    restarted to stamp on reception, steps its offset by tens to hundreds of milliseconds.
    A straight line through the passes' offsets (``_clock_drift``) then misplaces the
    passes at both ends and names a drift that is not there (a sixteenth probe: +0.15 s at
    565 s of 25 minutes taken for -91 ppm, delta_op 0.36 m against 0.17). The step is put
    between the two passes where two constant offsets fit best; it is taken when it leaves
    less than ``_STEP_BETTER`` of the line's scatter and stands clear of that scatter (a
    t-test at the drift's false-alarm rate, divided among the places tried).
    """
    if len(offsets) < _DRIFT_MIN_PASSES:
        return None
    rows = np.array(sorted(offsets), float)
    t, tau, w = rows[:, 0], rows[:, 1], rows[:, 2] / rows[:, 2].sum()
    n = t.size
    splits = (np.arange(_STEP_MIN_SIDE, n - _STEP_MIN_SIDE + 1) if at_s is None
              else np.array([int(np.searchsorted(t, at_s))]))
    splits = splits[(splits >= 1) & (splits <= n - 1)]
    if splits.size == 0:
        return None
    cum_w, cum_wt = np.cumsum(w), np.cumsum(w * tau)
    w_a, w_b = cum_w[splits - 1], 1.0 - cum_w[splits - 1]
    m_a = cum_wt[splits - 1] / w_a
    m_b = (cum_wt[-1] - cum_wt[splits - 1]) / w_b
    side = np.arange(n)[None, :] >= splits[:, None]
    fitted = np.where(side, m_b[:, None], m_a[:, None])
    rss = np.sum(w[None, :] * (tau[None, :] - fitted) ** 2, axis=1)
    k = int(np.argmin(rss))
    j, step = int(splits[k]), float(m_b[k] - m_a[k])
    dof = n - 2
    sigma = math.sqrt(float(rss[k]) / dof * (1.0 / w_a[k] + 1.0 / w_b[k]))
    at = 0.5 * (t[j - 1] + t[j]) if at_s is None else at_s
    # the reference on the side with the more information: its offset is the one reported
    reference = float(t[j:].mean() if w_b[k] > w_a[k] else t[:j].mean())
    if at_s is not None:
        if abs(step) < 2.0 * sigma:
            return None
        return ClockDrift(0.0, reference, sigma, step, at)
    _, line_rss, _ = _weighted_line(t, tau, w)
    critical = float(stats.t.ppf(1.0 - _DRIFT_FALSE_ALARM / (2.0 * splits.size), dof))
    _LOG.debug('clock step from %d passes: %.1f +- %.1f ms at %.0f s (needs %.1f sigma), '
               'scatter %.2f of the line\'s', n, 1e3 * step, 1e3 * sigma, at, critical,
               float(rss[k]) / max(line_rss, 1e-18))
    if (abs(step) < max(_STEP_MIN_S, critical * sigma)
            or float(rss[k]) >= _STEP_BETTER * line_rss):
        return None
    return ClockDrift(0.0, reference, sigma, step, at)


def _weighted_line(t: F64, tau: F64, w: F64) -> tuple[float, float, float]:
    """(slope, weighted residual sum of squares, weighted spread of ``t``) of the line
    through the passes' clock offsets ``tau`` at times ``t``, weights ``w`` summing to 1."""
    t_mean = float(np.sum(w * t))
    spread = float(np.sum(w * (t - t_mean) ** 2))
    rate = float(np.sum(w * (t - t_mean) * (tau - np.sum(w * tau)))) / max(spread, 1e-12)
    rss = float(np.sum(w * (tau - np.sum(w * tau) - rate * (t - t_mean)) ** 2))
    return rate, rss, spread


def _clock_drift(offsets: list[list[float]], reference_s: float,
                 found: bool = False) -> ClockDrift | None:
    """The radar clock's drift against the poses' from the passes' clock offsets, or None
    when they show none clearly.

    Why: a radar that stamps its scans with a clock of its own (no PTP or NTP) runs
    20-200 ppm off the GNSS time; over a twenty-minute drive 200 ppm is a quarter of a
    second, metres at driving speed. One offset for the whole recording then fits none
    of the passes, and where the directions driven change over time it lies along the
    boresight (an eleventh probe: 29 cm, against 4 cm without the drift). Each pass's
    offset is estimated alone (``_pass_time_offsets``); a straight line through them
    (weighted by their information, its error from their scatter about it) gives the rate.
    With ``found`` (a drift already corrected for), what is left of it is taken when it
    stands two standard errors clear of zero.
    """
    if len(offsets) < _DRIFT_MIN_PASSES:
        return None
    t, tau, information = (np.array(v, float) for v in zip(*offsets))
    w = _capped_weights(information)
    rate, rss, spread = _weighted_line(t, tau, w)
    if spread <= 0.0:
        return None
    dof = t.size - 2
    scatter = rss * t.size / dof
    sigma = math.sqrt(scatter / (spread * t.size))
    critical = 2.0 if found else float(stats.t.ppf(1.0 - _DRIFT_FALSE_ALARM / 2.0, dof))
    _LOG.debug('clock drift from %d passes: %.1f +- %.1f ppm (needs %.1f sigma)', t.size,
               1e6 * rate, 1e6 * sigma, critical)
    if abs(rate) < critical * sigma or (abs(rate) < _DRIFT_MIN_RATE and not found):
        return None
    return ClockDrift(rate, reference_s, sigma)
