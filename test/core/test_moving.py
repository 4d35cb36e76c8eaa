"""Stage 1: the moving-target filter."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from radar_calib_ros.config import MovingConfig
from radar_calib_ros.core.moving import filter_moving_targets


def test_boundaries_are_inclusive_and_symmetric() -> None:
    cfg = MovingConfig(min_speed_kmh=0.1)
    threshold = 0.1 / 3.6
    below = np.nextafter(threshold, 0.0)
    v = np.array([0.0, below, threshold, -threshold, -below, 5.0, -5.0, np.nan, np.inf])
    expected = np.array([False, False, True, True, False, True, True, False, True])
    np.testing.assert_array_equal(filter_moving_targets(v, cfg), expected)


def test_zero_threshold_keeps_every_finite_target() -> None:
    v = np.array([0.0, -0.0, 1e-300, -3.0])
    assert filter_moving_targets(v, MovingConfig(min_speed_kmh=0.0)).all()


def test_input_not_modified_and_shape_kept() -> None:
    v = np.array([0.01, -0.5, 0.2])
    before = v.copy()
    mask = filter_moving_targets(v, MovingConfig(min_speed_kmh=1.0))
    np.testing.assert_array_equal(v, before)
    assert mask.dtype == bool and mask.shape == v.shape
    np.testing.assert_array_equal(mask, [False, True, False])


@settings(deadline=None, max_examples=100)
@given(st.lists(st.floats(-30.0, 30.0), min_size=1, max_size=50),
       st.floats(0.0, 50.0), st.floats(0.0, 50.0))
def test_monotone_in_threshold(velocities: list[float], a: float, b: float) -> None:
    low, high = min(a, b), max(a, b)
    v = np.array(velocities)
    kept_low = filter_moving_targets(v, MovingConfig(min_speed_kmh=low))
    kept_high = filter_moving_targets(v, MovingConfig(min_speed_kmh=high))
    assert not np.any(kept_high & ~kept_low)
