"""The final refinement's (stage 8, ``core/refine.py``) diagnostics: residuals per pass and
per target for the report, the view coverage and the drives that would add to it.

``_diagnostics`` summarises a finished fit; ``_drive_candidates`` ranks roads through the
view by the (aspect, bearing) diversity they would add, and ``_turn_ranges`` finds where the
passes turned through the view, for ``uncertainty.drive_advice``. Separate because it only
reads a fit, for the report and the advice, and feeds nothing back into it.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import uncertainty
from radar_calib_ros.core.refine_model import _Fit, _Model, _Poses, _robust, _Selected
from radar_calib_ros.core.refine_targets import _vehicle_frame
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, Extrinsics


def _diagnostics(model: _Model, x: F64, r: F64, data: _Selected,
                 pc: uncertainty.PassCovariance, cov7: F64, est: Extrinsics,
                 recording: Recording, poses: _Poses, config: CalibConfig, fit: _Fit,
                 rounds: int, scatter: F64) -> dict[str, Any]:
    g = model.geometry(x, jacobian=False)
    n = data.index.size
    los, unit, err = g['los'], g['unit'], g['err']
    rng = g['range']
    # Residual components for the report: along the line of sight, across it (horizontal)
    # and vertical; azimuth is in the sensor frame.
    horiz = np.column_stack([-unit[:, 1], unit[:, 0], np.zeros(n)])
    horiz /= np.maximum(np.linalg.norm(horiz, axis=1), 1e-12)[:, None]
    along_los = np.einsum('ij,ij->i', err, unit)
    across_los = np.einsum('ij,ij->i', err, horiz)
    vel_res = g['v_pred'] - data.v_mps
    azimuth = np.arctan2(data.sensor_m[:, 1], data.sensor_m[:, 0])
    weight = data.sqrt_weight ** 2
    sig = uncertainty.sigma_summary(cov7, est.rotation)
    # Bearing of each target relative to the boresight's ground projection.
    bore = math.atan2(est.rotation[1, 0], est.rotation[0, 0])
    bearing = np.arctan2(los[:, 1], los[:, 0]) - bore
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    coverage = uncertainty.view_coverage(g['aspect'], bearing, weight)
    # The nearest the vehicle was seen: closer, it is below the radar's vertical view (a
    # steep or narrow beam leaves a blind zone of 15-20 m under a pole), and a drive
    # advised there would give nothing (seen on an independent recording: "about 11 m").
    nearest = float(np.percentile(np.hypot(*(g['pos'][:, :2] - est.translation_m[:2]).T), 2))
    candidates = _drive_candidates(recording, poses, est, g, data, coverage, bore, nearest)
    # The views decide how well the drives pin the position along the boresight; the
    # vehicle's own position error (what its fixes are worth, added to the covariance) no
    # drive takes away, and the data notes speak of it: drives are advised for the views'
    # part alone (a simulator's fixes taken as standalone GNSS had the tool blame 2 m on the
    # bearings and ask for more drives).
    fixes_sigma = recording.pose_sigma_m[0]
    views_along = math.sqrt(max(sig['sigma_along_boresight_m'] ** 2 - fixes_sigma ** 2, 0.0))
    vel = g['vel']
    headings = [math.atan2(float(np.sum(vel[m, 1])), float(np.sum(vel[m, 0])))
                for m in (data.pass_id == p for p in range(pc.n_passes)) if m.any()]
    advice = uncertainty.drive_advice(views_along, config.quality.max_boresight_sigma_m,
                                      coverage, candidates, bore, nearest, fixes_sigma,
                                      headings, _turn_ranges(g, data, est))
    passes = []
    i_t = slice(3, 6)
    t_target = data.times.t_s
    for p in range(pc.n_passes):
        m = data.pass_id == p
        if not m.any():
            continue
        vel = g['vel'][m]
        heading = math.atan2(float(np.sum(vel[:, 1])), float(np.sum(vel[:, 0])))
        passes.append({
            'pass': p,
            'start_s': float(t_target[m].min()), 'end_s': float(t_target[m].max()),
            'n_targets': int(m.sum()), 'weight': float(weight[m].sum()),
            'heading_compass': uncertainty.compass_name(heading),
            'heading_deg': float(np.degrees(heading)),
            'median_range_m': float(np.median(rng[m])),
            'bearing_deg': [float(np.degrees(bearing[m].min())),
                            float(np.degrees(bearing[m].max()))],
            'median_abs_along_los_m': float(np.median(np.abs(along_los[m]))),
            'median_along_los_m': float(np.median(along_los[m])),
            'median_across_los_m': float(np.median(across_los[m])),
            'median_vertical_m': float(np.median(err[m, 2])),
            'median_velocity_residual_mps': float(np.median(vel_res[m])),
            'influence_translation_m': [float(v) for v in pc.influences[p, i_t]],
            'influence_rotation_deg': [float(v) for v in np.degrees(pc.influences[p, :3])],
        })
    local = _vehicle_frame(g['world'], g['pos'], g['yaw'])
    return {
        **sig,
        'advice': advice,
        'passes': passes,
        'n_passes': pc.n_passes,
        'jackknife_t_scale': pc.t_scale,
        'rounds': rounds,
        'iterations': fit.iterations,
        'converged': fit.converged,
        'time_offset_s': est.time_offset_s,
        'scatter_sigma_m': [float(v) for v in scatter],
        'profile_harmonics': config.refine.profile_harmonics,
        'coverage': {'aspect_edges_deg': coverage.aspect_edges_deg,
                     'bearing_edges_deg': coverage.bearing_edges_deg,
                     'weights': coverage.weights,
                     'bearing_spread_deg': coverage.bearing_spread_deg},
        # Arrays for the report's figures (one entry per used target).
        'residuals': {
            'target_index': data.index, 'pass_id': data.pass_id, 'weight': weight,
            'range_m': rng, 'azimuth_rad': azimuth, 'aspect_rad': g['aspect'],
            'bearing_rad': bearing, 'along_los_m': along_los, 'across_los_m': across_los,
            'vertical_m': err[:, 2], 'velocity_mps': vel_res,
            'offset_vehicle_m': local,
        },
        'robust_weight_mean': float(np.mean(_robust(r, n)[0])),
    }


#: Largest yaw rate of a pose that shows a lane to drive again [rad/s].
_LANE_MAX_YAW_RATE_RPS = 0.2


#: A lane holds its heading to within this [rad] over this distance of travel either side
#: [m]: a bend of 45 m radius or more does (the junction turns' radii are 10-30 m).
_LANE_HEADING_HELD_RAD = math.radians(20.0)
_LANE_HEADING_SPAN_M = 15.0


def _held_heading(positions: F64, yaw: F64) -> np.ndarray:
    """(n,) poses (in time order) whose heading differs by less than
    ``_LANE_HEADING_HELD_RAD`` from the headings ``_LANE_HEADING_SPAN_M`` of travel before
    and after them."""
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(positions, axis=0).T))])
    heading = np.unwrap(yaw)
    held = np.ones(yaw.size, bool)
    for reach in (-_LANE_HEADING_SPAN_M, _LANE_HEADING_SPAN_M):
        held &= np.abs(np.interp(travelled + reach, travelled, heading)
                       - heading) < _LANE_HEADING_HELD_RAD
    return held


#: Heading change within the view [rad] from which a pass counts as a turn through it.
_TURN_RAD = math.radians(45.0)


def _turn_ranges(g: dict[str, F64], data: _Selected, est: Extrinsics) -> list[float]:
    """Distance from the radar [m] of each pass that turned through the view, where its
    heading was halfway through the turn."""
    vel, pos, t = g['vel'], g['pos'], data.times.t_s
    ranges: list[float] = []
    for p in np.unique(data.pass_id[data.pass_id >= 0]):
        idx = np.flatnonzero(data.pass_id == p)
        idx = idx[np.argsort(t[idx], kind='stable')]
        heading = np.unwrap(np.arctan2(vel[idx, 1], vel[idx, 0]))
        if idx.size < 2 or abs(heading[-1] - heading[0]) < _TURN_RAD:
            continue
        mid = idx[int(np.argmin(np.abs(heading - 0.5 * (heading[0] + heading[-1]))))]
        ranges.append(float(np.hypot(*(pos[mid, :2] - est.translation_m[:2]))))
    return ranges


#: Places the vehicle drove through are compared by how many of the fit's targets came from
#: it within this distance [m] per pose it had there (the time it spent), and a place is
#: hidden below this share of the median place's.
_SEEN_NEAR_M = 4.0
_HIDDEN_SHARE = 0.25


def _hidden(recording: Recording, inside: np.ndarray, seen_at: F64) -> np.ndarray:
    """(n,) the vehicle's poses (of those ``inside``) driven while the radar recorded, at
    places where few or none of the fit's targets came from it (``seen_at``: the vehicle's
    positions at the targets' stamps), per time spent there.

    Why: a parked truck between the radar and a lane hides the vehicle there on every
    pass, and bearings never seen at an aspect are what the advice looks for: a
    fifty-sixth probe's drives were sent, in 10 runs of 10, into the truck's shadow
    (77-100 % of the car hidden there). Driving it again shows nothing either; the same
    holds where the fit left the targets out (the vehicle in a queue of others). By the
    targets' rate, not by whether any came: at the shadow's edge a fifth of the car still
    shows.
    """
    from scipy.spatial import cKDTree

    hidden = np.zeros(inside.size, bool)
    stamps = recording.vehicle.stamps_ns
    if seen_at.shape[0] == 0 or recording.frame_stamps_ns.size == 0:
        return hidden
    during = np.flatnonzero(inside & (stamps >= recording.frame_stamps_ns[0])
                            & (stamps <= recording.frame_stamps_ns[-1]))
    if during.size == 0:
        return hidden
    at = recording.vehicle.positions_m[during, :2]
    seen = cKDTree(seen_at[:, :2]).query_ball_point(at, _SEEN_NEAR_M, return_length=True)
    spent = cKDTree(at).query_ball_point(at, _SEEN_NEAR_M, return_length=True)
    rate = seen / np.maximum(spent, 1)
    if not (rate > 0).any():
        return hidden
    hidden[during] = rate < _HIDDEN_SHARE * float(np.median(rate[rate > 0]))
    return hidden


def _drive_candidates(recording: Recording, poses: _Poses, est: Extrinsics,
                      g: dict[str, F64], data: _Selected, coverage: uncertainty.ViewCoverage,
                      bore: float, nearest_m: float) -> list[uncertainty.DriveCandidate]:
    """Drives through the view ranked by the (aspect, bearing) diversity they would add.

    Candidates are the vehicle's own recorded positions inside the part of the view where it
    was seen (range and bearing span of the used targets, no nearer than ``nearest_m``):
    roads it can drive. Each is tried
    in both directions; an (aspect bin, bearing) pair scores by its angular distance to the
    bearings already seen at that aspect (saturating at 30 deg).
    """
    rng = g['range']
    bearing = np.arctan2(g['los'][:, 1], g['los'][:, 0]) - bore
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    r_max = float(np.percentile(rng, 98))
    b_lo, b_hi = float(np.percentile(bearing, 1)), float(np.percentile(bearing, 99))
    pts = recording.vehicle.positions_m
    yaw = recording.vehicle.yaw_rad
    rel = pts[:, :2] - est.translation_m[:2]
    p_rng = np.hypot(rel[:, 0], rel[:, 1])
    p_bear = (np.arctan2(rel[:, 1], rel[:, 0]) - bore + np.pi) % (2 * np.pi) - np.pi
    # where a drive is most useful: close enough for the bearing to change across the car,
    # far enough to see the whole car
    # within the bearings its targets were seen at: a forty-ninth probe's radar seeing to
    # +-60.7 deg was sent 62-63 deg right of its boresight
    inside = ((p_rng <= min(r_max, 60.0)) & (p_rng >= max(10.0, nearest_m))
              & (p_bear >= b_lo) & (p_bear <= b_hi))
    # and not where the vehicle drove unseen (a parked truck's shadow)
    inside &= ~_hidden(recording, inside, g['pos'])
    # A heading met mid-turn is no lane's: a junction's turns pass through every diagonal,
    # and a twenty-fourth probe with only east-west and north-south roads was asked to drive
    # 'south-westbound ... on a lane already driven'. Lanes are where the vehicle drove
    # straight (or round a bend: 0.2 rad/s is a 50 m radius at 10 m/s), and held that
    # heading for a while: a fifty-second probe's turns ran through a stretch of a few
    # metres at a yaw rate of 0.03 rad/s halfway round, 57 deg turned 15 m before it and 33
    # deg 15 m after, and were offered as 'south-westbound again on a lane already driven'.
    straight = ((np.abs(recording.vehicle.yaw_rate_rps) < _LANE_MAX_YAW_RATE_RPS)
                & _held_heading(pts[:, :2], yaw))
    if (inside & straight).any():
        inside &= straight
    if not inside.any():
        return []
    # thin to about one sample per 5 m of road per direction
    key = np.stack([np.floor(pts[inside, 0] / 5.0), np.floor(pts[inside, 1] / 5.0),
                    np.floor(((yaw[inside] + np.pi) % (2 * np.pi)) / (np.pi / 4))], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    sel = np.flatnonzero(inside)[first]
    a_edges = np.radians(coverage.aspect_edges_deg)
    seen_aspect = g['aspect']
    # where each direction was driven: a lane's other way was driven where a pose within a
    # road's width heads that way (the other lane or carriageway). There that way's own
    # poses are the candidates: at this lane's place a forty-fifth probe on a divided
    # highway was sent the wrong way down the other carriageway ('drive north-eastbound
    # again on a lane already driven', a lane only south-westbound passes had used).
    driven_key = np.unique(key, axis=0)
    out: list[uncertainty.DriveCandidate] = []
    for flip, driven in ((0.0, True), (np.pi, False)):
        heading = yaw[sel] + flip
        if flip:
            turned = np.column_stack([key[first, :2], np.floor(
                ((heading + np.pi) % (2 * np.pi)) / (np.pi / 4))])
            near = (np.abs(turned[:, None, :2] - driven_key[None, :, :2]).max(axis=2) <= 1.0)
            turn = (turned[:, None, 2] - driven_key[None, :, 2]) % 8
            already = (near & ((turn <= 1) | (turn == 7))).any(axis=1)
        else:
            already = np.ones(sel.size, bool)
        los_dir = np.arctan2(rel[sel, 1], rel[sel, 0])
        aspect = (los_dir + np.pi - heading + np.pi) % (2 * np.pi) - np.pi
        a_bin = np.searchsorted(a_edges, (aspect - a_edges[0]) % (2 * np.pi) + a_edges[0],
                                side='right') - 1
        s_bin = np.searchsorted(a_edges, (seen_aspect - a_edges[0]) % (2 * np.pi)
                                + a_edges[0], side='right') - 1
        # distance to the nearest bearing already seen at the same aspect bin (vectorised
        # over candidates x used targets, thinned to at most 2000 targets)
        step = max(1, bearing.size // 2000)
        sb, ss = bearing[::step], s_bin[::step]
        same = a_bin[:, None] == ss[None, :]
        dist = np.abs((p_bear[sel][:, None] - sb[None, :] + np.pi) % (2 * np.pi) - np.pi)
        dist = np.where(same, dist, np.inf).min(axis=1)
        gain = np.where(np.isfinite(dist), np.minimum(dist / np.radians(30.0), 1.0), 0.0)
        open_lane = np.flatnonzero(~already) if flip else np.arange(sel.size)
        for i in open_lane[np.argsort(-gain[open_lane])][:3]:
            out.append(uncertainty.DriveCandidate(float(heading[i]), float(p_rng[sel][i]),
                                                  float(p_bear[sel][i]), float(gain[i]),
                                                  driven))
    # one suggestion per direction of travel, on a lane driven that way where there is one
    # that adds anything (a way never driven is asked for where its lanes allow, a way
    # driven is asked for again where it was driven), the best first
    out.sort(key=lambda c: (not (c.driven and c.gain > 0.0), -c.gain))
    unique: list[uncertainty.DriveCandidate] = []
    for cand in out:
        if all(abs((cand.heading_rad - u.heading_rad + np.pi) % (2 * np.pi) - np.pi) > 0.5
               for u in unique):
            unique.append(cand)
    unique.sort(key=lambda c: -c.gain)
    return unique
