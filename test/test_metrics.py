"""The paper's metrics r_i, delta_op, delta_p on hand-checked scenes."""
from __future__ import annotations

import numpy as np
import pytest

from radar_calib_ros import metrics
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import Extrinsics, Targets, TrackedTargets, VehicleTrack

S = 1_000_000_000
CFG = CalibConfig()  # box x in [-1.0, 3.9], y in [-0.95, 0.95] around the reference point


def _vehicle(speed_mps: float = 0.0, yaw_rad: float = 0.0) -> VehicleTrack:
    t = np.arange(0.0, 10.0, 0.02)
    xy = speed_mps * t[:, None] * [np.cos(yaw_rad), np.sin(yaw_rad)]
    return VehicleTrack((t * S).astype(np.int64), np.column_stack([xy, np.zeros(t.size)]),
                        np.full(t.size, yaw_rad),
                        np.column_stack([np.tile([speed_mps, 0.0], (t.size, 1)),
                                         np.zeros(t.size)]), np.zeros(t.size))


SENSOR = Extrinsics(np.eye(3), np.array([20.0, 10.0, 5.0]))


def test_hand_checked_values() -> None:
    world = np.array([[1.0, 0.5, 0.5], [4.9, 0.0, 0.5], [6.9, 4.95, 0.5],   # frame at 1 s
                      [0.0, 0.0, 0.5], [3.9, 0.95, 0.5]])                   # frame at 2 s
    stamps = np.array([1, 1, 1, 2, 2]) * S
    m = metrics.paper_metrics(SENSOR.inverse_apply(world), stamps, _vehicle(), SENSOR, CFG)
    # inside: 1st, 4th, and the 5th on the corner (edges count as inside)
    assert m.inlier_ratio == pytest.approx(3 / 5)
    assert m.outlier_distance_m == pytest.approx((1.0 + 5.0) / 2)
    # frame 1: closest to the sensor (20, 10) is (6.9, 4.95), 5 m from the corner
    # (3.9, 0.95) nearest the sensor; frame 2: the corner target itself
    assert m.closest_target_offset_m == pytest.approx((5.0 + 0.0) / 2)
    assert (m.n_targets, m.n_outside, m.n_frames) == (5, 2, 2)
    np.testing.assert_allclose(m.distance_m, [0.0, 1.0, 5.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m.closest_range_m, np.hypot(16.1, 9.05))


def test_vehicle_heading_rotates_the_box() -> None:
    # heading north: the box spans y in [-1, 3.9] and x in [-0.95, 0.95]
    vehicle = _vehicle(yaw_rad=np.pi / 2)
    world = np.array([[0.0, 3.5, 0.0], [1.5, 0.0, 0.0]])
    m = metrics.paper_metrics(SENSOR.inverse_apply(world), np.array([1, 1]) * S, vehicle,
                              SENSOR, CFG)
    assert m.inlier_ratio == pytest.approx(0.5)
    assert m.outlier_distance_m == pytest.approx(0.55)


def test_time_offsets_pick_the_pose_and_invalid_poses_drop() -> None:
    vehicle = _vehicle(speed_mps=10.0)
    # targets where the car's centre is 0.5 s after their radar stamp
    stamps = np.array([1, 2, 3]) * S
    world = np.column_stack([10.0 * (stamps / S + 0.5) + 1.45, np.zeros(3), np.zeros(3)])
    late = Extrinsics(np.eye(3), SENSOR.translation_m, time_offset_s=0.5)
    m = metrics.paper_metrics(late.inverse_apply(world), stamps, vehicle, late, CFG)
    assert m.inlier_ratio == 1.0
    m0 = metrics.paper_metrics(SENSOR.inverse_apply(world), stamps, vehicle, SENSOR, CFG)
    assert m0.inlier_ratio == 0.0
    assert m0.outlier_distance_m == pytest.approx(5.0 - 2.45)
    # the same offset from sync.time_offset; a stamp past the pose stream is left out
    cfg = CalibConfig.from_mapping({'sync': {'time_offset': 0.5}})
    m = metrics.paper_metrics(SENSOR.inverse_apply(world), np.array([1, 2, 30]) * S, vehicle,
                              SENSOR, cfg)
    assert (m.n_targets, m.inlier_ratio) == (2, 1.0)
    empty = metrics.paper_metrics(np.zeros((0, 3)), np.zeros(0, np.int64), vehicle, SENSOR, CFG)
    assert empty.n_targets == 0 and np.isnan(empty.inlier_ratio)


def test_vehicle_track_ids_follow_the_paper_protocol() -> None:
    vehicle = _vehicle()
    frames = np.array([1, 2, 3]) * S
    # track 7: on the car; track 8: 20 m away; track 9: 4 m from the box centre
    world = np.array([[1.5, 0.0, 0.0], [2.0, 0.3, 0.0], [1.0, -0.2, 0.0],
                      [21.0, 0.0, 0.0], [1.45, 4.0, 0.0]])
    targets = Targets(SENSOR.inverse_apply(world), np.ones(5), np.array([0, 1, 2, 0, 1]))
    recording = Recording(frames, targets, vehicle, LocalFrame.at(48.4, 9.99))
    tracked = TrackedTargets(np.arange(5), np.array([7, 7, 7, 8, 9]))
    ids = metrics.vehicle_track_ids(recording, tracked, SENSOR, CFG)
    np.testing.assert_array_equal(ids, [7, 9])
    index = metrics.track_target_index(tracked, ids)
    np.testing.assert_array_equal(index, [0, 1, 2, 4])
    m = metrics.recording_metrics(recording, index, SENSOR, CFG)
    assert m.n_targets == 4 and m.inlier_ratio == pytest.approx(0.75)


def test_targets_moving_unlike_the_vehicle_are_found() -> None:
    """Radial velocities off the vehicle's predicted ones by more than 0.5 m/s mark a
    target as moving unlike it (another road user merged into its track); one without a
    pose is not marked."""
    vehicle = _vehicle(speed_mps=10.0)
    frames = np.array([1, 2, 3, 20]) * S      # the last: after the poses end
    world = np.array([[10 + 1.5, 0.0, 0.5], [20 + 2.0, 0.3, 0.5], [30 + 1.0, -0.2, 0.5],
                      [200.0, 0.0, 0.5]])
    rays = world - SENSOR.translation_m
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    predicted = 10.0 * rays[:, 0]
    measured = predicted + np.array([0.1, -0.3, 2.0, 5.0])
    targets = Targets(SENSOR.inverse_apply(world), measured, np.arange(4))
    recording = Recording(frames, targets, vehicle, LocalFrame.at(48.4, 9.99))
    unlike = metrics.moving_unlike_vehicle(recording, np.arange(4), SENSOR, CFG)
    np.testing.assert_array_equal(unlike, [False, False, True, False])
