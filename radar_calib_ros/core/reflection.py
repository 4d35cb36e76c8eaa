"""The reflection profile: where on the calibration vehicle its radar targets lie, on average,
as a smooth function of the aspect angle.

Why a profile and not a face or box model: real cars reflect mostly from inside their
footprint (wheels, wheel houses, underbody, engine block, seats through the windows) plus
mirrors and multi-bounce returns that appear late along the line of sight. A model that puts
targets on the faces that face the radar is biased by decimetres on such data, and a model
fitted to one simulator's scatterers would be biased on the next car. What is physically
stable is weaker and is all we assume: the MEAN offset of the targets in the vehicle frame
depends (smoothly) on which side of the car faces the radar, i.e. on the aspect angle, and
the car is left-right symmetric. The profile is estimated from the data jointly with the
extrinsics (``core/refine.py``); aspect-only dependence is what makes it separable from the
radar's position once the same aspect is seen from different bearings.

Conventions
-----------
Aspect angle ``alpha`` (rad): the direction from the vehicle towards the radar, in the
vehicle frame (x forward, y left): 0 = the radar sees the front, +pi/2 = it sees the left
side, pi = the rear.

Coefficients of a profile of order K (``refine.profile_harmonics``), shape (2K + 4,)::

    [a_0 .. a_K,  b_1 .. b_K,  c_0,  s_x,  s_y]
    m_x(alpha) = a_0 + sum_k a_k cos(k alpha) + s_x S(cos alpha)   (even: mirror symmetry)
    m_y(alpha) =       sum_k b_k sin(k alpha) + s_y S(sin alpha)   (odd: mirror symmetry)
    m_z        = c_0                                               (one mean height)

in metres, vehicle frame, relative to the localisation reference point; S(u) =
tanh(u / sin(``STEP_WIDTH_DEG``)), a step smoothed over a few degrees.

Why the steps: the reflections on the faces that face the radar (the bumper corner nearest
it, the near side) switch from the front to the rear as the car passes broadside, and from
its left to its right as it passes head-on or tail-on. A Fourier series of order K smooths
such a switch over about 180/K degrees, and in doing so ties the offsets on either side of
it together: the near side's lateral offset is then pinned by how the series rings near
head-on, where it says nothing. That offset is exactly what trades against the radar's
position along the bisector of the headings driven when each side of the car is seen from
one heading only (a radar at a junction's corner looking across it, lanes in four
directions): a nineteenth probe whose cars reflect at the nearest point of their outline
had 22 of 30 recordings 0.2-0.8 m off along the boresight at a reported 0.09-0.3 m; with
the steps 0 of 30 outside two sigma, the error halved and the uncertainty shows what the
views cannot tell. (On our own simulator the horizontal medians moved 7.3 / 6.6 / 7.4 ->
5.2 / 5.5 / 8.8 cm, interior / mixed / skin.) ``refine.profile_steps`` false holds both at
zero.

The mirror symmetry (a car seen at aspect -alpha is the mirror image in y of the car seen
at alpha) is the gauge: it removes the sine terms of m_x and the cosine terms of m_y, which
would otherwise absorb a radar displacement across the line of sight. The one mode it does not
remove, a pure depth along the line of sight (a_1 = b_1), trades off against the radar's
position along its boresight when the vehicle is seen from one bearing only; the refinement
reports that uncertainty instead of assuming it away.

The height is one number, not a function of the aspect: the lanes towards and away from a
radar lie on either side of it, so a front/rear height difference would be confounded with
the radar's roll (measured on the simulator: 0.5-0.8 deg of roll error with cos(alpha)
height terms, 0.02-0.17 deg without).
"""
from __future__ import annotations

import numpy as np

from radar_calib_ros.types import F64


#: Width of the steps' smoothing [deg]: about the angle half a car subtends at 25-30 m, over
#: which a passing car's near face turns from its front to its side.
STEP_WIDTH_DEG = 4.0


def n_coefficients(harmonics: int) -> int:
    """Number of profile coefficients of order ``harmonics``: 2K + 4."""
    return 2 * harmonics + 4


def profile_basis(aspect_rad: F64, harmonics: int, derivative: bool = True
                  ) -> tuple[F64, F64 | None]:
    """Basis of the symmetric profile and its derivative over the aspect angle.

    Parameters
    ----------
    aspect_rad : ndarray of shape (n,)
    harmonics : int
        Fourier order K >= 0.
    derivative : bool
        False leaves the derivative out (None): a fit's trial steps need only the values.

    Returns
    -------
    basis : ndarray of shape (n, 3, 2K + 4)
        ``basis[i] @ coefficients`` is the mean offset (x, y, z) at ``aspect_rad[i]``.
    d_basis : ndarray of shape (n, 3, 2K + 4), or None
        Derivative of ``basis`` over the aspect angle [1/rad].
    """
    aspect = np.asarray(aspect_rad, float)
    n, k_max = aspect.shape[0], harmonics
    k = np.arange(1, k_max + 1, dtype=float)
    kal = aspect[:, None] * k[None, :]
    cos_k, sin_k = np.cos(kal), np.sin(kal)
    basis = np.zeros((n, 3, n_coefficients(k_max)))
    ix, iy, iz = 0, k_max + 1, 2 * k_max + 1
    basis[:, 0, ix] = 1.0
    basis[:, 0, ix + 1:iy] = cos_k
    basis[:, 1, iy:iz] = sin_k
    basis[:, 2, iz] = 1.0
    width = np.sin(np.radians(STEP_WIDTH_DEG))
    ca, sa = np.cos(aspect), np.sin(aspect)
    step_x, step_y = np.tanh(ca / width), np.tanh(sa / width)
    basis[:, 0, iz + 1] = step_x
    basis[:, 1, iz + 2] = step_y
    if not derivative:
        return basis, None
    d_basis = np.zeros_like(basis)
    d_basis[:, 0, ix + 1:iy] = -k * sin_k
    d_basis[:, 1, iy:iz] = k * cos_k
    d_basis[:, 0, iz + 1] = -sa / width * (1.0 - step_x ** 2)
    d_basis[:, 1, iz + 2] = ca / width * (1.0 - step_y ** 2)
    return basis, d_basis


def evaluate_profile(coefficients: F64, aspect_rad: F64) -> F64:
    """Mean target offset (n, 3) in the vehicle frame [m] at the given aspect angles.

    The order is inferred from the coefficient count (2K + 4), so a stored
    ``Refinement.reflection_profile`` can be drawn without the config.
    """
    coefficients = np.asarray(coefficients, float)
    harmonics = (coefficients.shape[0] - 4) // 2
    if coefficients.shape[0] < 4 or n_coefficients(harmonics) != coefficients.shape[0]:
        raise ValueError(f'a reflection profile has 2K + 4 coefficients, got '
                         f'{coefficients.shape[0]}')
    basis, _ = profile_basis(np.atleast_1d(np.asarray(aspect_rad, float)), harmonics)
    return basis @ coefficients


def coefficient_index(harmonics: int) -> dict[str, int]:
    """Index of the constant terms (``a0``, ``c0``), of the depth mode (``a1``, ``b1``;
    -1 when K = 0) and of the steps (``sx``, ``sy``) in the coefficient vector."""
    return {'a0': 0, 'a1': 1 if harmonics else -1, 'b1': harmonics + 1 if harmonics else -1,
            'c0': 2 * harmonics + 1, 'sx': 2 * harmonics + 2, 'sy': 2 * harmonics + 3}


def aspect_angles(line_of_sight_world: F64, yaw_rad: F64) -> F64:
    """(n,) aspect angle [rad] of each line of sight (radar -> target, world (n, >=2))
    seen from a vehicle with heading ``yaw_rad`` (n,)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    lx = c * line_of_sight_world[:, 0] + s * line_of_sight_world[:, 1]
    ly = -s * line_of_sight_world[:, 0] + c * line_of_sight_world[:, 1]
    return np.arctan2(-ly, -lx)
