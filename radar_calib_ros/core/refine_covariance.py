"""What the final refinement's (stage 8, ``core/refine.py``) result is worth: the checks
that the fit did not run off or blend two mounts, and the terms its reported covariance adds
to the jackknifes over passes and range bands.

The divergence check (``_check_not_diverged``, ``_Diverged``) refuses a fit that ran far
from the paper's stages; the halves check (``_halves_disagreement``,
``_turn_between_passes``) finds drives whose first and second halves disagree. The
"consider" terms put into the covariance what the data cannot show: a front/rear or
range-dependent reflection height (``_height_difference_shift``, ``_height_shift``), the
start's own error where only the prior holds the position (``_start_term``), and the lines
and lanes the vehicle's targets lie along (``_line_axis``, ``_lane_separation``,
``_position_spread``). Separate because these act on a finished fit, its Jacobian and its
per-pass terms (``uncertainty.PassCovariance``), never inside it.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, uncertainty
from radar_calib_ros.core.refine_model import (_START_SIGMA_M, _Model, _Poses,
                                               _Selected)
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, I64, Extrinsics, MountTurn

_LOG = logging.getLogger(__name__)


# --- the range bands of the second jackknife --------------------------------------------

#: Range bands of the second jackknife (``uncertainty.combined_covariance``): six, so the
#: t-factor of its five degrees of freedom stays near 1.3.
_RANGE_BANDS = 6


def _range_bands(data: _Selected) -> I64:
    """(n,) range band (0 .. _RANGE_BANDS - 1, equal information weight each) of each
    target, for the jackknife over range bands."""
    rng = np.linalg.norm(data.sensor_m, axis=1)
    weight = data.sqrt_weight ** 2
    order = np.argsort(rng)
    cum = np.cumsum(weight[order])
    quantiles = np.arange(1, _RANGE_BANDS) / _RANGE_BANDS
    edges = rng[order][np.searchsorted(cum, cum[-1] * quantiles)]
    return np.searchsorted(edges, rng).astype(np.int64)


#: Fewest passes the jackknife over passes is left to alone; a drive of fewer is split by
#: the vehicle's heading (``_jackknife_groups``), in steps of this many degrees.
_MIN_JACKKNIFE_PASSES = 3
_HEADING_GROUP_DEG = 45.0


def _jackknife_groups(pass_id: I64, heading_rad: F64) -> I64:
    """(n,) the groups the jackknife leaves out one at a time: the passes, or where there
    are fewer than ``_MIN_JACKKNIFE_PASSES`` of them, each pass split by the vehicle's
    heading (``_HEADING_GROUP_DEG`` steps from its first).

    Why: a car looping inside the view (a car park's aisles, a campus block) is one drive
    through it, or two, though it showed the radar every side from many bearings. Left out
    one pass at a time, one or two passes have no agreement to measure: the fallback and
    the t-factor of one degree of freedom put a sixty-fourth probe's 6 cm calibrations at
    a reported 93 m, 22 deg and 0.29 s. The stretches of such a drive in one heading are
    views of the car as different as passes are (each its own sides from its own
    bearings), and their agreement is what the calibration rests on."""
    passes = np.asarray(pass_id, np.int64)
    if passes.size == 0 or np.unique(passes).size >= _MIN_JACKKNIFE_PASSES:
        return passes
    heading = np.asarray(heading_rad, float)
    step = math.radians(_HEADING_GROUP_DEG)
    groups = np.empty_like(passes)
    for g in np.unique(passes):            # one or two passes
        m = passes == g
        first = heading[np.flatnonzero(m)[0]]
        groups[m] = np.floor((heading[m] - first) / step + 0.5).astype(np.int64)
    # numbered 0..G-1 over (pass, heading step)
    _, out = np.unique(np.column_stack([passes, groups]), axis=0, return_inverse=True)
    return out.ravel().astype(np.int64)


# --- divergence checks: a fit that ran off, halves that disagree --------------------------

#: Chi-square (3 degrees of freedom, 0.1 %) of the rotation difference between the halves
#: of the drives beyond which they disagree: on 53 of our simulator's ten-minute runs
#: (nine scenarios, seeds 1-2, three scatter models) it stayed at or below 4.8; on a
#: fourth probe's recording whose pole turned 1.5 deg halfway it was 38.
_HALVES_CHI2 = 16.27


#: Farthest the final refinement may take the estimate from the paper's stages' [m, deg]:
#: those are decimetres and about a degree off (on our benches the refinement moves them
#: by at most ~2 m, on mid-block views); a fit that runs farther is following something
#: else (a fourth probe's folded radial velocities took it 120 m and 173 deg away).
_MAX_SHIFT_M = 5.0
_MAX_TURN_DEG = 10.0
#: How far the fit may tilt the radar and move it vertically from the paper's stages where
#: it moves it neither horizontally nor in yaw beyond the limits above [deg, m]
#: (``_check_not_diverged``): a plane tilted by clutter, not a run-off. From how much of
#: either the start's plane is named as wrong [deg, m].
_MAX_PLANE_TILT_DEG = 30.0
_MAX_PLANE_HEIGHT_M = 20.0
_PLANE_TILT_DEG = 3.0
_PLANE_HEIGHT_M = 2.0
#: What most often puts radial velocities off the vehicle's motion, for the failures above.
_VELOCITY_SUSPECTS = "folded at the radar's unambiguous limit, or a scale or sign error?"


class _Diverged(InsufficientDataError):
    """The fit ran ``shift_m`` and ``turn_deg`` from the paper's estimate
    (``_check_not_diverged``)."""

    def __init__(self, stage: str, message: str, shift_m: float, turn_deg: float) -> None:
        super().__init__(stage, message)
        self.shift_m = shift_m
        self.turn_deg = turn_deg


def _check_not_diverged(start: Extrinsics, est: Extrinsics, planar: bool = False
                        ) -> tuple[float, float] | None:
    """Raise when the fit ran beyond ``_MAX_SHIFT_M`` / ``_MAX_TURN_DEG`` from the paper's
    stages; horizontally only for a 2-D radar (``planar``), whose altitude starts at the
    vehicle's and is found from the radial velocities metres higher.

    A run in tilt and height alone is no run-off: the paper's roll and pitch come from
    stage 4's plane, and where clutter near the radar tilted that (a thirty-ninth probe's
    spray, 100-300 returns a frame within 15 m: the plane 11 deg off and through the radar,
    so the start 12 deg and 6.6 m off), the vehicle's own elevations take the fit back to
    the road: it moved 12.3 deg and 6.6 m, to within 0.1 deg of the truth, and was refused.
    What runs off follows radial velocities that do not match (a yaw and a horizontal
    position), never the tilt alone. Returns (tilt [deg], vertical shift [m]) of such a
    run beyond ``_PLANE_TILT_DEG`` or ``_PLANE_HEIGHT_M``, else None.
    """
    turn = Rotation.from_matrix(est.rotation @ start.rotation.T).as_rotvec()
    angle = float(np.linalg.norm(turn))
    moved = est.translation_m - start.translation_m
    horizontal = float(np.hypot(moved[0], moved[1]))
    shift = horizontal if planar else float(np.linalg.norm(moved))
    yaw_deg = abs(math.degrees(float(turn[2])))
    tilt_deg = math.degrees(float(np.hypot(turn[0], turn[1])))
    vertical = abs(float(moved[2]))
    within = shift <= _MAX_SHIFT_M and math.degrees(angle) <= _MAX_TURN_DEG
    plane_only = (not planar and horizontal <= _MAX_SHIFT_M and yaw_deg <= _MAX_TURN_DEG
                  and tilt_deg <= _MAX_PLANE_TILT_DEG and vertical <= _MAX_PLANE_HEIGHT_M)
    if not (within or plane_only):
        raise _Diverged(
            'refine', f'the final refinement ran {shift:.1f} m and {math.degrees(angle):.1f} '
            'deg away from the paper\'s stages\' estimate (decimetres and about a degree '
            'off): it follows something other than the vehicle, most likely radial '
            f'velocities off its motion ({_VELOCITY_SUSPECTS})', shift, math.degrees(angle))
    if tilt_deg > _PLANE_TILT_DEG or vertical > _PLANE_HEIGHT_M:
        return tilt_deg, float(moved[2])
    return None


def _halves_disagreement(shift: F64 | None, cov7: F64,
                         geometry: tuple[F64, F64] | None = None
                         ) -> tuple[float, float] | None:
    """(rotation [deg], translation [m]) between the halves of the drives when their
    rotations differ beyond the reported covariance (the difference of two half-estimates
    has about four times the variance of the whole), else None. Rotation only: the
    translation's reported sigma carries model terms every half shares.

    ``geometry`` (``_halves_geometry``): the difference's covariance from each half's own
    information, and the whole's, from the passes' Hessians. The four times hold for halves
    that see alike; halves on different roads (the first along one, the second turning
    through the view) each see little of what the other shows, and their one-step
    estimates part by far more: a seventy-third probe's four- and five-pass drives were told
    'the halves disagree, the radar may have moved' at 17-31 (chi-square) with an actual
    error of centimetres, where their own information made it 0.4-0.9. The difference must
    then lie beyond both: the reported covariance scaled by the halves' geometry (its
    ratio to the whole's Hessian) as well.
    """
    if shift is None:
        return None
    d_rot = shift[:3]
    if _rotation_chi2(d_rot, cov7, 4.0) <= _HALVES_CHI2:
        return None
    if geometry is not None:
        apart, whole = geometry
        scale = float(np.trace(cov7[:3, :3]) / max(np.trace(whole[:3, :3]), 1e-30))
        if float(d_rot @ np.linalg.solve(scale * apart[:3, :3], d_rot)) <= _HALVES_CHI2:
            return None
    return float(np.degrees(np.linalg.norm(d_rot))), float(np.linalg.norm(shift[3:6]))


def _halves_geometry(passes: uncertainty.PassCovariance, prior_hessian: F64
                     ) -> tuple[F64, F64] | None:
    """((p, p) covariance of the halves' difference from each half's own Hessian and the
    priors, (p, p) the whole's inverse Hessian), for the halves of ``_halves_shift``; None
    with fewer than four passes or no per-pass Hessians."""
    if passes.n_passes < 4 or passes.hessians.shape[0] != passes.n_passes:
        return None
    later = np.arange(passes.n_passes) >= passes.n_passes // 2
    total = passes.hessians.sum(axis=0)
    second = passes.hessians[later].sum(axis=0)
    apart = (uncertainty._inverse(total - second + prior_hessian)
             + uncertainty._inverse(second + prior_hessian))
    return apart, uncertainty._inverse(total + prior_hessian)


def _halves_shift(passes: uncertainty.PassCovariance, prior_hessian: F64) -> F64 | None:
    """(p,) one-step estimate from the first half of the passes (in time: pass ids run in
    time order) minus that from the second half, None with fewer than four passes."""
    if passes.n_passes < 4:
        return None
    shift: F64 = -_split_step(passes, prior_hessian, passes.n_passes // 2)
    return shift


def _split_step(passes: uncertainty.PassCovariance, prior_hessian: F64, k: int) -> F64:
    """(p,) one-step estimate from the passes from ``k`` on (in time) minus that from the
    passes before it."""
    later = (np.arange(passes.n_passes) >= k).astype(np.int64)
    influences = uncertainty.group_influences(passes, later, prior_hessian)
    # influences[g]: the step that leaving group g out takes, i.e. towards the other group
    step: F64 = influences[0] - influences[1]
    return step


def _rotation_chi2(rotation_step: F64, cov7: F64, scale: float) -> float:
    """Chi-square of a rotation difference (3,) [rad] against ``scale`` times the rotation
    block of ``cov7``."""
    return float(rotation_step @ np.linalg.solve(scale * cov7[:3, :3], rotation_step))


def _turn_between_passes(passes: uncertainty.PassCovariance, prior_hessian: F64, cov7: F64,
                         data: _Selected, recording: Recording, estimate: Extrinsics,
                         config: CalibConfig) -> MountTurn | None:
    """Where the drives' halves disagree: the moment between two passes at which the
    rotations of the passes before and after differ most beyond the reported covariance,
    as a turn of the mount, when that is beyond ``_HALVES_CHI2`` with at least
    ``hypotheses.min_passes`` passes on each side; else None.

    Why: a turn that stage 6 did not see (its per-track rotations scatter by a degree, and
    a pitch or roll does not show in them at all) leaves a blend of two mounts, which the
    halves check only widens the uncertainty over (a simulated 4 deg re-aim between the
    third and the fourth of six passes: right, at 2.9 deg 1 sigma). Split where the step is,
    each side is one mount, and the later one is the radar as it is now.
    """
    n, least = passes.n_passes, config.hypotheses.min_passes
    best: tuple[float, int, F64] | None = None
    for k in range(least, n - least + 1):
        step = _split_step(passes, prior_hessian, k)
        # the difference of two part-estimates has G/k + G/(G-k) times the variance of
        # the whole
        chi2 = _rotation_chi2(step[:3], cov7, n / k + n / (n - k))
        if chi2 > _HALVES_CHI2 and (best is None or chi2 > best[0]):
            best = (chi2, k, step)
    if best is None:
        return None
    _, k, step = best
    at_ns, gap = _turn_moment(k, data, recording, estimate, config)
    yaw, tilt = math.degrees(step[2]), math.degrees(math.hypot(step[0], step[1]))
    return MountTurn(at_ns, gap, yaw, k, n - k, tilt)


def _turn_moment(k: int, data: _Selected, recording: Recording, estimate: Extrinsics,
                 config: CalibConfig) -> tuple[int, tuple[int, int]]:
    """The radar stamp at which the mount turned between pass ``k - 1`` and pass ``k``
    (``hypotheses.turn_moment_ns``), and the gap between those passes' targets [ns]."""
    stamps = recording.stamps_of(data.index)
    gap = (int(stamps[data.pass_id == k - 1].max()), int(stamps[data.pass_id == k].min()))
    local = recording.targets.positions_m[data.index]
    reach = float(np.hypot(local[:, 0], local[:, 1]).max()) + config.hypotheses.pass_margin_m
    at_ns = hypotheses.turn_moment_ns(recording.vehicle, estimate.translation_m[:2], reach,
                                      gap, config.sync.time_offset + estimate.time_offset_s)
    return at_ns, gap


#: A step in the passes' yaw (``_yaw_step_between_passes``) is a turn of the mount from
#: this many standard errors of the step, and this size [deg], on. (Without a turn the
#: largest step was at most 2.0 standard errors on 33 bench and 38 independent recordings;
#: a thirty-sixth probe's knocks of 1.5-3 deg were at 5.6-13.)
_YAW_STEP_Z = 5.0
_YAW_STEP_MIN_DEG = 0.3
#: The same where the reference's roll and pitch errors are held in the step's error
#: (``yaw_step``'s ``tilt_sigma``): the steps that views unlike on either side made of a
#: tilt, up to 7.5 standard errors without it (a forty-eighth probe's radar seen head-on
#: and at the edge of its view), are 1.8 at most with it on 40 evaluations of radars that
#: did not move during the drive, where a forty-first probe's 1 deg knock stands at 4.6.
YAW_STEP_TILT_Z = 4.0


def _pass_yaws(jacobian: F64, residuals: F64, data: _Selected, n_passes: int
               ) -> tuple[F64, F64]:
    """(G,) each pass's yaw [rad] from its radial velocities alone, all else held at the
    fit (one Gauss-Newton step on the yaw column of the velocity rows), and its weight
    (the inverse variance, from the whitened rows). ``jacobian`` and ``residuals`` are
    the weighted rows of the fit: 3n position rows, then n velocity rows."""
    n = data.index.size
    column = jacobian[3 * n:, 2]
    rows = residuals[3 * n:]
    hessian = np.bincount(data.pass_id, column * column, n_passes)
    gradient = np.bincount(data.pass_id, column * rows, n_passes)
    with np.errstate(invalid='ignore', divide='ignore'):
        yaw = -gradient / hessian
    return yaw, hessian


def _yaw_change(jacobian: F64, residuals: F64, prior_jacobian: F64, prior_residuals: F64,
                data: _Selected, k: int) -> float:
    """The yaw [rad] of the passes from ``k`` on less that of those before, every other
    parameter shared and fitted with it (one Gauss-Newton step from the blended fit: the
    passes' own yaws, each with all else held at the blend, show about half of it)."""
    later = np.concatenate([np.repeat(data.pass_id, 3), data.pass_id]) >= k
    extra = np.where(later, jacobian[:, 2], 0.0)
    full = np.column_stack([jacobian, extra])
    prior = np.column_stack([prior_jacobian, np.zeros(prior_jacobian.shape[0])])
    hessian = full.T @ full + prior.T @ prior
    gradient = full.T @ residuals + prior.T @ prior_residuals
    return float(-np.linalg.lstsq(hessian, gradient, rcond=None)[0][-1])


def yaw_step(yaw: F64, weight: F64, least: int, tilt_shift: F64 | None = None,
             tilt_sigma: F64 | None = None, min_z: float = _YAW_STEP_Z) -> int | None:
    """The first pass after a step in the passes' yaws (``yaw`` (G,) [rad], ``weight`` their
    inverse variances), where the step is ``min_z`` standard errors and
    ``_YAW_STEP_MIN_DEG`` or more with at least ``least`` passes on each side, else None.
    The standard error grows with the passes' scatter about their side's mean beyond their
    formal errors (passes whose yaw the radial velocities measure less well than they
    say). An error of the reference's roll and pitch (1-sigma ``tilt_sigma`` (2,) [rad])
    is common to every pass but moves each by what its view mixes of tilt into yaw
    (``tilt_shift`` (G, 2), ``metrics.PassYaws``): the sides' means are taken by
    generalised least squares with it, so that passes of unlike views tell it apart from
    a step where they can, and the step's error holds it where they cannot."""
    n = yaw.size
    if n < 2 * least or not (np.all(np.isfinite(yaw)) and np.all(weight > 0.0)):
        return None
    covariance = np.diag(1.0 / weight)
    if tilt_shift is not None and tilt_sigma is not None:
        covariance += (tilt_shift * np.asarray(tilt_sigma, np.float64) ** 2) @ tilt_shift.T
    information = np.linalg.inv(covariance)
    best: tuple[float, int, float] | None = None
    for k in range(least, n - least + 1):
        sides = np.zeros((n, 2))
        sides[:k, 0] = sides[k:, 1] = 1.0
        normal = sides.T @ information @ sides
        means = np.linalg.solve(normal, sides.T @ information @ yaw)
        residual = yaw - sides @ means
        scale2 = max(1.0, float(residual @ information @ residual) / (n - 2))
        step = float(means[1] - means[0])
        contrast = np.array([-1.0, 1.0])
        z = abs(step) / math.sqrt(scale2 * float(contrast @ np.linalg.solve(normal, contrast)))
        if best is None or z > best[0]:
            best = (z, k, step)
    assert best is not None
    z, k, step = best
    _LOG.debug('passes\' own yaws %s deg: largest step %+.2f deg after pass %d (%.1f standard '
               'errors)', np.round(np.degrees(yaw), 2).tolist(), math.degrees(step), k, z)
    if z < min_z or abs(math.degrees(step)) < _YAW_STEP_MIN_DEG:
        return None
    return k


def _yaw_step_between_passes(jacobian: F64, residuals: F64, prior_jacobian: F64,
                             prior_residuals: F64, data: _Selected, n_passes: int,
                             recording: Recording, estimate: Extrinsics,
                             config: CalibConfig) -> MountTurn | None:
    """A turn of the mount about the vertical between two passes, seen as a step in the
    passes' own yaws (``_pass_yaws``), else None.

    Why: the predicted radial velocities depend on the rotation and the clock, not on where
    the radar stands or on which part of the car reflected, so each pass measures the yaw
    on its own to a tenth of a degree, whatever the reflection model. A knock of the mount
    between passes makes those yaws step; the halves check (``_halves_disagreement``)
    compares the whole fit's halves against the reported uncertainty, whose model terms
    the halves share, and missed every 1.5 deg knock of a thirty-sixth probe (the result
    between the two mounts: 0.4-0.8 m and 0.25-0.75 deg off the mount as it is now). The
    step is taken where it is largest against the passes' scatter on either side (a fit
    that blends two mounts leaves each side at about half the turn), with at least
    ``hypotheses.min_passes`` passes on each.
    """
    yaw, weight = _pass_yaws(jacobian, residuals, data, n_passes)
    k = yaw_step(yaw, weight, config.hypotheses.min_passes)
    if k is None:
        return None
    at_ns, gap = _turn_moment(k, data, recording, estimate, config)
    change = _yaw_change(jacobian, residuals, prior_jacobian, prior_residuals, data, k)
    return MountTurn(at_ns, gap, math.degrees(change), k, n_passes - k, 0.0)


# --- the covariance's consider terms ----------------------------------------------------

def _line_axis(world: F64, data: _Selected) -> tuple[F64, F64, float]:
    """Horizontal unit direction (3,) in which the fitted targets spread most (the road's,
    where they lie along one road), their information-weighted centre (3,) [m], and their
    spread across it [m] (1 sigma): small where every target lies along one road through
    the view."""
    weight = data.sqrt_weight ** 2
    centre = np.average(world, axis=0, weights=weight)
    values, axes = np.linalg.eigh(np.cov((world[:, :2] - centre[:2]).T, aweights=weight))
    return (np.array([axes[0, 1], axes[1, 1], 0.0]), centre,
            math.sqrt(max(float(values[0]), 0.0)))


#: Least share of the information each direction along the road must hold to count.
_DIRECTION_SHARE = 0.1


def _lane_separation(world: F64, velocity: F64, axis: F64, data: _Selected) -> float | None:
    """Distance [m] across the road ``axis`` between the mean positions of the targets
    seen driving one way and those seen driving the other; None where one way holds less
    than ``_DIRECTION_SHARE`` of the information (a one-way street)."""
    weight = data.sqrt_weight ** 2
    forward = velocity[:, :2] @ axis[:2] >= 0.0
    if min(weight[forward].sum(), weight[~forward].sum()) < _DIRECTION_SHARE * weight.sum():
        return None
    lateral = world[:, :2] @ np.array([-axis[1], axis[0]])
    return abs(float(np.average(lateral[forward], weights=weight[forward])
                     - np.average(lateral[~forward], weights=weight[~forward])))


def _position_spread(data: _Selected, poses: _Poses, offset_s: float) -> float:
    """RMS horizontal distance [m] of the vehicle positions behind the fit's targets from
    their information-weighted mean (at least a car length)."""
    pos = poses.at(data.times.frame_t + offset_s)[0][data.times.inverse, :2]
    weight = data.sqrt_weight ** 2
    mean = np.average(pos, axis=0, weights=weight)
    spread = math.sqrt(float(np.average(np.sum((pos - mean) ** 2, axis=1), weights=weight)))
    return max(spread, 5.0)


def _height_difference_shift(model: _Model, x: F64, jacobian: F64, sqrt_w: F64,
                             j_prior: F64) -> F64:
    """Change of the fitted parameters per metre of front/rear reflection height difference.

    The profile keeps one reflection height for every aspect, because a height that differs
    between the front and the rear is confounded with the radar's roll wherever the lanes
    towards the radar lie on one side of it and those away on the other (see
    ``core/reflection.py``). Real cars do differ (engine block and grille at the front, boot
    and bumper at the rear), and that difference tilts the fit by about the height
    difference over the lanes' lateral spread: decimetres over a few metres, i.e. half a
    degree, for a radar looking along a road (measured on the simulator: roll errors of
    0.4-0.55 deg on mid-block views, reported at 0.19-0.26 deg). Its effect is a "consider"
    term: the linearised shift of the solution for a height offset of cos(aspect), which the
    caller scales by ``refine.model_sigma_height_difference_m``. Over 108 simulated
    ten-minute runs (three scatter models) the 95 % rotation ellipsoid covered 94 / 89 / 91 %
    of the errors (interior / mixed / skin) without it and 100 / 92 / 91 % with 0.1 m; it
    adds about 0.05 deg where diverse views pin the tilt and 0.5 deg on mid-block views.
    The linearisation gives the direction of the tilt but, on a synthetic head-on scene,
    about a quarter of its size (the gate and weights of the later rounds follow the data).
    """
    return _height_shift(model, x, jacobian, sqrt_w, j_prior,
                         np.cos(model.geometry(x, jacobian=False)['aspect']))


def _height_shift(model: _Model, x: F64, jacobian: F64, sqrt_w: F64, j_prior: F64,
                  offset_m: F64) -> F64:
    """Linearised change of the fitted parameters for the vehicle's targets raised by
    ``offset_m`` (n,) [m] each (a consider term, as ``_height_difference_shift``)."""
    d = model.data
    dz = np.zeros((d.index.size, 3))
    dz[:, 2] = -np.asarray(offset_m, float)
    dr = np.concatenate([(np.einsum('nij,nj->ni', d.whiten, dz) * d.sqrt_weight[:, None]).ravel(),
                         np.zeros(d.index.size)]) * sqrt_w
    jw = jacobian * sqrt_w[:, None]
    h = jw.T @ jw + j_prior.T @ j_prior
    shift: F64 = -np.linalg.solve(h, jw.T @ dr)
    return shift


def _yaw_rate_shift(model: _Model, x: F64, jacobian: F64, sqrt_w: F64, j_prior: F64) -> F64:
    """Linearised change of the fitted parameters per unit relative error of the vehicle's
    yaw rate (a consider term, as ``_height_difference_shift``).

    The radial velocity of a target ahead of or behind the reference point carries the
    rate times its lever arm across the line of sight, and the lever arm holds the radar's
    position: that is what pins the position on many drives, so the fit leans on the rate
    as given. From an INS it is a gyro's; from fixes alone it is differentiated twice, and
    its errors (a few per cent in turns, noise on straights, which the fit reads as a
    shorter lever) move the radar along the line of sight.
    """
    g = model.geometry(x, jacobian=False)
    d = model.data
    lever, rate = g['rel'], g['rate']
    point = rate[:, None] * np.column_stack([-lever[:, 1], lever[:, 0], np.zeros(rate.size)])
    dv = np.einsum('ij,ij->i', point, g['unit_v'])
    dr = np.concatenate([np.zeros(3 * d.index.size), dv / d.sigma_v * d.sqrt_weight]) * sqrt_w
    jw = jacobian * sqrt_w[:, None]
    h = jw.T @ jw + j_prior.T @ j_prior
    shift: F64 = -np.linalg.solve(h, jw.T @ dr)
    return shift


#: How far the start may leave the radar along a direction the final fit's data do not
#: measure, in vehicle lengths, where the vehicle is seen heading along the boresight (see
#: ``start_error_m``) ...
_START_ERROR_LENGTHS = 0.5
#: ... and where it is seen crossing the view or turning through it [m].
_START_ERROR_CROSSING_M = 1.0
#: Share of the information seen heading along the boresight from which the start may be
#: ``_START_ERROR_LENGTHS`` off (``start_error_m``).
_ALONG_SHARE_FULL = 0.9


def along_boresight_share(yaw_rad: F64, weights: F64, boresight_rad: float) -> float:
    """Share of the information (``weights``) seen while the vehicle headed towards or away
    from the radar (``uncertainty.near_axis`` of the boresight, heading ``yaw_rad``)."""
    total = float(np.sum(weights))
    if total <= 0.0:
        return 0.0
    return float(np.sum(weights * uncertainty.near_axis(yaw_rad, boresight_rad)) / total)


def start_error_m(along_share: float, config: CalibConfig) -> float:
    """How far the paper's stages may have left the radar [m] (1 sigma), from the share of
    the information seen heading along the boresight (``along_boresight_share``).

    Seen only head-on and tail-on, the vehicle's tracks reflect at its front when it comes
    and at its rear when it goes, and the paper's stages can be a car length off along the
    boresight (a twentieth probe: 1-4 m). The fit starts midway between the two ends that
    brackets (``polygon.bracketed_start``), and where it converges from there its
    reflection profile places the car: half a car length covers what was measured there
    (a twentieth probe's straight drives 0.8 m median, 2.2 m at most; a fifty-second
    probe's kerb and gantry radars 0.06-0.29 m; our simulator's radar looking down a road
    away from its junction 0.05-1.24 m on six runs, skin and interior). A car length there
    reported 4.4-4.8 m at those errors (a fifty-second probe: 30-75 times its errors, and
    its evaluation 6.4 m for a 10 cm difference); a fit that ran off and was held keeps the
    car length (``refine``). Seen from the side, the depth of the reflections
    is the width of the car or less: the paper's stages were 0.18-0.50 m off along the
    boresight on eight of a thirty-fourth probe's junction recordings, at most 0.96 m (along;
    metres across, where the data measured it) on our 33 bench runs. A car length there
    made the reported uncertainty 0.5-0.9 m along the boresight at true errors of 2-24 cm,
    and its advice asked for drives the calibration did not need. Between the two the
    scale follows the share, reaching half a car length where ``_ALONG_SHARE_FULL`` of it
    runs along the boresight (where the refinement also holds a fit that ran off, see
    ``refine._drives_along_boresight``).
    """
    length = _START_ERROR_LENGTHS * config.vehicle.length
    crossing = min(_START_ERROR_CROSSING_M, length)
    blend = min(max(along_share / _ALONG_SHARE_FULL, 0.0), 1.0)
    return crossing + blend * (length - crossing)


def _start_term(passes: uncertainty.PassCovariance, prior_hessian: F64,
                config: CalibConfig, start_sigma_m: float = _START_SIGMA_M,
                start_error: float | None = None) -> F64:
    """Covariance the start's own error adds where the data leave the horizontal position
    to the half-metre prior around the paper's estimate (``_START_SIGMA_M``).

    The prior keeps the fit near that estimate where the views say nothing, and its term in
    the covariance reports the half metre it assumes. But where the vehicle only drives
    straight along one road the paper's stages can be a car length off (tracks of a car
    reflecting at its front when it comes and its rear when it goes): a twentieth probe's
    radar looking along the road was 3.5-4 m off along the boresight at a reported 0.5 m,
    24 of 45 such drives outside two sigma. How much of the estimate the prior decides is
    H^-1 P; a start uncertain by ``start_error`` [m] (``start_error_m``; a car length when
    None) instead of the prior's half metre scales the prior's term H^-1 P H^-1 by their
    squared ratio, in the horizontal position only. Where the data measure the position
    (junctions, turns) it adds little.
    """
    if start_error is None:
        start_error = config.vehicle.length
    scale2 = (start_error / start_sigma_m) ** 2
    p_xy = np.zeros_like(prior_hessian)
    p_xy[3:5, 3:5] = prior_hessian[3:5, 3:5]
    term: F64 = max(scale2 - 1.0, 0.0) * uncertainty.prior_part_covariance(
        passes, prior_hessian, p_xy)
    return term


def _pose_block(covariance: F64, estimate_tau: bool) -> F64:
    """The 7x7 [rotation vector, translation, clock offset] block of a full covariance
    (zero for the clock offset when it was not estimated)."""
    out = np.zeros((7, 7))
    n = 7 if estimate_tau else 6
    out[:n, :n] = covariance[:n, :n]
    return out
