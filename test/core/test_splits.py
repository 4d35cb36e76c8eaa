"""The exact best split of a series into two constant pieces."""
from __future__ import annotations

import numpy as np
import pytest

from radar_calib_ros.core._splits import two_piece_rss


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_two_piece_rss_is_that_of_every_split_by_brute_force(seed: int) -> None:
    values = np.random.default_rng(seed).normal(0.0, 1.0, 40) + np.repeat([0.0, 3.0], 20)
    brute = [((values[:k] - values[:k].mean()) ** 2).sum()
             + ((values[k:] - values[k:].mean()) ** 2).sum() for k in range(1, values.size)]
    np.testing.assert_allclose(two_piece_rss(values), brute, rtol=1e-9, atol=1e-9)
    assert int(np.argmin(two_piece_rss(values))) + 1 == 20
    assert two_piece_rss(values[:1]).size == 0
