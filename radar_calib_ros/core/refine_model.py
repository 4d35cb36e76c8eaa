"""The model of the final refinement (stage 8, ``core/refine.py``): the vehicle's poses at
float times, the residuals and Jacobian of the joint fit, the solver, and the priors.

The vehicle's track is interpolated at each target's radar stamp plus the clock offset
(``_Poses``, ``_Times``; a drifting or stepped radar clock, ``ClockDrift``, moves those
stamps); ``_Model`` predicts every target's position and radial velocity from the rotation,
translation, clock offset and reflection profile; ``_solve`` fits it by a robust
Levenberg-Marquardt; ``_priors`` and ``_anchor`` state what the fit assumes where the data
say nothing. Separate from the stage because it is the mathematics of one fit, which the
stage runs many times (gate rounds, the model check, the tilt probes, the clock refits), and
which the target selection, the noise estimates and the covariance terms all evaluate; it
depends on none of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import reflection
from radar_calib_ros.core.vehicle import box_limits
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, I64, Extrinsics, VehicleTrack


#: Robust loss scale in whitened units: soft-L1 is quadratic within about one sigma and
#: linear beyond, so wheel micro-Doppler (several m/s) and stray targets of other cars keep a
#: bounded influence while the Gaussian core keeps most of its efficiency.
_LOSS_SCALE = 1.0
#: Width of the prior around the starting altitude [m]: none to speak of. The elevations
#: and the radial velocities' dip fix the radar's height above the vehicle's targets, and
#: the reflection-height prior says where those lie; the paper's stages know no more (their
#: altitude rests on the ground plane, and a 2-D radar's starts at the vehicle's, metres
#: below the pole). A half-metre prior there leaked into what only the reflection-height
#: prior should decide: on a 6 % road the start was 3.5 m high, and pulled the result
#: 50 cm up (an independent recording, sigma 21 cm).
_ALTITUDE_START_SIGMA_M = 30.0
#: Width of the prior around the starting translation [m] (see ``_priors``).
_START_SIGMA_M = 0.5


# --- vehicle poses at float times -------------------------------------------------------

@dataclass(frozen=True, slots=True)
class _Poses:
    """The vehicle track as float-time arrays for repeated interpolation at t + tau."""

    t_s: F64
    positions_m: F64
    yaw_unwrapped: F64
    velocities_mps: F64
    yaw_rate_rps: F64
    accelerations_mps2: F64
    yaw_accelerations_rps2: F64
    max_gap_s: float
    grades: F64

    @classmethod
    def from_track(cls, vehicle: VehicleTrack, t0_ns: int, max_gap_s: float,
                   fix_sigma_m: tuple[float, float] | None = None) -> _Poses:
        t = (vehicle.stamps_ns - t0_ns) * 1e-9
        vel = np.asarray(vehicle.velocities_mps, float)
        # Acceleration only enters the Jacobian of the clock offset (dv_r/dtau): a central
        # difference over +-0.25 s is ample.
        acc = np.column_stack([_central_difference(t, vel[:, i], 0.25) for i in range(3)])
        rate = np.asarray(vehicle.yaw_rate_rps, float)
        positions = np.asarray(vehicle.positions_m, float)
        return cls(t, positions, np.unwrap(vehicle.yaw_rad), vel, rate, acc,
                   _central_difference(t, rate, 0.25), max_gap_s,
                   _road_grades(positions, np.asarray(vehicle.yaw_rad, float), fix_sigma_m))

    def grade_at(self, t_s: F64) -> F64:
        """(n,) the road's grade along the vehicle's heading at t_s (see ``_road_grades``)."""
        return np.interp(t_s, self.t_s, self.grades)

    def at(self, t_s: F64) -> tuple[F64, F64, F64, F64, F64]:
        """Position (n, 3), yaw (n,), velocity (n, 3), yaw rate (n,), and the time
        derivatives of velocity and yaw rate (n, 4: acceleration x, y, z, yaw
        acceleration)."""
        tv = self.t_s
        pos = np.column_stack([np.interp(t_s, tv, self.positions_m[:, i]) for i in range(3)])
        vel = np.column_stack([np.interp(t_s, tv, self.velocities_mps[:, i])
                               for i in range(3)])
        acc = np.column_stack([np.interp(t_s, tv, self.accelerations_mps2[:, i])
                               for i in range(3)]
                              + [np.interp(t_s, tv, self.yaw_accelerations_rps2)])
        yaw = np.interp(t_s, tv, self.yaw_unwrapped)
        rate = np.interp(t_s, tv, self.yaw_rate_rps)
        return pos, yaw, vel, rate, acc

    def valid(self, t_s: F64) -> np.ndarray:
        """(n,) True inside the pose stream and away from gaps longer than max_gap_s."""
        tv = self.t_s
        upper = np.clip(np.searchsorted(tv, t_s, side='left'), 1, tv.size - 1)
        gap = tv[upper] - tv[upper - 1]
        return (t_s >= tv[0]) & (t_s <= tv[-1]) & (gap <= self.max_gap_s)


#: Half the stretch of road a grade is measured over [m], the fixes' largest vertical
#: sigma that gives one [m] (RTK's 2-5 cm: 0.3 % over 10 m; a standalone fix's metres would
#: invent grades), and the steepest grade believed (a road's; more is the altitude's noise).
_GRADE_HALF_PATH_M = 5.0
_GRADE_FIX_SIGMA_M = 0.1
_GRADE_MAX = 0.15


def _road_grades(positions: F64, yaw: F64, fix_sigma_m: tuple[float, float] | None) -> F64:
    """(n,) the road's grade along the vehicle's heading (rise per metre forward), from the
    fixes' altitude over +-``_GRADE_HALF_PATH_M`` of the path; zeros where the fixes do not
    declare a vertical sigma of at most ``_GRADE_FIX_SIGMA_M``.

    Why: a car on a grade is pitched with it, so what it shows the radar is raised by the
    grade times its distance ahead of the reference point: the front of a car climbing
    towards a radar sits higher, the rear of one climbing away lower. On a road along the
    line of sight the two directions drive on either side of the radar, and that height
    difference was fitted as roll (0.6-0.9 deg on an independent 6 % road, with 20-45 cm
    across the boresight).
    """
    n = positions.shape[0]
    if n < 2 or fix_sigma_m is None or not fix_sigma_m[1] <= _GRADE_FIX_SIGMA_M:
        return np.zeros(n)
    step = np.hypot(*np.diff(positions[:, :2], axis=0).T)
    path = np.concatenate([[0.0], np.cumsum(step)])
    lo = np.clip(np.searchsorted(path, path - _GRADE_HALF_PATH_M, side='left'), 0, n - 1)
    hi = np.clip(np.searchsorted(path, path + _GRADE_HALF_PATH_M, side='right') - 1, 0, n - 1)
    d = positions[hi] - positions[lo]
    # the climb per metre along the heading: a reversing car climbs backwards; at the ends
    # of the drive the stretch is one-sided, and shorter than 2.5 m says nothing
    forward = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
    enough = np.abs(forward) >= 0.5 * _GRADE_HALF_PATH_M
    grade = np.where(enough, d[:, 2] / np.where(enough, forward, 1.0), 0.0)
    return np.clip(grade, -_GRADE_MAX, _GRADE_MAX)


def _central_difference(t: F64, x: F64, half_span_s: float) -> F64:
    if t.size < 2:
        return np.zeros_like(x)
    lo = np.searchsorted(t, t - half_span_s, side='left')
    hi = np.searchsorted(t, t + half_span_s, side='right') - 1
    idx = np.arange(t.size)
    lo = np.minimum(lo, np.maximum(idx - 1, 0))
    hi = np.maximum(hi, np.minimum(idx + 1, t.size - 1))
    dt = t[hi] - t[lo]
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(dt > 0, (x[hi] - x[lo]) / np.where(dt > 0, dt, 1.0), 0.0)


def _small_unique(values: I64, upper: int) -> tuple[I64, I64]:
    """``np.unique(values, return_inverse=True)`` of integers in ``0 .. upper - 1`` (frame
    numbers) by counting instead of sorting: the same arrays, without a sort of millions of
    targets (2.6 million moving targets of an imaging radar, twice per fit)."""
    present = np.bincount(values, minlength=upper) > 0
    rank = np.cumsum(present) - 1
    return np.flatnonzero(present), rank[values]


@dataclass(frozen=True, slots=True)
class _Times:
    """Target times through their frames: every target of a frame shares its stamp, so the
    poses are interpolated once per frame and gathered (ten targets a frame: ten times
    fewer interpolations).

    frame_t : (f,) radar stamp + ``sync.time_offset`` of each distinct frame, seconds since
    the first pose; inverse : (n,) frame of each target.
    """

    frame_t: F64
    inverse: I64

    @classmethod
    def of(cls, recording: Recording, index: I64, sync_offset_s: float, t0_ns: int,
           drift: ClockDrift | None = None) -> _Times:
        frames, inverse = _small_unique(recording.targets.frame_index[index],
                                        recording.frame_stamps_ns.size)
        frame_t = (recording.frame_stamps_ns[frames] - t0_ns) * 1e-9 + sync_offset_s
        if drift is not None:
            frame_t = frame_t + drift.offset_change_s(frame_t)
        return cls(frame_t, inverse.ravel())

    @property
    def t_s(self) -> F64:
        """(n,) time of each target."""
        return self.frame_t[self.inverse]

    def subset(self, mask: np.ndarray) -> _Times:
        used, inverse = _small_unique(self.inverse[mask], self.frame_t.size)
        return _Times(self.frame_t[used], inverse)

    def poses(self, poses: _Poses, offset_s: float) -> tuple[F64, F64, F64, F64, F64]:
        """Per-target pose quantities (as ``_Poses.at``) at time + offset."""
        return tuple(a[self.inverse] for a in poses.at(self.frame_t + offset_s))  # type: ignore

    def valid(self, poses: _Poses, offset_s: float) -> np.ndarray:
        return poses.valid(self.frame_t + offset_s)[self.inverse]


@dataclass(frozen=True, slots=True)
class ClockDrift:
    """A radar clock running at its own rate against the poses', or one that stepped: the
    offset at radar time t (seconds since the first pose) is tau + rate * (t - reference_s)
    + step_s * ([t >= step_at_s] - [reference_s >= step_at_s]), tau the fitted offset at
    ``reference_s`` (for a drift the middle of the radar's frames, for a step a time on
    the side with the more passes' information)."""

    rate: float
    reference_s: float
    sigma: float
    step_s: float = 0.0
    step_at_s: float = math.inf

    @property
    def size(self) -> float:
        """How large it is, in its own unit (the step [s], else the rate), for telling when
        what is left of it no longer matters."""
        return abs(self.step_s) if self.step_s else abs(self.rate)

    def plus(self, more: ClockDrift) -> ClockDrift:
        """This clock model with ``more`` of the same kind (found after it) added."""
        if self.step_s:
            return ClockDrift(0.0, self.reference_s, more.sigma, self.step_s + more.step_s,
                              self.step_at_s)
        return ClockDrift(self.rate + more.rate, more.reference_s, more.sigma)

    def offset_change_s(self, t_s: F64) -> F64:
        """(n,) the offset at radar times ``t_s`` minus the offset at ``reference_s``."""
        change = self.rate * (t_s - self.reference_s)
        if self.step_s:
            change = change + self.step_s * (
                (t_s >= self.step_at_s).astype(float) - float(self.reference_s >= self.step_at_s))
        return change


def _vehicle_poses(recording: Recording, index: I64, config: CalibConfig,
                   drift: ClockDrift | None = None) -> tuple[_Poses, _Times]:
    """The vehicle's pose stream (time from its first pose) and the times of the targets
    ``index`` on it."""
    t0_ns = int(recording.vehicle.stamps_ns[0])
    poses = _Poses.from_track(recording.vehicle, t0_ns, config.sync.max_pose_gap,
                              recording.fix_sigma_m)
    return poses, _Times.of(recording, index, config.sync.time_offset, t0_ns, drift)


# --- the model --------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class _Selected:
    """The targets of one gate round and what stays fixed while fitting them."""

    index: I64             # into recording.targets
    sensor_m: F64          # (n, 3) sensor-frame positions
    times: _Times          # radar stamp + sync.time_offset, seconds since t0
    v_mps: F64             # (n,) measured radial velocity (positive = moving away)
    sqrt_weight: F64       # (n,) square root of the information weight
    pass_id: I64           # (n,) 0..G-1
    whiten: F64            # (n, 3, 3) inverse Cholesky factor of the position covariance
    sigma_v: F64           # (n,) radial-velocity sigma [m/s]
    vertical_ok: np.ndarray  # (n,) the target's height is used (vehicle inside the view)
    grade: F64             # (n,) the road's grade along the vehicle's heading


class _Model:
    """Residuals and analytic Jacobian of the joint fit around a base estimate.

    Parameters x = [w (3), dt (3), tau (1, if estimated), profile (2K + 2), its range
    slopes, azimuth scale (1, if fitted)]: R = exp([w]) R0 (left perturbation, world frame),
    t = t0 + dt, clock offset tau (absolute), the radar's azimuths taken as
    measured / (1 + scale).
    """

    def __init__(self, data: _Selected, poses: _Poses, rotation0: F64, translation0: F64,
                 tau_fixed: float | None, harmonics: int, velocity_sigma: float,
                 prior_mean: F64, prior_sigma: F64, centre_x_m: float,
                 range_terms: str = 'depth', azimuth_scale: bool = False) -> None:
        self.data = data
        self.xc = centre_x_m
        self.poses = poses
        self.r0 = rotation0
        self.t0 = translation0
        self.tau_fixed = tau_fixed
        self.k = harmonics
        self.sv = velocity_sigma
        self.i_prof = 6 if tau_fixed is not None else 7
        # the profile plus its range slopes (see ``geometry``)
        self.range_terms = range_terms
        self.n_range = n_range_terms(harmonics, range_terms)
        # the end of the profile and its slopes; the azimuth scale, if fitted, after it
        self.i_end = self.i_prof + reflection.n_coefficients(harmonics) + self.n_range
        self.n_par = self.i_end + (1 if azimuth_scale else 0)
        self.r_ref = float(np.median(np.linalg.norm(data.sensor_m[:, :2], axis=1)))
        # the road's grade of each frame (the same for all its targets)
        self.frame_grade = np.zeros(data.times.frame_t.size)
        self.frame_grade[data.times.inverse] = data.grade
        self.prior_mean = prior_mean      # (n_par,) NaN = no prior
        self.prior_sigma = prior_sigma

    def unpack(self, x: F64) -> tuple[F64, F64, float, F64]:
        rot = Rotation.from_rotvec(x[:3]).as_matrix() @ self.r0
        tau = float(x[6]) if self.tau_fixed is None else self.tau_fixed
        return rot, self.t0 + x[3:6], tau, x[self.i_prof:]

    def geometry(self, x: F64, jacobian: bool = True) -> dict[str, F64]:
        """Per-target quantities at x (shared by residuals, Jacobian and diagnostics).

        ``jacobian=False`` leaves out the derivatives over the aspect ('d_basis') and the
        range ('range_basis'): the fit's trial steps need only the residuals, and the
        derivatives were a third of the work of 30 000 targets (the same numbers).
        """
        rot, trans, tau, _ = self.unpack(x)
        prof = x[self.i_prof:self.i_end]
        d = self.data
        sensor = d.sensor_m
        if self.n_par > self.i_end:
            # The radar's own angle calibration: an azimuth scale error (1 % is 0.45 deg at
            # 45 deg, within datasheet accuracies) bends every target across the line of
            # sight in proportion to its azimuth, which a radar shifted along its boresight
            # mimics at one range (k r): unmodelled, a thirteenth probe's 1 % put the radar
            # 0.35-0.5 m forward at four to five sigma; fitted (prior 2 %), 4 cm. Targets at
            # many ranges tell the two apart, but only where the reflection profile holds
            # at every range: on our simulator, whose cars show other parts near and far,
            # the scale took up that change and the bench's horizontal median doubled
            # (interior 7.4 -> 14.4 cm, skin 7.7 -> 31 cm). Hence opt-in
            # (``refine.azimuth_scale_sigma``), not the default.
            azimuth = np.arctan2(sensor[:, 1], sensor[:, 0])
            turn = -x[self.i_end] * azimuth
            ct, st = np.cos(turn), np.sin(turn)
            sensor = np.column_stack([ct * sensor[:, 0] - st * sensor[:, 1],
                                      st * sensor[:, 0] + ct * sensor[:, 1], sensor[:, 2]])
        los = sensor @ rot.T
        world = los + trans
        # The vehicle's pose, the aspect and the reflection basis are the same for every
        # target of a frame: worked out per frame and gathered per target at the end (an
        # imaging radar puts tens of targets on the car in each frame; the same numbers).
        pos, yaw, vel, rate, acc = self.poses.at(d.times.frame_t + tau)
        c, s = np.cos(yaw), np.sin(yaw)
        # The aspect is that of the box centre, not of each target: it says which side of
        # the car faces the radar, the same for every target of a frame. (The target's own
        # line of sight would tie the aspect to where on the car the target lies and bias
        # the profile at short range.)
        centre_los = pos - trans
        centre_los[:, 0] += self.xc * c
        centre_los[:, 1] += self.xc * s
        aspect = reflection.aspect_angles(centre_los, yaw)
        basis, d_basis = reflection.profile_basis(aspect, self.k, derivative=jacobian)
        # Which parts of a car the radar detects changes with range (weak scatterers and
        # multipath images drop out far away; the field of view and nearer cars cut parts
        # off close by), so the apparent depth of the reflections along the line of sight
        # drifts with range. One extra coefficient lets the depth mode (towards the radar,
        # -(cos a, sin a)) change linearly with the centre's range, relative to the median
        # range: measured on the simulator it halves the largest horizontal error (interior
        # model 22 -> 10 cm) at no cost elsewhere.
        centre_range = np.hypot(centre_los[:, 0], centre_los[:, 1])
        rho = centre_range / self.r_ref - 1.0
        ca, sa = np.cos(aspect), np.sin(aspect)
        n = basis.shape[0]
        depth = np.zeros((n, 3, 1))
        depth[:, 0, 0], depth[:, 1, 0] = -ca, -sa
        d_depth = np.zeros_like(depth)
        d_depth[:, 0, 0], d_depth[:, 1, 0] = sa, -ca
        linear = np.full(n, 1.0 / self.r_ref)
        if self.range_terms == 'depth':
            range_basis, d_range_basis = depth, d_depth
            u, du_dr = rho[:, None], linear[:, None]
        else:
            columns = range_columns(self.k, self.range_terms)
            range_basis = basis[:, :, columns]
            d_range_basis = d_basis[:, :, columns] if d_basis is not None else None
            if self.range_terms == 'full':
                u = np.repeat(rho[:, None], columns.size, axis=1)
                du_dr = np.repeat(linear[:, None], columns.size, axis=1)
            else:
                # 'perspective' (the default): the depth as above, and every horizontal
                # coefficient up to ``_FULL_RANGE_HARMONICS`` in proportion to 1 / range.
                # A car spans L / r of the radar's view: each part of it is seen at its
                # own aspect and range, brighter where it faces the radar squarely and
                # where it is nearer, so the mean of what is detected at one aspect of
                # the centre moves ALONG the car, not only in depth, by about
                # (L^2 / 12) (d ln w / d alpha) / r. Unmodelled, with the vehicle's
                # targets known and at their true positions (no noise), the radar came
                # out behind its true position in 10 of 10 skin-model scenarios of our
                # bench (mean 11.5 cm, up to 22); with these terms 5.3 cm. On a
                # twenty-second probe's simulator (junction crossings, all three models)
                # the bias was the same, -0.11 to -0.44 m along the boresight in 15 of
                # 16 recordings; with these terms the median error fell 0.30 -> 0.09 m.
                clamped = np.maximum(centre_range, 1.0)
                inverse = self.r_ref / clamped - 1.0
                d_inverse = -self.r_ref / clamped ** 2
                range_basis = np.concatenate([depth, range_basis], axis=2)
                if d_range_basis is not None:
                    d_range_basis = np.concatenate([d_depth, d_range_basis], axis=2)
                u = np.column_stack([rho, np.repeat(inverse[:, None], columns.size, axis=1)])
                du_dr = np.column_stack([linear, np.repeat(d_inverse[:, None], columns.size,
                                                           axis=1)])
        # On a grade the car is pitched with the road: an offset ahead of the reference
        # point is raised by the grade times its length (see ``_road_grades``). A cross
        # slope (a road's 2 % camber) tilts the sides by centimetres and is not modelled.
        grade = self.frame_grade[:, None]
        range_basis[:, 2, :] = grade * range_basis[:, 0, :]
        basis = np.concatenate([basis, range_basis * u[:, None, :]], axis=2)
        basis[:, 2, :-self.n_range] += grade * basis[:, 0, :-self.n_range]
        if d_basis is not None and d_range_basis is not None:
            d_range_basis[:, 2, :] = grade * d_range_basis[:, 0, :]
            d_basis = np.concatenate([d_basis, d_range_basis * u[:, None, :]], axis=2)
            d_basis[:, 2, :-self.n_range] += grade * d_basis[:, 0, :-self.n_range]
        offset = basis @ prof
        rz_offset = np.column_stack([c * offset[:, 0] - s * offset[:, 1],
                                     s * offset[:, 0] + c * offset[:, 1], offset[:, 2]])
        of_target = d.times.inverse
        if d_basis is not None:
            d_basis = d_basis[of_target]
            range_slope = (range_basis * du_dr[:, None, :])[of_target]
        per_frame = (pos, yaw, vel, rate, acc, c, s, centre_los, aspect, rho, basis, offset,
                     rz_offset)
        (pos, yaw, vel, rate, acc, c, s, centre_los, aspect, rho, basis, offset,
         rz_offset) = (a[of_target] for a in per_frame)
        rel = world - pos
        err = rel - rz_offset
        point_velocity = vel + rate[:, None] * np.column_stack([-rel[:, 1], rel[:, 0],
                                                                np.zeros(len(rel))])
        rng = np.linalg.norm(los, axis=1)
        unit = los / rng[:, None]
        # The line of sight of the radial velocity: measured range and bearing, but the
        # height of the target from the model (vehicle height plus the profile), not from
        # the measured elevation. Elevation noise (1-2 deg) inside the nonlinear v_r model is
        # an errors-in-variables problem: at short range, where v_r is sensitive to pitch, it
        # biases the pitch by ~0.1 deg. Pitch and roll are left to the position residuals.
        los_v = los.copy()
        los_v[:, 2] = pos[:, 2] + offset[:, 2] - trans[2]
        dist_v = np.linalg.norm(los_v, axis=1)
        unit_v = los_v / dist_v[:, None]
        v_pred = np.einsum('ij,ij->i', point_velocity, unit_v)
        geo = {'sensor': sensor, 'rot': rot, 'los': los, 'world': world, 'pos': pos,
               'yaw': yaw, 'vel': vel, 'rate': rate, 'acc': acc, 'aspect': aspect,
               'basis': basis, 'offset': offset, 'rz_offset': rz_offset,
               'rel': rel, 'err': err, 'point_velocity': point_velocity, 'range': rng,
               'unit': unit, 'v_pred': v_pred, 'c': c, 's': s, 'centre_los': centre_los,
               'unit_v': unit_v, 'dist_v': dist_v, 'rho': rho}
        if d_basis is not None:
            geo['d_basis'] = d_basis
            geo['range_basis'] = range_slope
        if self.n_par > self.i_end:
            geo['azimuth'] = azimuth   # the measured azimuths the scale turns by
        return geo

    def residuals(self, x: F64, jac: bool) -> tuple[F64, F64 | None, F64, F64 | None]:
        """Data residuals (3n position + n velocity, whitened and information-weighted)
        and prior residuals, each with its Jacobian when asked."""
        g = self.geometry(x, jacobian=jac)
        d = self.data
        sw = d.sqrt_weight
        r_pos = np.einsum('nij,nj->ni', d.whiten, g['err']) * sw[:, None]
        r_vel = (g['v_pred'] - d.v_mps) / d.sigma_v * sw
        r_data = np.concatenate([r_pos.ravel(), r_vel])
        has_prior = np.isfinite(self.prior_mean)
        r_prior = ((x - np.nan_to_num(self.prior_mean)) / self.prior_sigma)[has_prior]
        if not jac:
            return r_data, None, r_prior, None
        n, n_par, ip, ie = len(sw), self.n_par, self.i_prof, self.i_end
        los, rate = g['los'], g['rate']
        c, s = g['c'], g['s']
        prof = x[ip:ie]
        # d(offset rotated to world)/d(aspect)
        dm = g['d_basis'] @ prof
        rz_dm = np.column_stack([c * dm[:, 0] - s * dm[:, 1], s * dm[:, 0] + c * dm[:, 1],
                                 dm[:, 2]])
        cl = g['centre_los']
        rho2 = np.maximum(cl[:, 0] ** 2 + cl[:, 1] ** 2, 1e-12)
        de = np.zeros((n, 3, n_par))
        # dx/dw = -[l]x (the centre's aspect does not depend on the rotation)
        de[:, 0, 1], de[:, 0, 2] = los[:, 2], -los[:, 1]
        de[:, 1, 0], de[:, 1, 2] = -los[:, 2], los[:, 0]
        de[:, 2, 0], de[:, 2, 1] = los[:, 1], -los[:, 0]
        # moving the radar by dt turns the centre's line of sight by (l_y, -l_x) . dt / rho^2
        dalpha_dt = np.column_stack([cl[:, 1] / rho2, -cl[:, 0] / rho2, np.zeros(n)])
        de[:, 0, 3] = de[:, 1, 4] = de[:, 2, 5] = 1.0
        de[:, :, 3:6] -= rz_dm[:, :, None] * dalpha_dt[:, None, :]
        # the range terms: their offset u(r) B(a) q moves with the centre's range r
        # ('range_basis' already holds B(a) du/dr)
        rho_h = np.sqrt(rho2)
        slope = g['range_basis'] @ x[ie - self.n_range:ie]
        slope_w = np.column_stack([c * slope[:, 0] - s * slope[:, 1],
                                   s * slope[:, 0] + c * slope[:, 1], slope[:, 2]])
        drho_dt = np.column_stack([-cl[:, 0], -cl[:, 1], np.zeros(n)]) / rho_h[:, None]
        de[:, :, 3:6] -= slope_w[:, :, None] * drho_dt[:, None, :]
        if self.tau_fixed is None:
            off = g['offset']
            z_cross_m = np.column_stack([-off[:, 1], off[:, 0], np.zeros(n)])
            rz_zm = np.column_stack([c * z_cross_m[:, 0] - s * z_cross_m[:, 1],
                                     s * z_cross_m[:, 0] + c * z_cross_m[:, 1],
                                     np.zeros(n)])
            # the aspect turns by -yaw_rate * dtau as the vehicle turns, and by the
            # centre's own motion across the line of sight
            vc_x = g['vel'][:, 0] - rate * self.xc * s
            vc_y = g['vel'][:, 1] + rate * self.xc * c
            dalpha_dtau = (cl[:, 0] * vc_y - cl[:, 1] * vc_x) / rho2 - rate
            drho_dtau = (cl[:, 0] * vc_x + cl[:, 1] * vc_y) / rho_h
            de[:, :, 6] = (-g['vel'] - rate[:, None] * rz_zm
                           - rz_dm * dalpha_dtau[:, None] - slope_w * drho_dtau[:, None])
        basis = g['basis']
        de[:, 0, ip:ie] = -(c[:, None] * basis[:, 0, :] - s[:, None] * basis[:, 1, :])
        de[:, 1, ip:ie] = -(s[:, None] * basis[:, 0, :] + c[:, None] * basis[:, 1, :])
        de[:, 2, ip:ie] = -basis[:, 2, :]
        if n_par > ie:
            # the scale turns each target about the radar's z by -scale * azimuth
            sen = g['sensor']
            d_sensor = -g['azimuth'][:, None] * np.column_stack([-sen[:, 1], sen[:, 0],
                                                                 np.zeros(n)])
            de[:, :, ie] = d_sensor @ g['rot'].T
        j_pos = np.einsum('nij,njk->nik', d.whiten, de) * sw[:, None, None]
        # v = V_pt . d / |d| with d = (l_x, l_y, P_z + m_z - t_z):
        # dv = (V_pt - v u)/|d| . dd + u . dV_pt
        uv, vp = g['unit_v'], g['point_velocity']
        dd = np.zeros((n, 3, n_par))
        dd[:, 0:2, 0:3] = de[:, 0:2, 0:3]
        dmz = dm[:, 2]
        dd[:, 2, 3:6] = dmz[:, None] * dalpha_dt + slope_w[:, 2, None] * drho_dt
        dd[:, 2, 5] -= 1.0
        if self.tau_fixed is None:
            dd[:, 2, 6] = g['vel'][:, 2] + dmz * dalpha_dtau + slope_w[:, 2] * drho_dtau
        dd[:, 2, ip:ie] = basis[:, 2, :]
        if n_par > ie:
            dd[:, 0:2, ie] = de[:, 0:2, ie]
        dvp = np.zeros((n, 3, n_par))
        # V_pt = V + rate z x (x - P): only the horizontal lever arm matters
        dvp[:, 0, 0:3] = -rate[:, None] * de[:, 1, 0:3]
        dvp[:, 1, 0:3] = rate[:, None] * de[:, 0, 0:3]
        if n_par > ie:
            dvp[:, 0, ie] = -rate * de[:, 1, ie]
            dvp[:, 1, ie] = rate * de[:, 0, ie]
        dvp[:, 0, 4] = -rate
        dvp[:, 1, 3] = rate
        if self.tau_fixed is None:
            vel = g['vel']
            rel = g['rel']
            yaw_acc = g['acc'][:, 3]
            dvp[:, :, 6] = g['acc'][:, :3] + rate[:, None] * np.column_stack(
                [vel[:, 1], -vel[:, 0], np.zeros(n)]) + yaw_acc[:, None] * np.column_stack(
                [-rel[:, 1], rel[:, 0], np.zeros(n)])
        proj = (vp - g['v_pred'][:, None] * uv) / g['dist_v'][:, None]
        dv = np.einsum('ni,nip->np', proj, dd) + np.einsum('ni,nip->np', uv, dvp)
        j_vel = dv / d.sigma_v[:, None] * sw[:, None]
        j_data = np.concatenate([j_pos.reshape(3 * n, n_par), j_vel])
        j_prior = np.diag(1.0 / self.prior_sigma)[has_prior]
        return r_data, j_data, r_prior, j_prior


#: Highest harmonic whose coefficients may drift with range under 'full' or 'perspective'
#: range terms.
#: Which parts of a car show changes slowly with range, and the low orders carry it; with
#: a slope for every one of order 8 the refit behind ``refine.model_check`` had 17 more
#: coefficients and its difference from the fit, added to the covariance, was noise (half
#: the targets of one scene doubled the sigma along the boresight).
_FULL_RANGE_HARMONICS = 4


def range_columns(harmonics: int, range_terms: str) -> I64:
    """Profile coefficients that get a range term under 'full' or 'perspective' (a_0..a_k,
    b_1..b_k with k = min(K, ``_FULL_RANGE_HARMONICS``)); empty under 'depth'."""
    if range_terms == 'depth':
        return np.zeros(0, np.int64)
    k = min(harmonics, _FULL_RANGE_HARMONICS)
    return np.concatenate([np.arange(k + 1), harmonics + 1 + np.arange(k)]).astype(np.int64)


def n_range_terms(harmonics: int, range_terms: str) -> int:
    """Number of range coefficients after the profile: one for the depth mode (linear in
    range) unless 'full', plus one per coefficient of ``range_columns``."""
    return range_columns(harmonics, range_terms).size + (0 if range_terms == 'full' else 1)


def _robust(r: F64, n_targets: int) -> tuple[F64, float]:
    """IRLS weight of every data row and the robust cost.

    Soft-L1, rho(s) = 2 f^2 (sqrt(1 + s / f^2) - 1), on the squared Mahalanobis norm of each
    target's whitened 3-D position residual (f^2 = 3 * scale^2) and on each velocity
    residual (f = scale). One weight per target, not per whitened component: the whitening
    mixes vertical and horizontal components in a range-dependent way, and a per-component
    weight would turn the asymmetric horizontal spread of the reflectors into a
    range-dependent vertical shift, i.e. a pitch bias.
    """
    f2_pos, f2_vel = 3.0 * _LOSS_SCALE ** 2, _LOSS_SCALE ** 2
    s_pos = np.sum(r[:3 * n_targets].reshape(n_targets, 3) ** 2, axis=1)
    s_vel = r[3 * n_targets:] ** 2
    w_pos = 1.0 / np.sqrt(1.0 + s_pos / f2_pos)
    w_vel = 1.0 / np.sqrt(1.0 + s_vel / f2_vel)
    cost = float(np.sum(2.0 * f2_pos * (np.sqrt(1.0 + s_pos / f2_pos) - 1.0))
                 + np.sum(2.0 * f2_vel * (np.sqrt(1.0 + s_vel / f2_vel) - 1.0)))
    return np.concatenate([np.repeat(w_pos, 3), w_vel]), cost


@dataclass(frozen=True, slots=True)
class _Fit:
    x: F64
    cost: float
    iterations: int
    converged: bool


def _solve(model: _Model, x0: F64, max_iter: int = 30) -> _Fit:
    """Levenberg-Marquardt on the iteratively reweighted (soft-L1) problem.

    A hand-written LM rather than scipy's least_squares because the covariance needs the
    very same weighted Hessian split by pass, and the priors must stay quadratic (scipy
    applies one loss to every residual).
    """
    x = x0.copy()
    n = model.data.index.size
    r, j, rp, jp = model.residuals(x, jac=True)
    w, cost = _robust(r, n)
    cost += float(rp @ rp)
    lam = 1e-3
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        assert j is not None and jp is not None
        jw = j * w[:, None]
        h = j.T @ jw + jp.T @ jp
        grad = jw.T @ r + jp.T @ rp
        diag = np.maximum(np.diag(h), 1e-12)
        improved = False
        for _ in range(10):
            step = -np.linalg.solve(h + lam * np.diag(diag), grad)
            x_new = x + step
            r_new, _, rp_new, _ = model.residuals(x_new, jac=False)
            cost_new = _robust(r_new, n)[1] + float(rp_new @ rp_new)
            if cost_new <= cost:
                improved = True
                break
            lam *= 8.0
        if not improved:
            converged = True
            break
        x, cost = x_new, cost_new
        lam = max(lam / 4.0, 1e-9)
        # Converged when the step is far below anything that matters: 1e-6 rad, 1e-5 m,
        # 1e-6 s (profile coefficients 1e-5 m).
        if (np.abs(step) < np.where(np.arange(x.size) < 3, 1e-6, 1e-5)).all():
            converged = True
            break
        r, j, rp, jp = model.residuals(x, jac=True)
        w = _robust(r, n)[0]
    return _Fit(x, cost, it, converged)


def _parameter_sigma(model: _Model, x: F64, i: int, stride: int = 1) -> float:
    """1-sigma of parameter ``i`` at ``x`` from the robust normal matrix and the priors, for
    all the targets when the model holds every ``stride``-th (its priors are weighed down
    by as much, so the whole matrix scales)."""
    r, j, _, jp = model.residuals(x, jac=True)
    assert j is not None and jp is not None
    w = _robust(r, model.data.index.size)[0]
    normal = ((j * w[:, None]).T @ j + jp.T @ jp) * stride
    try:
        return float(math.sqrt(max(np.linalg.inv(normal)[i, i], 0.0)))
    except np.linalg.LinAlgError:
        return math.inf


def _change(est: Extrinsics, rot: F64, trans: F64, tau: float) -> tuple[float, float, float]:
    """(rotation angle [rad], translation [m], clock offset [s]) between two estimates."""
    angle = float(np.linalg.norm(Rotation.from_matrix(rot @ est.rotation.T).as_rotvec()))
    return angle, float(np.linalg.norm(trans - est.translation_m)), abs(tau
                                                                        - est.time_offset_s)


# --- priors and anchors -----------------------------------------------------------------

def _anchor(prior_mean: F64, start: Extrinsics, est: Extrinsics,
            tilt: F64 | None = None) -> F64:
    """Prior means for a round based at ``est``: the translation prior is centred on the
    starting estimate, the tilt's (where there is one) on ``tilt`` (default the start's
    rotation); the parameters are offsets from the round's base."""
    mean = prior_mean.copy()
    mean[3:6] = start.translation_m - est.translation_m
    if np.isfinite(mean[:2]).any():
        anchor = start.rotation if tilt is None else tilt
        mean[:2] = Rotation.from_matrix(anchor @ est.rotation.T).as_rotvec()[:2]
    return mean


#: Radius around the radar of the vehicle poses that show the road's tilt [m], the most a
#: fix's declared vertical sigma may be [m], and the spread across the main direction of
#: travel [m] below which only the grade along it is taken (one road: no cross slope).
_ROAD_RADIUS_M = 100.0
_ROAD_FIX_SIGMA_M = 0.1
_ROAD_SPREAD_M = 3.0


def _road_up(poses: _Poses, est: Extrinsics, fix_sigma_m: tuple[float, float] | None) -> F64:
    """The road's unit normal in the world near the radar, from the vehicle's RTK altitude
    (a plane, or a grade along one road); straight up without RTK or without poses there."""
    up = np.array([0.0, 0.0, 1.0])
    if fix_sigma_m is None or not fix_sigma_m[1] <= _ROAD_FIX_SIGMA_M:
        return up
    p = poses.positions_m
    near = np.hypot(p[:, 0] - est.translation_m[0], p[:, 1] - est.translation_m[1])
    p = p[near < _ROAD_RADIUS_M]
    if p.shape[0] < 50:
        return up
    xy = p[:, :2] - p[:, :2].mean(axis=0)
    values, axes = np.linalg.eigh(np.cov(xy.T))
    if values[0] >= _ROAD_SPREAD_M ** 2:
        design = np.column_stack([np.ones(len(p)), xy])
        (_, gx, gy), *_ = np.linalg.lstsq(design, p[:, 2], rcond=None)
    else:
        along = xy @ axes[:, 1]
        (_, grade), *_ = np.linalg.lstsq(np.column_stack([np.ones(len(p)), along]), p[:, 2],
                                         rcond=None)
        gx, gy = grade * axes[:, 1]
    normal = np.array([-gx, -gy, 1.0])
    return normal / np.linalg.norm(normal)


def _rotation_between(a: F64, b: F64) -> F64:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    axis = np.cross(a, b)
    sine, cosine = float(np.linalg.norm(axis)), float(a @ b)
    if sine < 1e-12:
        return np.eye(3)
    return Rotation.from_rotvec(axis / sine * math.atan2(sine, cosine)).as_matrix()


#: Height of the car that ``refine.reflection_height_m`` and its sigma describe [m].
_CAR_HEIGHT_M = 1.5


def reflection_height_prior(config: CalibConfig) -> tuple[float, float]:
    """Prior mean height of the vehicle's targets above the road, and its sigma [m]:
    ``refine.reflection_height_m`` +- ``refine.reflection_height_sigma_m`` describe a car
    1.5 m tall, and both scale with ``vehicle.height``. A van or a bus shows the radar
    flat faces and sides up to its roof: a fifth probe's 2.9 m van and 3.2 m bus reflected
    at 0.82 m on average against its car's 0.52 m, and the car's prior put their radars
    50 cm low at a sigma of 19 cm."""
    scale = config.vehicle.height / _CAR_HEIGHT_M
    cfg = config.refine
    return cfg.reflection_height_m * scale, cfg.reflection_height_sigma_m * scale


#: Prior sigma that holds the profile's steps at zero (``refine.profile_steps`` false) [m].
_HELD_STEP_M = 1e-6
#: Prior sigma of the profile's perspective terms, in vehicle lengths (0.23 m for a car).
_PERSPECTIVE_SIGMA_LENGTHS = 0.05


def _priors(config: CalibConfig, harmonics: int, estimate_tau: bool,
            start_sigma_m: float = _START_SIGMA_M) -> tuple[F64, F64]:
    """Prior means (NaN = none) and sigmas of all parameters (see the module docstring)."""
    veh = config.vehicle
    i_prof = 7 if estimate_tau else 6
    n_range = n_range_terms(harmonics, config.refine.profile_range_terms)
    i_end = i_prof + reflection.n_coefficients(harmonics) + n_range
    n_par = i_end + (1 if config.refine.azimuth_scale_sigma > 0 else 0)
    mean = np.full(n_par, np.nan)
    sigma = np.ones(n_par)
    if estimate_tau:
        mean[6], sigma[6] = 0.0, max(config.sync.max_time_offset, 1e-3)
    # The paper's stages leave the radar decimetres from the truth. Where the views leave a
    # direction unobserved (the depth along the boresight when the car is only seen head-on
    # and tail-on), a half-metre prior around that start keeps the fit from wandering off
    # on model mismatch; elsewhere the data outweigh it a hundred-fold. It enters the
    # covariance, so there the reported uncertainty is the half metre it really is.
    mean[3:6], sigma[3:6] = 0.0, start_sigma_m
    sigma[5] = _ALTITUDE_START_SIGMA_M
    x0, x1, _, _ = box_limits(veh)
    idx = reflection.coefficient_index(harmonics)
    prof_mean = np.zeros(reflection.n_coefficients(harmonics))
    prof_sigma = np.full(prof_mean.size, 0.5 * veh.length)
    prof_mean[idx['a0']] = 0.5 * (x0 + x1)
    height, height_sigma = reflection_height_prior(config)
    prof_mean[idx['c0']] = height - veh.ref_height
    prof_sigma[idx['c0']] = height_sigma
    if not config.refine.profile_steps:
        prof_sigma[[idx['sx'], idx['sy']]] = _HELD_STEP_M
    mean[i_prof:i_prof + prof_mean.size] = prof_mean
    sigma[i_prof:i_prof + prof_mean.size] = prof_sigma
    # range slopes: metres per unit of relative range
    mean[i_end - n_range:i_end], sigma[i_end - n_range:i_end] = 0.0, 1.0
    if config.refine.profile_range_terms == 'perspective':
        # the size of the perspective change (see ``_Model.geometry``): a few decimetres for
        # a car between half and twice the median range; held to it, the terms cannot
        # stand in for a radar moved along its boresight where the views leave that open
        # (a twenty-second probe's straight drives with a few crossings: 0.47 -> 0.32 m)
        sigma[i_end - n_range + 1:i_end] = _PERSPECTIVE_SIGMA_LENGTHS * veh.length
    if n_par > i_end:
        mean[i_end], sigma[i_end] = 0.0, config.refine.azimuth_scale_sigma
    return mean, sigma
