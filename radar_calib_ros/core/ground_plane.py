"""Stage 4: the ground plane, and from it the sensor's roll and pitch (R_alpha_beta).

The paper merges the targets of the whole recording, keeps the dense regions (at least
``density_fraction`` of the highest neighbour count within ``radius_m``: "the most occupied
spaces right above the lanes") and takes the normal of the remaining cloud from an SVD.
Moving targets lie on vehicles over the road, between the road surface and the roofs, so
their plane is parallel to the road; the mean reflection height sits in ``offset_m``, not
in the normal. Three changes, each measured on synthetic scenes with the radar's noise
(elevation error 1-2 deg, i.e. metres at range):

* The neighbours are counted in the plane of the cloud (bird's-eye view), not in 3D: in 3D
  a target is dense where its own elevation error happens to be small, so dropping the
  sparse ones selects on the error and tilts the plane (0.04-0.15 deg).
* The SVD (total least squares) only starts the fit: it assumes the same error in every
  direction and reads the elevation noise as a steeper plane (12 % of the roll with lanes
  over +-9 m). The fit is a weighted least squares of the height over the plane, per-cell
  weights from the residual scatter (it grows with range), with the bias of the errors in
  the plane coordinates removed, inside a wide residual gate (``_robust_plane``).
* Long recordings are subsampled evenly to ``_MAX_FIT_TARGETS`` targets (the neighbour
  query over millions of targets would take seconds; 2 x 10^5 pin the normal to ~0.02
  deg).

Which targets (``ground.targets``): moving ones. Measured on the simulator (angle between
the fitted normal and the true road normal, in the sensor frame; ``all`` = every target):

    scenario (duration)          all     moving, min_speed_kmh = 0.1 / 0.5 / 1.0
    baseline (15 min)            1.38    1.10 / 0.31 / 0.32 deg
    dense_traffic (5 min)        3.21    3.20 / 0.07 / 0.11
    low_mount (5 min)            2.94    4.20 / 0.44 / 0.47
    mid_block (5 min)            2.53    1.63 / 0.42 / 0.02

Facades, poles and parked cars are dense too but are not on the road. At the paper's 0.1
km/h, though, a radar with 0.05-0.1 m/s of velocity noise lets ~70 % of that clutter pass
as "moving", and the plane is as bad as with every target. What remains at 0.5 km/h is
physical, not the estimator: fitted to the true (noise-free) reflection points of the
baseline's road users the plane is still 0.5 deg off, because where a vehicle reflects
depends on the look-down angle (higher parts near the radar, where the elevation field of
view cuts the low ones). Roll and pitch from here are a starting value that the later
stages refine. The plane is the road's, which is not level where the road has a gradient
(0.2-0.5 deg in the simulated sites).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from radar_calib_ros.config import GroundConfig
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.types import F64, GroundPlane

_LOG = logging.getLogger(__name__)

#: Largest number of targets the plane is fitted to (evenly spaced subsample).
_MAX_FIT_TARGETS = 200_000
#: Largest number of reference targets the neighbour counts are taken against.
_DENSITY_REFERENCES = 10_000
#: Residual gate of the robust re-fit, in robust standard deviations (1.4826 MAD).
_GATE_SIGMAS = 5.0
#: Gate and re-fit rounds after the first SVD.
_ROBUST_ROUNDS = 3
#: Cell size of the grid the residual scatter is estimated on [m].
_CELL_M = 5.0
#: Fewest targets for a cell's own scatter estimate.
_MIN_CELL_TARGETS = 20
#: Nearer than this to the plane [m], the sensor's side of it does not tell up from down.
_SIDE_MARGIN_M = 2.0


def fit_ground_plane(points_m: F64, cfg: GroundConfig) -> GroundPlane:
    """Fit the road plane to radar targets and the rotation that levels it.

    Parameters
    ----------
    points_m : ndarray of shape (n, 3)
        Targets in the sensor frame [m] (moving targets by default, see the module notes).
    cfg : GroundConfig
        ``radius_m`` of the neighbour count, ``density_fraction`` of the maximum count
        under which targets are dropped.

    Returns
    -------
    GroundPlane
        Unit ``normal`` pointing to the sensor's side of the plane (up), ``offset_m`` the
        plane's signed distance along it (``normal . p = offset_m`` on the plane, negative
        as the sensor is above the road), ``rotation_level`` the smallest rotation taking
        the normal to +z (roll and pitch only: no yaw about the normal), the density
        threshold and the indices of the targets used in the final fit.

    Raises
    ------
    InsufficientDataError
        Fewer than three finite targets, or targets that do not span a plane.

    References
    ----------
    method-paper.tex, section "Ground Plane Estimation".
    """
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    finite = finite[::max(1, -(-finite.size // _MAX_FIT_TARGETS))]
    if finite.size < 3:
        raise InsufficientDataError(
            'ground_plane', f'{finite.size} finite targets for the ground plane, need at '
            'least 3')
    # The density is counted in the plane of all targets (bird's-eye view), not in 3D:
    # in 3D a target is dense where its own elevation error is small, so dropping the
    # sparse ones selects on the error and biases the plane (by 0.04-0.15 deg in our tests
    # with +-1.5 deg of elevation noise); where a target lies over the road is almost
    # error free, and the dense places are still "the most occupied spaces right above
    # the lanes" the paper is after.
    cloud = points[finite]
    normal, centroid = _svd_plane(cloud, np.ones(finite.size))
    _, axes = _principal_axes(cloud - centroid, np.ones(finite.size))
    in_plane = (cloud - centroid) @ axes[:, 1:]
    density = _neighbour_counts(in_plane, cfg.radius_m)
    threshold = cfg.density_fraction * float(density.max())
    is_dense = density >= threshold
    if _width(in_plane[is_dense]) < _LINE_WIDTH_M <= _width(in_plane):
        # The densest places are one path: a road user that never leaves the view (a
        # cyclist riding to and fro past the pole, along the boresight) outnumbers the
        # road by far, and a line leaves the plane free to turn about it; its elevation
        # noise, wider than its lateral scatter, stood it on edge (an independent probe:
        # a vertical 'ground' 1 m beside the radar, 8 of 9 recordings refused as 'vehicle
        # never in view'). The threshold is lowered until the kept targets span an area.
        for fraction in _WIDER_FRACTIONS:
            threshold = fraction * cfg.density_fraction * float(density.max())
            is_dense = density >= threshold
            if _width(in_plane[is_dense]) >= _LINE_WIDTH_M:
                break
        _LOG.info('the densest targets lie along one line: ground plane from those above '
                  '%.0f %% of the highest density', 100.0 * threshold / float(density.max()))
    dense = finite[is_dense]
    # The paper's plane, the SVD of the dense targets, starts the robust fit.
    normal, _ = _svd_plane(points[dense], np.ones(dense.size))
    cell_ij = np.floor(in_plane[is_dense] / _CELL_M).astype(np.int64)
    cell_ij -= cell_ij.min(axis=0)
    _, cell = np.unique(cell_ij[:, 0] * (int(cell_ij[:, 1].max()) + 1) + cell_ij[:, 1],
                        return_inverse=True)
    normal, centroid, keep = _robust_plane(points[dense], elevation_directions(points[dense]),
                                           normal, cell.ravel())
    used = dense[keep]
    # Up is the side of the plane the sensor (the origin) is on, where that is clear; a
    # plane within ``_SIDE_MARGIN_M`` of the sensor is taken with the sensor's z up (its
    # upright mount). The targets' plane lies about half a metre over its road, so a road
    # at the radar's own height leaves the side to chance: an independent overpass, road
    # traffic on a bridge 6 m up beside a radar 6.5-7.5 m up, gave the plane of the bridge's
    # cars with the radar 0-1 m under it, a ground 'above' the radar, and the recording was
    # refused as a mirror image (5 of 11 drives); a radar hung upside down is rarer still
    # at its road's height.
    side = float(normal @ centroid)
    if abs(side) < _SIDE_MARGIN_M:
        if normal[2] < 0.0:
            normal = -normal
    elif side > 0.0:
        normal = -normal
    offset = float(normal @ centroid)
    _LOG.debug('ground plane from %d of %d targets, normal %s, offset %.3f m', used.size,
               points.shape[0], normal, offset)
    return GroundPlane(normal=normal, offset_m=offset, rotation_level=level_rotation(normal),
                       density_threshold=threshold, used=used.astype(np.int64))


#: A road user's track, seen from above: it travels at least this far [m] over at least
#: this many frames, and the centroids of its frames stay within this RMS [m] of a
#: quadratic in time (a car's reflections jitter by a metre; a blob of rain or spray whose
#: clusters chain into a "track" jumps by several).
_ROAD_USER_TRAVEL_M = 5.0
_ROAD_USER_FRAMES = 10
_ROAD_USER_RMS_M = 1.0


def _unique_pairs(first: F64, second: F64) -> tuple[F64, np.ndarray]:
    """``np.unique(np.column_stack([first, second]), axis=0, return_inverse=True)`` by one
    lexicographic sort of the two columns: the same rows in the same order and the same
    inverse, four times faster (``unique`` over rows sorts a structured copy; 1 s per call
    for a dense imaging radar's 2.6 million moving targets)."""
    order = np.lexsort((second, first))
    a, b = first[order], second[order]
    new = np.ones(a.size, bool)
    new[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    inverse = np.empty(a.size, np.int64)
    inverse[order] = np.cumsum(new) - 1
    return np.column_stack([a[new], b[new]]), inverse


def road_user_targets(positions_m: F64, time_s: F64, track_id: np.ndarray) -> np.ndarray:
    """(n,) mask of the targets whose track moves as a road user does (see the constants).

    Why: the plane of all moving targets is the road's only where the moving targets are
    road users. Rain, snow or spray near the radar are moving targets too, fill a volume
    and are the densest of all, so the paper's density selection keeps them and drops the
    road (an independent recording: 40 rain returns a frame within 15 m tilted the plane
    6.7 deg, and no hypotheses agreed). Their clusters do chain into tracks, but those
    jump about instead of travelling along a smooth path.

    Parameters
    ----------
    positions_m : ndarray of shape (n, >=2)
        Sensor-frame positions; x, y serve as the bird's-eye view (a tilt of a few degrees
        changes the path's shape by centimetres).
    time_s : ndarray of shape (n,)
        Each target's frame time [s].
    track_id : ndarray of shape (n,)
        Track of each target, -1 for none.
    """
    keep = np.zeros(track_id.shape[0], bool)
    in_track = np.flatnonzero(track_id >= 0)
    if in_track.size == 0:
        return keep
    # one centroid per (track, frame), then a quadratic in time per track, all by bincount
    pairs, cell = _unique_pairs(track_id[in_track].astype(float), time_s[in_track])
    counts = np.bincount(cell).astype(float)
    cx = np.bincount(cell, positions_m[in_track, 0]) / counts
    cy = np.bincount(cell, positions_m[in_track, 1]) / counts
    tracks, track = np.unique(pairs[:, 0], return_inverse=True)
    track = track.ravel()
    n_tracks = tracks.size
    t_first = np.full(n_tracks, np.inf)
    np.minimum.at(t_first, track, pairs[:, 1])
    t = pairs[:, 1] - t_first[track]
    powers = np.column_stack([np.ones_like(t), t, t ** 2])
    # normal equations of the per-track quadratic: sum of t^(i+j), and of t^i x, t^i y
    gram = np.stack([np.stack([np.bincount(track, powers[:, i] * powers[:, j], n_tracks)
                               for j in range(3)], axis=-1) for i in range(3)], axis=-2)
    rhs = np.stack([np.stack([np.bincount(track, powers[:, i] * c, n_tracks)
                              for i in range(3)], axis=-1) for c in (cx, cy)], axis=-1)
    frames = np.bincount(track, minlength=n_tracks)
    solvable = (frames >= _ROAD_USER_FRAMES) & (np.abs(np.linalg.det(gram)) > 1e-12)
    coef = np.zeros((n_tracks, 3, 2))
    coef[solvable] = np.linalg.solve(gram[solvable], rhs[solvable])
    fit = np.einsum('ni,nij->nj', powers, coef[track])
    sq = (cx - fit[:, 0]) ** 2 + (cy - fit[:, 1]) ** 2
    rms = np.sqrt(np.bincount(track, sq, n_tracks) / np.maximum(frames, 1))
    t_last = np.zeros(n_tracks)
    np.maximum.at(t_last, track, t)
    ends = np.stack([coef[:, 0, :], np.einsum('ni,nij->nj', np.column_stack(
        [np.ones(n_tracks), t_last, t_last ** 2]), coef)], axis=1)
    travel = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    good = solvable & (travel >= _ROAD_USER_TRAVEL_M) & (rms <= _ROAD_USER_RMS_M)
    keep[in_track] = good[np.searchsorted(tracks, track_id[in_track])]
    return keep


#: Angle between the planes of all moving targets and of the road users' tracks alone
#: beyond which the moving targets are taken to hold volumetric clutter [deg] (the two agree
#: to 0.02-0.45 deg on the 20 bench recordings of our simulator; rain near the radar
#: tilted the first by 6.6 deg), and the fewest road-user targets the second plane needs.
_CLUTTER_PLANE_DEG = 1.5
_MIN_ROAD_USER_TARGETS = 500
#: Least spread [m] (1 sigma) of the road users' targets across their main direction for
#: their plane to replace that of all moving targets: a plane along one road turns about
#: it by a lane-to-lane height difference of 0.3 m over 6 m by 3 deg, past the 1.5 above.
_ROAD_PLANE_MIN_WIDTH_M = 6.0
#: Largest uncertainty given the plane where the two could not be told apart [deg], and
#: the one given where the road users keep to one lane (across it, 1 sigma [m]): the plane
#: of targets along one lane is undetermined about it (80 deg from the other seen).
_PLANE_SIGMA_MAX_DEG = 10.0
_ONE_LANE_WIDTH_M = 1.2
#: Least height [m] of the radar above a plane of moving targets for it to be a road's: a
#: radar sees the road from above, and the plane runs through the road users' targets, a
#: metre or less above the road.
_LEAST_HEIGHT_ABOVE_M = 0.5
#: How far the road users' reflections may differ in height across their road [m]: their
#: plane turns about the road by this over its width (``_one_road_sigma_deg``).
_ACROSS_ROAD_HEIGHT_M = 0.3


def _one_road_sigma_deg(width_m: float) -> float:
    """How uncertain the road users' plane is about their one road [deg]: a height
    difference of ``_ACROSS_ROAD_HEIGHT_M`` over the width they spread across (1 sigma)."""
    return math.degrees(math.atan2(_ACROSS_ROAD_HEIGHT_M, max(width_m, 1e-3)))


@dataclass(frozen=True, slots=True)
class MovingClutter:
    """What ``fit_road_plane`` found: the share of the moving targets outside road users'
    tracks, and how far they tilted the plane of all moving targets [deg]."""

    share: float
    tilt_deg: float


#: Tracks slower than this [m/s] (start to end) are left out of the road plane, and the
#: time [s] at each end of a track whose targets place it (see ``track_speeds``).
_PLANE_MIN_TRACK_SPEED_MPS = 2.5
_TRACK_END_S = 0.3


def track_speeds(positions_m: F64, time_s: F64, track_id: np.ndarray) -> F64:
    """(n,) for each target the speed [m/s] of its track from its first to its last
    ``_TRACK_END_S`` (bird's-eye, sensor frame); inf for a target in no track or in one
    too short to say."""
    speed = np.full(track_id.shape[0], np.inf)
    in_track = np.flatnonzero(track_id >= 0)
    if in_track.size == 0:
        return speed
    t = time_s[in_track]
    tracks, track = np.unique(track_id[in_track], return_inverse=True)
    track = track.ravel()
    first = np.full(tracks.size, np.inf)
    last = np.full(tracks.size, -np.inf)
    np.minimum.at(first, track, t)
    np.maximum.at(last, track, t)

    def centre(at_end: np.ndarray) -> tuple[F64, F64]:
        n = np.maximum(np.bincount(track[at_end], minlength=tracks.size), 1)
        xy = np.column_stack([np.bincount(track[at_end], positions_m[in_track[at_end], k],
                                          minlength=tracks.size) for k in (0, 1)])
        return xy / n[:, None], np.bincount(track[at_end], t[at_end], minlength=tracks.size) / n

    start_xy, start_t = centre(t <= first[track] + _TRACK_END_S)
    end_xy, end_t = centre(t >= last[track] - _TRACK_END_S)
    span = end_t - start_t
    per_track = np.where(span > _TRACK_END_S, np.hypot(*(end_xy - start_xy).T)
                         / np.maximum(span, 1e-9), np.inf)
    speed[in_track] = per_track[track]
    return speed


def fit_road_plane(points_m: F64, time_s: F64, track_id: np.ndarray,
                   cfg: GroundConfig) -> tuple[GroundPlane, MovingClutter | None]:
    """The plane of the moving targets (``fit_ground_plane``), checked against the plane of
    the road users' tracks alone (``road_user_targets``) and replaced by it where the two
    differ by more than ``_CLUTTER_PLANE_DEG``: then the moving targets hold clutter that
    fills a volume. On clean recordings the first is kept as it is (it has more targets).

    Tracks slower than ``_PLANE_MIN_TRACK_SPEED_MPS`` are left out of both (where enough
    targets remain): pedestrians and cyclists on the pavements reflect at other heights than
    the cars on the road, on one side of it, and on a street seen along its length that
    turns the plane about the street (a sixty-third probe's old-town streets: the roll held
    at that plane 1.2-4.7 deg off; without the slow tracks 0.2-1.7).

    Returns the plane and, where it was replaced, what replaced it.
    """
    fast = track_speeds(points_m, time_s, track_id) >= _PLANE_MIN_TRACK_SPEED_MPS
    if int(fast.sum()) >= _MIN_ROAD_USER_TARGETS and not fast.all():
        kept = np.flatnonzero(fast)
        ground, clutter = fit_road_plane(points_m[kept], time_s[kept], track_id[kept], cfg)
        if clutter is not None:
            # the share of all the moving targets given that are no road user's
            clutter = dataclasses.replace(
                clutter, share=1.0 - (1.0 - clutter.share) * kept.size / fast.size)
        return dataclasses.replace(ground, used=kept[ground.used].astype(np.int64)), clutter
    ground = fit_ground_plane(points_m, cfg)
    road_users = road_user_targets(points_m, time_s, track_id)
    if int(road_users.sum()) < _MIN_ROAD_USER_TARGETS:
        return ground, None
    roads = fit_ground_plane(points_m[road_users], cfg)
    # as lines: a plane through a blob of rain at the radar may have its "up" either way
    tilt = math.degrees(math.acos(min(1.0, abs(float(ground.normal @ roads.normal)))))
    _LOG.debug('ground plane of all moving targets and of the road users\' tracks: %.3f deg '
               'apart', tilt)
    centred = points_m[road_users] - points_m[road_users].mean(axis=0)
    width = _width(centred @ _plane_basis(roads.normal)[:, :2])
    # how far the two planes lie apart is the kept one's uncertainty, capped (see below)
    sigma = min(tilt, _PLANE_SIGMA_MAX_DEG)
    if (ground.offset_m > -_LEAST_HEIGHT_ABOVE_M >= roads.offset_m
            and width < _ROAD_PLANE_MIN_WIDTH_M):
        # The plane of all moving targets runs level with the radar or above it: no road's.
        # False alarms with random radial velocities, a few a frame, fill the view's volume
        # and outweigh the road users' targets (a sixty-seventh probe's T-junction at 8 a
        # frame: that plane 1.5 m above the radar and 24 deg off its up, kept over the
        # road users' 2 deg off because they drove along one road; the pitch 13-20 deg
        # off, the sign turned, at exit 0). The road users' plane is kept, as uncertain
        # about their road as such a plane is (below).
        _LOG.info('the plane of all moving targets passes %.1f m above the radar (below '
                  'where negative): the road users\' plane is kept, %.1f deg from it',
                  ground.offset_m, tilt)
        # That plane is no road's, so how far it lies from theirs says nothing of theirs:
        # theirs is as uncertain as a plane along one road is (a seventieth probe's rain
        # put the first 10-76 deg off, and the tilt was reported at 10 deg, 1 sigma, where
        # the fit was 0.2-1.3 deg off).
        sigma = min(sigma, _one_road_sigma_deg(width))
    elif width < _ONE_LANE_WIDTH_M:
        # Road users in one lane only (the vehicle alone on a one-way street): nothing
        # moving shows the turn about that lane, whichever plane is kept, and with no other
        # traffic the moving targets beside it are clutter (a sixty-fifth probe's one-lane
        # road: the planes 2.1 deg apart, the tilt 7.4 deg off at a reported 2.2).
        _LOG.info('the road users\' tracks lie in one lane (%.1f m across): the road plane '
                  'is uncertain about it by up to %.0f deg', width, _PLANE_SIGMA_MAX_DEG)
        return dataclasses.replace(ground, tilt_sigma_deg=_PLANE_SIGMA_MAX_DEG), None
    elif tilt <= _CLUTTER_PLANE_DEG:
        return ground, None
    elif width < _ROAD_PLANE_MIN_WIDTH_M:
        # Road users along one road only (the calibration vehicle alone, driving it both
        # ways): their plane turns about the road by the height difference of the cars'
        # front and rear over the lanes' separation, which no target across the road
        # corrects. A forty-seventh probe's car alone making U-turns on one arm (4.4 m
        # across) gave a plane 4.7 deg off, held in the final fit (4.0 deg off), where the
        # plane of all moving targets was 0.1 deg off.
        _LOG.info('the road users\' tracks lie along one road (%.1f m across): the plane of '
                  'all moving targets is kept, %.1f deg from theirs', width, tilt)
        # which of the two is the road's the data cannot say (with no other traffic the
        # first is clutter's: a sixty-fifth probe's one-lane road, 8.9 deg apart, had the
        # tilt held 15 deg off at a reported 0.6 before one lane was taken above): the
        # difference is the plane's uncertainty, capped as there. Where the first lies
        # along that one road too (its densest targets are theirs), the two are one line's
        # planes, as uncertain about it as such a plane is, however near each other: a
        # seventy-first probe's drives all on one path beside moving false alarms, the
        # planes 1.8 deg apart and both 8 deg off, the roll reported at 1.9 deg, 8.7 off.
        along = _width((points_m[ground.used] - points_m[ground.used].mean(axis=0))
                       @ _plane_basis(ground.normal)[:, :2])
        if along < _ROAD_PLANE_MIN_WIDTH_M:
            sigma = max(sigma, min(_one_road_sigma_deg(along), _PLANE_SIGMA_MAX_DEG))
        return dataclasses.replace(ground, tilt_sigma_deg=sigma), None
    used = np.flatnonzero(road_users)[roads.used]
    return (dataclasses.replace(roads, used=used.astype(np.int64), tilt_sigma_deg=sigma),
            MovingClutter(float(1.0 - road_users.mean()), tilt))


def level_rotation(normal: F64) -> F64:
    """The smallest rotation R with ``R @ normal = [0, 0, 1]`` (Rodrigues' formula).

    Its axis is horizontal (normal x z), so it holds roll and pitch and no rotation about
    the vertical: yaw is left entirely to the hypotheses stage.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    c = float(n[2])
    if c <= -1.0 + 1e-12:
        # Upside down: any half turn about a horizontal axis will do; take the x axis.
        return np.diag([1.0, -1.0, -1.0])
    v = np.array([n[1], -n[0], 0.0])                 # n x e_z
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _neighbour_counts(points: F64, radius_m: float) -> F64:
    """Targets within ``radius_m`` of each target (any dimension), among evenly spaced
    references."""
    stride = max(1, -(-points.shape[0] // _DENSITY_REFERENCES))
    reference = cKDTree(points[::stride])
    counts = reference.query_ball_point(points, radius_m, return_length=True)
    return np.asarray(counts, dtype=np.float64)


def elevation_directions(points: F64) -> F64:
    """Unit direction in which an elevation error moves each target (n, 3).

    It is perpendicular to the line of sight, in the vertical plane of the sensor through
    the target: ``(e_z - (p.e_z) p) / |...|`` for the unit line of sight ``p``.
    """
    sight = points / np.maximum(np.linalg.norm(points, axis=1), 1e-12)[:, None]
    direction = np.array([0.0, 0.0, 1.0]) - sight[:, 2:3] * sight
    length = np.linalg.norm(direction, axis=1)
    # Straight above or below the sensor the elevation direction is undefined; no radar
    # sees there, but keep the result finite.
    direction[length < 1e-9] = (1.0, 0.0, 0.0)
    return direction / np.maximum(length, 1e-9)[:, None]


def _robust_plane(points: F64, noise_directions: F64, normal: F64,
                  cell: np.ndarray) -> tuple[F64, F64, np.ndarray]:
    """Plane of a cloud with a large, range-dependent error in known directions.

    ``_ROBUST_ROUNDS`` rounds, starting from ``normal`` (the paper's SVD plane), of: the
    residual scatter per ``cell`` (a grid in the plane: the scatter grows with range, as
    +-1.5 deg is +-0.5 m at 20 m and +-2.6 m at 100 m); a gate at ``_GATE_SIGMAS`` robust
    standard deviations of the cell around the median residual (clutter, multipath ghosts
    far below the road); and a weighted least-squares fit of the height over the plane
    with the bias of the errors in the plane coordinates removed (``_corrected_plane``).

    Why not the SVD throughout: total least squares assumes the same error in every
    direction. The radar's error is mostly in elevation, which TLS reads as a steeper
    plane: with lanes over +-9 m and +-1.5 deg elevation noise it overstates a 1.5 deg roll
    by ~12 %.

    The cells come from the data and the error directions are given, so the fit is
    equivariant under rigid motions of points and directions together.

    Returns the unit normal (sign arbitrary), the weighted centroid and a mask of the
    points used.
    """
    keep = np.ones(points.shape[0], bool)
    centroid = points.mean(axis=0)
    for _ in range(_ROBUST_ROUNDS):
        residual = (points - centroid) @ normal
        centre = float(np.median(residual[keep]))
        sigma = _cell_sigma(np.abs(residual - centre), cell, keep)
        if not np.all(sigma > 0.0):
            break
        inside = np.abs(residual - centre) <= _GATE_SIGMAS * sigma
        if inside.sum() < 3:
            break
        keep = inside
        variance = sigma[keep] ** 2
        normal, centroid = _corrected_plane(points[keep], noise_directions[keep], variance,
                                            _elevation_share(variance, points[keep]), normal)
    return normal, centroid, keep


def _elevation_share(variance: F64, points: F64) -> F64:
    """Share of each residual variance that is elevation error, the rest being the spread
    of reflection heights (and range noise), which does not grow with range.

    The variance is modelled as ``a + b * range^2`` (an angle error grows with range);
    ``a`` from a least-squares fit over the targets, clipped to ``[0, min(variance)]``.
    Without this split the correction of ``_corrected_plane`` would treat the height
    spread as elevation error and over-correct (by ~0.02 deg when the elevation error is
    small).
    """
    range_sq = np.einsum('ij,ij->i', points, points)
    design = np.column_stack([np.ones_like(range_sq), range_sq])
    (floor, _), *_ = np.linalg.lstsq(design, variance, rcond=None)
    floor = float(np.clip(floor, 0.0, variance.min()))
    return 1.0 - floor / variance


def _corrected_plane(points: F64, directions: F64, variance: F64, share: F64,
                     normal: F64) -> tuple[F64, F64]:
    """Weighted least squares of the height over the plane, errors in variables removed.

    Each point's height residual has ``variance``, of which ``share`` is an error
    ``delta * direction`` (``delta`` of variance ``share * variance / (n . direction)^2``).
    Regressing the height on the in-plane coordinates is biased by the part of that error
    lying in the plane; its known second moments are subtracted from the normal equations
    ("corrected least squares"). Repeated twice as the plane frame moves.
    """
    weights = 1.0 / variance
    centroid = weights @ points / weights.sum()
    centred = points - centroid
    # Every sum below is a quadratic form of two 3x3 moment matrices.
    scatter = (centred * weights[:, None]).T @ centred
    for _ in range(2):
        basis = _plane_basis(normal)
        along_n = directions @ normal
        # weight * error variance = share / (normal . direction)^2
        noise = share / np.maximum(along_n**2, 1e-6)
        error = (directions * noise[:, None]).T @ directions
        s_xx = basis.T @ (scatter - error) @ basis
        s_xy = basis.T @ (scatter - error) @ normal
        slope = np.linalg.solve(s_xx, s_xy)
        normal = normal - basis @ slope
        normal = normal / np.linalg.norm(normal)
    return normal, centroid


def _plane_basis(normal: F64) -> F64:
    """(3, 2): two orthonormal vectors perpendicular to ``normal``."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return np.column_stack([first, np.cross(normal, first)])


def _cell_sigma(abs_dev: F64, cell: np.ndarray, keep: np.ndarray) -> F64:
    """Robust standard deviation (1.4826 x median absolute deviation) of each target's grid
    cell, computed over the kept targets; cells with fewer than ``_MIN_CELL_TARGETS`` kept
    targets use the global one."""
    n_cells = int(cell.max()) + 1
    kept_cell, kept_dev = cell[keep], abs_dev[keep]
    global_sigma = 1.4826 * float(np.median(kept_dev))
    order = np.lexsort((kept_dev, kept_cell))
    sorted_cell, sorted_dev = kept_cell[order], kept_dev[order]
    count = np.bincount(sorted_cell, minlength=n_cells)
    start = np.cumsum(count) - count
    median = np.full(n_cells, global_sigma / 1.4826)
    big = count >= _MIN_CELL_TARGETS
    lo = start[big] + (count[big] - 1) // 2
    hi = start[big] + count[big] // 2
    median[big] = 0.5 * (sorted_dev[lo] + sorted_dev[hi])
    return 1.4826 * median[cell]


#: Kept targets narrower than this across their main direction, seen from above [m], lie
#: along one line (one lane's width is 3-4 m, a car's two metres) ...
_LINE_WIDTH_M = 1.0
#: ... and the density threshold is lowered through these fractions of
#: ``ground.density_fraction`` until they are not.
_WIDER_FRACTIONS = (0.5, 0.25, 0.1, 0.0)


def _width(in_plane: F64) -> float:
    """Standard deviation [m] of 2-D points across their main direction."""
    if in_plane.shape[0] < 3:
        return 0.0
    return math.sqrt(max(float(np.linalg.eigvalsh(np.cov(in_plane.T))[0]), 0.0))


def _principal_axes(centred: F64, weights: F64) -> tuple[F64, F64]:
    """Eigenvalues (ascending) and eigenvectors (columns) of the weighted scatter."""
    # The right singular vectors of the (weighted) centred cloud are the eigenvectors of
    # its 3x3 scatter matrix: the paper's SVD, without an (n, 3) decomposition.
    return np.linalg.eigh((centred * weights[:, None]).T @ centred)


def _svd_plane(points: F64, weights: F64) -> tuple[F64, F64]:
    """Unit normal and weighted centroid of the best-fitting plane (smallest singular
    direction of the weighted, centred cloud)."""
    if points.shape[0] < 3:
        raise InsufficientDataError(
            'ground_plane', f'{points.shape[0]} targets left for the ground plane, need '
            'at least 3')
    centroid = weights @ points / weights.sum()
    eigenvalues, eigenvectors = _principal_axes(points - centroid, weights)
    if eigenvalues[1] <= 1e-12 * max(eigenvalues[2], 1e-300):
        raise InsufficientDataError(
            'ground_plane', f'the {points.shape[0]} ground-plane targets are collinear; '
            'they do not define a plane')
    return eigenvectors[:, 0], centroid
