"""Stage 7: closest-target re-estimate and the polygon loss (the paper's refinement)."""
from __future__ import annotations

import numpy as np
import pytest
from calib_scene import make_scene
from refine_scene import make_scene as make_refine_scene

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, polygon, registration
from radar_calib_ros.types import Extrinsics


def _selection(scene):  # type: ignore[no-untyped-def]
    hyps = hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          scene.config)
    return hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                       scene.config)


def _perturbed(truth: Extrinsics, yaw_deg: float, dx: float, dy: float) -> Extrinsics:
    return Extrinsics(registration.yaw_rotation(np.radians(yaw_deg)) @ truth.rotation,
                      truth.translation_m + [dx, dy, 0.0])


def test_polygon_loss_inside_free_outside_distance() -> None:
    cfg = CalibConfig()  # box x in [-1.0, 3.9], y in [-0.95, 0.95]
    positions = np.zeros((4, 3))
    yaw = np.array([0.0, 0.0, 0.0, np.pi / 2])
    # inside; 1 m ahead of the front; corner diagonal (3, 4) m off; and a rotated vehicle
    world = np.array([[1.0, 0.5], [4.9, 0.0], [6.9, 4.95], [0.0, 4.9]])
    per_target = [0.0, 1.0, 5.0, 1.0]
    loss = polygon.polygon_loss(np.zeros(2), world, positions, yaw, cfg)
    assert loss == pytest.approx(np.mean(per_target))
    # an offset that moves the 2nd target inside (and the 1st stays in) drops its cost
    shifted = polygon.polygon_loss(np.array([-1.0, 0.0]), world[:2], positions[:2], yaw[:2],
                                   cfg)
    assert shifted == pytest.approx(0.0)


def test_closest_target_step_recovers_the_transform() -> None:
    # every frame holds the box point closest to the sensor (and interior points, which
    # are farther by convexity): the closest-target pairs are exact
    scene = make_scene(n_passes=5, seed=2)
    selection = _selection(scene)
    start = _perturbed(scene.truth, 1.0, 0.6, -0.4)
    est = polygon.refine_polygon(start, scene.recording, scene.tracked, selection,
                                 scene.config)
    assert float(registration.rotation_angle_deg(est.rotation, scene.truth.rotation)) < 1e-7
    np.testing.assert_allclose(est.translation_m, scene.truth.translation_m, atol=1e-7)


def test_refinement_moves_yaw_and_horizontal_position_only() -> None:
    scene = make_scene(n_passes=5, seed=4, target_noise_m=0.2)
    selection = _selection(scene)
    start = Extrinsics(scene.truth.rotation, scene.truth.translation_m + [0.0, 0.0, 0.7])
    est = polygon.refine_polygon(start, scene.recording, scene.tracked, selection,
                                 scene.config)
    # a rotation about the world z axis leaves the sensor's "up" where it was
    np.testing.assert_allclose(est.rotation[2], scene.truth.rotation[2], atol=1e-12)
    assert float(registration.rotation_angle_deg(est.rotation, scene.truth.rotation)) > 0.0
    assert est.translation_m[2] == pytest.approx(start.translation_m[2])


def test_noisy_targets_improve_on_a_perturbed_start() -> None:
    scene = make_scene(n_passes=6, seed=5, target_noise_m=0.15, interior_targets=8,
                       random_cars=5)
    selection = _selection(scene)
    start = _perturbed(scene.truth, 1.5, 0.8, 0.6)
    est = polygon.refine_polygon(start, scene.recording, scene.tracked, selection,
                                 scene.config)
    err_start = np.linalg.norm(start.translation_m[:2] - scene.truth.translation_m[:2])
    err = np.linalg.norm(est.translation_m[:2] - scene.truth.translation_m[:2])
    angle = float(registration.rotation_angle_deg(est.rotation, scene.truth.rotation))
    assert err < 0.25 < err_start
    assert angle < 0.5


def test_closest_targets_pick_the_nearest_target_per_frame() -> None:
    cfg = CalibConfig()
    targets = polygon.VehicleTargets(
        target_index=np.arange(4), stamps_ns=np.array([5, 5, 9, 9]),
        world_m=np.array([[10.0, 0.0, 0.0], [8.0, 0.5, 0.0], [3.0, 0.0, 0.0],
                          [4.0, 0.0, 0.0]]),
        positions_m=np.zeros((4, 3)), yaw_rad=np.zeros(4))
    closest = polygon.closest_targets(targets, np.array([20.0, 0.0, 5.0]), cfg)
    np.testing.assert_array_equal(closest.stamps_ns, [5, 9])
    np.testing.assert_allclose(closest.target_xy_m, [[10.0, 0.0], [4.0, 0.0]])
    # sensor straight ahead of the car: the box point is the middle of the front edge
    np.testing.assert_allclose(closest.box_xy_m, [[3.9, 0.0], [3.9, 0.0]])
    # diagonal: the front-left corner
    closest = polygon.closest_targets(targets, np.array([20.0, 10.0, 5.0]), cfg)
    np.testing.assert_allclose(closest.box_xy_m[0], [3.9, 0.95])


@pytest.mark.parametrize('model', ['interior', 'skin'])
def test_each_step_errs_to_its_own_side_where_only_front_and_rear_are_seen(
        model: str) -> None:
    """Seen head-on and tail-on only, the depth of the reflections trades against the
    radar's distance: the closest-target step puts the nearest target on the outline (too
    far out for a car that reflects from inside its footprint), the polygon loss draws the
    box over the targets (forward, as far as they let it). The final fit starts midway."""
    scene = make_refine_scene(1, model=model, geometry='head_on')
    boresight = scene.truth.rotation[:, 0].copy()
    boresight[2] = 0.0
    boresight /= np.linalg.norm(boresight)
    start = Extrinsics(scene.truth.rotation, scene.truth.translation_m + 0.8 * boresight)

    def along(est: Extrinsics) -> float:
        return float((est.translation_m - scene.truth.translation_m) @ boresight)
    closest = polygon.closest_target_fit(start, scene.recording, scene.tracked,
                                         scene.selection, scene.config)
    est = polygon.polygon_offset(closest, scene.recording, scene.tracked, scene.selection,
                                 scene.config)
    midway = polygon.bracketed_start(closest, est)
    assert along(est) > along(closest) + 0.25
    if model == 'interior':
        assert along(closest) < -0.5 and abs(along(est)) < 0.2
    assert along(midway) == pytest.approx(0.5 * (along(closest) + along(est)))
    np.testing.assert_array_equal(midway.rotation, est.rotation)
