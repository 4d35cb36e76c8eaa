"""Stage 1: the moving-target filter."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from radar_calib_ros.config import MovingConfig
import pytest

from radar_calib_ros.core.moving import (
    filter_moving_targets, moving_threshold_mps, stationary_velocity_sigma)


def test_boundaries_are_inclusive_and_symmetric() -> None:
    cfg = MovingConfig(noise_factor=0.0, min_speed_kmh=0.1)
    threshold = 0.1 / 3.6
    below = np.nextafter(threshold, 0.0)
    v = np.array([0.0, below, threshold, -threshold, -below, 5.0, -5.0, np.nan, np.inf])
    expected = np.array([False, False, True, True, False, True, True, False, True])
    np.testing.assert_array_equal(filter_moving_targets(v, cfg), expected)


def test_zero_threshold_keeps_every_finite_target() -> None:
    v = np.array([0.0, -0.0, 1e-300, -3.0])
    assert filter_moving_targets(v, MovingConfig(noise_factor=0.0, min_speed_kmh=0.0)).all()


def test_input_not_modified_and_shape_kept() -> None:
    v = np.array([0.01, -0.5, 0.2])
    before = v.copy()
    mask = filter_moving_targets(v, MovingConfig(noise_factor=0.0, min_speed_kmh=1.0))
    np.testing.assert_array_equal(v, before)
    assert mask.dtype == bool and mask.shape == v.shape
    np.testing.assert_array_equal(mask, [False, True, False])


@settings(deadline=None, max_examples=100)
@given(st.lists(st.floats(-30.0, 30.0), min_size=1, max_size=50),
       st.floats(0.0, 50.0), st.floats(0.0, 50.0))
def test_monotone_in_threshold(velocities: list[float], a: float, b: float) -> None:
    low, high = min(a, b), max(a, b)
    v = np.array(velocities)
    kept_low = filter_moving_targets(v, MovingConfig(noise_factor=0.0, min_speed_kmh=low))
    kept_high = filter_moving_targets(v, MovingConfig(noise_factor=0.0, min_speed_kmh=high))
    assert not np.any(kept_high & ~kept_low)


def test_noise_floor_raises_the_threshold_above_doppler_noise() -> None:
    rng = np.random.default_rng(3)
    sigma = 0.08
    clutter = rng.normal(0.0, sigma, 20000)
    road_users = rng.uniform(2.0, 15.0, 2000) * rng.choice([-1.0, 1.0], 2000)
    v = np.concatenate([clutter, road_users])
    estimated = stationary_velocity_sigma(v)
    assert abs(estimated - sigma) < 0.1 * sigma
    cfg = MovingConfig(min_speed_kmh=0.1, noise_factor=3.0)
    assert moving_threshold_mps(v, cfg) == pytest.approx(3.0 * estimated)
    mask = filter_moving_targets(v, cfg)
    assert mask[:20000].mean() < 0.01          # clutter dropped
    assert mask[20000:].all()                  # road users kept
    paper = filter_moving_targets(v, MovingConfig(min_speed_kmh=0.1, noise_factor=0.0))
    assert paper[:20000].mean() > 0.7          # the paper's threshold alone keeps clutter


def test_quantised_doppler_keeps_the_paper_threshold() -> None:
    v = np.concatenate([np.zeros(5000), np.full(100, 0.05), np.full(100, -3.0)])
    cfg = MovingConfig(min_speed_kmh=0.1, noise_factor=3.0)
    assert moving_threshold_mps(v, cfg) == pytest.approx(0.1 / 3.6)
    assert filter_moving_targets(v, cfg).sum() == 200


def test_too_few_targets_near_zero_use_the_floor() -> None:
    v = np.array([0.2, -0.3, 5.0, 7.0])
    assert stationary_velocity_sigma(v) == 0.0
