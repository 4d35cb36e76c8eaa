"""Closed-form rigid registration: known transforms, weights, reflections, angles."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from radar_calib_ros.core import registration


def _random_rigid(rng: np.random.Generator, dim: int) -> tuple[np.ndarray, np.ndarray]:
    if dim == 3:
        rot = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    else:
        a = rng.uniform(-np.pi, np.pi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return rot, rng.uniform(-500.0, 500.0, dim)


@pytest.mark.parametrize('dim', [2, 3])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_fit_rigid_recovers_known_transform(dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    rot, t = _random_rigid(rng, dim)
    source = rng.uniform(-60.0, 60.0, (50, dim))
    target = source @ rot.T + t
    fit = registration.fit_rigid(source, target, rng.uniform(0.1, 2.0, 50))
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(fit.translation_m, t, atol=1e-9)
    assert fit.rms_m < 1e-9
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)


def test_fit_rigid_planar_points_give_a_proper_rotation() -> None:
    # coplanar 3D points: the SVD has a zero singular value and V U^T may be a
    # reflection; the fit must still return the rotation, not a mirror
    rng = np.random.default_rng(3)
    rot, t = _random_rigid(rng, 3)
    source = np.column_stack([rng.uniform(-20, 20, (30, 2)), np.zeros(30)])
    fit = registration.fit_rigid(source, source @ rot.T + t)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-10)


def test_weights_equal_repetition_and_zero_weight_ignores() -> None:
    rng = np.random.default_rng(4)
    source = rng.normal(0.0, 10.0, (20, 2))
    target = source + rng.normal(0.0, 0.5, (20, 2)) + [3.0, -1.0]
    weights = np.ones(20)
    weights[:5] = 2.0
    weighted = registration.fit_rigid(source, target, weights)
    repeated = registration.fit_rigid(np.vstack([source, source[:5]]),
                                      np.vstack([target, target[:5]]))
    np.testing.assert_allclose(weighted.rotation, repeated.rotation, atol=1e-12)
    np.testing.assert_allclose(weighted.translation_m, repeated.translation_m, atol=1e-10)
    # a gross outlier with zero weight changes nothing
    outlier_target = target.copy()
    outlier_target[0] += 100.0
    w0 = np.ones(20)
    w0[0] = 0.0
    a = registration.fit_rigid(source, outlier_target, w0)
    b = registration.fit_rigid(source[1:], target[1:])
    np.testing.assert_allclose(a.translation_m, b.translation_m, atol=1e-10)


def test_fit_yaw_translation_keeps_z_axis_and_mean_height() -> None:
    rng = np.random.default_rng(5)
    yaw = np.radians(-140.0)
    rot = registration.yaw_rotation(yaw)
    t = np.array([120.0, -40.0, 7.5])
    source = rng.uniform(-50.0, 50.0, (40, 3))
    target = source @ rot.T + t
    # random reflection heights on the target side: a free 3D fit would tilt to follow
    # them, the levelled fit must only shift z by their mean
    noise = rng.normal(0.0, 0.3, 40)
    target[:, 2] += noise
    fit = registration.fit_yaw_translation(source, target)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(fit.translation_m[:2], t[:2], atol=1e-9)
    assert fit.translation_m[2] == pytest.approx(t[2] + noise.mean(), abs=1e-12)
    assert fit.rms_m < 1e-9  # horizontal RMS
    free = registration.fit_rigid(source, target)
    assert registration.rotation_angle_deg(free.rotation, rot) > 1e-3


def test_moments_fit_equals_direct_fit_batched() -> None:
    rng = np.random.default_rng(6)
    rot, t = _random_rigid(rng, 2)
    source = rng.normal(0.0, 20.0, (3, 30, 2))
    target = source @ rot.T + t + rng.normal(0.0, 0.3, source.shape)
    w = rng.uniform(0.5, 1.5, (3, 30))
    rots, trans = registration.rigid_2d_from_moments(
        w.sum(axis=1), np.einsum('bn,bni->bi', w, source), np.einsum('bn,bni->bi', w, target),
        np.einsum('bn,bni,bnj->bij', w, source, target))
    for b in range(3):
        fit = registration.fit_rigid(source[b], target[b], w[b])
        np.testing.assert_allclose(rots[b], fit.rotation, atol=1e-10)
        np.testing.assert_allclose(trans[b], fit.translation_m, atol=1e-8)


@pytest.mark.parametrize('deg', [0.0, 1e-6, 0.3, 45.0, 179.0, 180.0])
def test_rotation_angle_known_values(deg: float) -> None:
    axis = np.array([0.3, -0.5, 0.8])
    a = Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix()
    b = a @ Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    assert float(registration.rotation_angle_deg(a, b)) == pytest.approx(deg, abs=1e-9)


def test_pairwise_angles_symmetric_with_zero_diagonal() -> None:
    rots = np.array([registration.yaw_rotation(np.radians(d)) for d in (0.0, 2.0, 5.0)])
    angles = registration.pairwise_rotation_angles_deg(rots)
    np.testing.assert_allclose(angles, angles.T, atol=1e-12)
    np.testing.assert_allclose(np.diag(angles), 0.0, atol=1e-12)
    assert angles[0, 2] == pytest.approx(5.0)
    assert angles[1, 2] == pytest.approx(3.0)
