"""Which targets the final refinement (stage 8, ``core/refine.py``) takes, and how much each
counts.

The gate keeps the targets the current estimate puts on or near the vehicle's box, by track
and one by one (``_gate``); it leaves out frames where another road user hides the vehicle
(``_occluded``) or the edge of the view cuts it (``_box_inside_view``), and targets whose
radial velocity does not follow the vehicle's rigid motion (``_velocity_consistent``), and
keeps only runs of targets that make a pass (``_in_passes``). Before the rounds, the
targets stage 1 took for static are added near the moving vehicle (``with_static_targets``):
a slow car's broadside strip. ``_select`` then prepares the
chosen targets for a fit: positions freed of the angular noise's bias (and lifted out of a
2-D radar's plane), information weights per (position, aspect) cell, pass ids, and the
whitening of each target's position by the radar's noise and the reflectors' scatter.
Separate from the stage because it decides what the model sees, not how it is fitted: the
stage calls it every gate round and the rescan along the boresight calls the gate alone.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, reflection
from radar_calib_ros.core.moving import moving_threshold_mps
from radar_calib_ros.core.refine_model import (_Poses, _Selected, _Times,
                                               reflection_height_prior)
from radar_calib_ros.core.vehicle import (box_corners_world, box_distance, box_limits,
                                          world_to_vehicle)
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, I64, Extrinsics, RadarView, TrackedTargets


#: The largest sine of the dip of a 2-D radar's line of sight out of its plane (a target
#: nearer than its height).
_PLANAR_MAX_SIN = 0.98
#: Track id of the targets ``with_static_targets`` adds (-1 is a moving target in no track).
STATIC_TRACK = -2
#: The vehicle's speed [m/s] from which its targets' radial velocities tell it from static
#: clutter near it (walking pace; a queue's creep below it is left to the moving targets).
_STATIC_MIN_SPEED_MPS = 1.0
#: ... and how far from the box such a target may lie [m]: the car's own lie on or inside
#: its outline within the range noise, while road clutter beside it lies anywhere. With the
#: noise targets' 1 m, an imaging radar's ground clutter near broadside came in: three
#: 800-target recordings of a twenty-ninth probe had the radar 3.5-6 cm lower than before
#: this stage took static targets (2-4.5 cm at 0.3 m, the slow car's fix the same); inside
#: the outline only, the slow car's bias came back by half (-4.4 cm).
_STATIC_GATE_M = 0.3
#: Targets looked at at once for that (``with_static_targets``).
_STATIC_CHUNK = 2_000_000
#: Fewest targets a refinement is attempted with.
_MIN_TARGETS = 30
#: Fewest targets of a pass (see ``_in_passes``).
_MIN_PASS_TARGETS = 20
#: A track is taken as the calibration vehicle's when at least this fraction of its targets
#: lie in the gate: tracks of other cars that only brush past the box are left out.
_TRACK_FRACTION = 0.5
#: ... and when the median distance of its targets from the box is at most this [m], once
#: the first round has brought the estimate within centimetres-to-decimetres. Measured on
#: the simulator at the true pose: the vehicle's own tracks have medians of 0.00-0.28 m
#: (skin returns lie on the faces, interior ones inside), while a truck creeping 1 m ahead
#: in a queue, or a car in the next lane, forms tracks that are half inside the 1.5 m gate
#: with medians of 1.0-1.5 m; admitted, they pulled a dense-traffic calibration 0.5 m off.
_TRACK_MEDIAN_M = 0.5
#: Targets in no track are judged one by one, within this fraction of the gate: at the
#: truth, those 1.0-1.5 m from the box are 2-9 % the vehicle's (they are other road users'
#: stray returns), those within 0.5 m 76-100 %.
_NOISE_GATE_FRACTION = 2.0 / 3.0
#: Frames with the vehicle cut by the edge of the view are left out only while at least
#: this share of the gated targets remains (see ``_box_inside_view``).
_MIN_INSIDE_VIEW_SHARE = 0.5
#: The radial-velocity gate widens to this many robust sigma of the near targets' v_r
#: differences (see ``_velocity_consistent``).
_VELOCITY_GATE_SIGMAS = 4.0


# --- selecting targets, weights, passes -------------------------------------------------

def _vehicle_frame(world: F64, pos: F64, yaw: F64) -> F64:
    """World points (n, 3) in each one's vehicle pose: bird's-eye view plus height."""
    return np.column_stack([world_to_vehicle(world, pos, yaw), world[:, 2] - pos[:, 2]])


def _track_sizes(track_ids: I64) -> I64:
    """(n,) number of moving targets of each target's track (1 for noise targets)."""
    out = np.ones(track_ids.size, np.int64)
    has = track_ids >= 0
    if has.any():
        # track ids are numbered from 0: counted, not sorted (millions of moving targets)
        ids = track_ids[has]
        out[has] = np.bincount(ids)[ids]
    return out


#: The corridor looks at this many candidates at a time: it sees every tracked moving target
#: of the recording, and a dense imaging radar's 3.9 million (a twenty-ninth probe's, four
#: detections on every road user) held 1.1 GB of per-target poses and placed copies at once.
_CORRIDOR_CHUNK = 250_000


def _corridor(est: Extrinsics, candidates: I64, times: _Times, recording: Recording,
              poses: _Poses, config: CalibConfig) -> np.ndarray:
    """Mask of the candidates that may come within the gate while the estimate converges."""
    # The poses are interpolated once per frame (as ``_Times.poses`` does) and gathered per
    # chunk, only those used: the same numbers as all at once.
    frame_t = times.frame_t + est.time_offset_s
    frame_pos, frame_yaw, frame_vel, _, _ = poses.at(frame_t)
    frame_valid = poses.valid(frame_t)
    reach = config.sync.max_time_offset + abs(est.time_offset_s)
    keep = np.zeros(candidates.size, bool)
    for lo in range(0, candidates.size, _CORRIDOR_CHUNK):
        part = slice(lo, lo + _CORRIDOR_CHUNK)
        inverse = times.inverse[part]
        sensor = recording.targets.positions_m[candidates[part]]
        local = _vehicle_frame(est.apply(sensor), frame_pos[inverse], frame_yaw[inverse])
        vel = frame_vel[inverse]
        speed = np.hypot(vel[:, 0], vel[:, 1])
        rng = np.linalg.norm(sensor, axis=1)
        margin = config.refine.gate_m + 2.0 + 0.03 * rng + speed * reach
        keep[part] = frame_valid[inverse] & (
            box_distance(local[:, :2], config.vehicle) <= margin)
    return keep


def with_static_targets(est: Extrinsics, recording: Recording, tracked: TrackedTargets,
                        config: CalibConfig) -> TrackedTargets:
    """``tracked`` plus the targets stage 1 took for static that lie near the vehicle while
    it moves, as track ``STATIC_TRACK`` (judged one by one, after the radial-velocity check).

    The moving filter drops every |v_r| below the radar's noise floor, and on a moving car
    that is the strip of it where the line of sight stands square to its travel: near
    broadside, the part of the car nearest the foot of the perpendicular from the radar.
    That strip moves over the car as it passes, by an amount that depends on the range and
    the speed, not on the aspect alone, so no reflection profile can follow the gap: an
    independent probe's car at 15 km/h (noise floor 0.3 m/s, the strip +-4 deg wide) sat
    8.9 cm too far back along the boresight on average (8 of 8 seeds on one side), at
    8 km/h 26 cm; with them taken back, 0.2 and 4.7 cm. Those targets move exactly as the
    car's rigid motion predicts there (about zero), which is what the gate's velocity
    check asks of them; static clutter beside the car passes it only where the car's own
    v_r is near zero too. A stopped car is left out (everything near it is static then).
    """
    if config.refine.velocity_gate_mps <= 0 or len(recording.targets) == 0:
        return tracked
    targets = recording.targets
    threshold = moving_threshold_mps(targets.radial_velocity_mps, config.moving)
    t0_ns = int(recording.vehicle.stamps_ns[0])
    poses = _Poses.from_track(recording.vehicle, t0_ns, config.sync.max_pose_gap,
                              recording.fix_sigma_m)
    # Most of a recording's targets are static; a first cut per frame (the vehicle there
    # and moving) and per target (within a generous sphere around it in the sensor frame),
    # chunk by chunk, keeps an imaging radar's tens of millions out of memory at once.
    frame_t = ((recording.frame_stamps_ns - t0_ns) * 1e-9 + config.sync.time_offset
               + est.time_offset_s)
    pos, _, vel, _, _ = poses.at(frame_t)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    frame_ok = poses.valid(frame_t) & (speed >= _STATIC_MIN_SPEED_MPS)
    centre = est.inverse_apply(pos)
    reach = config.sync.max_time_offset + abs(est.time_offset_s)
    radius = (config.refine.gate_m + 3.0 + config.vehicle.length + config.vehicle.height
              + 0.03 * np.linalg.norm(centre, axis=1) + speed * reach)
    in_tracked = np.zeros(len(targets), bool)
    in_tracked[np.asarray(tracked.target_index, np.int64)] = True
    parts = []
    for lo in range(0, len(targets), _STATIC_CHUNK):
        part = slice(lo, lo + _STATIC_CHUNK)
        frame = targets.frame_index[part]
        ok = (frame_ok[frame] & ~in_tracked[part]
              & (np.abs(targets.radial_velocity_mps[part]) < threshold))  # NaN: left out
        near = np.flatnonzero(ok)
        off = targets.positions_m[part][near] - centre[frame[near]]
        parts.append(lo + near[np.einsum('ij,ij->i', off, off) <= radius[frame[near]] ** 2])
    static = np.concatenate(parts).astype(np.int64)
    if static.size == 0:
        return tracked
    times = _Times.of(recording, static, config.sync.time_offset, t0_ns)
    added = static[_corridor(est, static, times, recording, poses, config)]
    if added.size == 0:
        return tracked
    index = np.concatenate([np.asarray(tracked.target_index, np.int64), added])
    track_id = np.concatenate([np.asarray(tracked.track_id, np.int64),
                               np.full(added.size, STATIC_TRACK, np.int64)])
    order = np.argsort(index, kind='stable')
    return TrackedTargets(index[order], track_id[order])


def _gate(est: Extrinsics, candidates: I64, track_ids: I64, track_size: I64,
          accepted: np.ndarray, times: _Times, recording: Recording, poses: _Poses,
          config: CalibConfig, first_round: bool,
          view: RadarView) -> np.ndarray:
    """Mask over ``candidates`` of the targets the estimate puts on or near the vehicle.

    The first round starts from the paper's estimate, decimetres off: it gates at
    ``refine.gate_m``. Later rounds start within centimetres and gate at
    ``refine.final_gate_m``: measured at the true pose, the targets 0.75-1.5 m from the box
    are 0-48 % the vehicle's (wheel-house multi-bounce), in dense traffic 0-6 % (queued
    neighbours), while 94-99 % of the vehicle's targets lie within 0.5 m.
    """
    cfg = config.refine
    gate = cfg.gate_m if first_round else min(cfg.gate_m, cfg.final_gate_m)
    sensor = recording.targets.positions_m[candidates]
    valid = times.valid(poses, est.time_offset_s)
    pos, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    local = _vehicle_frame(est.apply(sensor), pos, yaw)
    dist = np.where(valid, box_distance(local[:, :2], config.vehicle), np.inf)
    near = dist <= gate
    # Tracks of other cars brush the box now and then; the calibration vehicle's own tracks
    # are mostly inside the gate and centred on the box. Noise targets (no track) are judged
    # one by one, more strictly.
    has_track = track_ids >= 0
    keep = near & (has_track | (dist <= _NOISE_GATE_FRACTION * gate))
    static = track_ids == STATIC_TRACK
    if first_round or cfg.velocity_gate_mps <= 0:
        # only the radial-velocity check below can tell the vehicle's slow targets from
        # static clutter beside it (``with_static_targets``)
        keep &= ~static
    else:
        keep &= ~static | (dist <= _STATIC_GATE_M)
    if has_track.any():
        tid = track_ids[has_track]
        uniq, inv = np.unique(tid, return_inverse=True)
        n_near = np.bincount(inv, near[has_track].astype(float), minlength=uniq.size)
        size = np.zeros(uniq.size)
        size[inv] = track_size[has_track]
        median = _group_median(inv, dist[has_track], uniq.size)
        # the first round starts decimetres off: only the fraction rule applies then
        limit = gate if first_round else _TRACK_MEDIAN_M
        track_ok = (((n_near / size >= _TRACK_FRACTION) & (median <= limit))
                    | np.isin(uniq, accepted))
        # A track the rule refuses may still hold the vehicle's targets: two cars close
        # together in a queue or side by side share a cluster, so their track is half the
        # vehicle's and half another's (its median far from the box). Its targets inside
        # the footprint are the vehicle's (two cars do not overlap); those around it may be
        # the other's, and are left out. Measured on the simulator's ten-minute runs: the
        # horizontal median 6.7 / 5.5 / 5.7 -> 5.9 / 5.0 / 5.6 cm (interior / mixed / skin),
        # the rotation median 0.160 / 0.108 / 0.202 -> 0.129 / 0.094 / 0.179 deg.
        ok = track_ok[inv]
        if not first_round:
            ok |= dist[has_track] <= 0.0
        keep[has_track] &= ok
    inside = keep & _box_inside_view(pos, yaw, est, view, config)
    # A narrow view (a long-range radar's +-9 deg) may rarely hold the whole car: then the
    # cut views are all there is, and losing most of the data would cost more than the cut.
    if inside.sum() >= max(_MIN_TARGETS, _MIN_INSIDE_VIEW_SHARE * keep.sum()):
        keep = inside
    if not first_round and cfg.velocity_gate_mps > 0 and keep.any():
        keep[keep] = _velocity_consistent(est, candidates[keep], times.subset(keep),
                                          recording, poses, cfg.velocity_gate_mps)
    return keep


def _occluded(est: Extrinsics, index: I64, times: _Times, recording: Recording,
              poses: _Poses, road_users: I64, config: CalibConfig) -> np.ndarray:
    """Mask over ``index`` (the vehicle's targets) of those in frames where another road
    user hides the vehicle's lower half: at least ``_OCCLUDER_TARGETS`` tracked moving
    targets within the box's bearings (plus ``_OCCLUDER_MARGIN_DEG``), nearer than its
    nearest corner by ``_OCCLUDER_GAP_M``, where a road user ``_OCCLUDER_HEIGHT_M`` tall
    reaches above the line from the radar to that corner at half the vehicle's height (a
    radar on a pole looks over a car ten metres ahead, not over one queued close behind or
    a truck alongside).

    A partly hidden car shows the radar only its unhidden part, and which part that is
    depends on where the occluder stands, not on the aspect: the reflection profile cannot
    follow it. A fourteenth probe's truck in the next lane, alongside the car on the
    radar's side in every pass, moved the radar 0.24-0.53 m along its boresight (up to
    2.3 sigma) while the same trucks without shadows left it at 0.01-0.11 m.
    """
    pos, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    frames = recording.targets.frame_index[index]
    unique, first = np.unique(frames, return_index=True)
    world = np.empty((unique.size, 4, 3))
    world[:, :, :2] = box_corners_world(pos[first], yaw[first], config.vehicle)
    road = pos[first, 2] - config.vehicle.ref_height
    world[:, :, 2] = road[:, None] + 0.5 * config.vehicle.height
    sensor = est.inverse_apply(world.reshape(-1, 3)).reshape(world.shape)
    bearing = np.arctan2(sensor[:, :, 1], sensor[:, :, 0])
    margin = math.radians(_OCCLUDER_MARGIN_DEG)
    low, high = bearing.min(axis=1) - margin, bearing.max(axis=1) + margin
    corner_range = np.hypot(world[:, :, 0] - est.translation_m[0],
                            world[:, :, 1] - est.translation_m[1])
    near_corner = np.argmin(corner_range, axis=1)
    reach = corner_range[np.arange(unique.size), near_corner]
    # the line of sight to the nearest corner at mid-height falls this much per metre
    drop = (est.translation_m[2] - world[np.arange(unique.size), near_corner, 2]) / reach
    nearest = reach - _OCCLUDER_GAP_M
    user_frames = recording.targets.frame_index[road_users]
    k = np.searchsorted(unique, user_frames)
    in_frame = (k < unique.size) & (unique[np.minimum(k, unique.size - 1)] == user_frames)
    k = k[in_frame]
    p = recording.targets.positions_m[road_users[in_frame]]
    b = np.arctan2(p[:, 1], p[:, 0])
    w = est.apply(p)
    rho = np.hypot(w[:, 0] - est.translation_m[0], w[:, 1] - est.translation_m[1])
    # The road user's top, not its targets (they lie mostly low, on wheels and underbody):
    # assumed a car's height above the vehicle's road, the least of what hides anything.
    top = road[k] + _OCCLUDER_HEIGHT_M
    above = top > est.translation_m[2] - drop[k] * rho
    ahead = (b >= low[k]) & (b <= high[k]) & (rho < nearest[k]) & above
    hidden = np.bincount(k[ahead], minlength=unique.size) >= _OCCLUDER_TARGETS
    return hidden[np.searchsorted(unique, frames)]


#: What counts as a road user between the radar and the vehicle (``_occluded``): tracked
#: moving targets, this many in one frame (one is a stray), within the box's bearings
#: widened by this much [deg] and nearer than its nearest corner by this much [m] (three
#: sigma of range noise: the vehicle's own targets are not).
_OCCLUDER_TARGETS = 2
_OCCLUDER_MARGIN_DEG = 1.0
_OCCLUDER_GAP_M = 0.5
_OCCLUDER_HEIGHT_M = 1.5


def _box_inside_view(pos: F64, yaw: F64, est: Extrinsics, view: RadarView,
                     config: CalibConfig) -> np.ndarray:
    """(n,) True where every corner of the vehicle's footprint lies inside the radar's view
    in range and azimuth.

    A car that the edge of the view cuts shows only its inner part: the mean of its
    reflections shifts towards the inside, by up to half a car, which no profile over the
    aspect can follow. Measured on a probe's recording with reflections spread uniformly
    over the footprint and a hard 70 m / +-50 deg view: 15 cm along the boresight with such
    frames, 1 cm without them (its other variants: 8 of them 106 -> 87 cm summed, one face
    model 12 -> 15 cm). Over 108 simulated ten-minute runs the horizontal median went from
    8.5 to 6.0 cm (skin), 6.3 to 6.2 (interior) and 6.0 to 6.1 (mixed).
    """
    max_range, (az_lo, az_hi) = view.range_m, view.azimuth_rad
    x0, x1, y0, y1 = box_limits(config.vehicle)
    c, s = np.cos(yaw), np.sin(yaw)
    ok = np.ones(pos.shape[0], bool)
    for cx in (x0, x1):
        for cy in (y0, y1):
            corner = pos.copy()
            corner[:, 0] += cx * c - cy * s
            corner[:, 1] += cx * s + cy * c
            corner[:, 2] -= config.vehicle.ref_height
            local = est.inverse_apply(corner)
            azimuth = np.arctan2(local[:, 1], local[:, 0])
            ok &= ((np.linalg.norm(local, axis=1) < max_range) & (azimuth > az_lo)
                   & (azimuth < az_hi))
    return ok


def _velocity_consistent(est: Extrinsics, index: I64, times: _Times, recording: Recording,
                         poses: _Poses, gate_mps: float) -> np.ndarray:
    """Mask of the targets whose radial velocity matches the vehicle's rigid motion.

    Within the box gate two kinds of target move unlike the car's body: another road user
    that overlaps the box for a while (a car turning across it, a truck alongside in a queue),
    and the wheels, whose micro-Doppler spreads over 0..2x the speed. Both carry position
    errors the soft-L1 loss only bounds: measured on the simulator, 4 % of foreign targets
    merged into a dense-traffic track moved the radar 25 cm along the boresight (1.5 cm
    without them), and wheel returns alone fit 0.6 m off. The body's v_r residual is
    0.06 m/s median; 0.6 m/s (``refine.velocity_gate_mps``) cuts 10-16 % of the targets.
    Over 108 simulated ten-minute runs the 90th percentile of the horizontal error fell
    from 19.5 to 11.5 cm (interior) and 20.2 to 15.7 cm (mixed), skin unchanged (8.5 cm
    median); dense traffic seed 1 from 27 to 12 cm. A radar with coarser velocities widens
    the gate to 4 robust sigma of the differences, so it never cuts into its noise. The
    first round, decimetres and about a degree off, is not gated.
    """
    sensor = recording.targets.positions_m[index]
    pos, _, vel, rate, _ = times.poses(poses, est.time_offset_s)
    world = est.apply(sensor)
    rel = world - pos
    point_velocity = vel + rate[:, None] * np.column_stack([-rel[:, 1], rel[:, 0],
                                                            np.zeros(len(rel))])
    los = world - est.translation_m
    unit = los / np.maximum(np.linalg.norm(los, axis=1), 1e-9)[:, None]
    diff = (np.einsum('ij,ij->i', point_velocity, unit)
            - recording.targets.radial_velocity_mps[index])
    robust_sigma = 1.4826 * float(np.median(np.abs(diff)))
    return np.abs(diff) <= max(gate_mps, _VELOCITY_GATE_SIGMAS * robust_sigma)


def _group_median(group: I64, values: F64, n_groups: int) -> F64:
    """(n_groups,) median of the finite ``values`` of each group (inf where none)."""
    finite = np.isfinite(values)
    g, v = group[finite], values[finite]
    out = np.full(n_groups, np.inf)
    # scipy.ndimage.median returns an arbitrary value for a label without members
    present = np.flatnonzero(np.bincount(g, minlength=n_groups))
    if present.size:
        out[present] = ndimage.median(v, g, present)
    return out


def _information_weights(frame_index: I64, pos: F64, aspect: F64, config: CalibConfig) -> F64:
    """Weight per target: the frames of one (vehicle position, aspect) cell share the weight
    of ``cell_frames`` frames, so a queued car counts as the few views it really gives."""
    cfg = config.refine
    ix = np.floor(pos[:, 0] / cfg.cell_size_m).astype(np.int64)
    iy = np.floor(pos[:, 1] / cfg.cell_size_m).astype(np.int64)
    ia = np.floor((np.degrees(aspect) % 360.0) / cfg.cell_aspect_deg).astype(np.int64)
    cells = np.stack([ix, iy, ia], axis=1)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    cell = cell.ravel()
    # distinct frames per cell
    pairs = np.unique(np.stack([cell, frame_index], axis=1), axis=0)
    frames_per_cell = np.bincount(pairs[:, 0], minlength=int(cell.max()) + 1)
    return np.minimum(1.0, cfg.cell_frames / frames_per_cell[cell])


def _in_passes(t_s: F64, gap_s: float) -> np.ndarray:
    """(n,) False for targets in runs of fewer than ``_MIN_PASS_TARGETS``: a few targets
    near the box for an instant are another road user or clutter, not a pass (they would
    also count as passes in the jackknife and shrink its t-factor)."""
    ids = hypotheses.target_runs(t_s, gap_s)
    return np.bincount(ids)[ids] >= _MIN_PASS_TARGETS


def _whitening(sensor: F64, rotation: F64, yaw: F64, scatter_sigma: F64,
               config: CalibConfig, vertical_ok: np.ndarray | None = None) -> F64:
    """(n, 3, 3) inverse Cholesky factors of each target's position covariance in the world:
    the radar's spherical noise (range, azimuth, elevation) plus the reflectors' scatter
    around their mean (diagonal in the vehicle frame)."""
    cfg = config.refine
    rng = np.linalg.norm(sensor, axis=1)
    az = np.arctan2(sensor[:, 1], sensor[:, 0])
    el = np.arcsin(np.clip(sensor[:, 2] / np.maximum(rng, 1e-9), -1.0, 1.0))
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    e_r = np.column_stack([ce * ca, ce * sa, se])
    e_az = np.column_stack([-sa, ca, np.zeros_like(sa)])
    e_el = np.column_stack([-se * ca, -se * sa, ce])
    var_r = cfg.range_sigma_m ** 2
    var_az = (rng * ce * math.radians(cfg.azimuth_sigma_deg)) ** 2
    var_el = (rng * math.radians(cfg.elevation_sigma_deg)) ** 2
    cov_s = (var_r * e_r[:, :, None] * e_r[:, None, :]
             + var_az[:, None, None] * e_az[:, :, None] * e_az[:, None, :]
             + var_el[:, None, None] * e_el[:, :, None] * e_el[:, None, :])
    cov_w = np.einsum('ij,njk,lk->nil', rotation, cov_s, rotation)
    c, s = np.cos(yaw), np.sin(yaw)
    sx2, sy2, sz2 = np.asarray(scatter_sigma, float) ** 2
    cov_w[:, 0, 0] += c * c * sx2 + s * s * sy2
    cov_w[:, 1, 1] += s * s * sx2 + c * c * sy2
    cov_w[:, 0, 1] += c * s * (sx2 - sy2)
    cov_w[:, 1, 0] += c * s * (sx2 - sy2)
    cov_w[:, 2, 2] += sz2
    if vertical_ok is not None:
        # no height information from these targets: an (almost) infinite vertical variance
        # drops the vertical row and leaves the horizontal ones as they were
        cov_w[~vertical_ok, 2, :2] = 0.0
        cov_w[~vertical_ok, :2, 2] = 0.0
        cov_w[~vertical_ok, 2, 2] = 1e8
    chol = np.linalg.cholesky(cov_w)
    return np.linalg.inv(chol)


# --- the selected targets for a fit -----------------------------------------------------

def _debiased_positions(sensor: F64, config: CalibConfig) -> F64:
    """Sensor-frame target positions with the bias of angular noise removed.

    The radar measures range, azimuth and elevation; noise n ~ N(0, s^2) on an angle
    shrinks the Cartesian position on average: E[cos(e + n)] = cos(e) exp(-s^2 / 2), the
    same for sin. With 1.5 deg of elevation noise that is 3.4e-4 of the range, 3 cm at
    100 m, a scale error that moves the radar along its boresight. Dividing by the expected
    shrink makes the positions unbiased.
    """
    cfg = config.refine
    s_el2 = math.radians(cfg.elevation_sigma_deg) ** 2
    s_az2 = math.radians(cfg.azimuth_sigma_deg) ** 2
    scale = np.array([math.exp(0.5 * (s_el2 + s_az2)), math.exp(0.5 * (s_el2 + s_az2)),
                      math.exp(0.5 * s_el2)])
    return sensor * scale


def _inside_elevation_view(pos: F64, yaw: F64, est: Extrinsics, fov: tuple[float, float],
                           config: CalibConfig) -> np.ndarray:
    """(n,) True where the whole vehicle and its mirror image below the road lie inside
    the elevation field of view.

    Where the field of view cuts off the lower part of the car (or its multipath image
    below the road), what is seen of it is higher on average, and more so the closer the
    car: the mean reflection height then changes with range, and a pitch error would be
    fitted to follow it (0.3-0.7 deg measured on the simulator). Such frames keep their
    horizontal and radial-velocity information but give no height information.
    """
    veh = config.vehicle
    x_lo, x_hi, _, _ = box_limits(veh)
    centre = pos.copy()
    centre[:, 0] += 0.5 * (x_lo + x_hi) * np.cos(yaw)
    centre[:, 1] += 0.5 * (x_lo + x_hi) * np.sin(yaw)
    road = pos[:, 2] - veh.ref_height
    ok = np.ones(pos.shape[0], bool)
    # the road under the vehicle's centre must be above the lower edge (a stricter test,
    # with the whole mirror image inside, drops the near passes that carry the pitch),
    # the roof below the upper one
    for dz, lower in ((0.0, True), (veh.height, False)):
        pt = centre.copy()
        pt[:, 2] = road + dz
        s = est.inverse_apply(pt)
        el = np.arcsin(np.clip(s[:, 2] / np.maximum(np.linalg.norm(s, axis=1), 1e-9), -1, 1))
        ok &= (el > fov[0]) if lower else (el < fov[1])
    return ok


def _slant_to_height(sensor: F64, height_m: F64, rotation: F64) -> F64:
    """A 2-D radar's targets (range and azimuth in its plane, z = 0) lifted out of the
    plane to ``height_m`` (n,) relative to the radar in the world, under ``rotation``.

    Its range is the slant range, so a target below the radar lies nearer horizontally, by
    height^2 / (2 range) (1.2 m at 15 m for a 6 m pole), a bias no reflection profile
    follows. The elevation e that puts the target at that height solves
    a cos e + b sin e = height / range, with (a, b) the world-vertical components of the
    azimuth's in-plane direction and of the plane's normal. The heights are the model's
    (the vehicle's plus the reflection prior) at the round's altitude, which the radial
    velocities fix: their line of sight dips by the same angle and shrinks them by its
    cosine.
    """
    rng = np.hypot(sensor[:, 0], sensor[:, 1])
    az = np.arctan2(sensor[:, 1], sensor[:, 0])
    a = rotation[2, 0] * np.cos(az) + rotation[2, 1] * np.sin(az)
    b = rotation[2, 2]
    norm = np.hypot(a, b)
    # sin(e + psi) = c / norm with psi = atan2(a, b); the root nearest the plane
    c = np.clip(height_m / np.maximum(rng, 1e-9) / norm, -_PLANAR_MAX_SIN, _PLANAR_MAX_SIN)
    e = np.arcsin(c) - np.arctan2(a, b)
    ce = np.cos(e)
    return np.column_stack([rng * ce * np.cos(az), rng * ce * np.sin(az), rng * np.sin(e)])


def _select(index: I64, times: _Times, est: Extrinsics, recording: Recording, poses: _Poses,
            scatter: F64, config: CalibConfig, fov: tuple[float, float]) -> _Selected:
    sensor = _debiased_positions(recording.targets.positions_m[index], config)
    pos, yaw, vel, _, _ = times.poses(poses, est.time_offset_s)
    # the model's target heights relative to the radar (the vehicle's plus the prior)
    above_radar = (pos[:, 2] + reflection_height_prior(config)[0] - config.vehicle.ref_height
                   - est.translation_m[2])
    if not recording.has_elevation:
        sensor = _slant_to_height(sensor, above_radar, est.rotation)
    x_lo, x_hi, _, _ = box_limits(config.vehicle)
    centre = pos - est.translation_m
    centre[:, 0] += 0.5 * (x_lo + x_hi) * np.cos(yaw)
    centre[:, 1] += 0.5 * (x_lo + x_hi) * np.sin(yaw)
    aspect = reflection.aspect_angles(centre, yaw)
    frame_index = recording.targets.frame_index[index]
    weight = _information_weights(frame_index, pos, aspect, config)
    pass_id = hypotheses.drive_passes(times.t_s, recording.vehicle,
                                      config.hypotheses.pass_gap_s)
    vertical_ok = _inside_elevation_view(pos, yaw, est, fov, config)
    whiten = _whitening(sensor, est.rotation, yaw, scatter, config, vertical_ok)
    # The v_r line of sight takes the target's height from the model; the reflectors'
    # height scatter then tilts it by dz/|d|: add that to the v_r noise.
    los = sensor @ est.rotation.T
    los[:, 2] = above_radar
    dist = np.linalg.norm(los, axis=1)
    unit = los / dist[:, None]
    v_along = np.einsum('ij,ij->i', vel, unit)
    dv_dh = (vel[:, 2] - v_along * unit[:, 2]) / dist
    sigma_v = np.sqrt(config.refine.velocity_sigma_mps ** 2 + (dv_dh * scatter[2]) ** 2)
    grade = poses.grade_at(times.frame_t + est.time_offset_s)[times.inverse]
    return _Selected(index, sensor, times, recording.targets.radial_velocity_mps[index],
                     np.sqrt(weight), pass_id, whiten, sigma_v, vertical_ok, grade)
