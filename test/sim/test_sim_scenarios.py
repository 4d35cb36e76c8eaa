"""Every named scenario runs and has the character its description promises."""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from radar_calib_ros.cli import main
from radar_calib_ros.errors import ConfigError
from radar_calib_ros.io import messages as msgs
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.sim import KIND_NAMES, SCENARIOS, simulate
from radar_calib_ros.sim.scenario import get_scenario, mount_rotation, perturbed_mount
from sim_truth import load


def _topics_and_fields(bag: Path, topic: str = '/radar/points',
                       frame_id: str = 'radar') -> tuple[dict[str, int], list[str]]:
    with AnyReader([bag], default_typestore=msgs.get_typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        radar = [c for c in reader.connections if c.topic == topic]
        _, _, raw = next(reader.messages(connections=radar))
        cloud = reader.deserialize(raw, radar[0].msgtype)
        assert cloud.header.frame_id == frame_id
        return counts, [f.name for f in cloud.fields]


@pytest.mark.parametrize('name', sorted(SCENARIOS))
def test_scenario_runs(name: str, tmp_path: Path) -> None:
    sim = simulate(tmp_path / name, seed=1, duration_s=12.0, scenario=name)
    truth = sim.truth
    spec = get_scenario(name)
    # a recording of several radars: radar_1 on /radar_1/points is the first
    topic = truth.get('radar_topic', '/radar/points')
    counts, fields = _topics_and_fields(sim.paths.bag, topic, truth['radar_frame'])
    assert counts[topic] == sim.n_frames > 150
    listed = truth.get('radars', [])
    assert len(listed) == (1 + len(spec.more_radars) if spec.more_radars else 0)
    assert all(counts[r['radar_topic']] > 150 for r in listed)
    assert counts['/vehicle/fix'] == int(12.0 * spec.fix_rate_hz) + 1
    assert ('/vehicle/odom' in counts) == spec.odometry
    if spec.point_layout == 'spherical':
        assert fields[:3] == ['range', 'azimuth', 'elevation']
    else:
        assert fields[:3] == ['x', 'y', 'z']
    assert spec.velocity_field in fields and 'rcs' in fields
    assert 4.0 - 1e-9 <= truth['radar_height_m'] <= 9.0 + 1e-9
    if spec.clock_offset_s is not None:
        assert truth['time_offset_s'] == pytest.approx(spec.clock_offset_s)
    assert truth['clock_drift_ppm'] == spec.clock_drift_ppm
    assert abs(truth['latitude'] - spec.site.lat_deg) < 0.01
    # the truth file's UTM zone is the site's (southern sites 327xx)
    assert truth['epsg'] == (32700 if spec.site.lat_deg < 0 else 32600) + int(
        (spec.site.lon_deg + 180) // 6) + 1
    _, z = load(sim.paths.bag)
    assert z['frame_index'].size == sim.n_targets > 50 * sim.n_frames
    # the radar's stamps run at its clock's rate against GNSS time (0.3 ms of jitter)
    stamp_s = (z['frame_stamp_ns'] - z['frame_stamp_ns'][0]) * 1e-9
    rate = np.polyfit(z['frame_time_s'], stamp_s - z['frame_time_s'], 1)[0]
    assert 1e6 * rate == pytest.approx(spec.clock_drift_ppm, abs=20.0)


def test_clock_offset_shifts_radar_stamps(tmp_path: Path) -> None:
    """Radar header stamp + time_offset_s = GNSS time of the measurement."""
    sim = simulate(tmp_path / 'c', seed=2, duration_s=12.0, scenario='clock_offset')
    truth, z = load(sim.paths.bag)
    gnss_time = (z['frame_stamp_ns'] - truth['stamp_origin_ns']) * 1e-9 + truth['time_offset_s']
    assert np.max(np.abs(gnss_time - z['frame_time_s'])) < 0.002
    assert truth['time_offset_s'] == pytest.approx(0.040)


def test_mounts_stay_in_real_ranges() -> None:
    rng = np.random.default_rng(0)
    for name in SCENARIOS:
        for _ in range(20):
            mount = perturbed_mount(get_scenario(name).radar, rng)
            assert 4.0 <= mount.height_m <= 9.0
            assert 3.0 <= mount.pitch_deg <= 15.0
            assert abs(mount.roll_deg) <= 2.0
            rotation, yaw = mount_rotation(mount)
            np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
            diff = math.atan2(rotation[1, 0], rotation[0, 0]) - yaw
            assert abs((diff + math.pi) % (2 * math.pi) - math.pi) < 1e-9


def test_sites_cover_convergence_and_hemispheres() -> None:
    convergence = {}
    for name in SCENARIOS:
        site = get_scenario(name).site
        frame = LocalFrame.at(site.lat_deg, site.lon_deg)
        convergence[name] = math.degrees(frame.utm_convergence_rad(site.lat_deg,
                                                                   site.lon_deg)[0])
    assert max(abs(c) for c in convergence.values()) > 2.0
    assert min(abs(c) for c in convergence.values()) < 1.0
    assert any(get_scenario(n).site.lat_deg < 0 for n in SCENARIOS)
    assert any(get_scenario(n).junction.left_hand for n in SCENARIOS)
    assert len({get_scenario(n).junction.arm_deg for n in SCENARIOS}) >= 7


def _pose(truth: dict) -> tuple[list[float], list[float]]:
    return truth['translation'], truth['quaternion_xyzw']


def test_the_seed_varies_the_drive_the_mount_seed_the_radar(tmp_path: Path) -> None:
    """A second recording of the same radar: another --seed is another drive (traffic,
    noise) past the same pole, mounted as the scenario says; --mount-seed moves it."""
    a = simulate(tmp_path / 'a', seed=3, duration_s=10.0)
    b = simulate(tmp_path / 'b', seed=4, duration_s=10.0)
    assert _pose(a.truth) == _pose(b.truth)
    assert a.truth['radar_height_m'] == b.truth['radar_height_m']
    assert a.truth['mount_seed'] is None
    _, za = load(a.paths.bag)
    _, zb = load(b.paths.bag)
    assert not np.array_equal(za['vehicle_position_m'][:50], zb['vehicle_position_m'][:50])
    # exactly the mount the scenario describes
    spec = get_scenario('baseline')
    mount = a.truth['radar_mount_local']
    assert mount['pitch_down_deg'] == spec.radar.pitch_deg
    assert mount['roll_deg'] == spec.radar.roll_deg
    assert a.truth['radar_height_m'] == pytest.approx(spec.radar.height_m)
    # the site's static scene is the same too: the stationary targets lie where they lay
    static = KIND_NAMES.index('static')
    static_a = za['position_true_sensor_m'][za['scatter_kind'] == static]
    static_b = zb['position_true_sensor_m'][zb['scatter_kind'] == static]
    common = np.intersect1d(np.round(static_a, 3).view([('', np.float32)] * 3),
                            np.round(static_b, 3).view([('', np.float32)] * 3))
    n_static = min(np.unique(static_a, axis=0).shape[0], np.unique(static_b, axis=0).shape[0])
    assert common.size > 0.5 * n_static
    # a mount seed: another installation, the same for every drive
    c = simulate(tmp_path / 'c', seed=3, duration_s=10.0, mount_seed=8)
    d = simulate(tmp_path / 'd', seed=5, duration_s=10.0, mount_seed=8)
    e = simulate(tmp_path / 'e', seed=3, duration_s=10.0, mount_seed=9)
    assert _pose(c.truth) == _pose(d.truth) != _pose(a.truth)
    assert _pose(e.truth) != _pose(c.truth)
    assert c.truth['mount_seed'] == 8
    # the mount seed changes the radar only: the drive of a seed stays what it was
    _, zc = load(c.paths.bag)
    np.testing.assert_array_equal(za['vehicle_position_m'], zc['vehicle_position_m'])
    with pytest.raises(ConfigError, match='mount seed'):
        simulate(tmp_path / 'f', seed=1, duration_s=10.0, mount_seed=-1)


def test_cli_mount_seed(tmp_path: Path) -> None:
    out = io.StringIO()
    assert main(['simulate', str(tmp_path / 'bag'), '--seed', '2', '--duration', '10',
                 '--mount-seed', '4'], out=out) == 0
    truth, _ = load(tmp_path / 'bag')
    assert truth['mount_seed'] == 4 and 'mount seed 4' in out.getvalue()
