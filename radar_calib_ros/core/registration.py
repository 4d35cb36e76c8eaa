"""Closed-form weighted rigid registration (Kabsch/Umeyama without scale), 2D and 3D.

Shared by the hypothesis stage (one transform per track and one over the accepted cluster),
the paper's refinement (the closest-target re-estimate) and the quality bootstrap. Every
fit goes through the weighted moments of the correspondences, so a bootstrap over passes
can re-fit from per-pass sums without touching the correspondences again.

References
----------
S. Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", IEEE TPAMI 13(4), 1991 (the reflection-safe SVD solution used here).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar_calib_ros.types import F64


@dataclass(frozen=True, slots=True)
class RigidFit:
    """A rigid transform ``target ~ rotation @ source + translation_m`` and its residual.

    rotation : (d, d); translation_m : (d,); rms_m : weighted RMS of the residuals over the
    fitted dimensions (horizontal only for :func:`fit_yaw_translation`).
    """

    rotation: F64
    translation_m: F64
    rms_m: float


def rotation_from_cross_covariance(cross: F64) -> F64:
    """The Kabsch solution: the proper rotation(s) best aligning centred source to target.

    Parameters
    ----------
    cross : ndarray of shape (..., d, d)
        Weighted cross-covariance ``H = sum_i w_i (s_i - s_bar)(t_i - t_bar)^T``.

    Returns
    -------
    ndarray of shape (..., d, d)
        R with det(R) = +1 that minimises ``sum_i w_i |R (s_i - s_bar) - (t_i - t_bar)|^2``.
    """
    u, _, vt = np.linalg.svd(cross)
    v = np.swapaxes(vt, -1, -2)
    ut = np.swapaxes(u, -1, -2)
    # flip the axis of the smallest singular value when V U^T is a reflection (Umeyama)
    d = np.sign(np.linalg.det(v @ ut))
    d = np.where(d == 0.0, 1.0, d)
    scale = np.ones(cross.shape[:-1])
    scale[..., -1] = d
    rotation: F64 = (v * scale[..., None, :]) @ ut
    return rotation


def fit_rigid(source: F64, target: F64, weights: F64 | None = None) -> RigidFit:
    """Weighted least-squares rigid transform (no scale) from source to target points.

    Parameters
    ----------
    source, target : ndarray of shape (n, d)
        Corresponding points, d = 2 or 3, n >= d (non-degenerate).
    weights : ndarray of shape (n,), optional
        Non-negative weights; uniform when omitted.

    Returns
    -------
    RigidFit
        ``target ~ R @ source + t`` with det(R) = +1.
    """
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    w = np.ones(source.shape[0]) if weights is None else np.asarray(weights, np.float64)
    w_sum = w.sum()
    source_mean = w @ source / w_sum
    target_mean = w @ target / w_sum
    # centre before forming moments: world coordinates are hundreds of metres, and
    # subtracting large raw moments would lose the ~1e-9 precision the tests ask for
    s = source - source_mean
    t = target - target_mean
    rotation = rotation_from_cross_covariance((s * w[:, None]).T @ t)
    translation = target_mean - rotation @ source_mean
    residual = s @ rotation.T - t
    rms = float(np.sqrt(w @ np.einsum('ij,ij->i', residual, residual) / w_sum))
    return RigidFit(rotation, translation, rms)


def fit_yaw_translation(source: F64, target: F64, weights: F64 | None = None) -> RigidFit:
    """Rotation about z plus a 3D translation, for levelled data.

    After levelling by the ground plane (R_αβ) the sensor and world z axes are parallel, so
    only yaw, x, y and a height offset remain. A free 3D Kabsch fit would also tilt the
    frame to explain the random height at which the car reflects (and the near-planar
    tracks leave roll and pitch barely observable): it would undo the ground plane's roll
    and pitch with noise. So: a 2D rigid fit on x, y and the weighted mean z difference.

    Parameters
    ----------
    source, target : ndarray of shape (n, 3)
    weights : ndarray of shape (n,), optional

    Returns
    -------
    RigidFit
        rotation (3, 3) about z, translation_m (3,), rms_m the horizontal RMS.
    """
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    w = np.ones(source.shape[0]) if weights is None else np.asarray(weights, np.float64)
    planar = fit_rigid(source[:, :2], target[:, :2], w)
    rotation = np.eye(3)
    rotation[:2, :2] = planar.rotation
    dz = float(w @ (target[:, 2] - source[:, 2]) / w.sum())
    translation = np.array([planar.translation_m[0], planar.translation_m[1], dz])
    return RigidFit(rotation, translation, planar.rms_m)


def rigid_2d_from_moments(w_sum: F64, source_sum: F64, target_sum: F64,
                          cross_sum: F64) -> tuple[F64, F64]:
    """Batched 2D :func:`fit_rigid` from weighted sums (a bootstrap over passes re-fits from
    per-pass sums instead of resampling correspondences).

    Parameters
    ----------
    w_sum : ndarray of shape (b,)
        Sum of weights.
    source_sum, target_sum : ndarray of shape (b, 2)
        Sums of w * s and w * t.
    cross_sum : ndarray of shape (b, 2, 2)
        Sum of w * s t^T. Centre source and target on a common reference first, so the
        subtraction of the mean product below does not cancel large numbers.

    Returns
    -------
    rotations : ndarray of shape (b, 2, 2)
    translations : ndarray of shape (b, 2)
    """
    s_mean = source_sum / w_sum[:, None]
    t_mean = target_sum / w_sum[:, None]
    cross = cross_sum - w_sum[:, None, None] * s_mean[:, :, None] * t_mean[:, None, :]
    rotations = rotation_from_cross_covariance(cross)
    translations = t_mean - np.einsum('bij,bj->bi', rotations, s_mean)
    return rotations, translations


def yaw_rotation(yaw_rad: float) -> F64:
    """(3, 3) rotation about z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_angle_deg(rot_a: F64, rot_b: F64) -> F64:
    """Angle of R_a^T R_b [deg] for (..., 3, 3) rotations, broadcast over leading axes.

    Uses atan2 of the rotation's sine and cosine rather than arccos of the trace alone,
    which loses precision below ~1e-4 rad.
    """
    rel = np.swapaxes(rot_a, -1, -2) @ rot_b
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
                     rel[..., 1, 0] - rel[..., 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(axis, axis=-1)
    angle: F64 = np.degrees(np.arctan2(sin, cos))
    return angle


def pairwise_rotation_angles_deg(rotations: F64) -> F64:
    """(h, h) angle of R_j^T R_i between every pair of rotations (h, 3, 3) [deg]."""
    return rotation_angle_deg(rotations[None, :, :, :], rotations[:, None, :, :])
