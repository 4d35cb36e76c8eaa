"""Stage 1: the moving-target filter.

The radar stands still, so a target on a static object (facade, pole, parked car, road
surface) has a radial velocity of zero up to noise; everything the method tracks moves.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.config import MovingConfig
from radar_calib_ros.types import F64


def filter_moving_targets(radial_velocity_mps: F64, cfg: MovingConfig) -> NDArray[np.bool_]:
    """Mask of the targets that move: ``|v_r| >= min_speed_kmh / 3.6``.

    Parameters
    ----------
    radial_velocity_mps : ndarray of shape (n,)
        Radial velocity of each target [m/s] (either sign convention: only the magnitude is
        used).
    cfg : MovingConfig
        ``min_speed_kmh``, the paper's 0.1 km/h by default. The boundary is inclusive.

    Returns
    -------
    ndarray of shape (n,), bool
        True for moving targets. Non-finite velocities are never moving.

    References
    ----------
    method-paper.tex, section "Clustering and Association".
    """
    speed = np.abs(np.asarray(radial_velocity_mps, dtype=np.float64))
    # NaN compares False, so a target without a valid velocity is treated as clutter.
    return speed >= cfg.min_speed_kmh / 3.6
