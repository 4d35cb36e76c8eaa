"""simulate(): the files it writes, reproducibility, reading the bag back, bad arguments."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import BagReadError, ConfigError
from radar_calib_ros.io.bag import read_recording
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import interpolate_poses
from radar_calib_ros.result import RESULT_KEYS, load_result, utm_to_extrinsics
from radar_calib_ros.sim import SCATTER_MODELS, SCENARIOS, SimulationSummary, simulate


def _raw_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with AnyReader([bag]) as reader:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


def test_public_names() -> None:
    assert SCATTER_MODELS == ('skin', 'interior', 'mixed')
    assert len(SCENARIOS) >= 9
    for name in ('baseline', 'dense_traffic_steep_pitch', 'low_mount', 'navsat_only',
                 'clock_offset', 'vehicle_never_in_view', 'mid_block'):
        assert name in SCENARIOS and SCENARIOS[name]


def test_same_seed_same_bag_other_seed_other_bag(tmp_path: Path) -> None:
    a = simulate(tmp_path / 'a', seed=3, duration_s=15.0, storage='sqlite3')
    b = simulate(tmp_path / 'b', seed=3, duration_s=15.0, storage='sqlite3')
    c = simulate(tmp_path / 'c', seed=4, duration_s=15.0, storage='sqlite3')
    msgs_a, msgs_b = _raw_messages(a.paths.bag), _raw_messages(b.paths.bag)
    assert len(msgs_a) > 1000
    assert msgs_a == msgs_b
    assert msgs_a != _raw_messages(c.paths.bag)
    assert a.truth == b.truth
    assert a.paths.ground_truth.read_text() == b.paths.ground_truth.read_text()
    with np.load(a.paths.targets) as za, np.load(b.paths.targets) as zb:
        for key in za.files:
            np.testing.assert_array_equal(za[key], zb[key])


def test_files_in_the_bag_directory(baseline_sim: SimulationSummary) -> None:
    bag = baseline_sim.paths.bag
    assert (bag / 'metadata.yaml').is_file()
    assert list(bag.glob('*.mcap'))
    for path in (baseline_sim.paths.ground_truth, baseline_sim.paths.params,
                 baseline_sim.paths.targets):
        assert path.parent == bag and path.is_file()
    assert baseline_sim.n_frames > 15 * 85
    assert baseline_sim.n_targets > 100 * baseline_sim.n_frames


def test_truth_file_is_a_valid_result_and_converts_back(baseline_sim: SimulationSummary
                                                        ) -> None:
    path = baseline_sim.paths.ground_truth
    truth = json.loads(path.read_text())
    for key in RESULT_KEYS:
        assert key in truth
    for key in ('scenario', 'seed', 'scatter_model', 'time_offset_s', 'radar_height_m',
                'n_passes', 'passes'):
        assert key in truth
    assert truth['scenario'] == 'baseline' and truth['seed'] == 7
    assert truth['scatter_model'] in SCATTER_MODELS
    assert 4.0 <= truth['radar_height_m'] <= 9.0
    assert abs(truth['time_offset_s']) <= 0.002
    doc = load_result(path)
    rot_utm = Rotation.from_quat(doc['quaternion_xyzw']).as_matrix()
    back = utm_to_extrinsics(rot_utm, np.asarray(doc['translation']), baseline_sim.frame)
    np.testing.assert_allclose(back.translation_m, baseline_sim.extrinsics.translation_m,
                               atol=1e-4)
    np.testing.assert_allclose(back.rotation, baseline_sim.extrinsics.rotation, atol=1e-8)
    # the mount's pitch is down, its roll small, as on a real pole
    pitch, roll = truth['radar_mount_local']['pitch_down_deg'], truth['radar_mount_local'][
        'roll_deg']
    assert 3.0 <= pitch <= 15.0 and abs(roll) <= 2.0
    boresight_down = -baseline_sim.extrinsics.rotation[2, 0]
    assert math.isclose(math.degrees(math.asin(boresight_down)), pitch, abs_tol=1e-6)


def test_params_file_is_accepted_and_describes_the_vehicle(baseline_sim: SimulationSummary
                                                           ) -> None:
    config = CalibConfig.from_file(baseline_sim.paths.params)
    truth = baseline_sim.truth
    for key in ('length', 'width', 'height', 'rear_overhang', 'ref_height'):
        assert getattr(config.vehicle, key) == pytest.approx(truth['vehicle'][key])
    assert config.radar_topic == '/radar/points'
    assert config.navsat_topic == '/vehicle/fix'
    assert config.odom_topic == '/vehicle/odom'


def test_bag_reads_back_exactly(baseline_sim: SimulationSummary) -> None:
    """The tool's reader gives exactly the simulator's targets, and poses within the
    GNSS/INS noise (RTK ~2 cm, heading ~0.1 deg) of the true ones."""
    bag = baseline_sim.paths.bag
    config = CalibConfig.from_file(baseline_sim.paths.params)
    recording = read_recording(bag, config)
    with np.load(baseline_sim.paths.targets) as z:
        np.testing.assert_array_equal(recording.frame_stamps_ns, z['frame_stamp_ns'])
        np.testing.assert_array_equal(recording.targets.frame_index, z['frame_index'])
        np.testing.assert_array_equal(recording.targets.positions_m, z['position_sensor_m'])
        truth_pos, truth_yaw = z['vehicle_position_m'], z['vehicle_yaw_rad']
    assert recording.counters['radar_frames'] == baseline_sim.n_frames
    offset_ns = round(baseline_sim.truth['time_offset_s'] * 1e9)
    poses = interpolate_poses(recording.vehicle, recording.frame_stamps_ns + offset_ns, 0.5)
    sim_frame: LocalFrame = baseline_sim.frame
    lat, lon, alt = sim_frame.local_to_geodetic(truth_pos)
    expected = recording.frame.geodetic_to_local(lat, lon, alt)
    ok = poses.valid
    assert ok.mean() > 0.9
    err = poses.positions_m[ok] - expected[ok]
    horizontal = np.hypot(err[:, 0], err[:, 1])
    assert 0.01 < np.sqrt(np.mean(horizontal ** 2)) < 0.04
    assert np.max(horizontal) < 0.15
    yaw_expected = (truth_yaw + sim_frame.local_convergence_rad(lat, lon)
                    - recording.frame.local_convergence_rad(lat, lon))
    dyaw = np.degrees((poses.yaw_rad[ok] - yaw_expected[ok] + np.pi) % (2 * np.pi) - np.pi)
    assert 0.02 < np.std(dyaw) < 0.2
    assert np.max(np.abs(dyaw)) < 0.6


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='scenario'):
        simulate(tmp_path / 'x', scenario='nowhere', duration_s=10.0)
    with pytest.raises(ConfigError, match='scatter model'):
        simulate(tmp_path / 'x', scatter_model='glitter', duration_s=10.0)
    with pytest.raises(ConfigError, match='storage'):
        simulate(tmp_path / 'x', storage='rosbag1', duration_s=10.0)
    with pytest.raises(ConfigError, match='duration'):
        simulate(tmp_path / 'x', duration_s=1.0)
    (tmp_path / 'exists').mkdir()
    with pytest.raises(BagReadError, match='exists'):
        simulate(tmp_path / 'exists', duration_s=10.0)
    assert not (tmp_path / 'x').exists()


def test_a_turned_mount_moves_the_targets_after_the_turn(tmp_path: Path) -> None:
    """The mount turned 10 deg at 45 s: the vehicle's true targets lie on it in the world
    through the mount before the turn for earlier frames and through the mount after it
    (the ground truth's) for later ones, never the other way round."""
    from scipy.spatial.transform import Rotation

    from sim_truth import load, vehicle_config
    from radar_calib_ros.core import vehicle as vehicle_box
    bag = tmp_path / 'turned'
    simulate(bag, seed=7, duration_s=90.0, mount_turn=(45.0, 10.0))
    truth, z = load(bag)
    before = Rotation.from_quat(truth['mount_before']['quaternion_xyzw']).as_matrix()
    after = Rotation.from_quat(truth['quaternion_xyzw']).as_matrix()
    turn = Rotation.from_matrix(after @ before.T).as_rotvec(degrees=True)
    np.testing.assert_allclose(turn, [0.0, 0.0, 10.0], atol=1e-6)
    assert truth['mount_turn'] == {'at_s': 45.0, 'yaw_deg': 10.0}
    sel = z['is_calibration_vehicle']
    frame = z['frame_index'][sel]
    late = z['frame_time_s'][frame] >= 45.0
    assert late.any() and (~late).any()
    box = vehicle_config(truth)

    def inside(rotation: np.ndarray) -> np.ndarray:
        world = (z['position_true_sensor_m'][sel].astype(np.float64) @ rotation.T
                 + z['radar_translation_m'])
        local = vehicle_box.world_to_vehicle(world, z['vehicle_position_m'][frame],
                                             z['vehicle_yaw_rad'][frame])
        return vehicle_box.box_distance(local, box) < 0.5

    right = np.where(late, inside(after), inside(before))
    wrong = np.where(late, inside(before), inside(after))
    assert right.mean() > 0.9 and wrong.mean() < 0.5, (right.mean(), wrong.mean())


def test_a_mount_turn_outside_the_recording_or_of_nothing_is_refused(tmp_path: Path) -> None:
    for turn in ((0.0, 3.0), (20.0, 3.0), (5.0, 0.0), (5.0, 120.0)):
        with pytest.raises(ConfigError, match='mount turn'):
            simulate(tmp_path / 'x', duration_s=10.0, mount_turn=turn)
    assert not (tmp_path / 'x').exists()
