"""The simulator behind ``radar-calib simulate``: a roadside radar at a busy junction.

Our only source of truth, so it is built to be as hard as the real world: a radar on a
pole geo-referenced at a real site, traffic that follows lanes, stops at signals and
queues, reflections from where a radar really sees road users (``scatter``), occlusion,
clutter, multipath ghosts, false alarms, timing jitter and dropped cycles, and an RTK
GNSS/INS with noise and outages. See ``scenario.SCENARIOS`` for the named settings.

Stages (each its own module, each seeded from its own stream so that e.g. the scatter
model does not change the traffic):

``scenario`` -> ``roads`` (lanes, routes) -> ``traffic`` (IDM, signals, calibration drive)
-> ``world`` (static scene) + ``scatter`` (regions per road user) -> ``radar`` (targets)
+ ``gnss`` (NavSatFix / Odometry) -> ``writer`` (bag, ground truth, parameters).

Everything is simulated in the site's local metric frame (``io.geo.LocalFrame`` centred on
the junction) and converted to WGS 84 / UTM at the edges, exactly as the tool converts
back.
"""
from __future__ import annotations

import datetime as _dt
import math
import os
import shutil
import time
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros.errors import BagReadError, ConfigError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.result import calibration_dict
from radar_calib_ros.sim.gnss import RATE_HZ, simulate_gnss, vehicle_poses
from radar_calib_ros.sim.radar import RadarModel, RadarPose, frame_times, simulate_radar
from radar_calib_ros.sim.roads import Junction
from radar_calib_ros.sim.scatter import (
    DEFAULT_SCATTER_MODEL, KIND_NAMES, SCATTER_MODELS, build_templates, check_scatter_model)
from radar_calib_ros.sim.scenario import (
    SCENARIOS, Scenario, get_scenario, mount_rotation, perturbed_mount)
from radar_calib_ros.sim.traffic import CLASS_NAMES, TrafficLog, simulate_traffic
from radar_calib_ros.sim.world import build_scene
from radar_calib_ros.sim.writer import (
    GROUND_TRUTH_FILE, PARAMS_FILE, RADAR_TOPIC, TARGETS_FILE, RadarStream, ground_truth_file,
    targets_file, write_ground_truth, write_params, write_recording, write_targets)
from radar_calib_ros.types import Extrinsics

__all__ = ['SCENARIOS', 'check_duration', 'SCATTER_MODELS', 'DEFAULT_SCATTER_MODEL', 'CLASS_NAMES',
           'KIND_NAMES', 'SimulationPaths', 'SimulationSummary', 'simulate']

#: Recording start of every simulation (UTC); stamps are deterministic per seed.
_EPOCH = _dt.datetime(2024, 6, 4, 7, 30, tzinfo=_dt.timezone.utc)
_STORAGES = ('mcap', 'sqlite3')
# seed-sequence entropy marking the site's streams apart from any drive seed's
_SITE_TAG = zlib.crc32(b'radar_calib_ros.sim.site')
_MOUNT_TAG = zlib.crc32(b'radar_calib_ros.sim.mount')


@dataclass(frozen=True)
class SimulationPaths:
    """Files of one simulation; ``bag`` is the rosbag2 directory holding the others."""

    bag: Path
    ground_truth: Path
    params: Path
    targets: Path


@dataclass(frozen=True)
class SimulationSummary:
    """What :func:`simulate` wrote.

    truth : the content of ``ground_truth.json``; extrinsics : the true calibration in
    ``frame`` (the simulator's local frame, centred on the junction).
    """

    paths: SimulationPaths
    n_frames: int
    n_targets: int
    n_passes: int
    truth: dict[str, Any]
    extrinsics: Extrinsics
    frame: LocalFrame
    elapsed_s: float
    #: a recording of several radars: the ground truth of each, by frame id (the first is
    #: ``truth`` / ``extrinsics`` above); empty for one radar
    radars: dict[str, dict[str, Any]] = field(default_factory=dict)


def check_duration(duration_s: float) -> None:
    """ConfigError unless a simulated drive's duration [s] lies in [10, 3600]."""
    if not (10.0 <= float(duration_s) <= 3600.0):
        raise ConfigError(f'duration {duration_s:g} s is outside [10, 3600] s')


def simulate(out_dir: str | Path, *, seed: int = 0, duration_s: float = 600.0,
             storage: str = 'mcap', scenario: str = 'baseline',
             scatter_model: str | None = None,
             mount_seed: int | None = None,
             max_unambiguous_velocity_mps: float = 0.0,
             mount_turn: tuple[float, float] | None = None) -> SimulationSummary:
    """Simulate a calibration drive past a roadside radar and write it as a rosbag2 bag.

    Parameters
    ----------
    out_dir : str or Path
        The bag directory to create (it must not exist). It receives ``metadata.yaml`` and
        the storage file, plus ``ground_truth.json``, ``params.yaml`` and
        ``ground_truth_targets.npz``.
    seed : int, default=0
        The drive: traffic, signal timing, the calibration vehicle's route, every noise
        draw and the radar's clock offset. Same seed, scenario, duration, model and mount
        seed -> identical bag contents.
    duration_s : float, default=600.0
        Length of the recording [s] (10 s to 1 h); the number of passes of the calibration
        vehicle grows with it (about one a minute, at least 4, at most 15).
    storage : {'mcap', 'sqlite3'}, default='mcap'
    scenario : str, default='baseline'
        One of :data:`SCENARIOS`.
    scatter_model : {'skin', 'interior', 'mixed'} or None
        Where on road users the radar sees them; None = :data:`DEFAULT_SCATTER_MODEL`.
    mount_seed : int or None, default=None
        The site's installation: None mounts the radar(s) exactly as the scenario describes
        them; an integer moves each mount a little (position, height, pitch, roll, yaw,
        within real installation ranges), the same way for every ``seed``. The site's
        static scene (buildings, poles, kerbs, parked cars) belongs to the scenario alone.
        So recordings with different seeds and the same scenario and mount seed are drives
        past the same radar: one calibrates, another evaluates.
    max_unambiguous_velocity_mps : float, default=0.0
        A radar whose radial velocities fold beyond +-this speed (0: none): the waveform of
        a radar tuned for range resolves Doppler only within an interval, and a car faster
        than its half-width along the line of sight is reported wrapped into it.
    mount_turn : (at_s, yaw_deg) or None, default=None
        The (first) radar's mount turned about the vertical by ``yaw_deg`` (anticlockwise
        seen from above) ``at_s`` seconds into the recording, the radar staying where it
        is: a technician re-aiming it, a bracket that slipped. The ground truth is the mount
        after the turn (the radar as it is now); ``mount_before`` records the other.

    Returns
    -------
    SimulationSummary

    Raises
    ------
    ConfigError
        Unknown scenario, scatter model or storage, or a duration out of range.
    BagReadError
        ``out_dir`` exists already, or the bag cannot be written.
    """
    started = time.perf_counter()
    spec = get_scenario(scenario)
    model_name = check_scatter_model(scatter_model)
    if storage not in _STORAGES:
        raise ConfigError(f'unknown bag storage {storage!r}; use mcap or sqlite3')
    check_duration(duration_s)
    if not isinstance(seed, int) or seed < 0:
        raise ConfigError(f'seed must be a non-negative integer, got {seed!r}')
    if not (max_unambiguous_velocity_mps == 0.0 or 2.0 <= max_unambiguous_velocity_mps <= 200.0):
        raise ConfigError(f'unambiguous velocity {max_unambiguous_velocity_mps} m/s is neither '
                          '0 (no folding) nor within [2, 200] m/s')
    if mount_seed is not None and (not isinstance(mount_seed, int) or mount_seed < 0):
        raise ConfigError(f'mount seed must be a non-negative integer, got {mount_seed!r}')
    if mount_turn is not None and not (0.0 < mount_turn[0] < float(duration_s)
                                       and 0.0 < abs(mount_turn[1]) <= 90.0):
        raise ConfigError(f'mount turn {mount_turn!r}: the time must lie within the recording '
                          f'(0, {duration_s:g}) s and the turn within +-90 deg, not 0')
    out = Path(out_dir)
    if out.exists():
        raise BagReadError(f'{str(out)!r} exists already; not overwriting')
    duration = float(duration_s)
    streams = np.random.SeedSequence([seed, zlib.crc32(spec.name.encode())]).spawn(10)
    rngs = [np.random.default_rng(s) for s in streams]
    # the drive's streams; the first and fourth (once the mount and the scene) stay in the
    # list, unused, so that every other stream of a seed is what it always was
    (_, r_drive, r_traffic, _, r_scatter, r_times, r_radar, r_gnss, r_stamps,
     r_clock) = rngs
    # the site's: the scene from the scenario alone, the mounts from the mount seed
    r_scene = np.random.default_rng([_SITE_TAG, zlib.crc32(spec.name.encode())])

    # --- world, radar mounts, traffic --------------------------------------------------
    frame = LocalFrame.at(spec.site.lat_deg, spec.site.lon_deg)
    junction = Junction(spec.junction)
    # Further radars draw from their own streams, so the first radar (and with it every
    # single-radar recording) is the same whether or not others are simulated beside it.
    extra_rngs = [[np.random.default_rng(s) for s in np.random.SeedSequence(
        [seed, zlib.crc32(spec.name.encode()), 1 + k]).spawn(5)]
        for k in range(len(spec.more_radars))]
    mounts = [spec.radar, *spec.more_radars]
    if mount_seed is not None:
        mounts = [perturbed_mount(m, np.random.default_rng(
            [_MOUNT_TAG, mount_seed, zlib.crc32(spec.name.encode()), k]))
            for k, m in enumerate(mounts)]
    scene = build_scene(spec, junction, r_scene)
    log = simulate_traffic(spec, junction, duration, r_traffic, r_drive)
    templates = build_templates(log.users, model_name, r_scatter)
    epoch_ns = int(_EPOCH.timestamp()) * 1_000_000_000 + 1_000_000_000 * 3600 * (
        list(SCENARIOS).index(spec.name))

    # --- radars -------------------------------------------------------------------------
    radar_model = RadarModel(max_unambiguous_velocity_mps=float(max_unambiguous_velocity_mps))
    multi = len(mounts) > 1
    runs = [_simulate_one_radar(
        spec, mount, scene, log, templates, radar_model, duration, epoch_ns, *streams_k,
        frame_id=f'radar_{k + 1}' if multi else 'radar',
        topic=f'/radar_{k + 1}/points' if multi else RADAR_TOPIC)
        for k, (mount, streams_k) in enumerate(zip(
            mounts, [(r_times, r_radar, r_stamps, r_clock)] + [tuple(g[1:]) for g in extra_rngs]))]
    first = runs[0]
    before: Extrinsics | None = None
    if mount_turn is not None:
        before = first.extrinsics
        first = _turned_mount(first, *mount_turn)
        runs[0] = first

    # --- GNSS / INS ---------------------------------------------------------------------
    gnss = simulate_gnss(log, frame, scene.ground, spec.vehicle, duration, r_gnss)
    gnss_stamps_ns = epoch_ns + np.round(gnss.time_s * 1e9).astype(np.int64)
    m = gnss.time_s.size
    # a driver that stamps a fix on output stamps it late, and it arrives just after
    fix_stamps_ns = gnss_stamps_ns + int(round(spec.fix_stamp_lag_s * 1e9))
    fix_receive_ns = fix_stamps_ns + np.round(r_stamps.uniform(0.003, 0.008, m) * 1e9).astype(
        np.int64)
    # a slower receiver publishes every k-th epoch (the Odometry keeps every one)
    fix_index = np.arange(0, m, max(1, int(round(RATE_HZ / spec.fix_rate_hz))))
    odom_receive_ns = (gnss_stamps_ns + np.round(r_stamps.uniform(0.002, 0.006, m) * 1e9)
                       .astype(np.int64)) if spec.odometry else None

    # --- files ----------------------------------------------------------------------------
    n_messages = write_recording(
        out, targets=first.targets, radar_stamps_ns=first.stamps_ns,
        radar_receive_ns=first.receive_ns, gnss=gnss, gnss_stamps_ns=gnss_stamps_ns,
        fix_receive_ns=fix_receive_ns[fix_index], fix_index=fix_index,
        fix_stamps_ns=fix_stamps_ns,
        odom_receive_ns=odom_receive_ns,
        layout=spec.point_layout, velocity_field=spec.velocity_field, storage=storage,
        radar_topic=first.topic, radar_frame=first.frame_id,
        extra_radars=[RadarStream(r.topic, r.frame_id, r.targets, r.stamps_ns, r.receive_ns)
                      for r in runs[1:]])
    truths: dict[str, dict[str, Any]] = {}
    for run in runs:
        passes = _passes(log, junction, run.times, run.targets)
        truth = _truth(spec, seed, model_name, duration, frame, run.extrinsics, run.mount,
                       run.ground_z, passes, log, templates.skin_weight[0], gnss,
                       run.times.size, run.targets, epoch_ns, n_messages)
        truth['mount_seed'] = mount_seed
        if before is not None and run is first:
            assert mount_turn is not None
            truth['mount_before'] = calibration_dict(before, frame, stamp=truth['stamp'])
            truth['mount_turn'] = {'at_s': float(mount_turn[0]),
                                   'yaw_deg': float(mount_turn[1])}
        truth['max_unambiguous_velocity_mps'] = radar_model.max_unambiguous_velocity_mps
        if multi:
            truth.update(radar_frame=run.frame_id, radar_topic=run.topic)
        truths[run.frame_id] = truth
    paths = SimulationPaths(out, out / GROUND_TRUTH_FILE, out / PARAMS_FILE, out / TARGETS_FILE)
    truth = dict(truths[first.frame_id])
    if multi:
        truth['radars'] = [{'radar_frame': r.frame_id, 'radar_topic': r.topic,
                            'ground_truth': ground_truth_file(r.frame_id),
                            'targets': targets_file(r.frame_id)} for r in runs]
        for run in runs:
            write_ground_truth(out / ground_truth_file(run.frame_id), truths[run.frame_id])
    write_ground_truth(paths.ground_truth, truth)
    veh = spec.vehicle
    write_params(paths.params, odometry=spec.odometry, vehicle={
        'length': veh.length, 'width': veh.width, 'height': veh.height,
        'rear_overhang': veh.rear_overhang, 'ref_height': veh.ref_height},
        header=f'Parameters for the simulated recording {out.name}: scenario '
               f'{spec.name!r}, seed {seed}'
               + ('' if mount_seed is None else f', mount seed {mount_seed}')
               + '.\nThe calibration tool may use them; it never '
               'reads ground_truth*.', radar_topic=None if multi else RADAR_TOPIC)
    for run in runs:
        path = out / targets_file(run.frame_id) if multi else paths.targets
        _write_run_targets(path, run, log, scene, spec, frame)
    if multi:
        # the first radar's origins also under the single-radar name (a link, not a copy)
        try:
            os.link(out / targets_file(first.frame_id), paths.targets)
        except OSError:
            shutil.copyfile(out / targets_file(first.frame_id), paths.targets)
    return SimulationSummary(paths, int(first.times.size), int(first.targets.frame.size),
                             int(truth['n_passes']), truth, first.extrinsics, frame,
                             time.perf_counter() - started,
                             radars={f: t for f, t in truths.items()} if multi else {})


@dataclass(frozen=True)
class _RadarRun:
    """One simulated radar: mount, true calibration (local frame), frames and targets."""

    frame_id: str
    topic: str
    mount: Any
    extrinsics: Extrinsics
    ground_z: float
    times: np.ndarray
    targets: Any
    stamps_ns: np.ndarray
    receive_ns: np.ndarray


def _simulate_one_radar(spec: Scenario, mount: Any, scene: Any, log: TrafficLog,
                        templates: Any, radar_model: RadarModel, duration: float,
                        epoch_ns: int, r_times: np.random.Generator,
                        r_radar: np.random.Generator, r_stamps: np.random.Generator,
                        r_clock: np.random.Generator, *, frame_id: str,
                        topic: str) -> _RadarRun:
    rotation, _ = mount_rotation(mount)
    xy = np.asarray(mount.position_xy_m, float)
    ground_z = float(scene.ground.z(xy))
    translation = np.array([xy[0], xy[1], ground_z + mount.height_m])
    pose = RadarPose(rotation, translation)
    times = frame_times(duration, radar_model, r_times)
    targets = simulate_radar(log, templates, scene, pose, radar_model, times, r_radar)
    if spec.clock_offset_s is None:
        clock_offset = float(r_clock.uniform(-0.002, 0.002))
    else:
        clock_offset = float(spec.clock_offset_s)
    # header stamp = radar clock = GNSS time - offset, time-tagged to ~0.3 ms; a
    # free-running clock runs fast by its drift, the offset being clock_offset mid-recording
    drift = 1e-6 * spec.clock_drift_ppm * (times - 0.5 * duration)
    radar_stamp_s = times - clock_offset + drift + r_stamps.normal(0.0, 0.0003, times.size)
    stamps_ns = epoch_ns + np.round(radar_stamp_s * 1e9).astype(np.int64)
    receive_ns = epoch_ns + np.round((times + r_stamps.uniform(0.025, 0.045, times.size))
                                     * 1e9).astype(np.int64)
    return _RadarRun(frame_id, topic, mount, Extrinsics(rotation, translation, clock_offset),
                     ground_z, times, targets, stamps_ns, receive_ns)


def _turned_mount(run: _RadarRun, at_s: float, yaw_deg: float) -> _RadarRun:
    """The run with its mount turned about the vertical by ``yaw_deg`` from ``at_s`` on.

    The frames after the turn are re-expressed in the turned sensor frame: ranges and
    radial velocities do not change under a rotation about the radar, azimuths and
    elevations do. The field of view stays where the scan was simulated, a few degrees off
    at its edges after the turn: the edges carry no part of the calibration."""
    turn = Rotation.from_euler('z', yaw_deg, degrees=True).as_matrix()
    rotation = turn @ run.extrinsics.rotation
    # sensor before -> sensor after: x_after = R_after^T R_before x_before
    change = rotation.T @ run.extrinsics.rotation
    targets = run.targets
    after = run.times[targets.frame] >= at_s
    position = targets.position_m.copy()
    position_true = targets.position_true_m.copy()
    position[after] = position[after] @ change.T
    position_true[after] = position_true[after] @ change.T
    return replace(run, extrinsics=replace(run.extrinsics, rotation=rotation),
                   targets=replace(targets, position_m=position, position_true_m=position_true))


def _write_run_targets(path: Path, run: _RadarRun, log: TrafficLog, scene: Any,
                       spec: Scenario, frame: LocalFrame) -> None:
    targets, times = run.targets, run.times
    poses = vehicle_poses(log, scene.ground, spec.vehicle, times)
    write_targets(path, {
        'frame_index': targets.frame,
        'object_id': targets.object_id,
        'object_class': targets.object_class,
        # the targets that appear on the calibration vehicle: its wall ghosts (object 0
        # too) lie behind building fronts, tens of metres away, and would turn any
        # figure computed from this flag into one about the buildings
        'is_calibration_vehicle': (targets.object_id == 0) & (
            targets.kind != KIND_NAMES.index('ghost_wall')),
        'scatter_kind': targets.kind,
        'position_true_sensor_m': targets.position_true_m,
        'position_sensor_m': targets.position_m,
        'radial_velocity_true_mps': targets.radial_velocity_true_mps,
        'frame_stamp_ns': run.stamps_ns,
        'frame_time_s': times,
        'vehicle_position_m': poses.position_m,
        'vehicle_yaw_rad': poses.yaw_rad,
        'vehicle_speed_mps': poses.speed_mps,
        'vehicle_yaw_rate_rps': poses.yaw_rate_rps,
        'radar_rotation': run.extrinsics.rotation,
        'radar_translation_m': run.extrinsics.translation_m,
        'class_names': np.asarray(CLASS_NAMES),
        'kind_names': np.asarray(KIND_NAMES),
        'local_frame': np.array([frame.lat0_deg, frame.lon0_deg, frame.epsg], float),
    })


def _passes(log: TrafficLog, junction: Junction, times: np.ndarray,
            targets: Any) -> list[dict[str, Any]]:
    """The calibration vehicle's passes that crossed the junction within the recording."""
    drive = log.drive
    if drive.mode == 'away' or not drive.passes:
        return []
    t_series, s_series, v_series = log.vehicle_series(0)
    end = float(times[-1]) if times.size else 0.0
    cal = targets.object_id == 0
    cal_times = times[targets.frame[cal]]
    out = []
    for k, (entry, exit_, lane_in, lane_out) in enumerate(drive.passes):
        s_start, s_stop, s_end = drive.pass_s[k]
        t_start, t_stop, t_end = (_first_time(x, s_series, t_series)
                                  for x in (s_start, s_stop, s_end))
        if t_stop < 0.0 or t_stop > end or s_series[-1] < s_stop:
            continue
        within = (t_series >= t_start) & (t_series <= t_end)
        stopped = float(np.count_nonzero(within & (v_series < 0.1)) * (
            t_series[1] - t_series[0]))
        n_seen = int(np.count_nonzero((cal_times >= t_start) & (cal_times <= t_end)))
        out.append({
            'index': k, 'entry_arm': int(entry), 'exit_arm': int(exit_),
            'movement': drive.movements[k], 'lane_in': int(lane_in), 'lane_out': int(lane_out),
            'heading_in_deg': _arm_heading(junction, entry, inbound=True),
            'heading_out_deg': _arm_heading(junction, exit_, inbound=False),
            't_start_s': round(max(t_start, 0.0), 3), 't_stop_line_s': round(t_stop, 3),
            't_end_s': round(min(t_end, end), 3), 'stopped_s': round(stopped, 1),
            'n_targets': n_seen})
    return out


def _first_time(s_mark: float, s: np.ndarray, t: np.ndarray) -> float:
    """When a non-decreasing arc length first reaches ``s_mark`` (linear between steps;
    waiting at the mark does not move the answer)."""
    i = int(np.clip(np.searchsorted(s, s_mark, side='left'), 1, s.size - 1))
    ds = s[i] - s[i - 1]
    frac = float(np.clip((s_mark - s[i - 1]) / ds, 0.0, 1.0)) if ds > 0 else 1.0
    return float(t[i - 1] + frac * (t[i] - t[i - 1]))


def _arm_heading(junction: Junction, arm: int, *, inbound: bool) -> float:
    """ENU heading of travel on an arm (local grid, deg, counter-clockwise from east, in
    [0, 360)): inbound traffic drives towards the centre, against the arm's direction."""
    angle = math.degrees(junction.arms[arm].angle_rad) + (180.0 if inbound else 0.0)
    return round(angle % 360.0, 6)


def _truth(spec: Scenario, seed: int, model: str, duration: float, frame: LocalFrame,
           extrinsics: Extrinsics, mount: Any, ground_z: Any, passes: list[dict[str, Any]],
           log: TrafficLog, skin_weight: float, gnss: Any, n_frames: int, targets: Any,
           epoch_ns: int, n_messages: int) -> dict[str, Any]:
    stamp = _dt.datetime.fromtimestamp(epoch_ns / 1e9, _dt.timezone.utc).isoformat(
        timespec='seconds')
    truth = calibration_dict(extrinsics, frame, stamp=stamp)
    rpy = Rotation.from_matrix(extrinsics.rotation).as_euler('xyz', degrees=True)
    veh = spec.vehicle
    truth.update({
        'scenario': spec.name,
        'description': spec.description,
        'seed': seed,
        'scatter_model': model,
        'calibration_vehicle_skin_weight': float(skin_weight),
        'duration_s': duration,
        'time_offset_s': extrinsics.time_offset_s,
        'clock_drift_ppm': float(spec.clock_drift_ppm),
        'radar_height_m': float(extrinsics.translation_m[2] - ground_z),
        'radar_mount_local': {
            'translation_m': [float(v) for v in extrinsics.translation_m],
            'rpy_deg': [float(v) for v in rpy],
            'pitch_down_deg': float(mount.pitch_deg), 'roll_deg': float(mount.roll_deg)},
        'local_frame': {'lat0_deg': frame.lat0_deg, 'lon0_deg': frame.lon0_deg,
                        'epsg': int(frame.epsg)},
        'site': spec.site.name,
        'vehicle': {'length': veh.length, 'width': veh.width, 'height': veh.height,
                    'rear_overhang': veh.rear_overhang, 'ref_height': veh.ref_height},
        'drive_mode': log.drive.mode,
        'n_passes': len(passes),
        'passes': passes,
        'n_frames': n_frames,
        'n_targets': int(targets.frame.size),
        'n_calibration_vehicle_targets': int(np.count_nonzero(targets.object_id == 0)),
        'n_messages': n_messages,
        'gnss_outages_s': gnss.outages_s.tolist(),
        'point_layout': spec.point_layout,
        'velocity_field': spec.velocity_field,
        'odometry': spec.odometry,
        'stamp_origin_ns': epoch_ns,
    })
    return truth
