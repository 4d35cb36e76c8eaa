"""A synthetic calibration scene for the stage 6, 7 and 9 tests (not a test module).

A radar at known extrinsics looks at a road; the calibration vehicle drives straight,
accelerating, through the view once per pass and waits far away in between. Smoothed
tracks and targets are built directly (no clustering or filtering), noise-free unless
asked, so the stages can be checked against known answers.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import vehicle as vehicle_box
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import (
    Extrinsics, GroundPlane, SmoothedTrack, Targets, TrackedTargets, VehicleTrack)

ROAD_Z = 480.0
YAW0_DEG = 30.0
PASS_S = 6.0
PASS_PERIOD_S = 20.0
POSE_HZ = 50.0
RADAR_HZ = 15.0
PARKED = np.array([900.0, 900.0])

#: Lanes in the levelled sensor frame: start (x, y) and heading [deg].
LANES = [((70.0, -4.0), 180.0), ((16.0, 4.0), 0.0), ((35.0, -27.0), 90.0),
         ((45.0, 27.0), -90.0), ((20.0, -20.0), 45.0), ((70.0, 20.0), -135.0)]


@dataclass(frozen=True)
class Scene:
    recording: Recording
    tracks: tuple[SmoothedTrack, ...]
    tracked: TrackedTargets
    ground: GroundPlane
    truth: Extrinsics
    config: CalibConfig
    vehicle_track_ids: tuple[int, ...]
    windows_s: list[tuple[float, float]]


def _rz(deg: float) -> np.ndarray:
    return Rotation.from_euler('z', deg, degrees=True).as_matrix()


def truth_extrinsics() -> tuple[Extrinsics, np.ndarray]:
    """True sensor -> world and R_level (pitch 10 deg down, roll -1.5 deg)."""
    level = Rotation.from_euler('yx', [10.0, -1.5], degrees=True).as_matrix()
    rotation = _rz(YAW0_DEG) @ level
    return Extrinsics(rotation, np.array([5.0, -3.0, ROAD_Z + 6.0])), level


def _lane_path(lane: int, tau: np.ndarray, truth: Extrinsics) -> tuple[np.ndarray, float]:
    """World xy of the reference point after tau s on a lane, and the world heading."""
    (x0, y0), heading = LANES[lane % len(LANES)]
    s = 6.0 * tau + 0.5 * 1.0 * tau ** 2
    h = np.radians(heading)
    xy_l = np.column_stack([x0 + s * np.cos(h), y0 + s * np.sin(h)])
    rz = _rz(YAW0_DEG)[:2, :2]
    return xy_l @ rz.T + truth.translation_m[:2], np.radians(heading + YAW0_DEG)


def _loop_path(radius_m: float, tau: np.ndarray, truth: Extrinsics
               ) -> tuple[np.ndarray, np.ndarray]:
    """World xy and heading after tau s round a circle 35 m ahead of the sensor."""
    s = 6.0 * tau + 0.5 * 1.0 * tau ** 2
    phi = s / radius_m - 0.5 * np.pi
    xy_l = np.column_stack([35.0 + radius_m * np.cos(phi), radius_m * np.sin(phi)])
    rz = _rz(YAW0_DEG)[:2, :2]
    return xy_l @ rz.T + truth.translation_m[:2], phi + 0.5 * np.pi + np.radians(YAW0_DEG)


def make_scene(*, n_passes: int = 5, lanes: list[int] | None = None, seed: int = 0,
               target_noise_m: float = 0.0, interior_targets: int = 5,
               split_pass: int | None = None, random_cars: int = 0,
               followers: float | None = None, radar_stamp_shift_s: float = 0.0,
               stop_pass: int | None = None, stop_s: float = 12.0,
               escort_m: float | None = None, beside_m: float | None = None,
               hidden_pass: int | None = None, radial_velocities: bool = False,
               loop_radius_m: float | None = None,
               config: CalibConfig | None = None) -> Scene:
    """Build a scene.

    lanes: lane index per pass (default 0, 1, 2, ...); split_pass: that pass's track is
    cut in two fragments; random_cars: other cars on random straight paths (hypotheses
    that do not fit); followers: a car following the vehicle on every pass with this lag
    [s]; radar_stamp_shift_s: radar stamps are this much late against the pose clock;
    stop_pass: in that pass the vehicle stops for stop_s in view after 3 s (a stopped car
    has no moving targets: its track is cut in two); escort_m: a car of the vehicle's size
    kept this far ahead of it on every pass (a convoy); beside_m: a 10 m truck, 2.5 m wide,
    kept alongside the vehicle this far to its left (negative: right) on every pass, with a
    track and eight targets a frame over its footprint; hidden_pass: on that pass the
    vehicle gives no track and no target (hidden by the truck); radial_velocities: the
    targets' radial velocities are those of the vehicle's motion (the truck's alike),
    else 5 m/s each; loop_radius_m: every pass drives anticlockwise round a circle of this
    radius 35 m ahead of the radar instead of along its lane (8 m: once round and a bit).
    """
    rng = np.random.default_rng(seed)
    config = config or CalibConfig()
    truth, level = truth_extrinsics()
    lanes = lanes if lanes is not None else list(range(n_passes))
    windows = [(10.0 + PASS_PERIOD_S * k, 10.0 + PASS_PERIOD_S * k + PASS_S
                + (stop_s if k == stop_pass else 0.0)) for k in range(n_passes)]
    total_s = windows[-1][1] + 10.0

    # vehicle poses: on the lane during a pass, parked far away otherwise
    t_pose = np.arange(0.0, total_s, 1.0 / POSE_HZ)
    xy = np.tile(PARKED, (t_pose.size, 1))
    yaw = np.zeros(t_pose.size)
    vel = np.zeros((t_pose.size, 3))
    for k, ((start, end), lane) in enumerate(zip(windows, lanes)):
        m = (t_pose >= start) & (t_pose <= end)
        tau = _path_time(t_pose[m] - start, stop_s if k == stop_pass else 0.0)
        xy[m], heading = (_lane_path(lane, tau, truth) if loop_radius_m is None
                          else _loop_path(loop_radius_m, tau, truth))
        yaw[m] = heading
        speed = np.where(np.diff(tau, append=np.inf) > 0, 6.0 + tau, 0.0)
        vel[m, 0], vel[m, 1] = speed * np.cos(heading), speed * np.sin(heading)
    ref_z = ROAD_Z + config.vehicle.ref_height
    pose_ns = (t_pose * 1e9).astype(np.int64) + 1_000_000_000
    vehicle = VehicleTrack(pose_ns, np.column_stack([xy, np.full(t_pose.size, ref_z)]), yaw,
                           vel, np.zeros(t_pose.size))

    # radar frames at 15 Hz, not aligned with the pose samples
    shift_ns = round(radar_stamp_shift_s * 1e9)
    frame_ns = (np.arange(0.003, total_s, 1.0 / RADAR_HZ) * 1e9).astype(np.int64) + (
        1_000_000_000 + shift_ns)
    # the pose-clock time of each frame, from the integer stamps the stages will see
    t_radar = (frame_ns - 1_000_000_000 - shift_ns) * 1e-9
    pos_at = _pose_at(t_pose, xy, yaw)

    positions, frames, track_ids = [], [], []
    tracks: list[SmoothedTrack] = []
    vehicle_ids: list[int] = []
    x0, x1, y0, y1 = vehicle_box.box_limits(config.vehicle)
    centre_forward = 0.5 * (x0 + x1)
    next_id = 0

    def add_track(frame_idx: np.ndarray, centre_world: np.ndarray) -> int:
        nonlocal next_id
        levelled = (centre_world - truth.translation_m) @ _rz(YAW0_DEG)
        tracks.append(SmoothedTrack(next_id, frame_idx, frame_ns[frame_idx],
                                    levelled[:, :2].copy(), levelled[:, 2].copy(),
                                    np.zeros((frame_idx.size, 6)),
                                    np.zeros((frame_idx.size, 6, 6))))
        next_id += 1
        return next_id - 1

    for k, (start, end) in enumerate(windows):
        idx = np.flatnonzero((t_radar > start + 0.1) & (t_radar < end - 0.1))
        if beside_m is not None:
            bxy, byaw = pos_at(t_radar[idx])
            truck = np.stack([rng.uniform(centre_forward - 5.0, centre_forward + 5.0,
                                          (idx.size, 8)),
                              rng.uniform(beside_m - 1.25, beside_m + 1.25, (idx.size, 8))],
                             axis=-1).reshape(-1, 2)
            truck_world = vehicle_box.vehicle_to_world(truck, np.repeat(bxy, 8, axis=0),
                                                       np.repeat(byaw, 8))
            positions.append(truth.inverse_apply(np.column_stack([
                truck_world, ROAD_Z + rng.uniform(0.3, 2.5, truck_world.shape[0])])))
            frames.append(np.repeat(idx, 8))
            tc = vehicle_box.vehicle_to_world(
                np.column_stack([np.full(idx.size, centre_forward),
                                 np.full(idx.size, beside_m)]), bxy, byaw)
            tid = add_track(idx, np.column_stack([tc, np.full(idx.size, ROAD_Z + 1.0)]))
            track_ids.append(np.full(idx.size * 8, tid))
        if k == hidden_pass:
            continue
        if k == stop_pass:
            tau = t_radar[idx] - start
            idx = idx[(tau < 2.9) | (tau > 3.1 + stop_s)]
        pxy, pyaw = pos_at(t_radar[idx])
        centre = np.column_stack([
            vehicle_box.vehicle_to_world(np.column_stack([np.full(idx.size, centre_forward),
                                                          np.zeros(idx.size)]), pxy, pyaw),
            np.full(idx.size, ROAD_Z + config.hypotheses.reflection_height_m)])
        if k == split_pass:
            parts = np.array_split(np.arange(idx.size), 2)
        elif k == stop_pass:
            before = t_radar[idx] - start < 3.0
            parts = [np.flatnonzero(before), np.flatnonzero(~before)]
        else:
            parts = [np.arange(idx.size)]
        part_ids = []
        for part in parts:
            part_ids.append(add_track(idx[part], centre[part]))
        vehicle_ids += part_ids
        # targets: the box point closest to the sensor, then interior points
        sensor_local = vehicle_box.world_to_vehicle(
            np.broadcast_to(truth.translation_m[:2], (idx.size, 2)), pxy, pyaw)
        clamp = np.column_stack([np.clip(sensor_local[:, 0], x0, x1),
                                 np.clip(sensor_local[:, 1], y0, y1)])
        local = [clamp[:, None, :]]
        if interior_targets:
            u = rng.uniform(size=(idx.size, interior_targets, 2))
            local.append(np.stack([x0 + (x1 - x0) * u[..., 0], y0 + (y1 - y0) * u[..., 1]],
                                  axis=-1))
        local_all = np.concatenate(local, axis=1)
        n_per = local_all.shape[1]
        world_xy = vehicle_box.vehicle_to_world(
            local_all.reshape(-1, 2), np.repeat(pxy, n_per, axis=0), np.repeat(pyaw, n_per))
        world_xy = world_xy + rng.normal(0.0, target_noise_m, world_xy.shape)
        z = ROAD_Z + rng.uniform(0.2, 0.8, world_xy.shape[0])
        world = np.column_stack([world_xy, z])
        positions.append(truth.inverse_apply(world))
        frames.append(np.repeat(idx, n_per))
        owner = np.empty(idx.size, np.int64)
        for part, tid in zip(parts, part_ids):
            owner[part] = tid
        track_ids.append(np.repeat(owner, n_per))

        if followers is not None:
            fidx = idx[(t_radar[idx] - start) > followers + 0.1]
            tau = t_radar[fidx] - start - followers
            fxy, heading = _lane_path(lanes[k], tau, truth)
            fc = vehicle_box.vehicle_to_world(
                np.column_stack([np.full(fidx.size, centre_forward), np.zeros(fidx.size)]),
                fxy, np.full(fidx.size, heading))
            add_track(fidx, np.column_stack([fc, np.full(fidx.size, ROAD_Z + 0.5)]))

        if escort_m is not None:
            ec = vehicle_box.vehicle_to_world(
                np.column_stack([np.full(idx.size, centre_forward + escort_m),
                                 np.zeros(idx.size)]), pxy, pyaw)
            add_track(idx, np.column_stack([ec, np.full(idx.size, ROAD_Z + 0.5)]))

    for _ in range(random_cars):
        start = rng.uniform(0.0, total_s - 8.0)
        idx = np.flatnonzero((t_radar > start) & (t_radar < start + 8.0))
        tau = t_radar[idx] - start
        p0 = rng.uniform([15.0, -30.0], [70.0, 30.0])
        h = rng.uniform(-np.pi, np.pi)
        speed = rng.uniform(4.0, 15.0)
        xy_l = p0 + speed * tau[:, None] * np.array([np.cos(h), np.sin(h)])
        world = np.column_stack([xy_l @ _rz(YAW0_DEG)[:2, :2].T + truth.translation_m[:2],
                                 np.full(idx.size, ROAD_Z + 0.5)])
        add_track(idx, world)

    positions_m = np.concatenate(positions)
    frame_index = np.concatenate(frames)
    order = np.argsort(frame_index, kind='stable')
    radial = np.full(order.size, 5.0)
    if radial_velocities:
        t_frame = t_radar[frame_index[order]]
        v = np.column_stack([np.interp(t_frame, t_pose, vel[:, i]) for i in range(3)])
        rays = truth.apply(positions_m[order]) - truth.translation_m
        radial = np.einsum('ij,ij->i', v, rays) / np.linalg.norm(rays, axis=1)
    targets = Targets(positions_m[order], radial, frame_index[order])
    tracked = TrackedTargets(np.arange(order.size, dtype=np.int64),
                             np.concatenate(track_ids)[order])
    recording = Recording(frame_ns, targets, vehicle, LocalFrame.at(48.4, 9.99))
    normal = level.T @ np.array([0.0, 0.0, 1.0])
    ground = GroundPlane(normal, -6.0, level, 0.0, np.zeros(0, np.int64))
    return Scene(recording, tuple(tracks), tracked, ground, truth, config,
                 tuple(vehicle_ids), windows)


def _path_time(tau: np.ndarray, stop_s: float) -> np.ndarray:
    """Time along the lane's motion profile with a stop of stop_s after 3 s."""
    return np.minimum(tau, 3.0) + np.maximum(tau - 3.0 - stop_s, 0.0)


def _pose_at(t_pose: np.ndarray, xy: np.ndarray, yaw: np.ndarray):
    def at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.column_stack([np.interp(t, t_pose, xy[:, i]) for i in range(2)])
        return p, np.interp(t, t_pose, np.unwrap(yaw))
    return at


def with_hypotheses(config: CalibConfig, **changes: object) -> CalibConfig:
    """A config with some ``hypotheses`` fields changed."""
    return replace(config, hypotheses=replace(config.hypotheses, **changes))
