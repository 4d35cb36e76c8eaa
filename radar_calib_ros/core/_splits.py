"""The best split of an ordered series into two constant pieces, exactly, in one pass."""
from __future__ import annotations

import numpy as np

from radar_calib_ros.types import F64


def two_piece_rss(values: F64) -> F64:
    """(n - 1,) the residual sum of squares of ``values`` (n,) about two constant pieces,
    the first ``k`` of them and the rest, for k = 1 .. n - 1 (by cumulative sums: the
    1-D 2-means of sorted values, or a step in a series). Centred first, and NaN rather
    than a warning where the numbers overflow (corrupted stamps)."""
    n = values.size
    if n < 2:
        return np.zeros(0)
    with np.errstate(all='ignore'):
        centred = values - values.mean()
        cum, cum_sq = np.cumsum(centred), np.cumsum(centred ** 2)
        k = np.arange(1, n)
        head = cum_sq[:-1] - cum[:-1] ** 2 / k
        tail = (cum_sq[-1] - cum_sq[:-1]) - (cum[-1] - cum[:-1]) ** 2 / (n - k)
        return head + tail
