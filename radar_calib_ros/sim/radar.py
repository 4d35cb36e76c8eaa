"""The roadside radar: timing, detection, occlusion, ghosts, false alarms, resolution, noise.

Per frame (vectorised over a batch of frames, never per target):

1. Candidate reflections: every road user's scattering regions (``scatter``) and every
   static scatterer in the field of view (``world``).
2. Detection: SNR = RCS + aspect gain + fluctuation (Swerling I, or steady for poles) +
   ``snr_ref_db`` - 40 log10(range) - antenna pattern loss, against a CFAR threshold; so
   detection falls with range, with aspect (faces turned away, far-side wheels) and off
   boresight.
3. Occlusion: a line of sight that passes through a nearer car's or truck's body (from
   0.3 m above the road to its roof) is blocked; low rays under a car body pass.
4. Ghosts: detected road-user returns mirrored in the road (double bounce: below the road,
   slightly farther) and in building fronts (behind the wall, with the mirrored velocity).
   Both lie beyond the real reflector along the line of sight, never on the radar's side.
5. False alarms: a Poisson number per frame, uniform in the field of view, any velocity.
6. Resolution: targets sharing a range / azimuth / radial-velocity cell merge into the
   strongest.
7. Noise in spherical coordinates, growing with range: range 0.1-0.2 m, azimuth 0.25-0.5
   deg, elevation 1-2 deg; radial velocity 0.05-0.1 m/s from 0 to 150 m for moving
   reflectors, but only the Doppler estimate's own noise (~0.01 m/s at the detection
   threshold, falling as 1/sqrt(SNR)) for stationary ones.

Radial velocity is the reflecting point's velocity (rigid body v + omega x r, plus wheel or
limb motion) projected on the line of sight, positive moving away.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.sim.scatter import (
    FALSE_ALARM, GHOST_ROAD, GHOST_WALL, MULTIBOUNCE, STATIC, ScatterTemplates,
    sample_candidates)
from radar_calib_ros.sim.traffic import CAR, TRUCK, TrafficLog
from radar_calib_ros.sim.world import StaticScene

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class RadarModel:
    """Sensor constants (a 77 GHz long-range traffic radar)."""

    rate_hz: float = 15.0
    jitter_s: float = 0.002
    drop_probability: float = 0.004
    fov_azimuth_deg: float = 60.0
    fov_elevation_deg: float = 10.0
    max_range_m: float = 150.0
    min_range_m: float = 0.5
    snr_ref_db: float = 89.0
    threshold_db: float = 12.0
    sigma_range_m: float = 0.10
    sigma_azimuth_deg: float = 0.25
    sigma_elevation_deg: float = 1.0
    #: radial-velocity noise of a moving reflector (motion within the coherent interval:
    #: vibration, acceleration, range migration) at short range [m/s]
    sigma_velocity_mps: float = 0.05
    #: the Doppler estimate's own noise at SNR 1 (Cramer-Rao bound of a tone's frequency:
    #: sqrt(6) / (2 pi) of a velocity cell), falling as 1 / sqrt(SNR) [m/s]
    doppler_crlb_mps: float = 0.39 * 0.12
    #: oscillator phase noise: the floor of a strong stationary reflector [m/s]
    sigma_velocity_floor_mps: float = 0.002
    resolution_range_m: float = 0.4
    resolution_azimuth_deg: float = 2.0
    resolution_velocity_mps: float = 0.12
    masking_db: float = 12.0
    false_alarms_per_frame: float = 4.0
    road_ghost_probability: float = 0.5
    wall_ghost_probability: float = 0.6
    #: the largest radial speed the waveform resolves; beyond it the Doppler folds over
    #: (v -> v - 2V round(v / 2V)), as a radar tuned for range rather than speed does.
    #: 0 = no folding [m/s]
    max_unambiguous_velocity_mps: float = 0.0


@dataclass(frozen=True)
class RadarPose:
    """x_world = rotation @ x_sensor + translation (local metric frame)."""

    rotation: F64
    translation: F64

    def to_sensor(self, points: F64) -> F64:
        return (points - self.translation) @ self.rotation

    @property
    def boresight_yaw(self) -> float:
        return math.atan2(self.rotation[1, 0], self.rotation[0, 0])


@dataclass(frozen=True)
class RadarTargets:
    """Every target of a recording (bag order) with its truth.

    frame : (n,) frame index; position_m : (n, 3) measured, sensor frame;
    radial_velocity_mps, rcs_dbsm : (n,) measured; object_id : (n,) (-1 clutter and false
    alarms); object_class, kind : (n,) codes (``traffic.CLASS_NAMES``,
    ``scatter.KIND_NAMES``); position_true_m : (n, 3) noise-free sensor-frame position of
    the (apparent) reflection; radial_velocity_true_mps : (n,). Stored compactly: int32
    indices, int8 codes, float32 values (as the bag carries them).
    """

    frame: I64
    position_m: F64
    radial_velocity_mps: F64
    rcs_dbsm: F64
    object_id: I64
    object_class: NDArray[np.int8]
    kind: NDArray[np.int8]
    position_true_m: F64
    radial_velocity_true_mps: F64


def frame_times(duration_s: float, model: RadarModel, rng: np.random.Generator) -> F64:
    """True measurement times of the radar cycles: 15 Hz with jitter, some cycles lost."""
    period = 1.0 / model.rate_hz
    n = int(duration_s * model.rate_hz) + 2
    start = float(rng.uniform(0.05, 0.05 + period))
    times = start + np.arange(n) * period + rng.normal(0.0, model.jitter_s, n)
    times = np.sort(times)
    keep = rng.random(n) >= model.drop_probability
    # now and then the radar skips a short burst of cycles (processing overload)
    for burst in rng.integers(0, n, max(1, int(duration_s / 240.0))):
        keep[burst:burst + int(rng.integers(2, 6))] = False
    times = times[keep]
    return times[(times > 0.0) & (times < duration_s)]


def _spherical(points_s: F64) -> tuple[F64, F64, F64]:
    rng_m = np.linalg.norm(points_s, axis=1)
    az = np.arctan2(points_s[:, 1], points_s[:, 0])
    el = np.arcsin(np.clip(points_s[:, 2] / np.maximum(rng_m, 1e-9), -1.0, 1.0))
    return rng_m, az, el


def _in_fov(model: RadarModel, r: F64, az: F64, el: F64) -> NDArray[np.bool_]:
    return ((r >= model.min_range_m) & (r <= model.max_range_m)
            & (np.abs(az) <= math.radians(model.fov_azimuth_deg))
            & (np.abs(el) <= math.radians(model.fov_elevation_deg)))


def _snr_db(model: RadarModel, rcs: F64, gain: F64, fluct: F64, r: F64, az: F64,
            el: F64) -> F64:
    loss = 3.0 * (az / math.radians(model.fov_azimuth_deg)) ** 2 + 2.0 * (
        el / math.radians(model.fov_elevation_deg)) ** 2
    return (rcs + 10.0 * np.log10(np.maximum(gain * fluct, 1e-12)) + model.snr_ref_db
            - 40.0 * np.log10(np.maximum(r, 0.1)) - loss)


@dataclass(frozen=True)
class _Static:
    """Static scatterers that can ever be detected, with their fixed geometry."""

    index: I64
    point_s: F64
    base_snr: F64
    steady: NDArray[np.bool_]


def _visible_static(scene: StaticScene, pose: RadarPose, model: RadarModel) -> _Static:
    p_s = pose.to_sensor(scene.point_m)
    r, az, el = _spherical(p_s)
    to_radar = pose.translation[:2] - scene.point_m[:, :2]
    to_radar /= np.maximum(np.linalg.norm(to_radar, axis=1, keepdims=True), 1e-9)
    omni = np.all(scene.lobe == 0, axis=1)
    cos_l = np.maximum(np.sum(scene.lobe * to_radar, axis=1), 0.0)
    gain = np.where(omni, 1.0, scene.floor + (1 - scene.floor) * cos_l ** scene.lobe_exp)
    base = _snr_db(model, scene.rcs_dbsm, gain, np.ones_like(gain), r, az, el)
    keep = np.flatnonzero(_in_fov(model, r, az, el) & (base > model.threshold_db - 14.0))
    return _Static(keep, p_s[keep], base[keep], scene.steady[keep])


def simulate_radar(log: TrafficLog, templates: ScatterTemplates, scene: StaticScene,
                   pose: RadarPose, model: RadarModel, times: F64, rng: np.random.Generator,
                   batch: int = 96) -> RadarTargets:
    """Targets of every radar frame at the given true measurement times.

    Parameters
    ----------
    log : TrafficLog
    templates : ScatterTemplates
        Scattering regions of every road user (``scatter.build_templates``).
    scene : StaticScene
    pose : RadarPose
    model : RadarModel
    times : ndarray of shape (f,)
        True measurement times [s] (``frame_times``).
    rng : numpy.random.Generator
    batch : int
        Frames simulated together (memory against per-call overhead).
    """
    static = _visible_static(scene, pose, model)
    parts: list[dict[str, np.ndarray]] = []
    for b0 in range(0, times.size, batch):
        parts.append(_observe_batch(log, templates, scene, static, pose, model,
                                    times[b0:b0 + batch], b0, rng))
    cat = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return RadarTargets(
        frame=cat['frame'], position_m=cat['position_m'], radial_velocity_mps=cat['v_meas'],
        rcs_dbsm=cat['rcs'], object_id=cat['obj'], object_class=cat['cls'],
        kind=cat['kind'], position_true_m=cat['position_true_m'],
        radial_velocity_true_mps=cat['v_true'])


def _user_states(log: TrafficLog, times: F64) -> tuple[I64, I64, F64, F64]:
    frames, ids, s, v = [], [], [], []
    for f, t in enumerate(times):
        i, si, vi = log.states_at(float(t))
        frames.append(np.full(i.size, f, np.int64))
        ids.append(i)
        s.append(si)
        v.append(vi)
    return np.concatenate(frames), np.concatenate(ids), np.concatenate(s), np.concatenate(v)


def _observe_batch(log: TrafficLog, templates: ScatterTemplates, scene: StaticScene,
                   static: _Static, pose: RadarPose, model: RadarModel, times: F64,
                   frame0: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    n_frames = times.size
    radar = pose.translation
    # --- road users near the field of view ---------------------------------------------
    frame, obj, s, v = _user_states(log, times)
    xy, heading, speed, yaw_rate = log.poses(obj, s, v)
    dxy = xy - radar[:2]
    dist = np.hypot(dxy[:, 0], dxy[:, 1])
    bearing = np.abs((np.arctan2(dxy[:, 1], dxy[:, 0]) - pose.boresight_yaw + math.pi)
                     % (2 * math.pi) - math.pi)
    near = (dist < model.max_range_m + 20.0) & ((bearing < math.radians(
        model.fov_azimuth_deg + 25.0)) | (dist < 25.0))
    frame, obj, xy, heading, speed, yaw_rate = (frame[near], obj[near], xy[near],
                                                heading[near], speed[near], yaw_rate[near])
    ground_z = scene.ground.z(xy)
    cls = log.users.object_class[obj]
    cand = sample_candidates(templates, frame, obj, xy, heading, speed, yaw_rate, ground_z,
                             radar[:2], rng, scene.ground.slope)
    point = cand.point_m.copy()
    # multi-bounce: along the line of sight to the road image, extra / 2 beyond it
    mb = np.flatnonzero(cand.kind == MULTIBOUNCE)
    if mb.size:
        image = point[mb].copy()
        image[:, 2] = 2.0 * scene.ground.z(image[:, :2]) - image[:, 2]
        ray = image - radar
        length = np.linalg.norm(ray, axis=1)
        point[mb] = radar + ray * ((length + 0.5 * cand.extra_path_m[mb]) / length)[:, None]
    p_s = pose.to_sensor(point)
    r, az, el = _spherical(p_s)
    los = (point - radar) / np.maximum(r, 1e-9)[:, None]
    v_r = np.sum(cand.velocity_mps * los, axis=1)
    fluct = rng.exponential(1.0, r.size)
    snr = _snr_db(model, cand.rcs_dbsm, cand.gain, fluct, r, az, el)
    det = np.flatnonzero((snr > model.threshold_db) & _in_fov(model, r, az, el))
    det = det[_unmasked(cand.frame[det], cand.obj[det], snr[det], model.masking_db)]
    u_frame, u_obj, u_kind = cand.frame[det], cand.obj[det], cand.kind[det]
    u_point, u_vel, u_snr = point[det], cand.velocity_mps[det], snr[det]
    u_ps, u_vr = p_s[det], v_r[det]
    u_rcs = cand.rcs_dbsm[det] + 10.0 * np.log10(cand.gain[det] * fluct[det])
    # --- static scatterers -------------------------------------------------------------
    n_st = static.index.size
    fl = np.where(static.steady[None, :], 10.0 ** (rng.normal(0.0, 0.4, (n_frames, n_st)) / 10),
                  rng.exponential(1.0, (n_frames, n_st)))
    st_snr = static.base_snr[None, :] + 10.0 * np.log10(fl)
    sf, si = np.nonzero(st_snr > model.threshold_db)
    s_point = scene.point_m[static.index[si]]
    # --- occlusion by nearer cars and trucks -------------------------------------------
    occluders = np.flatnonzero((cls == CAR) | (cls == TRUCK))
    all_frame = np.concatenate([u_frame, sf])
    all_point = np.concatenate([u_point, s_point])
    all_obj = np.concatenate([u_obj, np.full(sf.size, -1, np.int64)])
    blocked = _occluded(all_frame, all_point, all_obj, frame[occluders], obj[occluders],
                        xy[occluders], heading[occluders], ground_z[occluders],
                        log, radar, n_frames)
    ok_u = ~blocked[:u_frame.size]
    ok_s = ~blocked[u_frame.size:]
    u_frame, u_obj, u_kind, u_point, u_vel = (u_frame[ok_u], u_obj[ok_u], u_kind[ok_u],
                                              u_point[ok_u], u_vel[ok_u])
    u_snr, u_ps, u_vr, u_rcs = u_snr[ok_u], u_ps[ok_u], u_vr[ok_u], u_rcs[ok_u]
    sf, si = sf[ok_s], si[ok_s]
    # --- ghosts of the detected road-user returns --------------------------------------
    direct = u_kind != MULTIBOUNCE
    g = _ghosts(scene, pose, model, u_frame[direct], u_obj[direct], u_point[direct],
                u_vel[direct], u_snr[direct], rng)
    # --- false alarms --------------------------------------------------------------------
    n_fa = rng.poisson(model.false_alarms_per_frame, n_frames)
    fa_frame = np.repeat(np.arange(n_frames), n_fa)
    m = fa_frame.size
    fa_r = rng.uniform(2.0, model.max_range_m, m)
    fa_az = rng.uniform(-1, 1, m) * math.radians(model.fov_azimuth_deg)
    fa_el = rng.uniform(-1, 1, m) * math.radians(model.fov_elevation_deg)
    fa_ps = np.column_stack([fa_r * np.cos(fa_el) * np.cos(fa_az),
                             fa_r * np.cos(fa_el) * np.sin(fa_az), fa_r * np.sin(fa_el)])
    fa_v = np.where(rng.random(m) < 0.5, 0.0, rng.uniform(-20.0, 20.0, m))
    # --- all targets of the batch ------------------------------------------------------
    st_ps = static.point_s[si]
    cat_frame = np.concatenate([u_frame, sf, g['frame'], fa_frame])
    cat_ps = np.concatenate([u_ps, st_ps, g['p_s'], fa_ps])
    cat_vr = np.concatenate([u_vr, np.zeros(sf.size), g['v_r'], fa_v])
    cat_snr = np.concatenate([u_snr, st_snr[sf, si], g['snr'],
                              model.threshold_db + rng.exponential(2.0, m)])
    cat_rcs = np.concatenate([u_rcs, scene.rcs_dbsm[static.index[si]], g['rcs'],
                              rng.normal(-15.0, 4.0, m)])
    cat_obj = np.concatenate([u_obj, np.full(sf.size, -1), g['obj'], np.full(m, -1)])
    cat_kind = np.concatenate([u_kind, np.full(sf.size, STATIC), g['kind'],
                               np.full(m, FALSE_ALARM)]).astype(np.int64)
    cat_cls = np.where(cat_obj >= 0, log.users.object_class[np.maximum(cat_obj, 0)], 0)
    cat_cls = np.where(cat_kind == FALSE_ALARM, 5, cat_cls)
    keep = _merge_cells(model, cat_frame, cat_ps, cat_vr, cat_snr, rng)
    cat = {'frame': cat_frame[keep], 'p': cat_ps[keep], 'v': cat_vr[keep],
           'rcs': cat_rcs[keep], 'obj': cat_obj[keep], 'kind': cat_kind[keep],
           'cls': cat_cls[keep], 'snr': cat_snr[keep]}
    # --- measurement noise, growing with range ------------------------------------------
    r, az, el = _spherical(cat['p'])
    grow = 1.0 + r / model.max_range_m
    n = r.size
    r_m = r + rng.normal(0.0, 1.0, n) * model.sigma_range_m * grow
    az_m = az + rng.normal(0.0, 1.0, n) * math.radians(model.sigma_azimuth_deg) * grow
    el_m = el + rng.normal(0.0, 1.0, n) * math.radians(model.sigma_elevation_deg) * grow
    # A stationary reflector (clutter, a queued car) keeps its phase from chirp to chirp:
    # only the Doppler estimate's own noise remains, so clutter stays below the paper's
    # 0.1 km/h moving-target threshold (a radar whose clutter crossed it would make
    # that filter useless). Moving reflectors add motion within the coherent interval.
    # (the motion term fades below 0.5 m/s: a car creeping or at a standstill, whose
    # speed is a round-off residue, does not shake its Doppler by centimetres per second)
    snr_lin = 10.0 ** (cat['snr'] / 10.0)
    moves = np.minimum(np.abs(cat['v']) / 0.5, 1.0)
    sigma_v = np.sqrt(model.doppler_crlb_mps ** 2 / snr_lin
                      + model.sigma_velocity_floor_mps ** 2
                      + (moves * model.sigma_velocity_mps * grow) ** 2)
    v_m = cat['v'] + rng.normal(0.0, 1.0, n) * sigma_v
    if model.max_unambiguous_velocity_mps > 0.0:
        period = 2.0 * model.max_unambiguous_velocity_mps
        v_m = v_m - period * np.round(v_m / period)
    p_m = np.column_stack([r_m * np.cos(el_m) * np.cos(az_m),
                           r_m * np.cos(el_m) * np.sin(az_m), r_m * np.sin(el_m)])
    rcs_m = cat['rcs'] + rng.normal(0.0, 1.0, n)
    # radars list their targets in no useful order: shuffle within each frame
    order = np.lexsort((rng.random(n), cat['frame']))
    # compact types from here on (the bag carries float32): a 15-minute recording holds
    # millions of targets
    f32 = np.float32
    return {'frame': (cat['frame'][order] + frame0).astype(np.int32),
            'position_m': p_m[order].astype(f32), 'v_meas': v_m[order].astype(f32),
            'rcs': rcs_m[order].astype(f32), 'obj': cat['obj'][order].astype(np.int32),
            'cls': cat['cls'][order].astype(np.int8), 'kind': cat['kind'][order].astype(
                np.int8), 'position_true_m': cat['p'][order].astype(f32),
            'v_true': cat['v'][order].astype(f32)}


def _occluded(c_frame: I64, c_point: F64, c_obj: I64, o_frame: I64, o_obj: I64, o_xy: F64,
              o_heading: F64, o_ground: F64, log: TrafficLog, radar: F64,
              n_frames: int) -> NDArray[np.bool_]:
    """True where the line of sight radar -> point passes through another road user's body.

    Slab test of the segment against each same-frame occluder's box in its own frame.
    """
    blocked = np.zeros(c_frame.size, bool)
    if c_frame.size == 0 or o_frame.size == 0:
        return blocked
    users = log.users
    # pair each point only with the occluders covering its bearing: occluders are spread
    # over 1-degree bearing bins, points looked up in them (one sort, two searches)
    d_pt = np.hypot(c_point[:, 0] - radar[0], c_point[:, 1] - radar[1])
    b_pt = np.arctan2(c_point[:, 1] - radar[1], c_point[:, 0] - radar[0])
    d_oc = np.hypot(o_xy[:, 0] - radar[0], o_xy[:, 1] - radar[1])
    b_oc = np.arctan2(o_xy[:, 1] - radar[1], o_xy[:, 0] - radar[0])
    reach = users.length[o_obj]
    width = np.arctan2(reach, np.maximum(d_oc - reach, 0.5))
    n_bins = 360
    scale = n_bins / (2.0 * math.pi)
    lo = np.floor((b_oc - width) * scale).astype(np.int64)
    count = np.floor((b_oc + width) * scale).astype(np.int64) - lo + 1
    o_rep = np.repeat(np.arange(o_frame.size), count)
    bins = (np.repeat(lo, count) + np.arange(o_rep.size)
            - np.repeat(np.cumsum(count) - count, count)) % n_bins
    o_key = o_frame[o_rep] * n_bins + bins
    order = np.argsort(o_key, kind='stable')
    o_key, o_rep = o_key[order], o_rep[order]
    c_key = c_frame * n_bins + np.floor(b_pt * scale).astype(np.int64) % n_bins
    first = np.searchsorted(o_key, c_key, 'left')
    per = np.searchsorted(o_key, c_key, 'right') - first
    ci = np.repeat(np.arange(c_frame.size), per)
    within = np.arange(ci.size) - np.repeat(np.cumsum(per) - per, per)
    oi = o_rep[np.repeat(first, per) + within]
    keep = (o_obj[oi] != c_obj[ci]) & ((d_oc - reach)[oi] < d_pt[ci])
    ci, oi = ci[keep], oi[keep]
    ident = o_obj[oi]
    if ci.size == 0:
        return blocked
    c, s = np.cos(o_heading[oi]), np.sin(o_heading[oi])

    def to_local(p: F64) -> tuple[F64, F64, F64]:
        dx, dy = p[:, 0] - o_xy[oi, 0], p[:, 1] - o_xy[oi, 1]
        return c * dx + s * dy, -s * dx + c * dy, p[:, 2] - o_ground[oi]

    ax, ay, az_ = to_local(np.broadcast_to(radar, (ci.size, 3)))
    bx, by, bz = to_local(c_point[ci])
    lo = np.column_stack([-users.rear_overhang[ident] + 0.1, -0.5 * users.width[ident] + 0.1,
                          np.full(ci.size, 0.3)])
    hi = np.column_stack([users.length[ident] - users.rear_overhang[ident] - 0.1,
                          0.5 * users.width[ident] - 0.1, users.height[ident]])
    start = np.column_stack([ax, ay, az_])
    delta = np.column_stack([bx - ax, by - ay, bz - az_])
    with np.errstate(divide='ignore', invalid='ignore'):
        t1 = (lo - start) / delta
        t2 = (hi - start) / delta
    tmin = np.where(delta == 0, np.where((start >= lo) & (start <= hi), -np.inf, np.inf),
                    np.minimum(t1, t2))
    tmax = np.where(delta == 0, np.where((start >= lo) & (start <= hi), np.inf, -np.inf),
                    np.maximum(t1, t2))
    enter = tmin.max(axis=1)
    leave = tmax.min(axis=1)
    hit = (enter < leave) & (leave > 0.0) & (enter < 0.97)
    blocked[ci[hit]] = True
    return blocked


def _ghosts(scene: StaticScene, pose: RadarPose, model: RadarModel, frame: I64, obj: I64,
            point: F64, vel: F64, snr: F64, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Road and wall mirror images of detected road-user returns that are still detected."""
    radar = pose.translation
    names = ('frame', 'obj', 'p_s', 'v_r', 'snr', 'rcs', 'kind')
    out: dict[str, list[np.ndarray]] = {k: [] for k in names}

    def emit(sel: I64, img: F64, img_v: F64, loss: F64, kind: int) -> None:
        p_s = pose.to_sensor(img)
        r, az, el = _spherical(p_s)
        g_snr = snr[sel] - loss
        ok = (g_snr > model.threshold_db) & _in_fov(model, r, az, el)
        los = (img - radar) / np.maximum(r, 1e-9)[:, None]
        out['frame'].append(frame[sel][ok])
        out['obj'].append(obj[sel][ok])
        out['p_s'].append(p_s[ok])
        out['v_r'].append(np.sum(img_v * los, axis=1)[ok])
        out['snr'].append(g_snr[ok])
        out['rcs'].append(g_snr[ok] - model.snr_ref_db + 40.0 * np.log10(r[ok]))
        out['kind'].append(np.full(int(ok.sum()), kind))

    # double bounce off the road: the mirror image, below the road
    sel = np.flatnonzero(rng.random(frame.size) < model.road_ghost_probability)
    if sel.size:
        img = point[sel].copy()
        img[:, 2] = 2.0 * scene.ground.z(img[:, :2]) - img[:, 2]
        img_v = vel[sel] * np.array([1.0, 1.0, -1.0])
        emit(sel, img, img_v, rng.uniform(5.0, 13.0, sel.size), GHOST_ROAD)
    # building fronts: mirror in the wall's vertical plane, valid when the specular point
    # lies on the wall, below its top, and radar and reflector face the same side
    walls = scene.walls
    if walls.shape[0] and frame.size:
        a, b = walls[:, 0], walls[:, 1]
        d = b - a
        wlen = np.linalg.norm(d, axis=1)
        t_hat = d / wlen[:, None]
        n_hat = np.column_stack([-t_hat[:, 1], t_hat[:, 0]])
        side_radar = np.sum((radar[:2] - a) * n_hat, axis=1)
        # the whole test as (n points, w walls) matrices: signed distance to the wall
        # line, and where the ray radar -> mirror image crosses it (mirroring keeps the
        # coordinate along the wall)
        side_all = point[:, :2] @ n_hat.T - np.sum(a * n_hat, axis=1)
        along_pt = point[:, :2] @ t_hat.T - np.sum(a * t_hat, axis=1)
        along_radar = np.sum((radar[:2] - a) * t_hat, axis=1)
        with np.errstate(divide='ignore', invalid='ignore'):
            frac = side_radar / (side_radar + side_all)
        along = along_radar + frac * (along_pt - along_radar)
        z_spec = radar[2] + frac * (point[:, 2:3] - radar[2])
        ok = ((np.sign(side_all) == np.sign(side_radar)) & (np.abs(side_all) > 0.5)
              & (along > 0.0) & (along < wlen) & (z_spec < scene.wall_top_m))
        ci, wi = np.nonzero(ok)
        keep = rng.random(ci.size) < model.wall_ghost_probability
        ci, wi = ci[keep], wi[keep]
        img_xy = point[ci, :2] - 2.0 * side_all[ci, wi][:, None] * n_hat[wi]
        if ci.size:
            img = np.column_stack([img_xy, point[ci, 2]])
            nv = np.sum(vel[ci, :2] * n_hat[wi], axis=1)
            img_v = vel[ci].copy()
            img_v[:, :2] -= 2.0 * nv[:, None] * n_hat[wi]
            emit(ci, img, img_v, rng.uniform(7.0, 16.0, ci.size), GHOST_WALL)
    if not out['frame']:
        return {'frame': np.zeros(0, np.int64), 'obj': np.zeros(0, np.int64),
                'p_s': np.zeros((0, 3)), 'v_r': np.zeros(0), 'snr': np.zeros(0),
                'rcs': np.zeros(0), 'kind': np.zeros(0, np.int64)}
    return {k: np.concatenate(v) for k, v in out.items()}


def _unmasked(frame: I64, obj: I64, snr: F64, masking_db: float) -> NDArray[np.bool_]:
    """False for returns weaker than their road user's strongest by more than
    ``masking_db``: the strong scatterers' sidelobes and the CFAR window's noise estimate
    (raised by the rest of the extended target) hide them."""
    if frame.size == 0:
        return np.zeros(0, bool)
    key = frame * (int(obj.max()) + 1) + obj
    uniq, inverse = np.unique(key, return_inverse=True)
    strongest = np.full(uniq.size, -np.inf)
    np.maximum.at(strongest, inverse, snr)
    return snr >= strongest[inverse] - masking_db


def _merge_cells(model: RadarModel, frame: I64, p_s: F64, v_r: F64, snr: F64,
                 rng: np.random.Generator) -> I64:
    """Indices of the targets that survive resolution: the strongest per range / azimuth /
    radial-velocity cell of each frame (the cell grid shifted randomly per batch)."""
    if frame.size == 0:
        return np.zeros(0, np.int64)
    r, az, _ = _spherical(p_s)
    shift = rng.random(3)
    ir = np.floor(r / model.resolution_range_m + shift[0]).astype(np.int64)
    ia = np.floor(az / math.radians(model.resolution_azimuth_deg) + shift[1]).astype(np.int64)
    iv = np.floor(v_r / model.resolution_velocity_mps + shift[2]).astype(np.int64)
    order = np.lexsort((-snr, iv, ia, ir, frame))
    key = np.column_stack([frame, ir, ia, iv])[order]
    first = np.ones(order.size, bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    return np.sort(order[first])
