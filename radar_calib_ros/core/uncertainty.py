"""Calibrated uncertainty of the final refinement, and advice on the drive that would shrink it.

Why not the textbook covariance: the targets of one pass are strongly correlated (the same
car, the same reflectors, the same GNSS error, the same stretch of aspect angles), so the
inverse Hessian of a per-target least-squares fit shrinks like 1/n_targets and claims
millimetres where the truth is off by centimetres. And r_i says nothing about the error: a
wrong calibration can score a higher r_i. What does carry the error is the disagreement
between passes, so the covariance here is a jackknife over passes (the clustered, leverage-
corrected cousin of the sandwich estimator, "CR3"): for each pass p the refit without it is
approximated by one Gauss-Newton step from the full solution, delta_p = (H - H_p)^-1 g_p,
which costs one small solve per pass instead of a refit. Removing the only pass that sees
an aspect from a second bearing makes H - H_p nearly singular and delta_p large: the
estimate then reports the large uncertainty it really has. With G passes the jackknife
variance has about G - 1 degrees of freedom, so the reported 1-sigma is scaled by
t_{G-1}(97.7 %) / 2 so that "2 sigma" keeps its ~95 % meaning with few passes. Priors (the
mean reflection height, the weak bounds on the profile and the clock offset) are the same in
every jackknife replicate, so their own contribution H^-1 P H^-1 is added explicitly: the
vertical uncertainty can never be smaller than what the height prior leaves open.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats

from radar_calib_ros.types import F64, I64

# 2-sided 2-sigma coverage of a normal variable: the quantile a t-interval must match.
_TWO_SIGMA_QUANTILE = float(stats.norm.cdf(2.0))


@dataclass(frozen=True, slots=True)
class PassCovariance:
    """Covariance of the parameters from agreement across passes.

    covariance : (p, p) reported covariance (jackknife, t-scaled, plus priors);
    influences : (G, p) one-step change of the estimate when each pass is left out;
    n_passes : G; t_scale : the factor applied to the jackknife standard deviations;
    hessians, gradients : (G, p, p) and (G, p) each pass's J^T J and J^T r, for leaving
    out coarser groups of passes (:func:`group_influences`).
    """

    covariance: F64
    influences: F64
    n_passes: int
    t_scale: float
    hessians: F64 = field(default_factory=lambda: np.zeros((0, 0, 0)))
    gradients: F64 = field(default_factory=lambda: np.zeros((0, 0)))


def pass_jackknife_covariance(jacobian: F64, residuals: F64, pass_id: I64,
                              prior_hessian: F64, *, prior_term: bool = True) -> PassCovariance:
    """Jackknife-over-passes covariance of an M-estimate at its solution.

    Parameters
    ----------
    jacobian : ndarray of shape (m, p)
        Data rows of the Jacobian, whitened and multiplied by the square root of the robust
        (IRLS) weight and of the information weight of each row.
    residuals : ndarray of shape (m,)
        The matching residuals, scaled the same way.
    pass_id : ndarray of shape (m,), int
        Pass of each row, 0..G-1.
    prior_hessian : ndarray of shape (p, p)
        J_prior^T J_prior of the whitened prior residuals (same in every replicate).
    prior_term : bool, default=True
        Add the priors' own contribution H^-1 P H^-1 (once, when several jackknifes over
        different groupings are summed).

    Returns
    -------
    PassCovariance
    """
    n_par = jacobian.shape[1]
    passes, inverse = np.unique(pass_id, return_inverse=True)
    n_passes = int(passes.size)
    # Per-pass Hessians and gradients: rows sorted by pass, one product per pass (a loop
    # over a handful of passes, never over rows).
    order = np.argsort(inverse, kind='stable')
    bounds = np.searchsorted(inverse[order], np.arange(n_passes + 1))
    h_pass = np.zeros((n_passes, n_par, n_par))
    g_pass = np.zeros((n_passes, n_par))
    for g in range(n_passes):
        rows = order[bounds[g]:bounds[g + 1]]
        j_g = jacobian[rows]
        h_pass[g] = j_g.T @ j_g
        g_pass[g] = j_g.T @ residuals[rows]
    hessian = h_pass.sum(axis=0) + prior_hessian
    h_inv = _inverse(hessian)
    influences = _left_out_steps(h_pass, g_pass, hessian)
    if n_passes >= 2:
        centred = influences - influences.mean(axis=0)
        jack = (n_passes - 1) / n_passes * centred.T @ centred
        t_scale = float(stats.t.ppf(_TWO_SIGMA_QUANTILE, n_passes - 1) / 2.0)
    else:
        # One pass: no agreement to measure. Fall back to the naive covariance inflated by
        # the number of targets a pass is worth (every target correlated): honest, large.
        jack = h_inv * float(jacobian.shape[0])
        t_scale = 1.0
    covariance = t_scale ** 2 * jack
    if prior_term:
        covariance = covariance + _prior_term(h_inv, prior_hessian)
    covariance = 0.5 * (covariance + covariance.T)
    return PassCovariance(covariance, influences, n_passes, t_scale, h_pass, g_pass)


def pass_scatter(passes: PassCovariance) -> F64:
    """The jackknife part of :func:`pass_jackknife_covariance` alone (t-scaled, no prior
    term): how much the passes disagree, without what the priors leave open. Two fits that
    share the priors (a calibration and a check of it on another recording with the same
    vehicle) differ by their scatters, not by the priors' width. NaN with fewer than two
    passes."""
    n = passes.n_passes
    if n < 2:
        return np.full((passes.influences.shape[1],) * 2, np.nan)
    centred = passes.influences - passes.influences.mean(axis=0)
    out: F64 = passes.t_scale ** 2 * (n - 1) / n * centred.T @ centred
    return out


def _prior_term(h_inv: F64, prior_part: F64) -> F64:
    """H^-1 P H^-1: the covariance a prior (or the part ``prior_part`` of the priors) adds
    where the data leave the estimate to it."""
    term: F64 = h_inv @ prior_part @ h_inv
    return term


def prior_part_covariance(passes: PassCovariance, prior_hessian: F64,
                          prior_part: F64) -> F64:
    """The covariance term of ``prior_part`` (a part of ``prior_hessian``) at the solution
    of ``passes``, as :func:`pass_jackknife_covariance` adds it for all the priors: for
    asking how much a prior whose own uncertainty was understated would add."""
    term = _prior_term(_inverse(passes.hessians.sum(axis=0) + prior_hessian), prior_part)
    return 0.5 * (term + term.T)


def _left_out_steps(h_groups: F64, g_groups: F64, hessian: F64) -> F64:
    """(G, p) one-step change of the estimate when each group's rows are left out. The
    full solution balances data and prior gradients; without group g the rest of the
    gradient is -g_g, hence the step (H - H_g)^-1 g_g."""
    if h_groups.shape[0] == 0:
        return np.zeros((0, hessian.shape[0]))
    return np.stack([_inverse(hessian - h) @ g for h, g in zip(h_groups, g_groups)])


def group_influences(passes: PassCovariance, group_of_pass: I64, prior_hessian: F64) -> F64:
    """(K, p) one-step change of the estimate when each group of passes (0..K-1, one label
    per pass of ``passes``) is left out: the passes' own Hessians and gradients summed per
    group, no second pass over the data (e.g. the first and second half of a drive)."""
    hessian = passes.hessians.sum(axis=0) + prior_hessian
    groups = np.unique(group_of_pass)
    h_groups = np.stack([passes.hessians[group_of_pass == k].sum(axis=0) for k in groups])
    g_groups = np.stack([passes.gradients[group_of_pass == k].sum(axis=0) for k in groups])
    return _left_out_steps(h_groups, g_groups, hessian)


def combined_covariance(passes: PassCovariance, bands: PassCovariance,
                        block: tuple[int, ...] = (2, 3, 4, 6)) -> F64:
    """The reported covariance: agreement across passes, raised toward the agreement across
    range bands for yaw, the horizontal translation and the clock offset where the bands
    disagree more.

    The pass jackknife cannot see an error every pass shares. The one that matters here is
    range-dependent: which parts of a car are seen (signal strength, the elevation field of
    view, occlusion by nearer cars) changes with range, which an aspect-only reflection
    profile cannot follow, and the fit then trades it against the radar's position along the
    boresight and, through the distance travelled, against the clock offset (measured on
    the simulator's skin model: 5-18 cm while the passes agreed to 2-6 cm). Leaving out one
    range band at a time exposes it. Both jackknifes estimate the same error from two
    groupings of the data, and the band jackknife also counts the range leverage a band
    takes with it, so in every direction where the bands disagree more the variance is
    raised halfway to theirs. Measured over 33 simulated runs (2-D / 3-D 95 % ellipsoids):
    the pass jackknife alone covered 91 % of the horizontal and 88 % of the rotation
    errors, the larger of the two 100 % (horizontal median error at 0.49 sigma: too
    wide), halfway 97 % and 94 %. Yaw is in the block because a range-dependent reflection
    depth turns the bearing as well as the position; roll and pitch are not: for them
    leaving out a band removes range leverage, and the band jackknife would report that
    loss of leverage (0.3-0.8 deg, 30-50 cm measured) rather than a disagreement.
    """
    out = passes.covariance.copy()
    idx = np.array([i for i in block if i < out.shape[0]])
    # in every direction of the block halfway to the larger of the two variances: add half
    # the positive part of the difference (a positive semidefinite update keeps the whole
    # matrix valid)
    diff = bands.covariance[np.ix_(idx, idx)] - out[np.ix_(idx, idx)]
    values, vectors = np.linalg.eigh(0.5 * (diff + diff.T))
    out[np.ix_(idx, idx)] += 0.5 * (vectors * np.clip(values, 0.0, None)) @ vectors.T
    return out


def add_along_boresight(covariance: F64, rotation: F64, sigma_m: float) -> F64:
    """``covariance`` (7x7, [rotation vector, translation, time offset]) with a variance of
    ``sigma_m`` squared added to the horizontal translation along the boresight's ground
    projection.

    Neither jackknife sees an error that every pass and every range band share. The one
    left is the reflection model's: where on the car the targets lie changes with range
    (which scatterers clear the detection threshold, what the elevation field of view cuts
    off), an aspect-only profile follows it only on average, and the remainder trades
    against the radar's position along the boresight, the weakest direction. Measured on
    the simulator over 66 ten-minute runs of all three scatter models, the error along the
    boresight was biased by a few centimetres with a sign set by the model (interior:
    radar too far forward, skin: too far back), while passes and bands agreed: the 2-sigma
    ellipse covered 83 % of the interior runs, 96 % with a 2 cm term.
    """
    out = np.array(covariance, float, copy=True)
    boresight = np.asarray(rotation, float)[:2, 0]
    norm = float(np.hypot(*boresight))
    if sigma_m <= 0.0 or norm < 1e-9:
        return out
    along = boresight / norm
    out[3:5, 3:5] += sigma_m ** 2 * np.outer(along, along)
    return out


def add_tilt(covariance: F64, sigma_rad: float) -> F64:
    """``covariance`` (7x7) with a variance of ``sigma_rad`` squared added to the rotations
    about the two horizontal world axes (roll and pitch whatever the yaw).

    The tilt comes from the heights of the vehicle's targets across the range, and the mean
    height of what a radar sees of a car changes with range (the multipath images below
    the road and the weak scatterers drop out with distance, the field of view cuts the
    lower parts close by): a tilt every pass shares, which neither jackknife sees.
    Measured over 106 simulated ten-minute runs of all three scatter models: the 95 %
    rotation ellipsoid covered 75 / 69 / 79 % (interior / mixed / skin) of the errors
    without it, about 97 / 94 / 88 % with 0.1 deg (diagonal approximation).
    """
    out = np.array(covariance, float, copy=True)
    out[0, 0] += sigma_rad ** 2
    out[1, 1] += sigma_rad ** 2
    return out


def boresight_axes(rotation: F64) -> F64:
    """(3, 3) rows: the horizontal direction of the radar's boresight (its x axis in the
    world), the horizontal direction left of it, and the vertical; world x and y for a
    radar looking straight down, which has no horizontal boresight."""
    boresight = np.asarray(rotation, np.float64)[:2, 0]
    norm = np.linalg.norm(boresight)
    along = boresight / norm if norm > 1e-9 else np.array([1.0, 0.0])
    return np.array([[along[0], along[1], 0.0], [-along[1], along[0], 0.0],
                     [0.0, 0.0, 1.0]])


def add_roll_pitch(covariance: F64, rotation: F64, roll_sigma_rad: float,
                   pitch_sigma_rad: float) -> F64:
    """``covariance`` (7x7) with variances added to the rotations about the horizontal
    boresight (roll) and the horizontal axis left of it (pitch): :func:`add_tilt` with a
    sigma of each."""
    along, left, _ = boresight_axes(rotation)
    out = np.array(covariance, float, copy=True)
    out[:2, :2] += (roll_sigma_rad ** 2 * np.outer(along[:2], along[:2])
                    + pitch_sigma_rad ** 2 * np.outer(left[:2], left[:2]))
    return out


def model_term(difference: F64, covariance: F64) -> F64:
    """Covariance of a model difference (a position from another model minus this one,
    ``difference``), capped at ``covariance``'s variance along it: the squared length, or
    the variance the data already give in that direction, whichever is smaller, times the
    outer product of its direction. See ``refine_extrinsics`` for why the cap."""
    d = np.asarray(difference, float)
    length2 = float(d @ d)
    if length2 <= 0.0:
        return np.zeros((d.size, d.size))
    unit = d / math.sqrt(length2)
    return min(length2, float(unit @ covariance @ unit)) * np.outer(unit, unit)


def shrink_correlations(covariance: F64, n_groups: int, block: int = 3) -> F64:
    """Covariance with its correlations shrunk toward zero, variances kept.

    A jackknife over G groups has G - 1 degrees of freedom: with four or five passes the
    3x3 rotation block is estimated from three or four difference vectors, its shape is
    noise, and it is nearly singular in the directions no pass happened to disagree in
    (measured on the simulator: only 79 % of 33 rotation errors inside the 3-D 95 %
    ellipsoid although each axis alone was covered 91-97 % of the time). The per-axis
    variances are the well-estimated part; the correlations are kept with the weight
    (G - 1) / (G - 1 + block), the usual shrinkage toward the diagonal when the sample
    is not much larger than the dimension.
    """
    cov = np.asarray(covariance, float)
    if n_groups <= 1:
        return cov.copy()
    keep = (n_groups - 1) / (n_groups - 1 + block)
    d = np.diag(np.diag(cov))
    return d + keep * (cov - d)


def _inverse(matrix: F64) -> F64:
    """Inverse of a symmetric positive (semi)definite matrix; pseudo-inverse if singular."""
    try:
        return np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(matrix, hermitian=True)


# --- figures of the covariance ----------------------------------------------------------

def sigma_summary(covariance: F64, rotation: F64) -> dict[str, Any]:
    """1-sigma figures of a 7x7 [rotation vector, translation, time offset] covariance.

    ``along``/``across`` are horizontal, along and across the boresight's ground
    projection; rotation sigmas are about the world axes (z = yaw) in degrees.
    """
    c_t = covariance[3:6, 3:6]
    boresight = np.asarray(rotation)[:2, 0]
    norm = float(np.hypot(*boresight))
    along = boresight / norm if norm > 1e-9 else np.array([1.0, 0.0])
    across = np.array([-along[1], along[0]])
    c_h = c_t[:2, :2]
    rot_deg = np.degrees(np.sqrt(np.clip(np.diag(covariance[:3, :3]), 0.0, None)))
    return {
        'sigma_translation_m': math.sqrt(max(float(np.trace(c_t)), 0.0)),
        'sigma_horizontal_m': math.sqrt(max(float(np.trace(c_h)), 0.0)),
        'sigma_along_boresight_m': math.sqrt(max(float(along @ c_h @ along), 0.0)),
        'sigma_across_boresight_m': math.sqrt(max(float(across @ c_h @ across), 0.0)),
        'sigma_vertical_m': math.sqrt(max(float(c_t[2, 2]), 0.0)),
        'sigma_rotation_deg': math.degrees(math.sqrt(max(float(np.trace(covariance[:3, :3])),
                                                         0.0))),
        'sigma_roll_pitch_yaw_world_deg': [float(v) for v in rot_deg],
        'sigma_time_offset_s': math.sqrt(max(float(covariance[6, 6]), 0.0)),
    }


# --- advice ------------------------------------------------------------------------------

_COMPASS = ('north', 'north-east', 'east', 'south-east', 'south', 'south-west', 'west',
            'north-west')
_SIDES = {0: 'front', 1: 'front-left', 2: 'left side', 3: 'rear-left', 4: 'rear',
          5: 'rear-right', 6: 'right side', 7: 'front-right'}


def compass_name(enu_angle_rad: float) -> str:
    """'north', 'south-east', ... of an ENU direction (counter-clockwise from east)."""
    compass_deg = (90.0 - math.degrees(enu_angle_rad)) % 360.0
    return _COMPASS[int(((compass_deg + 22.5) % 360.0) // 45.0)]


def drive_name(start_s: float, end_s: float, heading_rad: float) -> str:
    """'120-131 s north-eastbound': a drive as the advice names it (seconds from the first
    pose)."""
    return f'{start_s:.0f}-{end_s:.0f} s {compass_name(heading_rad)}bound'


def aspect_name(aspect_rad: float) -> str:
    """'front', 'left side', ... of an aspect angle (0 = front, +pi/2 = left)."""
    return _SIDES[int(((math.degrees(aspect_rad) + 22.5) % 360.0) // 45.0)]


@dataclass(frozen=True, slots=True)
class ViewCoverage:
    """Where the vehicle was seen from: weighted histogram over (aspect, bearing).

    aspect_edges_deg : (A + 1,), bearing_edges_deg : (B + 1,) bearing relative to the
    boresight (positive = left of it); weights : (A, B) information weight per cell;
    bearing_spread_deg : (A,) weighted circular std of the bearing per aspect bin (NaN
    where the aspect was not seen). A depth along the line of sight is separable from the
    radar's position only where one aspect is seen from different bearings.
    """

    aspect_edges_deg: F64
    bearing_edges_deg: F64
    weights: F64
    bearing_spread_deg: F64


def view_coverage(aspect_rad: F64, bearing_rad: F64, weights: F64,
                  aspect_bin_deg: float = 45.0, bearing_bin_deg: float = 10.0) -> ViewCoverage:
    """Histogram of the (aspect, bearing) coverage of the used targets.

    Parameters
    ----------
    aspect_rad : (n,) aspect angle of each target [rad];
    bearing_rad : (n,) bearing of each target relative to the boresight [rad];
    weights : (n,) information weight of each target.
    """
    a_deg = (np.degrees(aspect_rad) + aspect_bin_deg / 2.0) % 360.0 - aspect_bin_deg / 2.0
    a_edges = np.arange(-aspect_bin_deg / 2.0, 360.0 - aspect_bin_deg / 2.0 + 1e-9,
                        aspect_bin_deg)
    b_deg = np.degrees(bearing_rad)
    lim = max(90.0, float(np.ceil(np.abs(b_deg).max() / bearing_bin_deg) * bearing_bin_deg)
              if b_deg.size else 90.0)
    b_edges = np.arange(-lim, lim + 1e-9, bearing_bin_deg)
    hist, _, _ = np.histogram2d(a_deg, b_deg, bins=[a_edges, b_edges], weights=weights)
    a_bin = np.clip(np.searchsorted(a_edges, a_deg, side='right') - 1, 0, a_edges.size - 2)
    w_sum = np.bincount(a_bin, weights, minlength=a_edges.size - 1)
    c = np.bincount(a_bin, weights * np.cos(bearing_rad), minlength=a_edges.size - 1)
    s = np.bincount(a_bin, weights * np.sin(bearing_rad), minlength=a_edges.size - 1)
    with np.errstate(invalid='ignore', divide='ignore'):
        resultant = np.hypot(c, s) / w_sum
        spread = np.degrees(np.sqrt(-2.0 * np.log(np.clip(resultant, 1e-12, 1.0))))
    spread[w_sum <= 0] = np.nan
    return ViewCoverage(a_edges, b_edges, hist, spread)


@dataclass(frozen=True, slots=True)
class DriveCandidate:
    """A drive the vehicle could make through the view: a stretch of road it already used,
    in one direction. heading_rad (ENU), range_m and bearing_rad (relative to the
    boresight) of its middle; gain: how much new (aspect, bearing) diversity it adds."""

    heading_rad: float
    range_m: float
    bearing_rad: float
    gain: float
    driven: bool


def drive_advice(sigma_along_m: float, threshold_m: float, coverage: ViewCoverage,
                 candidates: list[DriveCandidate], boresight_rad: float,
                 nearest_m: float = 0.0, fixes_sigma_m: float = 0.0,
                 headings_rad: Sequence[float] = (),
                 turn_ranges_m: Sequence[float] = ()) -> list[str]:
    """Plain sentences naming the drive that would shrink a large along-boresight sigma.

    Parameters
    ----------
    sigma_along_m : 1-sigma of the translation along the boresight [m]
    threshold_m : ``quality.max_boresight_sigma_m``
    coverage : the (aspect, bearing) histogram of the used targets
    candidates : drives through the view, best first (see ``core.refine``)
    boresight_rad : ENU direction of the boresight's ground projection
    nearest_m : the nearest the vehicle was seen (the vertical view's edge) [m]
    fixes_sigma_m : the vehicle's own position error, which ``sigma_along_m`` leaves out
        and the reported uncertainty adds; named where it is above the threshold too [m]
    headings_rad : ENU headings of the passes used
    turn_ranges_m : distances from the radar [m] at which passes turned through the view
    """
    if not sigma_along_m > threshold_m:
        return []
    total = max(float(coverage.weights.sum()), 1e-12)
    seen = np.flatnonzero(coverage.weights.sum(axis=1) > 0.02 * total)
    centres = 0.5 * (coverage.aspect_edges_deg[:-1] + coverage.aspect_edges_deg[1:])
    sides = sorted({aspect_name(math.radians(centres[i])) for i in seen},
                   key=lambda n: list(_SIDES.values()).index(n))
    spread = coverage.bearing_spread_deg[seen]
    finite = spread[np.isfinite(spread)]
    median_spread = float(np.median(finite)) if finite.size else 0.0
    besides = (f', besides the {fixes_sigma_m:.1f} m of the vehicle\'s fixes'
               if fixes_sigma_m > threshold_m else '')
    sentences = [
        f'The position along the boresight is uncertain by {_centimetres(sigma_along_m)} cm '
        f'(1 sigma, more than {100 * threshold_m:.0f} cm{besides}): each side of the vehicle '
        f'({_join(sides) or "none"}) was seen from bearings spread by only about '
        f'{median_spread:.0f} deg, so the depth of its reflections trades off against the '
        'radar\'s distance. Where that is good enough for the radar\'s use, the '
        'calibration is done; to narrow it, drive as follows.']
    across = boresight_rad + math.pi / 2.0
    # 20-40 m: near enough for wide bearings, far enough to see the whole car; never nearer
    # than the vehicle was seen at all
    near = max(20.0, 5.0 * math.ceil(nearest_m / 5.0))
    turn = f'about {near:.0f}-{near + 20.0:.0f} m from the radar'
    turns = np.asarray(turn_ranges_m, float)
    if turns.size:
        # turns already driven at that range show those bearings again (a twenty-fourth
        # probe's junction turns at 15-25 m were told to turn at 20-40 m): farther out
        start = max(near, 5.0 * math.ceil((float(turns.max()) + 10.0) / 5.0))
        turn = (f'again about {start:.0f}-{start + 20.0:.0f} m from the radar (the turns so '
                f'far were {_span(turns)} m from it)')
    crossing = (f'cross the view (heading {compass_name(across)} or '
                f'{compass_name(across + math.pi)}) or turn through it {turn}')
    headings = np.asarray(headings_rad, float)
    along_road = headings.size > 0 and bool(near_axis(headings, boresight_rad).all())
    if along_road:
        # Every pass runs towards or away from the radar (a radar mid-block looking down
        # its road): only the front and rear are seen, and from another lane at bearings a
        # few degrees apart. A twentieth probe drove the lanes the advice named, to no
        # avail; two drives across the view took the error from 3.5 m to 5 cm.
        sentences.append(
            f'First, where the roads allow, {crossing}: the passes so far all run towards '
            'or away from the radar, where the vehicle shows only its front and rear, and '
            'other lanes of that road show them from bearings only a few degrees apart; '
            'then calibrate again.')
    lanes = []
    for cand in [c for c in candidates if c.gain > 0.0][:2]:
        side = 'left' if cand.bearing_rad > 0 else 'right'
        # a road driven one way may be one carriageway of a divided road (a seventeenth
        # probe's motorway gantry was asked to drive against the traffic)
        what = ('again on a lane already driven' if cand.driven
                else 'on a road already driven the other way (where its lanes allow)')
        lanes.append(
            f'{compass_name(cand.heading_rad)}bound {what} through the view about '
            f'{cand.range_m:.0f} m from the radar and {abs(math.degrees(cand.bearing_rad)):.0f} '
            f'deg {side} of its boresight')
    if along_road:
        return sentences + [f'Drive {lane}: it shows sides already seen from new bearings.'
                            for lane in lanes]
    # The turn or crossing comes first, the lanes already driven after it: an operator
    # who followed the advice in its order (a thirty-eighth probe) found the lanes'
    # drives left the uncertainty as it was (0.94 -> 0.93 m) and were asked for again,
    # while the turn took it to 0.17-0.24 m.
    crossing_passes = near_axis(headings, across)
    if headings.size > 0 and crossing_passes.all():
        # a side-fire radar's passes already cross its view: on a straight road each side
        # is seen at one bearing per lane, and only another road's angle adds bearings (an
        # eleventh probe was told to cross the view, as every pass had)
        other = (f'drive through it heading {compass_name(boresight_rad)} or '
                 f'{compass_name(boresight_rad + math.pi)} (towards or away from the radar)')
        sentences.append(
            f'Where the roads allow, turn through the view {turn}, or {other}: the passes so '
            'far all cross it, where each side of the vehicle is seen at one bearing per '
            'lane; then calibrate again.')
    elif crossing_passes.any():
        # some passes cross the view already: more of the same at that range adds little
        # (a twenty-second probe crossed 4 and 8 times and was told to cross again)
        sentences.append(
            f'Where the roads allow, turn through the view {turn}, or cross it at another '
            'range than before, so the front and rear are seen from other bearings; then '
            'calibrate again.')
    else:
        sentences.append(
            f'Where the roads allow, {crossing}, so the front and rear are seen from bearings '
            'far from the boresight; then calibrate again.')
    return sentences + [f'{"Where they do not, drive" if i == 0 else "Or drive"} {lane}: it '
                        'shows sides already seen from new bearings (less than a turn or a '
                        'crossing does).' for i, lane in enumerate(lanes)]


#: A heading within this angle of an axis (either way) runs along it [rad]: across the
#: boresight, a pass crosses the view; along it, the pass runs towards or away from the radar.
_NEAR_AXIS_RAD = math.radians(25.0)
#: 1-sigma along the boresight [m] from which the drives leave the position there open to
#: where the fit started (half a car length's worth of the start, ``refine_covariance``:
#: 0.67-0.96 m on our mid-block views, 0.05-0.5 m on views the drives measure).
OPEN_ALONG_BORESIGHT_M = 0.6


def near_axis(headings_rad: F64, axis_rad: float) -> np.ndarray:
    """(n,) True for the headings (ENU, rad) within ``_NEAR_AXIS_RAD`` of the axis
    ``axis_rad``, in either direction along it."""
    return np.abs(np.sin(np.asarray(headings_rad, float) - axis_rad)) < math.sin(
        _NEAR_AXIS_RAD)


def _span(values: F64) -> str:
    """'20' or '15-25': the range of ``values``, rounded to metres."""
    lo, hi = round(float(values.min())), round(float(values.max()))
    return f'{lo}' if lo == hi else f'{lo}-{hi}'


def _centimetres(metres: float) -> str:
    """Centimetres to a tenth below ten (5.4 cm is not '5 cm, more than 5 cm')."""
    return f'{100 * metres:.1f}' if metres < 0.1 else f'{100 * metres:.0f}'


def _join(names: list[str]) -> str:
    if len(names) <= 1:
        return ''.join(names)
    return ', '.join(names[:-1]) + ' and ' + names[-1]
