"""A small synthetic scene for the refinement tests: a radar at a known pose, a calibration
vehicle driving passes on several lanes and directions, targets drawn in the vehicle frame
from a scatter model (``skin`` on the radar-facing faces, ``interior`` from wheels,
underbody, engine, seats and late multi-bounce returns, or ``profile``: exactly on a
given reflection profile), spherical radar noise and rigid-body radial velocities.

Independent of the project's simulator on purpose: the refinement must not be tuned to one
generator. Everything is vectorised over targets; a scene of a few passes builds in well
under a second.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import reflection
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import (
    Extrinsics, HypothesisSelection, Targets, TrackedTargets, VehicleTrack)

RATE_HZ = 15.0
POSE_HZ = 50.0
GEOMETRIES = {
    # (u0, v0, u1, v1) in boresight-aligned ground coordinates (u forward, v left) [m];
    # 'turn' entries are (u0, v0, radius, sign) arcs.
    'junction': [('line', 100, 3.5, 8, 3.5), ('line', 8, -3.5, 100, -3.5),
                 ('line', 35, -40, 35, 40), ('line', 55, 45, 55, -45),
                 ('turn', 80, 3.5, 12.0, -1.0), ('line', 90, -1.0, 10, -1.0)],
    # roads through the view at several angles, both directions: every aspect is seen
    # from several bearings
    'diverse': [('line', 90, 4.0, 6, 4.0), ('line', 6, -4.0, 90, -4.0),
                ('line', 10, -45, 60, 45), ('line', 60, 40, 15, -40),
                ('line', 25, -45, 25, 45), ('line', 70, 40, 30, -40),
                ('turn', 70, 3.5, 10.0, -1.0), ('turn', 70, -2.0, 14.0, 1.0)],
    # far down an arm: seen head-on and tail-on only, beyond 40 m
    'head_on': [('line', 130, 3.5, 40, 3.5), ('line', 40, -3.5, 130, -3.5),
                ('line', 130, 0.5, 40, 0.5), ('line', 40, -0.5, 130, -0.5),
                ('line', 130, 3.5, 40, 3.5), ('line', 40, -3.5, 130, -3.5)],
    # a divided road down the view: each direction on its own carriageway, 11 m apart
    'divided': [('line', 130, 5.5, 40, 5.5), ('line', 40, -5.5, 130, -5.5),
                ('line', 130, 9.0, 40, 9.0), ('line', 40, -9.0, 130, -9.0),
                ('line', 130, 5.5, 40, 5.5), ('line', 40, -5.5, 130, -5.5)],
    # one straight road through the view at 45 deg to the boresight, two lanes both ways:
    # each aspect is seen from one bearing per direction
    'oblique': [('line', 15, -35, 75, 25), ('line', 72, 28, 12, -32),
                ('line', 18, -38, 78, 22), ('line', 75, 25, 15, -35)],
    # mid-block: straight drives along the road the radar looks down (head-on, tail-on),
    # then two drives across its view (the last two passes)
    'mid_block': [('line', 90, 3.5, 12, 3.5), ('line', 12, -3.5, 90, -3.5),
                  ('line', 90, 0.5, 12, 0.5), ('line', 12, -0.5, 90, -0.5),
                  ('line', 90, 3.5, 12, 3.5), ('line', 12, -3.5, 90, -3.5),
                  ('line', 30, -40, 30, 40), ('line', 34, 40, 34, -40)],
}


@dataclass(frozen=True)
class Scene:
    recording: Recording
    tracked: TrackedTargets
    selection: HypothesisSelection
    truth: Extrinsics
    initial: Extrinsics
    config: CalibConfig
    vehicle_target_index: np.ndarray
    pass_of_target: np.ndarray


def radar_truth(yaw_deg: float = 20.0, pitch_deg: float = 6.0, roll_deg: float = 0.5,
                height_m: float = 6.0) -> Extrinsics:
    rot = Rotation.from_euler('ZYX', [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    return Extrinsics(rot, np.array([3.0, -2.0, height_m]), 0.0)


def _path(kind: tuple, yaw_r: float) -> tuple[np.ndarray, np.ndarray]:
    """Dense path points (k, 2) in the world and their headings (k,)."""
    if kind[0] == 'line':
        _, u0, v0, u1, v1 = kind
        n = int(np.hypot(u1 - u0, v1 - v0) / 0.1) + 2
        uv = np.column_stack([np.linspace(u0, u1, n), np.linspace(v0, v1, n)])
    else:
        _, u0, v0, radius, sign = kind
        # approach along -u, quarter turn of the given radius, leave along sign * v
        n1 = int((u0 - 30.0) / 0.1) + 2
        straight = np.column_stack([np.linspace(u0, 30.0, n1), np.full(n1, v0)])
        ang = np.linspace(0, np.pi / 2, 200)
        cu, cv = 30.0, v0 + sign * radius
        arc = np.column_stack([cu - radius * np.sin(ang), cv - sign * radius * np.cos(ang)])
        n2 = 400
        tail = np.column_stack([np.full(n2, cu - radius),
                                cv + sign * np.linspace(0, 40.0, n2)])
        uv = np.concatenate([straight, arc[1:], tail[1:]])
    c, s = np.cos(yaw_r), np.sin(yaw_r)
    xy = np.column_stack([c * uv[:, 0] - s * uv[:, 1], s * uv[:, 0] + c * uv[:, 1]])
    d = np.gradient(xy, axis=0)
    return xy, np.unwrap(np.arctan2(d[:, 1], d[:, 0]))


def _vehicle_targets(rng: np.random.Generator, model: str, aspect: np.ndarray, vehicle_cfg,
                     profile: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """(n, 3) reflector positions in the vehicle frame, (n,) True for wheels, (n,) extra
    delay along the line of sight [m] (multi-bounce)."""
    n = aspect.size
    x0, x1 = -vehicle_cfg.rear_overhang, vehicle_cfg.length - vehicle_cfg.rear_overhang
    hw = 0.5 * vehicle_cfg.width
    ground = -vehicle_cfg.ref_height
    wheel = np.zeros(n, bool)
    delay = np.zeros(n)
    if model == 'profile':
        return reflection.evaluate_profile(profile, aspect), wheel, delay
    to_radar = np.column_stack([np.cos(aspect), np.sin(aspect)])
    if model == 'skin':
        # faces: front (+x), rear (-x), left (+y), right (-y); weight = projected area
        normals = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], float)
        size = np.array([2 * hw, 2 * hw, x1 - x0, x1 - x0])
        w = np.clip(to_radar @ normals.T, 0, None) * size
        w /= w.sum(axis=1, keepdims=True)
        face = (rng.random(n)[:, None] > np.cumsum(w, axis=1)).sum(axis=1)
        face = np.minimum(face, 3)
        t = rng.random(n)
        pts = np.zeros((n, 3))
        pts[:, 0] = np.select([face == 0, face == 1], [x1, x0], x0 + t * (x1 - x0))
        pts[:, 1] = np.select([face == 2, face == 3], [hw, -hw], -hw + t * 2 * hw)
        pts[:, 2] = ground + rng.uniform(0.2, 1.4, n)
        return pts, wheel, delay
    # interior: wheels, underbody, engine block, seats, multi-bounce behind wheel houses
    comp = rng.choice(5, size=n, p=[0.35, 0.2, 0.2, 0.1, 0.15])
    pts = np.zeros((n, 3))
    wx = np.where(rng.random(n) < 0.5, 0.0, 2.8)
    # the wheels on the radar's side are seen more often
    near_side = np.sign(to_radar[:, 1] + 1e-9)
    wy = np.where(rng.random(n) < 0.5 + 0.35 * np.abs(to_radar[:, 1]), near_side, -near_side)
    pts[:, 0] = np.select([comp == 0, comp == 1, comp == 2, comp == 3, comp == 4],
                          [wx, rng.uniform(-0.5, 3.3, n), 3.3, 1.4, wx])
    pts[:, 1] = np.select([comp == 0, comp == 1, comp == 2, comp == 3, comp == 4],
                          [wy * 0.78, rng.uniform(-0.6, 0.6, n), 0.0,
                           np.where(rng.random(n) < 0.5, 0.4, -0.4), wy * 0.6])
    pts[:, 2] = ground + np.select([comp == 0, comp == 1, comp == 2, comp == 3, comp == 4],
                                   [0.33, 0.22, 0.6, 0.85, 0.2])
    pts += rng.normal(0.0, [0.15, 0.1, 0.08], (n, 3))
    wheel = comp == 0
    delay = np.where(comp == 4, rng.uniform(0.3, 0.8, n), 0.0)
    return pts, wheel, delay


def make_scene(seed: int, *, model: str = 'interior', geometry: str = 'junction',
               time_offset_s: float = 0.04, noise: bool = True, targets_per_frame: float = 6.0,
               profile: np.ndarray | None = None, n_passes: int | None = None,
               initial_error: tuple[float, float, float] = (0.3, 1.0, 0.0),
               crawl: bool = False, config: CalibConfig | None = None,
               grade: float = 0.0, steady: bool = False,
               azimuth_noise_deg: float = 0.3, elevation_noise_deg: float = 1.5,
               perspective_m: float = 0.0, azimuth_bias_deg: float = 0.0) -> Scene:
    """Build a scene; ``initial_error`` = (translation [m], yaw [deg], clock offset [s]);
    ``grade``: the road climbs this much per metre along the boresight, and the car is
    pitched with it (the fixes then declare RTK's 2-3 cm, which the grade is measured by);
    ``steady``: every pass at one constant speed (11 m/s), as on a road without lights;
    ``azimuth_noise_deg``, ``elevation_noise_deg``: the radar's angle noise (1 sigma)
    when ``noise``; ``perspective_m``: the targets' mean moves along the car and across it
    by this much times (20 m / range of the centre), more at oblique aspects (what a car
    spanning more of the view shows nearer the radar); ``azimuth_bias_deg``: the radar's
    azimuths off by this much at +-50 deg, as t|t| of t = azimuth / 50 deg (an antenna
    array's angle calibration)."""
    rng = np.random.default_rng(seed)
    cfg = config or CalibConfig()
    truth = radar_truth()
    truth = Extrinsics(truth.rotation, truth.translation_m, time_offset_s)
    yaw_r = float(np.arctan2(truth.rotation[1, 0], truth.rotation[0, 0]))
    kinds = GEOMETRIES[geometry][:n_passes]
    ref_z = cfg.vehicle.ref_height
    t_cursor = 1.0
    stamps, pos, yaw, vel, rate, pass_t = [], [], [], [], [], []
    for k, kind in enumerate(kinds):
        xy, head = _path(kind, yaw_r)
        xy = xy + truth.translation_m[:2]
        s_path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        v0 = rng.uniform(8.0, 13.0)
        t = np.arange(0.0, 200.0, 1.0 / POSE_HZ)
        speed = v0 + 2.5 * np.sin(2 * np.pi * t / rng.uniform(6.0, 10.0) + rng.uniform(0, 6))
        if steady:
            speed = np.full(t.size, 11.0)
        if crawl and k == 0:
            # a queue: creeping at 0.4 m/s for 40 s in the middle of the first pass
            speed = np.where((t > 4.0) & (t < 44.0), 0.4, speed)
        s = np.concatenate([[0.0], np.cumsum(speed[:-1] / POSE_HZ)])
        end = np.searchsorted(s, s_path[-1])
        t, s, speed = t[:end], s[:end], speed[:end]
        p = np.column_stack([np.interp(s, s_path, xy[:, 0]), np.interp(s, s_path, xy[:, 1]),
                             np.full(s.size, ref_z)])
        h = np.interp(s, s_path, head)
        p[:, 2] += grade * ((p[:, 0] - truth.translation_m[0]) * np.cos(yaw_r)
                            + (p[:, 1] - truth.translation_m[1]) * np.sin(yaw_r))
        climb = speed * grade * np.cos(h - yaw_r)
        hr = np.gradient(h, t)
        stamps.append(t + t_cursor)
        pos.append(p)
        yaw.append(h)
        vel.append(np.column_stack([speed * np.cos(h), speed * np.sin(h), climb]))
        rate.append(hr)
        pass_t.append((t_cursor, t_cursor + t[-1]))
        t_cursor += t[-1] + 4.0
    p_t = np.concatenate(stamps)
    p_pos, p_yaw = np.concatenate(pos), np.concatenate(yaw)
    p_vel, p_rate = np.concatenate(vel), np.concatenate(rate)
    vehicle = VehicleTrack((p_t * 1e9).astype(np.int64), p_pos,
                           (p_yaw + np.pi) % (2 * np.pi) - np.pi, p_vel, p_rate)
    # radar frames in true time; stamps are true time minus the clock offset
    frame_t = np.arange(0.5, t_cursor, 1.0 / RATE_HZ)
    frame_stamp = frame_t - time_offset_s
    pass_of_frame = np.full(frame_t.size, -1)
    for k, (a, b) in enumerate(pass_t):
        pass_of_frame[(frame_t >= a) & (frame_t <= b)] = k
    in_pass = pass_of_frame >= 0
    f_idx = np.flatnonzero(in_pass)
    ft = frame_t[f_idx]
    fp = np.column_stack([np.interp(ft, p_t, p_pos[:, i]) for i in range(3)])
    fy = np.interp(ft, p_t, p_yaw)
    fv = np.column_stack([np.interp(ft, p_t, p_vel[:, i]) for i in range(3)])
    fr = np.interp(ft, p_t, p_rate)
    # visible when inside 3-140 m and +-60 deg of the boresight
    rel = fp - truth.translation_m
    sens = rel @ truth.rotation
    az = np.arctan2(sens[:, 1], sens[:, 0])
    dist = np.linalg.norm(sens, axis=1)
    visible = (dist > 3.0) & (dist < 140.0) & (np.abs(az) < np.radians(60))
    counts = rng.poisson(targets_per_frame, f_idx.size) * visible
    tgt_frame = np.repeat(np.arange(f_idx.size), counts)
    # aspect of the box centre (the refinement's definition)
    x_c = 0.5 * cfg.vehicle.length - cfg.vehicle.rear_overhang
    centre = fp[tgt_frame] + x_c * np.column_stack([np.cos(fy[tgt_frame]),
                                                    np.sin(fy[tgt_frame]),
                                                    np.zeros(tgt_frame.size)])
    aspect = reflection.aspect_angles(centre - truth.translation_m, fy[tgt_frame])
    local, wheel, delay = _vehicle_targets(rng, model, aspect, cfg.vehicle, profile)
    if perspective_m:
        near = 20.0 / np.hypot(*(centre - truth.translation_m)[:, :2].T)
        local[:, 0] += perspective_m * np.sin(aspect) ** 2 * near
        local[:, 1] += perspective_m * np.sin(2.0 * aspect) * near
    # pitched with the road: a point ahead of the reference point sits higher uphill
    local[:, 2] += grade * np.cos(fy[tgt_frame] - yaw_r) * local[:, 0]
    c, s = np.cos(fy[tgt_frame]), np.sin(fy[tgt_frame])
    world = fp[tgt_frame] + np.column_stack([c * local[:, 0] - s * local[:, 1],
                                             s * local[:, 0] + c * local[:, 1], local[:, 2]])
    los = world - truth.translation_m
    unit = los / np.linalg.norm(los, axis=1)[:, None]
    rel_pt = world - fp[tgt_frame]
    v_pt = fv[tgt_frame] + fr[tgt_frame, None] * np.column_stack(
        [-rel_pt[:, 1], rel_pt[:, 0], np.zeros(len(rel_pt))])
    vr = np.einsum('ij,ij->i', v_pt, unit)
    world = world + unit * delay[:, None]
    sensor = (world - truth.translation_m) @ truth.rotation
    if noise:
        r = np.linalg.norm(sensor, axis=1)
        a = np.arctan2(sensor[:, 1], sensor[:, 0])
        e = np.arcsin(sensor[:, 2] / r)
        r = r + rng.normal(0, 0.15, r.size)
        a = a + rng.normal(0, np.radians(azimuth_noise_deg), r.size)
        t = a / np.radians(50.0)
        a = a + np.radians(azimuth_bias_deg) * t * np.abs(t)
        e = e + rng.normal(0, np.radians(elevation_noise_deg), r.size)
        sensor = np.column_stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a),
                                  r * np.sin(e)])
        vr = vr + rng.normal(0, 0.1, vr.size)
        vr = vr + wheel * rng.uniform(-1.0, 1.0, vr.size) * np.einsum(
            'ij,ij->i', fv[tgt_frame], unit)
    # clutter: moving targets far from the vehicle, stationary targets (never used)
    n_clutter = 3 * f_idx.size
    cl_frame = rng.integers(0, frame_t.size, n_clutter)
    cl_sensor = np.column_stack([rng.uniform(5, 120, n_clutter),
                                 rng.uniform(-60, 60, n_clutter),
                                 rng.uniform(-6, -4, n_clutter)])
    cl_v = np.where(rng.random(n_clutter) < 0.5, 0.0, rng.uniform(-15, 15, n_clutter))
    frame_of_target = np.concatenate([f_idx[tgt_frame], cl_frame])
    positions = np.concatenate([sensor, cl_sensor])
    velocities = np.concatenate([vr, cl_v])
    order = np.argsort(frame_of_target, kind='stable')
    frame_of_target, positions, velocities = (frame_of_target[order], positions[order],
                                              velocities[order])
    is_vehicle = order < len(sensor)
    pass_of_target = np.where(is_vehicle, pass_of_frame[frame_of_target], -1)
    targets = Targets(positions, velocities, frame_of_target.astype(np.int64))
    frame = LocalFrame.at(48.4, 9.9)
    recording = Recording((frame_stamp * 1e9).astype(np.int64), targets, vehicle, frame,
                          fix_sigma_m=(0.02, 0.03) if grade else None)
    moving = np.flatnonzero(np.abs(velocities) > 0.1 / 3.6)
    track_id = np.where(is_vehicle[moving], pass_of_target[moving], -1)
    tracked = TrackedTargets(moving.astype(np.int64), track_id.astype(np.int64))
    tr_err, yaw_err, tau0 = initial_error
    direction = rng.normal(size=3)
    direction[2] *= 0.3
    direction /= np.linalg.norm(direction)
    initial = Extrinsics(
        Rotation.from_euler('z', yaw_err, degrees=True).as_matrix() @ truth.rotation,
        truth.translation_m + tr_err * direction, tau0)
    selection = HypothesisSelection(
        hypotheses=(), labels=np.zeros(0, np.int64), accepted_label=0, mean_angles_deg={},
        accepted_track_ids=tuple(range(len(kinds))), extrinsics=initial, n_correspondences=0)
    return Scene(recording, tracked, selection, truth, initial, cfg,
                 np.flatnonzero(is_vehicle), pass_of_target)


def errors(est: Extrinsics, truth: Extrinsics) -> dict[str, float]:
    """Horizontal and vertical translation error [m], rotation error [deg], clock offset
    error [s]."""
    d = est.translation_m - truth.translation_m
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(
        truth.rotation.T @ est.rotation).as_rotvec()))
    return {'horizontal': float(np.hypot(d[0], d[1])), 'vertical': float(abs(d[2])),
            'rotation': float(angle), 'time': float(abs(est.time_offset_s
                                                        - truth.time_offset_s))}
