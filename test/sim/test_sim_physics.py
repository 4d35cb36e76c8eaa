"""The radar and GNSS models: field of view, radial velocity, multipath, timing, noise."""
from __future__ import annotations

import math

import numpy as np

from scipy.spatial.transform import Rotation

from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.sim import KIND_NAMES, SimulationSummary
from radar_calib_ros.sim.gnss import simulate_gnss
from radar_calib_ros.sim.roads import Junction
from radar_calib_ros.sim.scenario import get_scenario
from radar_calib_ros.sim.traffic import simulate_traffic
from radar_calib_ros.sim.world import Ground
from sim_truth import load


def _spherical(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r = np.linalg.norm(p, axis=1)
    return r, np.arctan2(p[:, 1], p[:, 0]), np.arcsin(p[:, 2] / r)


def test_targets_in_field_of_view(baseline_sim: SimulationSummary) -> None:
    _, z = load(baseline_sim.paths.bag)
    r, az, el = _spherical(z['position_true_sensor_m'].astype(float))
    assert np.all(r <= 150.0 + 1e-3) and np.all(r >= 0.5 - 1e-3)
    assert np.all(np.abs(az) <= math.radians(60.0) + 1e-5)
    assert np.all(np.abs(el) <= math.radians(10.0) + 1e-5)
    # measured = true + spherical noise: elevation the worst, growing with range
    rm, azm, elm = _spherical(z['position_sensor_m'].astype(float))
    near, far = r < 40.0, r > 90.0
    assert near.sum() > 1000 and far.sum() > 1000
    bounds = ((r, rm, 0.08, 0.25), (az, azm, math.radians(0.2), math.radians(0.6)),
              (el, elm, math.radians(0.9), math.radians(2.3)))
    for true, meas, lo, hi in bounds:
        sd_near, sd_far = np.std((meas - true)[near]), np.std((meas - true)[far])
        assert lo < sd_near < sd_far < hi


def test_most_targets_are_static_clutter(baseline_sim: SimulationSummary) -> None:
    _, z = load(baseline_sim.paths.bag)
    kinds = z['scatter_kind']
    per_frame = kinds.size / baseline_sim.n_frames
    assert 140 < per_frame < 280
    static = np.mean(kinds == KIND_NAMES.index('static'))
    assert 0.5 < static < 0.8
    for kind in ('false_alarm', 'ghost_road', 'ghost_wall', 'wheel', 'multibounce'):
        assert np.any(kinds == KIND_NAMES.index(kind)), kind


def test_radial_velocity_is_the_rigid_body_projection(baseline_sim: SimulationSummary
                                                      ) -> None:
    """Rigid returns of the calibration vehicle: v_r = (v + omega x r) . line of sight,
    positive moving away; wheels spread around it (micro-Doppler)."""
    _, z = load(baseline_sim.paths.bag)
    rotation, translation = z['radar_rotation'], z['radar_translation_m']
    cal = z['is_calibration_vehicle']
    kinds = z['scatter_kind']
    rigid = cal & np.isin(kinds, [KIND_NAMES.index(k) for k in (
        'wheel_house', 'underbody', 'engine', 'seat', 'mirror', 'face', 'corner')])
    frame = z['frame_index'][rigid]
    world = z['position_true_sensor_m'][rigid].astype(float) @ rotation.T + translation
    ref = z['vehicle_position_m'][frame]
    yaw, speed = z['vehicle_yaw_rad'][frame], z['vehicle_speed_mps'][frame]
    omega = z['vehicle_yaw_rate_rps'][frame]
    d = world[:, :2] - ref[:, :2]
    vx = speed * np.cos(yaw) - omega * d[:, 1]
    vy = speed * np.sin(yaw) + omega * d[:, 0]
    # on the road's gradient the car climbs as it moves (0.4-0.6 % at the baseline site)
    slope_x, slope_y = get_scenario('baseline').site.slope
    assert slope_x or slope_y
    velocity = np.column_stack([vx, vy, slope_x * vx + slope_y * vy])
    los = world - translation
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    predicted = np.sum(velocity * los, axis=1)
    v_true = z['radial_velocity_true_mps'][rigid]
    assert rigid.sum() > 500
    # float32 storage only
    assert np.max(np.abs(v_true - predicted)) < 1e-3
    assert np.any(predicted > 1.0) and np.any(predicted < -1.0)
    wheels = cal & (kinds == KIND_NAMES.index('wheel'))
    spread = np.abs(z['radial_velocity_true_mps'][wheels])
    assert spread.size > 100 and np.std(spread) > 0.5


def test_multipath_lies_below_the_road_and_beyond_the_vehicle(baseline_sim: SimulationSummary
                                                              ) -> None:
    truth, z = load(baseline_sim.paths.bag)
    rotation, translation = z['radar_rotation'], z['radar_translation_m']
    cal = z['is_calibration_vehicle']
    frame = z['frame_index']
    ref = z['vehicle_position_m']
    road_height = ref[:, 2] - truth['vehicle']['ref_height']
    for kind in ('multibounce', 'ghost_road'):
        sel = cal & (z['scatter_kind'] == KIND_NAMES.index(kind))
        assert sel.sum() > 50, kind
        world = z['position_true_sensor_m'][sel].astype(float) @ rotation.T + translation
        below = world[:, 2] < road_height[frame[sel]] + 0.05
        assert below.mean() > 0.95, kind
        # never on the radar's side: farther from the radar than the vehicle's near edge
        d_target = np.hypot(*(world[:, :2] - translation[:2]).T)
        d_ref = np.hypot(*(ref[frame[sel], :2] - translation[:2]).T)
        assert np.all(d_target > d_ref - truth['vehicle']['length']), kind


def test_radar_timing_jitter_and_dropped_cycles(baseline_sim: SimulationSummary) -> None:
    _, z = load(baseline_sim.paths.bag)
    dt = np.diff(z['frame_stamp_ns']) * 1e-9
    period = 1.0 / 15.0
    regular = dt[dt < 1.5 * period]
    assert abs(np.median(regular) - period) < 0.002
    assert 0.0005 < np.std(regular) < 0.006
    assert np.any(dt > 1.5 * period)  # a lost cycle
    assert np.all(dt > 0.0)


def test_gnss_noise_outages_and_rate() -> None:
    """50 Hz, RTK-level noise (~2 cm), INS heading noise ~0.1 deg against TRUE north, and
    no-fix outages flagged with status -1."""
    scenario = get_scenario('far_from_meridian')  # UTM convergence ~ -2.5 deg there
    junction = Junction(scenario.junction)
    log = simulate_traffic(scenario, junction, 600.0, np.random.default_rng(1),
                           np.random.default_rng(2))
    frame = LocalFrame.at(scenario.site.lat_deg, scenario.site.lon_deg)
    ground = Ground(scenario.site.ground_alt_m, scenario.site.slope)
    gnss = simulate_gnss(log, frame, ground, scenario.vehicle, 600.0,
                         np.random.default_rng(3))
    assert np.allclose(np.diff(gnss.time_s), 0.02)
    assert gnss.outages_s.shape[0] >= 1
    inside = np.zeros(gnss.time_s.size, bool)
    for t0, t1 in gnss.outages_s:
        inside |= (gnss.time_s >= t0) & (gnss.time_s < t1)
    assert np.all(gnss.status[inside] == -1) and np.all(gnss.status[~inside] == 2)
    measured = frame.geodetic_to_local(gnss.lat_deg, gnss.lon_deg, gnss.alt_m)
    err = measured - gnss.truth.position_m
    horizontal = np.hypot(err[~inside, 0], err[~inside, 1])
    assert 0.012 < np.sqrt(np.mean(horizontal ** 2)) < 0.035
    assert np.max(np.hypot(err[inside, 0], err[inside, 1])) > 0.5
    # Odometry yaw is against true north: grid yaw + convergence (+ ~0.1 deg noise)
    yaw_true = Rotation.from_quat(gnss.quaternion_xyzw).as_euler('xyz')[:, 2]
    lat, lon, _ = frame.local_to_geodetic(gnss.truth.position_m)
    expected = gnss.truth.yaw_rad + frame.local_convergence_rad(lat, lon)
    dyaw = np.degrees((yaw_true - expected + np.pi) % (2 * np.pi) - np.pi)
    assert 0.04 < np.std(dyaw) < 0.2 and abs(np.mean(dyaw)) < 0.1
    utm = frame.utm_convergence_rad(lat[:1], lon[:1])[0]
    assert abs(math.degrees(utm)) > 2.0  # the scenario's point: far from the zone meridian
