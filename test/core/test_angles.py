"""Property tests of the angle helpers shared by tracking and refinement."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from radar_calib_ros.core._angles import angle_residual, circular_mean, wrap_angle

finite_angles = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)


@settings(deadline=None, max_examples=300)
@given(finite_angles)
def test_wrap_is_in_range_and_a_whole_number_of_turns_away(angle: float) -> None:
    wrapped = float(wrap_angle(angle))
    assert -math.pi <= wrapped < math.pi
    turns = (angle - wrapped) / (2.0 * math.pi)
    assert abs(turns - round(turns)) < 1e-9 * max(1.0, abs(angle))


def test_wrap_boundaries() -> None:
    assert float(wrap_angle(math.pi)) == -math.pi
    assert float(wrap_angle(-math.pi)) == -math.pi
    assert float(wrap_angle(0.0)) == 0.0
    # just under a full turn must not round up to +pi
    assert -math.pi <= float(wrap_angle(np.nextafter(math.pi, 0.0) + 2 * math.pi)) < math.pi
    np.testing.assert_allclose(wrap_angle(np.array([3 * math.pi / 2, -3 * math.pi / 2])),
                               [-math.pi / 2, math.pi / 2])


@settings(deadline=None, max_examples=300)
@given(finite_angles, finite_angles)
def test_residual_is_shortest_signed_difference(a: float, b: float) -> None:
    d = float(angle_residual(a, b))
    assert -math.pi <= d < math.pi
    # b + d is a up to whole turns
    assert abs(math.sin(b + d) - math.sin(a)) < 1e-6
    assert abs(math.cos(b + d) - math.cos(a)) < 1e-6
    # no shorter way round
    assert abs(d) <= math.pi


@settings(deadline=None, max_examples=200)
@given(st.floats(min_value=-math.pi, max_value=math.pi),
       st.lists(st.floats(min_value=-1.4, max_value=1.4), min_size=1, max_size=20),
       st.floats(min_value=-50.0, max_value=50.0))
def test_circular_mean_of_spread_about_a_direction(centre: float, offsets: list[float],
                                                   shift: float) -> None:
    offsets_arr = np.array(offsets)
    symmetric = np.concatenate([offsets_arr, -offsets_arr])
    # a symmetric spread (< pi/2 each side) averages to its centre, across the +-pi seam
    mean = float(circular_mean(wrap_angle(centre + symmetric)))
    assert abs(float(angle_residual(mean, centre))) < 1e-9
    # equivariant under rotation
    shifted = float(circular_mean(centre + offsets_arr + shift))
    unshifted = float(circular_mean(centre + offsets_arr))
    assert abs(float(angle_residual(shifted, unshifted + shift))) < 1e-9


def test_circular_mean_weights_and_axis() -> None:
    angles = np.array([[math.pi - 0.1, -math.pi + 0.1], [0.2, 0.4]])
    np.testing.assert_allclose(
        angle_residual(circular_mean(angles, axis=1), [-math.pi, 0.3]), [0.0, 0.0], atol=1e-12)
    # weights, a negative one included (the unscented transform's central weight may be)
    weighted = circular_mean(np.array([0.0, 1.0, 2.0]), weights=np.array([-0.5, 1.0, 0.5]))
    s = -0.5 * 0 + math.sin(1.0) + 0.5 * math.sin(2.0)
    c = -0.5 + math.cos(1.0) + 0.5 * math.cos(2.0)
    assert abs(float(weighted) - math.atan2(s, c)) < 1e-12
