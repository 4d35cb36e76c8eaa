"""Angle helpers shared by the tracking and refinement stages.

Headings live on the circle: a plain difference or arithmetic mean of 3.1 rad and -3.1 rad
is wrong by a full turn. Every function here works elementwise on arrays of any shape and
returns angles in [-pi, pi).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def wrap_angle(angle_rad: ArrayLike) -> F64:
    """Wrap angles to [-pi, pi).

    Parameters
    ----------
    angle_rad : array_like
        Angles of any shape [rad].

    Returns
    -------
    ndarray
        Same shape, each angle shifted by a multiple of 2 pi into [-pi, pi).
    """
    wrapped = np.mod(np.asarray(angle_rad, dtype=np.float64) + np.pi, 2.0 * np.pi) - np.pi
    # np.mod can round a value just below 2 pi up to exactly 2 pi, which would give +pi.
    return np.where(wrapped >= np.pi, -np.pi, wrapped)


def angle_residual(a_rad: ArrayLike, b_rad: ArrayLike) -> F64:
    """The shortest signed angle from ``b`` to ``a``: ``wrap(a - b)`` in [-pi, pi)."""
    return wrap_angle(np.asarray(a_rad, dtype=np.float64) - np.asarray(b_rad, dtype=np.float64))


def circular_mean(angles_rad: ArrayLike, weights: ArrayLike | None = None,
                  axis: int = -1) -> F64:
    """Weighted mean direction: atan2 of the weighted sums of sines and cosines.

    Parameters
    ----------
    angles_rad : array_like
        Angles [rad].
    weights : array_like, optional
        Broadcastable to ``angles_rad``; may contain negative entries (the unscented
        transform's central weight can be negative). Default: equal weights.
    axis : int, default=-1
        Axis to average over.

    Returns
    -------
    ndarray
        The mean direction in [-pi, pi); where the weighted resultant vanishes (directions
        that cancel) the result is the atan2 of zeros, i.e. 0.
    """
    angles = np.asarray(angles_rad, dtype=np.float64)
    if weights is None:
        s, c = np.sin(angles).sum(axis=axis), np.cos(angles).sum(axis=axis)
    else:
        w = np.asarray(weights, dtype=np.float64)
        s, c = (w * np.sin(angles)).sum(axis=axis), (w * np.cos(angles)).sum(axis=axis)
    return wrap_angle(np.arctan2(s, c))


def interp_angle(tq: F64, t: F64, angle: F64) -> F64:
    """Interpolate an angle series (samples ``angle`` at increasing times ``t``) at ``tq`` on
    the circle (unwrapped first, so a heading crossing +-pi does not swing through zero);
    result wrapped to [-pi, pi)."""
    unwrapped = np.unwrap(angle)
    return (np.interp(tq, t, unwrapped) + np.pi) % (2.0 * np.pi) - np.pi
