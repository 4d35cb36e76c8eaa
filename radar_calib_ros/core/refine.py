"""Stage 8 (beyond the paper): joint robust refinement of the six degrees of freedom, the
radar/GNSS clock offset and the vehicle's reflection profile over every target the current
calibration places on or near the calibration vehicle.

The paper stops at decimetres (delta_op 0.26-0.39 m) because it fits cluster centres and
then a polygon loss that is biased when most targets lie inside the footprint. Here every
target counts, through two kinds of residuals:

* Radial velocity. For a rigid car v_r = (v_ref + omega x r) . u, u the unit line of sight,
  whatever point reflected. It depends on the rotation and the clock offset, not on the
  radar's position (to first order) and not on where on the car the target lies: it pins
  the yaw and the clock offset free of any reflection model. (Its line of sight takes the
  target's height from the model, not from the 1-2 deg elevation noise: used inside the
  nonlinear model that noise biases the pitch by ~0.1-0.5 deg; a corrected-score version
  was tried and carried too little pitch information to be worth it. Pitch and roll come
  from the heights.) Wheels break rigidity (micro-Doppler), hence a robust loss.
* Position. The target in the vehicle frame minus the reflection profile m(alpha), the mean
  offset of the targets as a function of the aspect angle (``core/reflection.py``),
  estimated jointly. Residuals are whitened per target by the radar's spherical noise
  (range ~0.15 m, azimuth ~0.3 deg, elevation ~1.5 deg: the cross-range and vertical parts
  grow with range) plus the scatter of the reflectors around their mean; the scatter is
  re-estimated every gate round.

Gauge and priors (the least we can defend):
* Left-right symmetry of the car (m_x even, m_y odd in alpha, one mean height) fixes the
  lateral profile; the depth along the line of sight stays free (and may drift linearly
  with range, one more coefficient) and is resolved only by seeing an aspect from several
  bearings. Its trade-off with the radar's position along the boresight is reported, not
  hidden. The low orders of the profile also change as 1 / range (perspective: the car
  spans L / r of the view, and its nearer, squarer parts show more), with a prior of a
  twentieth of the vehicle's length. Two smoothed steps let the near face switch from
  front to rear and from one side to the other (``core/reflection.py``): smoothed by the
  Fourier terms, that switch pinned the near side's offset, and with it the position,
  where the views do not.
* The mean reflection height cannot be told from the radar's altitude by the vehicle alone
  (both shift every target's height equally). A stated prior fixes it:
  ``refine.reflection_height_m`` above the road, +- ``refine.reflection_height_sigma_m``;
  the road is the vehicle's reference point minus ``vehicle.ref_height``. It is the mean of
  ALL the vehicle's targets, multipath images below the road included: direct returns
  average about 0.5 m (wheels, underbody, engine, sills), while the road ghosts and the
  multi-bounce returns of the wheel houses and underbody (15-30 % of the targets) sit about
  as far below the road, hence 0.35 +- 0.3 m for a car 1.5 m tall, scaled with
  ``vehicle.height`` for others (``reflection_height_prior``). (Measured on the simulator at
  the true pose: 0.17-0.38 m interior, 0.15-0.68 m skin. Independent simulators' cars
  averaged 0.48-1.15 m without road ghosts: a twenty-third probe's panel cars at 0.84-0.93 m
  put the radar 0.54-0.75 m low at a reported 0.3, 29 of 38 outside 2 sigma with +- 0.2.)
  The ghosts' mirror symmetry about the road does in principle show the road itself; a
  mirror-mixture fit was tried and, at 1-2 deg of elevation noise, scattered by 5-50 cm:
  not better than the prior, so not used.
* Where the elevation field of view (found from all targets' elevations) cuts off the lower
  part of the car, what remains is higher on average, and more so at short range; a pitch
  error would follow it. Those frames give no height information (``_inside_elevation_view``).
* Weak bounds keep the profile on the car (coefficients within about a car length), the
  clock offset within ``sync.max_time_offset`` and the horizontal translation within half a
  metre of the paper's estimate; they only matter when the data say nothing, and then they
  are what the reported uncertainty shows. The altitude has no such bound: only the height
  prior above may decide it (``_ALTITUDE_START_SIGMA_M``).
* On a grade the car is pitched with the road (``_road_grades``): the profile's offsets
  ahead of the reference point are raised by the grade.

Information, not frame count: a car crawling in a queue gives hundreds of near-identical
frames from one place and one aspect. Frames are binned by (vehicle position, aspect) and
the frames of a bin share the weight of ``refine.cell_frames`` frames.

The uncertainty comes from agreement across passes and across range bands
(``core/uncertainty.py``), never from the per-target fit or from r_i.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage, stats
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, reflection, uncertainty
from radar_calib_ros.core.vehicle import (box_corners_world, box_distance, box_limits,
                                          world_to_vehicle)
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import (
    F64, I64, Extrinsics, HypothesisSelection, MountTurn, RadarView, Refinement,
    TrackedTargets, VehicleTrack)

_LOG = logging.getLogger(__name__)

#: Robust loss scale in whitened units: soft-L1 is quadratic within about one sigma and
#: linear beyond, so wheel micro-Doppler (several m/s) and stray targets of other cars keep a
#: bounded influence while the Gaussian core keeps most of its efficiency.
_LOSS_SCALE = 1.0
#: What a 2-D radar leaves of roll/pitch and altitude (1 sigma): a roadside radar's mount is
#: within a few degrees of level, nothing better; its altitude comes from the dip of the
#: radial velocities' line of sight, which the reflection heights and the held tilt blur
#: (a fifth probe's 2-D radars: 23-39 cm below the truth, with 17 cm from the heights).
_PLANAR_TILT_SIGMA_DEG = 5.0
_PLANAR_HEIGHT_SIGMA_M = 0.3
#: Prior sigma that holds a 2-D radar's roll and pitch at the start [rad], and the largest
#: sine of the dip of its line of sight out of its plane (a target nearer than its height).
_PLANAR_HOLD_RAD = 1e-5
_PLANAR_MAX_SIN = 0.98
#: Tilt by which a 2-D radar's held roll and pitch are moved to see what they carry [deg].
_PLANAR_PROBE_DEG = 2.0
#: Width of the prior around the starting altitude [m]: none to speak of. The elevations
#: and the radial velocities' dip fix the radar's height above the vehicle's targets, and
#: the reflection-height prior says where those lie; the paper's stages know no more (their
#: altitude rests on the ground plane, and a 2-D radar's starts at the vehicle's, metres
#: below the pole). A half-metre prior there leaked into what only the reflection-height
#: prior should decide: on a 6 % road the start was 3.5 m high, and pulled the result
#: 50 cm up (an independent recording, sigma 21 cm).
_ALTITUDE_START_SIGMA_M = 30.0
#: Fewest targets a refinement is attempted with.
_MIN_TARGETS = 30
#: Fewest targets of a pass (see ``_in_passes``).
_MIN_PASS_TARGETS = 20
#: Range bands of the second jackknife (``uncertainty.combined_covariance``): six, so the
#: t-factor of its five degrees of freedom stays near 1.3.
_RANGE_BANDS = 6
#: A track is taken as the calibration vehicle's when at least this fraction of its targets
#: lie in the gate: tracks of other cars that only brush past the box are left out.
_TRACK_FRACTION = 0.5
#: ... and when the median distance of its targets from the box is at most this [m], once
#: the first round has brought the estimate within centimetres-to-decimetres. Measured on
#: the simulator at the true pose: the vehicle's own tracks have medians of 0.00-0.28 m
#: (skin returns lie on the faces, interior ones inside), while a truck creeping 1 m ahead
#: in a queue, or a car in the next lane, forms tracks that are half inside the 1.5 m gate
#: with medians of 1.0-1.5 m; admitted, they pulled a dense-traffic calibration 0.5 m off.
_TRACK_MEDIAN_M = 0.5
#: Targets in no track are judged one by one, within this fraction of the gate: at the
#: truth, those 1.0-1.5 m from the box are 2-9 % the vehicle's (they are other road users'
#: stray returns), those within 0.5 m 76-100 %.
_NOISE_GATE_FRACTION = 2.0 / 3.0
#: Frames with the vehicle cut by the edge of the view are left out only while at least
#: this share of the gated targets remains (see ``_box_inside_view``).
_MIN_INSIDE_VIEW_SHARE = 0.5
#: The radial-velocity gate widens to this many robust sigma of the near targets' v_r
#: differences (see ``_velocity_consistent``).
_VELOCITY_GATE_SIGMAS = 4.0
#: Width of the prior around the starting translation [m] (see ``_priors``).
_START_SIGMA_M = 0.5
#: Gate rounds fit at most about this many targets; the final fit takes them all. An
#: imaging radar puts 100+ targets on the car in every frame (120 000 in five minutes at
#: 20 Hz), and each LM step costs in proportion; the gate and the scatter need far fewer.
_ROUND_TARGETS = 40_000
#: ... and the final fit at most about this many: a 4D imaging radar gives 300 000 targets
#: on the car in ten minutes (100+ per frame, each frame's nearly the same reflectors), and
#: the Jacobian of the fit of all of them held 1.2 GB; every second of them carries the
#: same views and the same agreement across passes. Our simulator's fits hold 3 000-25 000.
_FINAL_TARGETS = 150_000


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
        frames, inverse = np.unique(recording.targets.frame_index[index], return_inverse=True)
        frame_t = (recording.frame_stamps_ns[frames] - t0_ns) * 1e-9 + sync_offset_s
        if drift is not None:
            frame_t = frame_t + drift.offset_change_s(frame_t)
        return cls(frame_t, inverse.ravel())

    @property
    def t_s(self) -> F64:
        """(n,) time of each target."""
        return self.frame_t[self.inverse]

    def subset(self, mask: np.ndarray) -> _Times:
        used, inverse = np.unique(self.inverse[mask], return_inverse=True)
        return _Times(self.frame_t[used], inverse.ravel())

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
        self.prior_mean = prior_mean      # (n_par,) NaN = no prior
        self.prior_sigma = prior_sigma

    def unpack(self, x: F64) -> tuple[F64, F64, float, F64]:
        rot = Rotation.from_rotvec(x[:3]).as_matrix() @ self.r0
        tau = float(x[6]) if self.tau_fixed is None else self.tau_fixed
        return rot, self.t0 + x[3:6], tau, x[self.i_prof:]

    def geometry(self, x: F64) -> dict[str, F64]:
        """Per-target quantities at x (shared by residuals, Jacobian and diagnostics)."""
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
        pos, yaw, vel, rate, acc = d.times.poses(self.poses, tau)
        c, s = np.cos(yaw), np.sin(yaw)
        # The aspect is that of the box centre, not of each target: it says which side of
        # the car faces the radar, the same for every target of a frame. (The target's own
        # line of sight would tie the aspect to where on the car the target lies and bias
        # the profile at short range.)
        centre_los = pos - trans
        centre_los[:, 0] += self.xc * c
        centre_los[:, 1] += self.xc * s
        aspect = reflection.aspect_angles(centre_los, yaw)
        basis, d_basis = reflection.profile_basis(aspect, self.k)
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
            d_range_basis = d_basis[:, :, columns]
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
                d_range_basis = np.concatenate([d_depth, d_range_basis], axis=2)
                u = np.column_stack([rho, np.repeat(inverse[:, None], columns.size, axis=1)])
                du_dr = np.column_stack([linear, np.repeat(d_inverse[:, None], columns.size,
                                                           axis=1)])
        # On a grade the car is pitched with the road: an offset ahead of the reference
        # point is raised by the grade times its length (see ``_road_grades``). A cross
        # slope (a road's 2 % camber) tilts the sides by centimetres and is not modelled.
        grade = d.grade[:, None]
        for b in (range_basis, d_range_basis):
            b[:, 2, :] = grade * b[:, 0, :]
        extra = range_basis * u[:, None, :]
        d_extra = d_range_basis * u[:, None, :]
        basis = np.concatenate([basis, extra], axis=2)
        d_basis = np.concatenate([d_basis, d_extra], axis=2)
        basis[:, 2, :-self.n_range] += grade * basis[:, 0, :-self.n_range]
        d_basis[:, 2, :-self.n_range] += grade * d_basis[:, 0, :-self.n_range]
        offset = basis @ prof
        rz_offset = np.column_stack([c * offset[:, 0] - s * offset[:, 1],
                                     s * offset[:, 0] + c * offset[:, 1], offset[:, 2]])
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
               'basis': basis, 'd_basis': d_basis, 'offset': offset, 'rz_offset': rz_offset,
               'rel': rel, 'err': err, 'point_velocity': point_velocity, 'range': rng,
               'unit': unit, 'v_pred': v_pred, 'c': c, 's': s, 'centre_los': centre_los,
               'unit_v': unit_v, 'dist_v': dist_v, 'rho': rho,
               'range_basis': range_basis * du_dr[:, None, :]}
        if self.n_par > self.i_end:
            geo['azimuth'] = azimuth   # the measured azimuths the scale turns by
        return geo

    def residuals(self, x: F64, jac: bool) -> tuple[F64, F64 | None, F64, F64 | None]:
        """Data residuals (3n position + n velocity, whitened and information-weighted)
        and prior residuals, each with its Jacobian when asked."""
        g = self.geometry(x)
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


# --- selecting targets, weights, passes ---------------------------------------------------

def _vehicle_frame(world: F64, pos: F64, yaw: F64) -> F64:
    """World points (n, 3) in each one's vehicle pose: bird's-eye view plus height."""
    return np.column_stack([world_to_vehicle(world, pos, yaw), world[:, 2] - pos[:, 2]])


def _track_sizes(track_ids: I64) -> I64:
    """(n,) number of moving targets of each target's track (1 for noise targets)."""
    out = np.ones(track_ids.size, np.int64)
    has = track_ids >= 0
    if has.any():
        _, inv, counts = np.unique(track_ids[has], return_inverse=True, return_counts=True)
        out[has] = counts[inv]
    return out


def _corridor(est: Extrinsics, candidates: I64, times: _Times, recording: Recording,
              poses: _Poses, config: CalibConfig) -> np.ndarray:
    """Mask of the candidates that may come within the gate while the estimate converges."""
    sensor = recording.targets.positions_m[candidates]
    pos, yaw, vel, _, _ = times.poses(poses, est.time_offset_s)
    local = _vehicle_frame(est.apply(sensor), pos, yaw)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    rng = np.linalg.norm(sensor, axis=1)
    margin = (config.refine.gate_m + 2.0 + 0.03 * rng
              + speed * (config.sync.max_time_offset + abs(est.time_offset_s)))
    return times.valid(poses, est.time_offset_s) & (
        box_distance(local[:, :2], config.vehicle) <= margin)


def _gate(est: Extrinsics, candidates: I64, track_ids: I64, track_size: I64,
          accepted: np.ndarray, times: _Times, recording: Recording, poses: _Poses,
          config: CalibConfig, first_round: bool,
          view: RadarView) -> np.ndarray:
    """Mask over ``candidates`` of the targets the estimate puts on or near the vehicle.

    The first round starts from the paper's estimate, decimetres off: it gates at
    ``refine.gate_m``. Later rounds start within centimetres and gate at
    ``refine.final_gate_m``: measured at the true pose, the targets 0.75-1.5 m from the box
    are 0-48 % the vehicle's (wheel-house multi-bounce), in dense traffic 0-6 % (queued
    neighbours), while 94-99 % of the vehicle's targets lie within 0.5 m.
    """
    cfg = config.refine
    gate = cfg.gate_m if first_round else min(cfg.gate_m, cfg.final_gate_m)
    sensor = recording.targets.positions_m[candidates]
    valid = times.valid(poses, est.time_offset_s)
    pos, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    local = _vehicle_frame(est.apply(sensor), pos, yaw)
    dist = np.where(valid, box_distance(local[:, :2], config.vehicle), np.inf)
    near = dist <= gate
    # Tracks of other cars brush the box now and then; the calibration vehicle's own tracks
    # are mostly inside the gate and centred on the box. Noise targets (no track) are judged
    # one by one, more strictly.
    has_track = track_ids >= 0
    keep = near & (has_track | (dist <= _NOISE_GATE_FRACTION * gate))
    if has_track.any():
        tid = track_ids[has_track]
        uniq, inv = np.unique(tid, return_inverse=True)
        n_near = np.bincount(inv, near[has_track].astype(float), minlength=uniq.size)
        size = np.zeros(uniq.size)
        size[inv] = track_size[has_track]
        median = _group_median(inv, dist[has_track], uniq.size)
        # the first round starts decimetres off: only the fraction rule applies then
        limit = gate if first_round else _TRACK_MEDIAN_M
        track_ok = (((n_near / size >= _TRACK_FRACTION) & (median <= limit))
                    | np.isin(uniq, accepted))
        keep[has_track] &= track_ok[inv]
    inside = keep & _box_inside_view(pos, yaw, est, view, config)
    # A narrow view (a long-range radar's +-9 deg) may rarely hold the whole car: then the
    # cut views are all there is, and losing most of the data would cost more than the cut.
    if inside.sum() >= max(_MIN_TARGETS, _MIN_INSIDE_VIEW_SHARE * keep.sum()):
        keep = inside
    if not first_round and cfg.velocity_gate_mps > 0 and keep.any():
        keep[keep] = _velocity_consistent(est, candidates[keep], times.subset(keep),
                                          recording, poses, cfg.velocity_gate_mps)
    return keep


def _occluded(est: Extrinsics, index: I64, times: _Times, recording: Recording,
              poses: _Poses, road_users: I64, config: CalibConfig) -> np.ndarray:
    """Mask over ``index`` (the vehicle's targets) of those in frames where another road
    user hides the vehicle's lower half: at least ``_OCCLUDER_TARGETS`` tracked moving
    targets within the box's bearings (plus ``_OCCLUDER_MARGIN_DEG``), nearer than its
    nearest corner by ``_OCCLUDER_GAP_M``, where a road user ``_OCCLUDER_HEIGHT_M`` tall
    reaches above the line from the radar to that corner at half the vehicle's height (a
    radar on a pole looks over a car ten metres ahead, not over one queued close behind or
    a truck alongside).

    A partly hidden car shows the radar only its unhidden part, and which part that is
    depends on where the occluder stands, not on the aspect: the reflection profile cannot
    follow it. A fourteenth probe's truck in the next lane, alongside the car on the
    radar's side in every pass, moved the radar 0.24-0.53 m along its boresight (up to
    2.3 sigma) while the same trucks without shadows left it at 0.01-0.11 m.
    """
    pos, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    frames = recording.targets.frame_index[index]
    unique, first = np.unique(frames, return_index=True)
    world = np.empty((unique.size, 4, 3))
    world[:, :, :2] = box_corners_world(pos[first], yaw[first], config.vehicle)
    road = pos[first, 2] - config.vehicle.ref_height
    world[:, :, 2] = road[:, None] + 0.5 * config.vehicle.height
    sensor = est.inverse_apply(world.reshape(-1, 3)).reshape(world.shape)
    bearing = np.arctan2(sensor[:, :, 1], sensor[:, :, 0])
    margin = math.radians(_OCCLUDER_MARGIN_DEG)
    low, high = bearing.min(axis=1) - margin, bearing.max(axis=1) + margin
    corner_range = np.hypot(world[:, :, 0] - est.translation_m[0],
                            world[:, :, 1] - est.translation_m[1])
    near_corner = np.argmin(corner_range, axis=1)
    reach = corner_range[np.arange(unique.size), near_corner]
    # the line of sight to the nearest corner at mid-height falls this much per metre
    drop = (est.translation_m[2] - world[np.arange(unique.size), near_corner, 2]) / reach
    nearest = reach - _OCCLUDER_GAP_M
    user_frames = recording.targets.frame_index[road_users]
    k = np.searchsorted(unique, user_frames)
    in_frame = (k < unique.size) & (unique[np.minimum(k, unique.size - 1)] == user_frames)
    k = k[in_frame]
    p = recording.targets.positions_m[road_users[in_frame]]
    b = np.arctan2(p[:, 1], p[:, 0])
    w = est.apply(p)
    rho = np.hypot(w[:, 0] - est.translation_m[0], w[:, 1] - est.translation_m[1])
    # The road user's top, not its targets (they lie mostly low, on wheels and underbody):
    # assumed a car's height above the vehicle's road, the least of what hides anything.
    top = road[k] + _OCCLUDER_HEIGHT_M
    above = top > est.translation_m[2] - drop[k] * rho
    ahead = (b >= low[k]) & (b <= high[k]) & (rho < nearest[k]) & above
    hidden = np.bincount(k[ahead], minlength=unique.size) >= _OCCLUDER_TARGETS
    return hidden[np.searchsorted(unique, frames)]


#: What counts as a road user between the radar and the vehicle (``_occluded``): tracked
#: moving targets, this many in one frame (one is a stray), within the box's bearings
#: widened by this much [deg] and nearer than its nearest corner by this much [m] (three
#: sigma of range noise: the vehicle's own targets are not).
_OCCLUDER_TARGETS = 2
_OCCLUDER_MARGIN_DEG = 1.0
_OCCLUDER_GAP_M = 0.5
_OCCLUDER_HEIGHT_M = 1.5


def _box_inside_view(pos: F64, yaw: F64, est: Extrinsics, view: RadarView,
                     config: CalibConfig) -> np.ndarray:
    """(n,) True where every corner of the vehicle's footprint lies inside the radar's view
    in range and azimuth.

    A car that the edge of the view cuts shows only its inner part: the mean of its
    reflections shifts towards the inside, by up to half a car, which no profile over the
    aspect can follow. Measured on a probe's recording with reflections spread uniformly
    over the footprint and a hard 70 m / +-50 deg view: 15 cm along the boresight with such
    frames, 1 cm without them (its other variants: 8 of them 106 -> 87 cm summed, one face
    model 12 -> 15 cm). Over 108 simulated ten-minute runs the horizontal median went from
    8.5 to 6.0 cm (skin), 6.3 to 6.2 (interior) and 6.0 to 6.1 (mixed).
    """
    max_range, (az_lo, az_hi) = view.range_m, view.azimuth_rad
    x0, x1, y0, y1 = box_limits(config.vehicle)
    c, s = np.cos(yaw), np.sin(yaw)
    ok = np.ones(pos.shape[0], bool)
    for cx in (x0, x1):
        for cy in (y0, y1):
            corner = pos.copy()
            corner[:, 0] += cx * c - cy * s
            corner[:, 1] += cx * s + cy * c
            corner[:, 2] -= config.vehicle.ref_height
            local = est.inverse_apply(corner)
            azimuth = np.arctan2(local[:, 1], local[:, 0])
            ok &= ((np.linalg.norm(local, axis=1) < max_range) & (azimuth > az_lo)
                   & (azimuth < az_hi))
    return ok


def _velocity_consistent(est: Extrinsics, index: I64, times: _Times, recording: Recording,
                         poses: _Poses, gate_mps: float) -> np.ndarray:
    """Mask of the targets whose radial velocity matches the vehicle's rigid motion.

    Within the box gate two kinds of target move unlike the car's body: another road user
    that overlaps the box for a while (a car turning across it, a truck alongside in a queue),
    and the wheels, whose micro-Doppler spreads over 0..2x the speed. Both carry position
    errors the soft-L1 loss only bounds: measured on the simulator, 4 % of foreign targets
    merged into a dense-traffic track moved the radar 25 cm along the boresight (1.5 cm
    without them), and wheel returns alone fit 0.6 m off. The body's v_r residual is
    0.06 m/s median; 0.6 m/s (``refine.velocity_gate_mps``) cuts 10-16 % of the targets.
    Over 108 simulated ten-minute runs the 90th percentile of the horizontal error fell
    from 19.5 to 11.5 cm (interior) and 20.2 to 15.7 cm (mixed), skin unchanged (8.5 cm
    median); dense traffic seed 1 from 27 to 12 cm. A radar with coarser velocities widens
    the gate to 4 robust sigma of the differences, so it never cuts into its noise. The
    first round, decimetres and about a degree off, is not gated.
    """
    sensor = recording.targets.positions_m[index]
    pos, _, vel, rate, _ = times.poses(poses, est.time_offset_s)
    world = est.apply(sensor)
    rel = world - pos
    point_velocity = vel + rate[:, None] * np.column_stack([-rel[:, 1], rel[:, 0],
                                                            np.zeros(len(rel))])
    los = world - est.translation_m
    unit = los / np.maximum(np.linalg.norm(los, axis=1), 1e-9)[:, None]
    diff = (np.einsum('ij,ij->i', point_velocity, unit)
            - recording.targets.radial_velocity_mps[index])
    robust_sigma = 1.4826 * float(np.median(np.abs(diff)))
    return np.abs(diff) <= max(gate_mps, _VELOCITY_GATE_SIGMAS * robust_sigma)


def _group_median(group: I64, values: F64, n_groups: int) -> F64:
    """(n_groups,) median of the finite ``values`` of each group (inf where none)."""
    finite = np.isfinite(values)
    g, v = group[finite], values[finite]
    out = np.full(n_groups, np.inf)
    # scipy.ndimage.median returns an arbitrary value for a label without members
    present = np.flatnonzero(np.bincount(g, minlength=n_groups))
    if present.size:
        out[present] = ndimage.median(v, g, present)
    return out


def _information_weights(frame_index: I64, pos: F64, aspect: F64, config: CalibConfig) -> F64:
    """Weight per target: the frames of one (vehicle position, aspect) cell share the weight
    of ``cell_frames`` frames, so a queued car counts as the few views it really gives."""
    cfg = config.refine
    ix = np.floor(pos[:, 0] / cfg.cell_size_m).astype(np.int64)
    iy = np.floor(pos[:, 1] / cfg.cell_size_m).astype(np.int64)
    ia = np.floor((np.degrees(aspect) % 360.0) / cfg.cell_aspect_deg).astype(np.int64)
    cells = np.stack([ix, iy, ia], axis=1)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    cell = cell.ravel()
    # distinct frames per cell
    pairs = np.unique(np.stack([cell, frame_index], axis=1), axis=0)
    frames_per_cell = np.bincount(pairs[:, 0], minlength=int(cell.max()) + 1)
    return np.minimum(1.0, cfg.cell_frames / frames_per_cell[cell])


def _in_passes(t_s: F64, gap_s: float) -> np.ndarray:
    """(n,) False for targets in runs of fewer than ``_MIN_PASS_TARGETS``: a few targets
    near the box for an instant are another road user or clutter, not a pass (they would
    also count as passes in the jackknife and shrink its t-factor)."""
    ids = _passes(t_s, gap_s)
    return np.bincount(ids)[ids] >= _MIN_PASS_TARGETS


def _range_bands(data: _Selected) -> I64:
    """(n,) range band (0 .. _RANGE_BANDS - 1, equal information weight each) of each
    target, for the jackknife over range bands."""
    rng = np.linalg.norm(data.sensor_m, axis=1)
    weight = data.sqrt_weight ** 2
    order = np.argsort(rng)
    cum = np.cumsum(weight[order])
    quantiles = np.arange(1, _RANGE_BANDS) / _RANGE_BANDS
    edges = rng[order][np.searchsorted(cum, cum[-1] * quantiles)]
    return np.searchsorted(edges, rng).astype(np.int64)


def _passes(times: F64, gap_s: float) -> I64:
    """Pass id per target (0..G-1): runs of targets without a gap longer than gap_s."""
    order = np.argsort(times, kind='stable')
    breaks = np.concatenate([[0], (np.diff(times[order]) > gap_s).astype(np.int64)])
    ids = np.empty(times.size, np.int64)
    ids[order] = np.cumsum(breaks)
    return ids


def _whitening(sensor: F64, rotation: F64, yaw: F64, scatter_sigma: F64,
               config: CalibConfig, vertical_ok: np.ndarray | None = None) -> F64:
    """(n, 3, 3) inverse Cholesky factors of each target's position covariance in the world:
    the radar's spherical noise (range, azimuth, elevation) plus the reflectors' scatter
    around their mean (diagonal in the vehicle frame)."""
    cfg = config.refine
    rng = np.linalg.norm(sensor, axis=1)
    az = np.arctan2(sensor[:, 1], sensor[:, 0])
    el = np.arcsin(np.clip(sensor[:, 2] / np.maximum(rng, 1e-9), -1.0, 1.0))
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    e_r = np.column_stack([ce * ca, ce * sa, se])
    e_az = np.column_stack([-sa, ca, np.zeros_like(sa)])
    e_el = np.column_stack([-se * ca, -se * sa, ce])
    var_r = cfg.range_sigma_m ** 2
    var_az = (rng * ce * math.radians(cfg.azimuth_sigma_deg)) ** 2
    var_el = (rng * math.radians(cfg.elevation_sigma_deg)) ** 2
    cov_s = (var_r * e_r[:, :, None] * e_r[:, None, :]
             + var_az[:, None, None] * e_az[:, :, None] * e_az[:, None, :]
             + var_el[:, None, None] * e_el[:, :, None] * e_el[:, None, :])
    cov_w = np.einsum('ij,njk,lk->nil', rotation, cov_s, rotation)
    c, s = np.cos(yaw), np.sin(yaw)
    sx2, sy2, sz2 = np.asarray(scatter_sigma, float) ** 2
    cov_w[:, 0, 0] += c * c * sx2 + s * s * sy2
    cov_w[:, 1, 1] += s * s * sx2 + c * c * sy2
    cov_w[:, 0, 1] += c * s * (sx2 - sy2)
    cov_w[:, 1, 0] += c * s * (sx2 - sy2)
    cov_w[:, 2, 2] += sz2
    if vertical_ok is not None:
        # no height information from these targets: an (almost) infinite vertical variance
        # drops the vertical row and leaves the horizontal ones as they were
        cov_w[~vertical_ok, 2, :2] = 0.0
        cov_w[~vertical_ok, :2, 2] = 0.0
        cov_w[~vertical_ok, 2, 2] = 1e8
    chol = np.linalg.cholesky(cov_w)
    return np.linalg.inv(chol)


# --- the clock offset's starting value --------------------------------------------------

def _scan_time_offset(est: Extrinsics, candidates: I64, times: _Times, recording: Recording,
                      poses: _Poses, config: CalibConfig) -> float:
    """Coarse start for the clock offset: the offset that puts the most moving targets near
    the box (soft count). The fit itself refines it; the scan only keeps a large offset
    (vehicle displaced by metres) from starving the gate."""
    max_off = config.sync.max_time_offset
    if max_off <= 0.0 or candidates.size == 0:
        return est.time_offset_s
    # around the bound's centre, and around where stage 6 found agreement (beyond the bound
    # when the fixes' and the Odometry's stamps disagree: ``pipeline._hypotheses``)
    grid = np.union1d(np.arange(-max_off, max_off + 1e-9, 0.02),
                      est.time_offset_s + np.arange(-0.1, 0.1 + 1e-9, 0.02))
    world = est.apply(recording.targets.positions_m[candidates])
    gate = config.refine.gate_m
    scores = np.empty(grid.size)
    for i, tau in enumerate(grid):   # a few dozen offsets, each vectorised over targets
        pos, yaw, _, _, _ = times.poses(poses, tau)
        dist = box_distance(_vehicle_frame(world, pos, yaw)[:, :2], config.vehicle)
        scores[i] = np.sum(np.clip(1.0 - dist / gate, 0.0, 1.0) * times.valid(poses, tau))
    best = float(grid[int(np.argmax(scores))])
    # A flat score (no information) keeps the given offset.
    if scores.max() <= 1.001 * scores[int(np.argmin(np.abs(grid - est.time_offset_s)))]:
        return est.time_offset_s
    return best


# --- the stage --------------------------------------------------------------------------

def refine_extrinsics(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
                      selection: HypothesisSelection, config: CalibConfig, *,
                      ground_normal: F64 | None = None) -> Refinement:
    """Final robust refinement of rotation, translation, clock offset and reflection profile.

    Parameters
    ----------
    initial : Extrinsics
        Estimate after the paper's stages (decimetres, about a degree off; clock offset
        unknown within ``sync.max_time_offset``).
    recording : Recording
    tracked : TrackedTargets
        Moving targets with track ids; seeds the selection (stationary targets never count).
    selection : HypothesisSelection
        Its accepted tracks are always admitted to the gate.
    config : CalibConfig
        Uses ``refine``, ``sync``, ``vehicle``, ``hypotheses.pass_gap_s`` and
        ``quality.max_boresight_sigma_m``.
    ground_normal : ndarray of shape (3,), optional
        The road plane's normal in the sensor frame (stage 4): a weak prior on the tilt
        (``_TILT_PRIOR_DEG``) where the vehicle's views leave it undetermined.

    Returns
    -------
    Refinement
        ``extrinsics`` (clock offset on top of ``sync.time_offset``), the 7x7 covariance over
        [rotation vector (world, left perturbation), translation, time offset] from a
        jackknife over passes, the reflection profile (``core/reflection.py`` layout) and
        diagnostics: sigmas, advice, coverage, per-pass summaries and residual arrays.

    Raises
    ------
    InsufficientDataError
        Fewer than a handful of targets near the vehicle.

    References
    ----------
    method-paper.tex, Sec. "Result Refinement" (what this stage goes beyond).
    """
    # The products here are tall and skinny (tens of thousands of rows, ~20 columns):
    # memory-bound, and multi-threaded BLAS only spins on a busy machine (measured 10x
    # slower with 2 cores shared). One thread is as fast when idle and far faster when not.
    with threadpool_limits(limits=1, user_api='blas'):
        start_sigma = _START_SIGMA_M
        held_note: _Diverged | None = None
        try:
            refinement = _refine_checked(initial, recording, tracked, selection, config,
                                         ground_normal, None)
        except _Diverged as err:
            # Every drive runs towards or away from the radar: the position along the
            # boresight is a flat valley that the reflection depth trades along, and the
            # half-metre prior did not hold the fit in it (a twenty-second probe's straight
            # drives: 9 of 17 ran 5-9 m off and were refused as radial velocities gone
            # wrong, which they were not). There the position is held at the paper's
            # estimate, whose error the uncertainty reports (a car length, ``_start_term``).
            if not _drives_along_boresight(initial, recording, tracked, selection, config):
                raise
            start_sigma = _HELD_START_SIGMA_M
            try:
                refinement = _refine_checked(initial, recording, tracked, selection, config,
                                             ground_normal, None, start_sigma)
            except InsufficientDataError:
                raise err from None
            held_note = err
        # Drives along one road leave the position along the boresight open by up to a car
        # length, and a drive across the view that would close it then lies that far from
        # the box, outside the gate: seen from a place it was never fitted at (see
        # ``_rescan_along_boresight``), it is fitted from there and kept where it agrees.
        rescan = _rescan_along_boresight(refinement, recording, tracked, config)
        if rescan is not None:
            try:
                other = _refine_checked(rescan, recording, tracked, selection, config,
                                        ground_normal, None)
            except InsufficientDataError:
                other = None
            if other is not None and _rescan_better(other, refinement):
                _LOG.info('started again %.2f m along the boresight: %d passes (%d before), '
                          'along-boresight sigma %.2f m (%.2f before)',
                          float(np.linalg.norm(rescan.translation_m
                                               - refinement.extrinsics.translation_m)),
                          other.n_passes, refinement.n_passes,
                          other.diagnostics['sigma_along_boresight_m'],
                          refinement.diagnostics['sigma_along_boresight_m'])
                other.diagnostics['rescan_shift_m'] = [
                    float(v) for v in rescan.translation_m - refinement.extrinsics.translation_m]
                initial, refinement = rescan, other
        # Where the offsets the passes show change steadily with time, the fit is run again
        # with the radar's stamps on a clock of that rate (see ``_clock_drift``). The
        # passes' offsets are taken at a fit that has partly followed the drift with its
        # other parameters (the position, where the directions driven change over time), so
        # they show less of it than there is: what they still show is added, a few times.
        # A clock that stepped between two passes (``_clock_step``) is tested first: a
        # straight line drawn through a step misplaces every pass but the middle ones.
        drift: ClockDrift | None = None
        reference_s = _mid_recording_s(recording, config)
        for _ in range(_DRIFT_REFITS):
            # once a drift or step is found, what is left of it is estimated, not tested
            # for again
            offsets = refinement.diagnostics.get('pass_time_offsets', [])
            if drift is None:
                more = (_clock_step(offsets) or _clock_drift(offsets, reference_s))
            elif drift.step_s:
                more = _clock_step(offsets, at_s=drift.step_at_s)
            else:
                more = _clock_drift(offsets, reference_s, found=True)
            if more is None or (drift is not None
                                and more.size < _DRIFT_SETTLED * drift.size):
                break
            drift = more if drift is None else drift.plus(more)
            try:
                refinement = _refine_checked(initial, recording, tracked, selection, config,
                                             ground_normal, drift, start_sigma)
            except InsufficientDataError:
                break
            _LOG.info('radar clock drift %.0f +- %.0f ppm, step %.0f ms: refitted',
                      1e6 * drift.rate, 1e6 * drift.sigma, 1e3 * drift.step_s)
        if held_note is not None:
            sigma = refinement.diagnostics['sigma_along_boresight_m']
            refinement.diagnostics['advice'] = [
                'Every drive ran towards or away from the radar, which leaves its position '
                'along the boresight to where the paper\'s stages put it: the fit, left free, '
                f'ran {held_note.shift_m:.1f} m (and {held_note.turn_deg:.1f} deg) off along '
                'that open direction. The horizontal position was held at the paper\'s '
                f'estimate, uncertain by about a car length ({sigma:.1f} m along the '
                'boresight, 1 sigma): cross the view or turn through it to measure it.',
                *refinement.diagnostics['advice']]
            _LOG.info('%s', refinement.diagnostics['advice'][0])
        return refinement


#: Width of the prior that holds the horizontal position at the paper's estimate where
#: every drive runs along the boresight and the fit ran off along it [m].
_HELD_START_SIGMA_M = 0.05
#: The drives all run along the boresight (``uncertainty.near_axis``) when this share of
#: the accepted tracks' targets are seen so.
_ALONG_BORESIGHT_SHARE = 0.9


def _drives_along_boresight(est: Extrinsics, recording: Recording, tracked: TrackedTargets,
                            selection: HypothesisSelection, config: CalibConfig) -> bool:
    """Whether the vehicle heads towards or away from the radar (``uncertainty.near_axis``
    of its boresight) wherever the accepted tracks see it."""
    index = np.asarray(tracked.target_index, np.int64)[np.isin(
        tracked.track_id, np.asarray(selection.accepted_track_ids, np.int64))]
    if index.size == 0:
        return False
    poses, times = _vehicle_poses(recording, index, config)
    valid = times.valid(poses, est.time_offset_s)
    if not valid.any():
        return False
    _, yaw, _, _, _ = times.poses(poses, est.time_offset_s)
    boresight = math.atan2(est.rotation[1, 0], est.rotation[0, 0])
    return float(np.mean(uncertainty.near_axis(yaw[valid], boresight))) >= _ALONG_BORESIGHT_SHARE


#: Shifts along the boresight are searched for left-out drives only where the fit leaves the
#: position open by at least this much (3 sigma) [m]: nearer, the gate sees them already.
_RESCAN_MIN_HALF_WIDTH_M = 1.0
#: ... at most this many vehicle lengths either way, in steps of [m].
_RESCAN_MAX_LENGTHS = 1.5
_RESCAN_STEP_M = 0.25
#: Left-out drives join only with at least this share of the fitted targets (and a pass's
#: worth): a few stray targets of other road users do not move the start.
_RESCAN_MIN_SHARE = 0.1


def _rescan_along_boresight(refinement: Refinement, recording: Recording,
                            tracked: TrackedTargets, config: CalibConfig) -> Extrinsics | None:
    """A start shifted along the boresight at which drives the fit left out join it.

    Straight drives along one road (a radar mid-block) show the car head-on and tail-on
    only: its reflection depth trades off exactly against the radar's distance, and the
    paper's stages leave the radar up to a car length off along the boresight (a twentieth
    probe: 1-4 m). A drive across the view would show the sides and settle it, but from
    that start its targets lie metres beside the box and the gate leaves them out: two such
    drives were reported "without targets" while the fit stayed 3.5 and 4.3 m off. So the
    open direction is searched, within 3 sigma of it (at most ``_RESCAN_MAX_LENGTHS``
    vehicle lengths), for the shift that brings the most targets of the left-out drives
    into the gate, their radial velocities matching the vehicle's; the centre of that
    stretch is the new start (the caller keeps the fit from there only where it takes in
    more passes and narrows the open direction).
    """
    est = refinement.extrinsics
    sigma = float(refinement.diagnostics.get('sigma_along_boresight_m', 0.0))
    half = min(3.0 * sigma, _RESCAN_MAX_LENGTHS * config.vehicle.length)
    boresight = np.array([est.rotation[0, 0], est.rotation[1, 0], 0.0])
    norm = float(np.linalg.norm(boresight))
    if half < _RESCAN_MIN_HALF_WIDTH_M or norm < 1e-6:
        return None
    boresight /= norm
    candidates = np.asarray(tracked.target_index, np.int64)
    track_ids = np.asarray(tracked.track_id, np.int64)
    track_size = _track_sizes(track_ids)
    poses, times = _vehicle_poses(recording, candidates, config)
    fitted = np.asarray(refinement.diagnostics['residuals']['target_index'], np.int64)
    fitted_t = np.sort(times.t_s[np.isin(candidates, fitted)])
    if fitted_t.size == 0:
        return None
    # the targets of drives with no fitted target (none within a pass gap in time)
    after = np.clip(np.searchsorted(fitted_t, times.t_s), 0, fitted_t.size - 1)
    before = np.maximum(after - 1, 0)
    gap = np.minimum(np.abs(times.t_s - fitted_t[after]), np.abs(times.t_s - fitted_t[before]))
    unused = gap > config.hypotheses.pass_gap_s
    if not unused.any():
        return None
    candidates, track_ids, track_size = (candidates[unused], track_ids[unused],
                                         track_size[unused])
    times = times.subset(unused)
    view = recording.radar_view()
    shifts = np.arange(-half, half + 1e-9, _RESCAN_STEP_M)
    counts = np.zeros(shifts.size)
    for i, shift in enumerate(shifts):
        moved = Extrinsics(est.rotation, est.translation_m + shift * boresight,
                           est.time_offset_s)
        keep = _gate(moved, candidates, track_ids, track_size, np.zeros(0, np.int64), times,
                     recording, poses, config, first_round=False, view=view)
        if keep.any():
            keep[keep] = _in_passes(times.subset(keep).t_s, config.hypotheses.pass_gap_s)
        counts[i] = keep.sum()
    best = int(np.argmax(counts))
    if counts[best] < max(_MIN_PASS_TARGETS, _RESCAN_MIN_SHARE * fitted.size):
        return None
    # the gate is a stretch as wide as the car and the gate: its centre, not its edge
    lo = hi = best
    while lo > 0 and counts[lo - 1] >= 0.5 * counts[best]:
        lo -= 1
    while hi < shifts.size - 1 and counts[hi + 1] >= 0.5 * counts[best]:
        hi += 1
    shift = float(np.average(shifts[lo:hi + 1], weights=counts[lo:hi + 1]))
    return Extrinsics(est.rotation, est.translation_m + shift * boresight, est.time_offset_s)


def _rescan_better(other: Refinement, first: Refinement) -> bool:
    """The fit from a rescanned start is kept where it takes in more passes and narrows
    the position along the boresight: the drives it added agree with the others."""
    return (other.n_passes > first.n_passes
            and other.diagnostics['sigma_along_boresight_m']
            < first.diagnostics['sigma_along_boresight_m'])


def _refine_checked(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
                    selection: HypothesisSelection, config: CalibConfig,
                    ground_normal: F64 | None, drift: ClockDrift | None,
                    start_sigma_m: float = _START_SIGMA_M) -> Refinement:
    """``_refine`` with the model check and a 2-D radar's tilt probes (below)."""
    alternative = None
    if config.refine.model_check:
        # The reflection model is the largest error left, and neither jackknife sees the
        # part every pass shares. The same fit under another range law of the profile
        # (perspective -> depth only; depth <-> full) shows how much the position depends
        # on that choice; the squared difference enters the reported covariance along its
        # direction, capped at this fit's own variance there (at most sqrt(2) wider):
        # a difference far beyond the data's precision says the alternative, with its
        # many more range terms, is ill-determined in that geometry (seen: 2 m apart
        # where this fit erred by 11 cm), not that this fit is off by that much.
        # Measured over 106 simulated ten-minute runs (with the 2 cm along-boresight
        # term): the 2-sigma ellipse covered 97 / 100 / 82 % of the interior / mixed /
        # skin horizontal errors without it, 97 / 100 / 97 % with it, for one more fit.
        other = 'full' if config.refine.profile_range_terms == 'depth' else 'depth'
        alt_config = dataclasses.replace(config, refine=dataclasses.replace(
            config.refine, profile_range_terms=other, model_check=False))
        try:
            alternative = _refine(initial, recording, tracked, selection, alt_config,
                                  None, ground_normal=ground_normal, drift=drift,
                                  start_sigma_m=start_sigma_m).extrinsics.translation_m
        except InsufficientDataError:
            alternative = None
    tilted: list[F64] = []
    if not recording.has_elevation:
        # A 2-D radar's roll and pitch are held level (nothing measures them), yet they
        # still move its position: a tilted plane maps azimuth to bearing differently
        # off the boresight (a fifth probe's radar pitched 7 deg: 45 cm along the
        # boresight, reported at 18). The fit is run again with each held at a tilt, and
        # what it moves joins the covariance for their reported uncertainty.
        single = dataclasses.replace(config, refine=dataclasses.replace(
            config.refine, model_check=False))
        for axis in np.eye(3)[:2]:
            turn = Rotation.from_rotvec(math.radians(_PLANAR_PROBE_DEG) * axis)
            start = Extrinsics(np.asarray(initial.rotation, float) @ turn.as_matrix(),
                               np.asarray(initial.translation_m, float),
                               float(initial.time_offset_s))
            try:
                tilted.append(_refine(start, recording, tracked, selection, single,
                                      None, drift=drift, start_sigma_m=start_sigma_m
                                      ).extrinsics.translation_m)
            except InsufficientDataError:
                continue
    refinement = _refine(initial, recording, tracked, selection, config, alternative,
                         tilted, ground_normal=ground_normal, drift=drift,
                         start_sigma_m=start_sigma_m)
    moved = refinement.diagnostics.get('tilt_from_plane_deg', 0.0)
    spread = refinement.diagnostics.get('line_spread_m', math.inf)
    if moved <= _TILT_MOVED_DEG or spread >= _LINE_SPREAD_M:
        return refinement
    # Every target lies along one road (one lane of a one-way street; a narrow beam
    # across a road far away): a tilt about that road, with the altitude, moves them by
    # the road's width times the angle, i.e. centimetres per degree, and what decides it
    # then is how the reflections' height differs from the model (the near and far side
    # of the car, front and rear), not the radar's tilt. An eighteenth probe: 1.0-3.4 deg
    # and 0.5-2 m of altitude off at a reported 0.4-0.6 deg, where the road plane (stage
    # 4) had the tilt to 0.1 deg. Such a fit is run again with the tilt held at the road
    # plane's, and the difference between the two joins the covariance as its 2 sigma.
    try:
        held = _refine(initial, recording, tracked, selection, config, alternative,
                       tilted, ground_normal=ground_normal, drift=drift,
                       tilt_prior_deg=_HELD_TILT_DEG, start_sigma_m=start_sigma_m)
    except InsufficientDataError:
        return refinement
    free, kept = refinement.extrinsics, held.extrinsics
    difference = np.concatenate([
        Rotation.from_matrix(free.rotation @ kept.rotation.T).as_rotvec(),
        free.translation_m - kept.translation_m, [free.time_offset_s - kept.time_offset_s]])
    covariance = held.covariance + 0.25 * np.outer(difference, difference)
    # The road plane is no surer of that tilt where the road carries traffic both ways: the
    # road users' reflections lie in it at heights that differ from lane to lane (traffic
    # comes towards the radar on one side of the road showing its front, goes away on the
    # other showing its rear), and that height difference over the lanes' separation is its
    # roll about the road. A twenty-fourth probe's radars beside a two-way road: the plane
    # 3 deg off in roll (8 of 8 runs), reported at 1.0-1.8; an eighteenth probe's one-way
    # streets had it to 0.2 deg. Held there, the fit's altitude and position follow that
    # roll (targets metres below and beside the radar swing with it): a consider term of the
    # vehicle's front/rear height difference (``refine.model_sigma_height_difference_m``)
    # over the separation of the two directions' lanes, rotating about the road through the
    # radar.
    axis = held.diagnostics.get('line_axis')
    offset = held.diagnostics.get('target_offset_m')
    lanes = held.diagnostics.get('lane_separation_m')
    if axis is not None and offset is not None and lanes is not None:
        roll = math.atan2(config.refine.model_sigma_height_difference_m,
                          max(lanes, _MIN_LANE_SEPARATION_M))
        swing = np.concatenate([axis, -np.cross(axis, offset), [0.0]])
        covariance = covariance + roll ** 2 * np.outer(swing, swing)
    diagnostics = dict(held.diagnostics)
    diagnostics.update(uncertainty.sigma_summary(covariance, kept.rotation))
    diagnostics['tilt_held'] = {'moved_deg': moved, 'line_spread_m': spread,
                                'altitude_change_m': float(-difference[5])}
    diagnostics['advice'] = [
        f'The vehicle was seen along one road only (its targets spread {spread:.1f} m across '
        f'it), which cannot show the radar\'s roll and pitch about that road: the fit tilted '
        f'the radar {moved:.1f} deg from the road plane the other road users show, following '
        'the vehicle\'s reflection heights instead. The tilt was held at the road plane '
        f'(the altitude moved {-difference[5]:+.2f} m with it) and the uncertainty widened. '
        'Drive through the view on a second road, or turn through it, to measure the tilt.',
        *diagnostics['advice']]
    _LOG.info('%s', diagnostics['advice'][0])
    return dataclasses.replace(held, covariance=covariance, diagnostics=diagnostics)


def _refine(initial: Extrinsics, recording: Recording, tracked: TrackedTargets,
            selection: HypothesisSelection, config: CalibConfig,
            alternative_translation: F64 | None,
            tilted_translations: list[F64] | None = None, *,
            ground_normal: F64 | None = None, drift: ClockDrift | None = None,
            tilt_prior_deg: float | None = None,
            start_sigma_m: float = _START_SIGMA_M) -> Refinement:
    cfg = config.refine
    candidates = np.asarray(tracked.target_index, np.int64)
    track_ids = np.asarray(tracked.track_id, np.int64)
    accepted = np.asarray(selection.accepted_track_ids, np.int64)
    poses, times = _vehicle_poses(recording, candidates, config, drift)
    estimate_tau = bool(config.sync.estimate_time_offset) and config.sync.max_time_offset > 0
    est = Extrinsics(np.asarray(initial.rotation, float),
                     np.asarray(initial.translation_m, float), float(initial.time_offset_s))
    # Every later step looks only at targets that could come near the box: a generous
    # corridor around the initial estimate (its decimetres and ~1 deg, the largest clock
    # offset at the vehicle's speed) cuts a busy junction's moving targets ten-fold.
    # Track sizes are counted before, so the track rule of the gate keeps its meaning.
    track_size = _track_sizes(track_ids)
    view = recording.radar_view()
    fov = view.elevation_rad

    def linearised_at(data: _Selected, est: Extrinsics, profile: F64,
                      stride: int = 1) -> tuple[_Model, F64]:
        """The model linearised at ``est`` and the parameter vector of that point (each
        round's start, and the final point for the covariance). A fit of every
        ``stride``-th target weighs its priors down by as much: they keep their say
        against the data, while the data's robust loss sees the same residuals."""
        model = _Model(data, poses, est.rotation, est.translation_m,
                       None if estimate_tau else est.time_offset_s, harmonics,
                       cfg.velocity_sigma_mps, _anchor(prior_mean, start, est, tilt_anchor),
                       prior_sigma * math.sqrt(stride), centre_x, cfg.profile_range_terms,
                       cfg.azimuth_scale_sigma > 0)
        x = np.zeros(model.n_par)
        if estimate_tau:
            x[6] = est.time_offset_s
        x[model.i_prof:] = profile
        return model, x
    # every tracked moving target, what may hide the car (but not the vehicle's own tracks)
    road_users, road_user_tracks = candidates.copy(), track_ids.copy()
    corridor = _corridor(est, candidates, times, recording, poses, config)
    candidates, track_ids = candidates[corridor], track_ids[corridor]
    times = times.subset(corridor)
    track_size = track_size[corridor]
    if estimate_tau:
        tau0 = _scan_time_offset(est, candidates, times, recording, poses, config)
        est = Extrinsics(est.rotation, est.translation_m, tau0)
    harmonics = cfg.profile_harmonics
    x_lo, x_hi, _, _ = box_limits(config.vehicle)
    centre_x = 0.5 * (x_lo + x_hi)
    prior_mean, prior_sigma = _priors(config, harmonics, estimate_tau, start_sigma_m)
    if not recording.has_elevation:
        # A 2-D radar (z = 0 for every target) measures no height, so its targets hold no
        # roll or pitch: left free, the fit tilts the radar's plane until it passes through
        # the car (a fifth probe's six such recordings ran 8-22 deg off and were refused).
        # They stay where the paper's stages put them (level), and the covariance says how
        # little that is worth. The altitude is left to the radial velocities, which the
        # line of sight's dip shrinks (see ``_slant_to_height``).
        prior_mean[:2], prior_sigma[:2] = 0.0, _PLANAR_HOLD_RAD
    start = est
    tilt_anchor = start.rotation
    if recording.has_elevation and ground_normal is not None:
        # The road plane of every road user (stage 4) holds the tilt where the vehicle's
        # own views cannot: seen only along one direction (a single road at the edge of the
        # view, a narrow long-range beam), the rotation about that direction moves its
        # targets by millimetres, and the fit wandered 2-3 deg off while the plane had it
        # to 0.1 (an independent recording: 3.6 deg, reported at 1.1). The plane is the
        # road's, not level: the road's own tilt comes from the vehicle's RTK altitude.
        up = start.rotation @ np.asarray(ground_normal, float)
        tilt_anchor = _rotation_between(up, _road_up(poses, start, recording.fix_sigma_m)
                                        ) @ start.rotation
        prior_mean[:2] = 0.0
        prior_sigma[:2] = math.radians(_TILT_PRIOR_DEG if tilt_prior_deg is None
                                       else tilt_prior_deg)
    profile = np.nan_to_num(prior_mean[(7 if estimate_tau else 6):])
    scatter = np.full(3, cfg.position_sigma_m)
    previous: I64 | None = None
    tau_held: float | None = None
    data: _Selected | None = None
    model: _Model | None = None
    fit: _Fit | None = None
    rounds = 0
    stride = 1
    noise_config = config
    azimuth_noise = 0.0
    elevation_noise = 0.0
    hidden_targets = 0

    def fit_round(keep: np.ndarray, every: int) -> tuple[float, float, float]:
        """Fit the gated targets (every ``every``-th by target number) from ``est``;
        returns how far it moved."""
        nonlocal data, model, fit, est, profile, scatter, noise_config, azimuth_noise
        nonlocal elevation_noise
        if every > 1:
            keep = keep & (candidates % every == 0)
        data = _select(candidates[keep], times.subset(keep), est, recording, poses, scatter,
                       noise_config, fov)
        model, x0 = linearised_at(data, est, profile, every)
        fit = _solve(model, x0)
        rot, trans, tau, profile = model.unpack(fit.x)
        moved = _change(est, rot, trans, tau)
        est = Extrinsics(rot, trans, tau)
        # the next round whitens with the azimuth noise the radar shows where that is far
        # above the configured one (each round anew: the first, gated wide, shows more)
        geometry = model.geometry(fit.x)
        azimuth_noise = _azimuth_noise_deg(geometry, data)
        elevation_noise = _elevation_noise_deg(geometry, data)
        measured = {}
        if _noisy_azimuth(azimuth_noise, cfg.azimuth_sigma_deg):
            measured['azimuth_sigma_deg'] = azimuth_noise
        if _noisy_elevation(elevation_noise, cfg.elevation_sigma_deg):
            measured['elevation_sigma_deg'] = elevation_noise
        noise_config = (dataclasses.replace(config, refine=dataclasses.replace(cfg, **measured))
                        if measured else config)
        scatter = _scatter(geometry, cfg.position_sigma_m, noise_config)
        _LOG.debug('refine round %d: %d targets (every %d), %d iterations, moved %s', rounds,
                   data.index.size, every, fit.iterations, moved)
        return moved

    for rounds in range(1, cfg.max_iterations + 1):
        keep = _gate(est, candidates, track_ids, track_size, accepted, times, recording, poses,
                     config, first_round=rounds == 1, view=view)
        if rounds > 1 and keep.any():
            # not from the paper's estimate: a box metres off takes the vehicle's own
            # targets for something in front of it (a fourteenth probe's van: 0.1 -> 3 m)
            others = road_users[(road_user_tracks >= 0)
                                & ~np.isin(road_user_tracks, track_ids[keep])]
            hidden = _occluded(est, candidates[keep], times.subset(keep), recording, poses,
                               others, config)
            hidden_targets = int(hidden.sum())
            keep[keep] = ~hidden
        keep[keep] = _in_passes(times.subset(keep).t_s, config.hypotheses.pass_gap_s)
        index = candidates[keep]
        if index.size < _MIN_TARGETS:
            # Said with where the estimate came from: in the first round it is the paper's
            # stages', and a vehicle with nothing near it there means those stages agreed
            # on something else (a fourth probe's radar folded a third of the car's radial
            # velocities, and the bare count told the user nothing).
            if rounds == 1:
                where = ('where the paper\'s stages put it: they agreed on tracks that were '
                         'not the vehicle\'s (other road users by chance, or a radar whose '
                         'radial velocities fold at its unambiguous limit); check the drive '
                         'and the radar\'s velocity range')
            else:
                unchecked = config if cfg.velocity_gate_mps <= 0 else dataclasses.replace(
                    config, refine=dataclasses.replace(cfg, velocity_gate_mps=0.0))
                near = int(_gate(est, candidates, track_ids, track_size, accepted, times,
                                 recording, poses, unchecked, first_round=False,
                                 view=view).sum())
                angle, shift, clock = _change(start, est.rotation, est.translation_m,
                                              est.time_offset_s)
                why = f'radial velocities off the vehicle\'s motion: {_VELOCITY_SUSPECTS}'
                if clock > 0.05:
                    # the vehicle moved along its travel by its speed times that
                    why = ('a clock offset the drives cannot pin down (set sync.time_offset '
                           'and sync.estimate_time_offset: false if it is known), or ' + why)
                where = (f'moving as the vehicle does ({near} lie near it, but with {why})'
                         if near >= _MIN_TARGETS else
                         f'after the first round moved the estimate {shift:.1f} m, '
                         f'{math.degrees(angle):.1f} deg and the clock offset by {clock:.2f} s '
                         f'from the paper\'s stages\' (what pulls it away is most likely '
                         f'{why})')
            reason = (f'only {index.size} targets within {cfg.gate_m} m of the vehicle '
                      f'box {where}, need at least {_MIN_TARGETS}')
            if rounds == 1:
                raise InsufficientDataError('refine', reason)
            # the first round took the estimate away from the vehicle
            raise _Diverged('refine', reason, shift, math.degrees(angle))
        # Targets are numbered frame by frame, so every k-th number thins each frame evenly
        # and picks the same targets again when the gate barely changes.
        stride = max(1, index.size // _ROUND_TARGETS)
        moved = fit_round(keep, stride)
        if rounds == 1 and estimate_tau and tau_held is None:
            assert model is not None and fit is not None
            tau_sigma = _parameter_sigma(model, fit.x, 6, stride)
            if tau_sigma > _TAU_HOLD_SIGMA_S:
                # the drives cannot show the clock offset: hold it where the paper's stages
                # had it and fit this round again from their estimate. What it is uncertain
                # by counts how far the free round put it from there too: a nineteenth
                # probe's held offsets were 35 ms off at a first-round sigma of 10-13 ms.
                tau_held = math.hypot(tau_sigma, est.time_offset_s - initial.time_offset_s)
                _LOG.info('the clock offset is not observable here (sigma %.3f s after the '
                          'first round, which moved it %+.3f s): held at %+.3f s', tau_sigma,
                          est.time_offset_s - start.time_offset_s, initial.time_offset_s)
                prior_mean[6], prior_sigma[6] = float(initial.time_offset_s), _TAU_HOLD_S
                est = Extrinsics(start.rotation, start.translation_m,
                                 float(initial.time_offset_s))
                profile = np.nan_to_num(prior_mean[7:])
                scatter = np.full(3, cfg.position_sigma_m)
                moved = fit_round(keep, stride)
        _check_not_diverged(start, est, planar=not recording.has_elevation)
        same = previous is not None and np.array_equal(previous, index)
        previous = index
        if same and moved[0] < 1e-4 and moved[1] < 1e-3 and moved[2] < 1e-4:
            break
    final_stride = max(1, -(-int(keep.sum()) // _FINAL_TARGETS))
    if stride > final_stride:
        fit_round(keep, final_stride)
        stride = final_stride
    assert data is not None and model is not None and fit is not None
    # Covariance at the final solution, re-based so w = 0 is the reported rotation.
    # A thinned final fit stands in for all its targets: each row counts ``stride`` times
    # against the priors at full strength (as in the fit, where the priors were weighed
    # down instead), or the prior-held directions (the height) would widen by sqrt(stride).
    model, x_hat = linearised_at(data, est, profile)
    r, j, _, jp = model.residuals(x_hat, jac=True)
    assert j is not None and jp is not None
    w = np.sqrt(_robust(r, data.index.size)[0] * stride)
    row_pass = np.concatenate([np.repeat(data.pass_id, 3), data.pass_id])
    pc = uncertainty.pass_jackknife_covariance(j * w[:, None], r * w, row_pass, jp.T @ jp)
    band = _range_bands(data)
    row_band = np.concatenate([np.repeat(band, 3), band])
    pb = uncertainty.pass_jackknife_covariance(j * w[:, None], r * w, row_band, jp.T @ jp,
                                               prior_term=False)
    halves_shift = _halves_shift(pc, jp.T @ jp)
    start_term = _start_term(pc, jp.T @ jp, config, start_sigma_m)
    covariance = uncertainty.shrink_correlations(uncertainty.combined_covariance(pc, pb),
                                                 pc.n_passes) + start_term
    cov7 = uncertainty.add_along_boresight(_pose_block(covariance, estimate_tau), est.rotation,
                                           cfg.model_sigma_along_m)
    cov7 = uncertainty.add_tilt(cov7, math.radians(cfg.model_sigma_tilt_deg))
    height_shift = _height_difference_shift(model, x_hat, j, w, jp)
    cov7 += _pose_block(np.outer(height_shift, height_shift), estimate_tau) * (
        cfg.model_sigma_height_difference_m ** 2)
    # The vehicle's mean reflection height changes with range (the roof seen from near and
    # above, road-multipath images merging far away): on our simulator by -0.17 to +0.48 m
    # from the median range to twice it, on an independent mesh car with 20 % road
    # ghosts by about 0.35 m. The fit cannot tell that from a pitch (a height growing with
    # range is a pitch wherever the targets lie ahead) or, where range follows azimuth (one
    # bend through the view), from a roll: it tilted that mesh car's radar by 0.55-1.15
    # deg at a reported 0.24 (all 11 such drives outside 2 sigma). A consider term of
    # ``refine.model_sigma_height_range_m`` per unit of relative range says so: about 2
    # deg of tilt per metre, i.e. 0.3-0.4 deg at 0.2 m.
    range_shift = _height_shift(model, x_hat, j, w, jp, model.geometry(x_hat)['rho'])
    cov7 += _pose_block(np.outer(range_shift, range_shift), estimate_tau) * (
        cfg.model_sigma_height_range_m ** 2)
    if not recording.has_elevation:
        # A 2-D radar (z = 0 for every target) measures no height: its targets carry no
        # roll, pitch or altitude (the field of view found from the data is zero wide, so
        # no target gives height information above), and those come from the start and
        # second-order effects only. Say so in the covariance rather than report the
        # jackknife's agreement on values nothing measured.
        cov7 = uncertainty.add_tilt(cov7, math.radians(_PLANAR_TILT_SIGMA_DEG))
        cov7[5, 5] += _PLANAR_HEIGHT_SIGMA_M ** 2
        for moved in tilted_translations or []:
            shift = (np.asarray(moved, float) - est.translation_m) * (
                _PLANAR_TILT_SIGMA_DEG / _PLANAR_PROBE_DEG)
            _LOG.debug('2-D radar: %.1f deg of held tilt moves the position by %s m',
                       _PLANAR_TILT_SIGMA_DEG, np.round(shift, 3))
            cov7[3:6, 3:6] += np.outer(shift, shift)
    model_difference = (np.zeros(3) if alternative_translation is None
                        else np.asarray(alternative_translation, float) - est.translation_m)
    cov7[3:6, 3:6] += uncertainty.model_term(model_difference, cov7[3:6, 3:6])
    # The vehicle's own position error passes one to one into the radar's, and a GNSS
    # error drifts over minutes, so the passes share it: the fixes' declared 1-sigma
    # (median over the drive; assumed from their status where they declare none) joins
    # the translation (RTK: ~2 cm, nothing; a standalone fix: metres, which the fit
    # cannot see).
    sigma_h, sigma_v = recording.pose_sigma_m
    cov7[3:6, 3:6] += np.diag([sigma_h ** 2, sigma_h ** 2, sigma_v ** 2])
    # The same error tilts and turns the fit where it differs along the drive: heights
    # off by sigma_v at one end of the vehicle positions and not at the other tilt the
    # radar by about sigma_v over their spread (RTK: 2 cm over 25 m, 0.05 deg; a
    # standalone fix's metres of wander: degrees, which the jackknife of a few passes
    # missed by half on an independent recording, 6.4 deg off at 2.9 deg 1 sigma).
    spread = _position_spread(data, poses, est.time_offset_s)
    cov7 = uncertainty.add_tilt(cov7, sigma_v / spread)
    cov7[2, 2] += (sigma_h / spread) ** 2
    halves = _halves_disagreement(halves_shift, cov7)
    if halves is not None and halves_shift is not None:
        # The result is a blend of two different poses: either could be the radar's, so the
        # whole difference joins the covariance (a fourth probe's pole turned 1.5 deg halfway
        # through: 227 cm and 0.79 deg off, reported at 44 cm and 0.18 deg).
        cov7[:6, :6] += np.outer(halves_shift[:6], halves_shift[:6])
    diagnostics = _diagnostics(model, x_hat, r, data, pc, cov7, est, recording, poses,
                               config, fit, rounds, scatter)
    if halves is not None:
        diagnostics['halves_rotation_deg'], diagnostics['halves_translation_m'] = halves
        turn = _turn_between_passes(pc, jp.T @ jp, cov7, data, recording, est, config)
        if turn is not None:
            diagnostics['mount_turn'] = turn
        diagnostics['advice'] = [
            f'The first and the second half of the drives disagree by {halves[0]:.2f} deg and '
            f'{100 * halves[1]:.0f} cm, far beyond their uncertainty: the radar may have moved '
            'during the recording (a bumped or loose mount), or its clock drifted. The '
            'uncertainty includes the difference; calibrate each half on its own (cut the '
            'recording) to see which holds.', *diagnostics['advice']]
    if tau_held is not None:
        diagnostics['time_offset_held_sigma_s'] = tau_held
    elif estimate_tau:
        diagnostics['pass_time_offsets'] = _pass_time_offsets(pc, data, est.time_offset_s)
    if drift is not None and drift.step_s:
        first_s = _radar_clock_s(recording, config, int(recording.frame_stamps_ns[0]))
        diagnostics['clock_step_ms'] = 1e3 * drift.step_s
        diagnostics['clock_step_sigma_ms'] = 1e3 * drift.sigma
        diagnostics['clock_step_at_s'] = drift.step_at_s - first_s
        before = est.time_offset_s - drift.step_s * float(drift.reference_s >= drift.step_at_s)
        diagnostics['advice'] = [
            f'The radar\'s clock offset against the vehicle\'s stepped by '
            f'{1000 * drift.step_s:+.0f} ms (+-{1000 * drift.sigma:.0f}) between two passes, '
            f'about {drift.step_at_s - first_s:.0f} s after the radar\'s first frame: '
            f'{1000 * before:+.0f} ms before, {1000 * (before + drift.step_s):+.0f} ms after '
            '(a clock set by NTP or after a reboot, or a driver restarted to stamp otherwise). '
            'The fit took both (the clock offset reported is the one of the side with the '
            'more passes). Synchronise the radar\'s clock (PTP or NTP) before recording.',
            *diagnostics['advice']]
    elif drift is not None:
        diagnostics['clock_drift_ppm'] = 1e6 * drift.rate
        diagnostics['clock_drift_sigma_ppm'] = 1e6 * drift.sigma
        span = [est.time_offset_s + drift.rate * (_radar_clock_s(recording, config, stamp)
                                                  - drift.reference_s)
                for stamp in recording.frame_stamps_ns[[0, -1]]]
        diagnostics['time_offset_span_s'] = span
        diagnostics['advice'] = [
            f'The radar\'s clock drifts {1e6 * drift.rate:+.0f} ppm against the vehicle\'s '
            f'(+-{1e6 * drift.sigma:.0f}): its offset went from {1000 * span[0]:+.0f} ms at '
            f'the start of the recording to {1000 * span[1]:+.0f} ms at the end, pass by '
            'pass, and the fit followed it as a straight line (the clock offset reported is '
            'the one at the middle). Synchronise the radar\'s clock (PTP or NTP), or stamp '
            'its scans with a synchronised host clock.', *diagnostics['advice']]
    # the vehicle's targets near its box the last round left out as hidden (``_occluded``)
    diagnostics['hidden_targets'] = hidden_targets
    if recording.has_elevation and ground_normal is not None:
        diagnostics['tilt_from_plane_deg'] = math.degrees(float(np.linalg.norm(
            Rotation.from_matrix(tilt_anchor @ est.rotation.T).as_rotvec()[:2])))
        geometry = model.geometry(x_hat)
        world = geometry['world']
        axis, centre, diagnostics['line_spread_m'] = _line_axis(world, data)
        diagnostics['line_axis'] = axis
        diagnostics['target_offset_m'] = centre - est.translation_m
        diagnostics['lane_separation_m'] = _lane_separation(world, geometry['vel'], axis, data)
    if _noisy_azimuth(azimuth_noise, cfg.azimuth_sigma_deg):
        diagnostics['azimuth_noise_deg'] = azimuth_noise
        diagnostics['advice'] = [
            f'The radial velocities show about {azimuth_noise:.1f} deg of azimuth noise '
            f'(refine.azimuth_sigma_deg is {cfg.azimuth_sigma_deg:g}); the fit used it. At '
            'that noise the lines of sight the radial velocities are predicted along are '
            'noisy too, which biases the position along the boresight by decimetres '
            '(measured on independent generators: 0.3-0.7 m forward at 2 deg and 0.1-0.3 m '
            'at 1 deg on one, 0.2-0.5 m back at 1.5-2 deg on another, within the reported '
            'uncertainty about as often as not). '
            'Set refine.azimuth_sigma_deg to what the radar\'s datasheet says; where it is '
            'this noisy, trust the position along the boresight less than its sigma says.',
            *diagnostics['advice']]
    if _noisy_elevation(elevation_noise, cfg.elevation_sigma_deg):
        diagnostics['elevation_noise_deg'] = elevation_noise
        diagnostics['advice'] = [
            f'The heights of the vehicle\'s targets show about {elevation_noise:.1f} deg of '
            f'elevation noise (refine.elevation_sigma_deg is {cfg.elevation_sigma_deg:g}): '
            'their scatter grows with range as that noise does. The fit weighed the heights '
            'by it; at the configured noise it had trusted the far targets\' heights too much '
            'and put the radar decimetres low (an independent generator at 2.5-3 deg: '
            '0.5-0.7 m, outside its uncertainty). Set refine.elevation_sigma_deg to what the '
            'radar\'s datasheet says.', *diagnostics['advice']]
    if model.n_par > model.i_end:
        scale = float(x_hat[model.i_end])
        scale_sigma = float(math.sqrt(max(pc.covariance[model.i_end, model.i_end], 0.0)))
        diagnostics['azimuth_scale'] = scale
        diagnostics['azimuth_scale_sigma'] = scale_sigma
        if abs(scale) >= _AZIMUTH_SCALE_NOTE and abs(scale) >= 3.0 * scale_sigma:
            diagnostics['advice'] = [
                f'The radar\'s azimuths are {"stretched" if scale > 0 else "compressed"} by '
                f'{100 * abs(scale):.1f} % (+-{100 * scale_sigma:.2f}): '
                f'{math.degrees(abs(scale) * math.radians(45.0)):.2f} deg at 45 deg, an error '
                'of its own angle calibration (or of its mount on the pole)? The fit took it out '
                '(unmodelled, it moves the radar along its boresight by about that share of the '
                'range). Check the radar\'s angle calibration.', *diagnostics['advice']]
    diagnostics.update({
        'range_slopes_m': [float(v) for v in profile[
            reflection.n_coefficients(harmonics):model.i_end - model.i_prof]],
        'depth_reference_range_m': model.r_ref,
        'elevation_view_deg': [math.degrees(fov[0]), math.degrees(fov[1])],
        'height_used_fraction': float(np.mean(data.vertical_ok)),
        'reflection_height_prior_m': list(reflection_height_prior(config)),
        'range_band_t_scale': pb.t_scale,
        # position under the other range law of the profile minus this one (zero unchecked)
        'model_difference_m': [float(v) for v in model_difference],
        # the two jackknifes behind the reported covariance (7x7 blocks, as cov7)
        'covariance_passes': _pose_block(pc.covariance, estimate_tau),
        'covariance_bands': _pose_block(pb.covariance, estimate_tau),
    })
    return Refinement(extrinsics=est, covariance=cov7, n_targets=int(data.index.size),
                      n_passes=pc.n_passes,
                      reflection_profile=np.asarray(profile[:reflection.n_coefficients(harmonics)],
                                                    float),
                      diagnostics=diagnostics)


#: Fitted azimuth scale errors from this size (and three sigma) are named.
_AZIMUTH_SCALE_NOTE = 0.005
#: Azimuth noise shown by the radial velocities [deg] from which, when also twice
#: ``refine.azimuth_sigma_deg``, it replaces that in the whitening and is named. Our
#: simulator's radar (0.25-0.5 deg) shows 0.3-0.8 there (other noise grows with the
#: tangential speed too), an independent generator's 0.3 / 0.6 / 1 / 2 deg show 0.28 /
#: 0.52 / 0.89 / 1.80.
_AZIMUTH_NOISE_NOTE_DEG = 1.0


def _noisy_azimuth(shown_deg: float, configured_deg: float) -> bool:
    return shown_deg >= max(_AZIMUTH_NOISE_NOTE_DEG, 2.0 * configured_deg)


def _azimuth_noise_deg(g: dict[str, F64], data: _Selected) -> float:
    """The radar's azimuth noise [deg] as the radial velocities show it, from the fit's
    geometry ``g`` (``_Model.geometry``) over ``data``.

    A line of sight turned by azimuth noise n changes the predicted v_r by n times the
    speed across it (W_perp, the rigid car's velocity field at the radar, across the line
    of sight), whatever point of the car reflected: the v_r residuals' variance grows as
    s_v^2 + s_az^2 W_perp^2. Fitted over ten quantile bins of |W_perp| with a robust spread
    per bin (wheel micro-Doppler and stray targets are not Gaussian); 0 where the slope is
    not three of its standard errors above zero or the car never crossed the lines of sight
    fast. Position residuals cannot show it: the car's own extent across the line of sight
    swamps the noise there.
    """
    if data.index.size < 10 * _NOISE_BIN_TARGETS:
        return 0.0
    unit, velocity = g['unit_v'], g['point_velocity']
    w_perp = velocity[:, 1] * unit[:, 0] - velocity[:, 0] * unit[:, 1]
    slope, top = _spread_growth(np.abs(w_perp), g['v_pred'] - data.v_mps)
    if top < _NOISE_CROSS_SPEED_MPS ** 2:
        return 0.0    # seen head-on only: too little speed across the lines of sight
    return float(np.degrees(math.sqrt(slope)))


def _spread_growth(driver: F64, residual: F64) -> tuple[float, float]:
    """How the residuals' variance grows with the square of ``driver`` (>= 0): over ten
    quantile bins of the driver, the robust spread (1.4826 MAD about the bin's median) of
    the residuals against the bin's mean driver squared, fitted by a straight line. Returns
    its slope (0 where not three of its standard errors above zero: no growth beyond the
    scatter of the bins) and the top bin's mean driver squared."""
    edges = np.quantile(driver, np.linspace(0.0, 1.0, 11))
    bins = np.clip(np.searchsorted(edges, driver, side='right') - 1, 0, 9)
    d2 = np.bincount(bins, driver ** 2, minlength=10) / np.maximum(
        np.bincount(bins, minlength=10), 1)
    spread2 = np.array([(1.4826 * np.median(np.abs(r - np.median(r)))) ** 2 if r.size else 0.0
                        for r in (residual[bins == b] for b in range(10))])
    design = np.column_stack([np.ones(10), d2])
    coef, *_ = np.linalg.lstsq(design, spread2, rcond=None)
    misfit = spread2 - design @ coef
    slope_var = float(misfit @ misfit) / 8.0 * np.linalg.inv(design.T @ design)[1, 1]
    slope = float(coef[1]) if coef[1] > 3.0 * math.sqrt(max(slope_var, 0.0)) else 0.0
    return slope, float(d2[-1])


def _noisy_elevation(shown_deg: float, configured_deg: float) -> bool:
    return shown_deg >= _ELEVATION_NOISE_RATIO * configured_deg


#: Elevation noise shown by the heights, as a multiple of ``refine.elevation_sigma_deg``,
#: from which it replaces that in the whitening and is named.
_ELEVATION_NOISE_RATIO = 1.4


def _elevation_noise_deg(g: dict[str, F64], data: _Selected) -> float:
    """The radar's elevation noise [deg] as the heights of the vehicle's targets show it,
    from the fit's geometry ``g`` (``_Model.geometry``) over ``data``.

    Elevation noise e moves a target vertically by its range times e, so the vertical
    residuals' variance grows as s_z^2 + (r s_el)^2, s_z the reflectors' own scatter in
    height. Fitted over ten quantile bins of range with a robust spread per bin (each bin
    centred on its own median, so a mean height that changes with range does not count);
    0 where the slope is not three of its standard errors above zero. Only targets that
    give height information count (``_inside_elevation_view``).
    """
    ok = data.vertical_ok
    if int(ok.sum()) < 10 * _NOISE_BIN_TARGETS:
        return 0.0
    slope, _ = _spread_growth(g['range'][ok], g['err'][ok, 2])
    return float(np.degrees(math.sqrt(slope)))


#: Fewest targets per bin of the azimuth-noise fit, and the least RMS speed across the
#: lines of sight [m/s] its top bin must reach (1 deg of noise then adds 0.07 m/s).
_NOISE_BIN_TARGETS = 30
_NOISE_CROSS_SPEED_MPS = 4.0


def _radar_clock_s(recording: Recording, config: CalibConfig, stamp_ns: int) -> float:
    """A radar stamp on the refinement's time axis (``_Times``): seconds since the first
    vehicle pose, plus ``sync.time_offset``."""
    return float((int(stamp_ns) - int(recording.vehicle.stamps_ns[0])) * 1e-9
                 + config.sync.time_offset)


def _mid_recording_s(recording: Recording, config: CalibConfig) -> float:
    """The middle of the radar's frames on the refinement's time axis: where a drifting
    clock's offset is reported (``ClockDrift.reference_s``)."""
    stamps = recording.frame_stamps_ns
    return _radar_clock_s(recording, config, int(stamps[0] + (stamps[-1] - stamps[0]) // 2))


def _pass_time_offsets(pc: uncertainty.PassCovariance, data: _Selected,
                       tau: float) -> list[list[float]]:
    """(time [s], clock offset [s], information [1/s^2]) of each pass: the one-step
    estimate of the offset from that pass's targets alone, everything else held at the
    joint fit (its own gradient and curvature along the offset)."""
    t_s = data.times.t_s
    out = []
    for p in range(pc.n_passes):
        m = data.pass_id == p
        information = float(pc.hessians[p, 6, 6])
        if not m.any() or information <= 0.0:
            continue
        out.append([float(np.median(t_s[m])), tau - float(pc.gradients[p, 6]) / information,
                    information])
    return out


#: Clock drift: the fewest passes it is judged on, the two-sided false-alarm rate of its
#: t-test (the offsets' scatter about the line, not their formal precision, sets its
#: error: reflection-model errors move a pass's offset more than its noise), and the least
#: rate worth a second fit (20 ppm: 12 ms over ten minutes, 18 cm at 15 m/s at the ends,
#: half of which the fit's constant offset takes).
_DRIFT_MIN_PASSES = 5
_DRIFT_FALSE_ALARM = 0.001
_DRIFT_MIN_RATE = 20e-6
#: At most this many refits for a drift, stopped once what is left of it is below this
#: fraction of the rate found.
_DRIFT_REFITS = 3
_DRIFT_SETTLED = 0.1


#: Clock step: the fewest passes on either side of it, its least size worth a refit [s],
#: and how much less scatter than a straight line it must leave (a drift is a line).
_STEP_MIN_SIDE = 2
_STEP_MIN_S = 0.02
_STEP_BETTER = 0.5


def _clock_step(offsets: list[list[float]], at_s: float | None = None) -> ClockDrift | None:
    """A step of the radar clock's offset between two passes, from the passes' clock
    offsets, or None when they show none clearly (or, with ``at_s``, what is left of a
    step found there before, taken when two standard errors clear of zero).

    Why: a radar whose clock is set by NTP mid-recording, or reboots, or whose driver is
    restarted to stamp on reception, steps its offset by tens to hundreds of milliseconds.
    A straight line through the passes' offsets (``_clock_drift``) then misplaces the
    passes at both ends and names a drift that is not there (a sixteenth probe: +0.15 s at
    565 s of 25 minutes taken for -91 ppm, delta_op 0.36 m against 0.17). The step is put
    between the two passes where two constant offsets fit best; it is taken when it leaves
    less than ``_STEP_BETTER`` of the line's scatter and stands clear of that scatter (a
    t-test at the drift's false-alarm rate, divided among the places tried).
    """
    if len(offsets) < _DRIFT_MIN_PASSES:
        return None
    rows = np.array(sorted(offsets), float)
    t, tau, w = rows[:, 0], rows[:, 1], rows[:, 2] / rows[:, 2].sum()
    n = t.size
    splits = (np.arange(_STEP_MIN_SIDE, n - _STEP_MIN_SIDE + 1) if at_s is None
              else np.array([int(np.searchsorted(t, at_s))]))
    splits = splits[(splits >= 1) & (splits <= n - 1)]
    if splits.size == 0:
        return None
    cum_w, cum_wt = np.cumsum(w), np.cumsum(w * tau)
    w_a, w_b = cum_w[splits - 1], 1.0 - cum_w[splits - 1]
    m_a = cum_wt[splits - 1] / w_a
    m_b = (cum_wt[-1] - cum_wt[splits - 1]) / w_b
    side = np.arange(n)[None, :] >= splits[:, None]
    fitted = np.where(side, m_b[:, None], m_a[:, None])
    rss = np.sum(w[None, :] * (tau[None, :] - fitted) ** 2, axis=1)
    k = int(np.argmin(rss))
    j, step = int(splits[k]), float(m_b[k] - m_a[k])
    dof = n - 2
    sigma = math.sqrt(float(rss[k]) / dof * (1.0 / w_a[k] + 1.0 / w_b[k]))
    at = 0.5 * (t[j - 1] + t[j]) if at_s is None else at_s
    # the reference on the side with the more information: its offset is the one reported
    reference = float(t[j:].mean() if w_b[k] > w_a[k] else t[:j].mean())
    if at_s is not None:
        if abs(step) < 2.0 * sigma:
            return None
        return ClockDrift(0.0, reference, sigma, step, at)
    _, line_rss, _ = _weighted_line(t, tau, w)
    critical = float(stats.t.ppf(1.0 - _DRIFT_FALSE_ALARM / (2.0 * splits.size), dof))
    _LOG.debug('clock step from %d passes: %.1f +- %.1f ms at %.0f s (needs %.1f sigma), '
               'scatter %.2f of the line\'s', n, 1e3 * step, 1e3 * sigma, at, critical,
               float(rss[k]) / max(line_rss, 1e-18))
    if (abs(step) < max(_STEP_MIN_S, critical * sigma)
            or float(rss[k]) >= _STEP_BETTER * line_rss):
        return None
    return ClockDrift(0.0, reference, sigma, step, at)


def _weighted_line(t: F64, tau: F64, w: F64) -> tuple[float, float, float]:
    """(slope, weighted residual sum of squares, weighted spread of ``t``) of the line
    through the passes' clock offsets ``tau`` at times ``t``, weights ``w`` summing to 1."""
    t_mean = float(np.sum(w * t))
    spread = float(np.sum(w * (t - t_mean) ** 2))
    rate = float(np.sum(w * (t - t_mean) * (tau - np.sum(w * tau)))) / max(spread, 1e-12)
    rss = float(np.sum(w * (tau - np.sum(w * tau) - rate * (t - t_mean)) ** 2))
    return rate, rss, spread


def _clock_drift(offsets: list[list[float]], reference_s: float,
                 found: bool = False) -> ClockDrift | None:
    """The radar clock's drift against the poses' from the passes' clock offsets, or None
    when they show none clearly.

    Why: a radar that stamps its scans with a clock of its own (no PTP or NTP) runs
    20-200 ppm off the GNSS time; over a twenty-minute drive 200 ppm is a quarter of a
    second, metres at driving speed. One offset for the whole recording then fits none
    of the passes, and where the directions driven change over time it lies along the
    boresight (an eleventh probe: 29 cm, against 4 cm without the drift). Each pass's
    offset is estimated alone (``_pass_time_offsets``); a straight line through them
    (weighted by their information, its error from their scatter about it) gives the rate.
    With ``found`` (a drift already corrected for), what is left of it is taken when it
    stands two standard errors clear of zero.
    """
    if len(offsets) < _DRIFT_MIN_PASSES:
        return None
    t, tau, w = (np.array(v, float) for v in zip(*offsets))
    w = w / w.sum()
    rate, rss, spread = _weighted_line(t, tau, w)
    if spread <= 0.0:
        return None
    dof = t.size - 2
    scatter = rss * t.size / dof
    sigma = math.sqrt(scatter / (spread * t.size))
    critical = 2.0 if found else float(stats.t.ppf(1.0 - _DRIFT_FALSE_ALARM / 2.0, dof))
    _LOG.debug('clock drift from %d passes: %.1f +- %.1f ppm (needs %.1f sigma)', t.size,
               1e6 * rate, 1e6 * sigma, critical)
    if abs(rate) < critical * sigma or (abs(rate) < _DRIFT_MIN_RATE and not found):
        return None
    return ClockDrift(rate, reference_s, sigma)


#: Chi-square (3 degrees of freedom, 0.1 %) of the rotation difference between the halves
#: of the drives beyond which they disagree: on 53 of our simulator's ten-minute runs
#: (nine scenarios, seeds 1-2, three scatter models) it stayed at or below 4.8; on a
#: fourth probe's recording whose pole turned 1.5 deg halfway it was 38.
_HALVES_CHI2 = 16.27


#: Farthest the final refinement may take the estimate from the paper's stages' [m, deg]:
#: those are decimetres and about a degree off (on our benches the refinement moves them
#: by at most ~2 m, on mid-block views); a fit that runs farther is following something
#: else (a fourth probe's folded radial velocities took it 120 m and 173 deg away).
_MAX_SHIFT_M = 5.0
_MAX_TURN_DEG = 10.0
#: What most often puts radial velocities off the vehicle's motion, for the failures above.
_VELOCITY_SUSPECTS = "folded at the radar's unambiguous limit, or a scale or sign error?"


class _Diverged(InsufficientDataError):
    """The fit ran ``shift_m`` and ``turn_deg`` from the paper's estimate
    (``_check_not_diverged``)."""

    def __init__(self, stage: str, message: str, shift_m: float, turn_deg: float) -> None:
        super().__init__(stage, message)
        self.shift_m = shift_m
        self.turn_deg = turn_deg


def _check_not_diverged(start: Extrinsics, est: Extrinsics, planar: bool = False) -> None:
    """Raise when the fit ran beyond ``_MAX_SHIFT_M`` / ``_MAX_TURN_DEG`` from the paper's
    stages; horizontally only for a 2-D radar (``planar``), whose altitude starts at the
    vehicle's and is found from the radial velocities metres higher."""
    angle, shift, _ = _change(start, est.rotation, est.translation_m, est.time_offset_s)
    if planar:
        shift = float(np.hypot(*(est.translation_m[:2] - start.translation_m[:2])))
    if shift > _MAX_SHIFT_M or math.degrees(angle) > _MAX_TURN_DEG:
        raise _Diverged(
            'refine', f'the final refinement ran {shift:.1f} m and {math.degrees(angle):.1f} '
            'deg away from the paper\'s stages\' estimate (decimetres and about a degree '
            'off): it follows something other than the vehicle, most likely radial '
            f'velocities off its motion ({_VELOCITY_SUSPECTS})', shift, math.degrees(angle))


def _halves_disagreement(shift: F64 | None, cov7: F64) -> tuple[float, float] | None:
    """(rotation [deg], translation [m]) between the halves of the drives when their
    rotations differ beyond the reported covariance (the difference of two half-estimates
    has about four times the variance of the whole), else None. Rotation only: the
    translation's reported sigma carries model terms every half shares."""
    if shift is None:
        return None
    d_rot = shift[:3]
    if _rotation_chi2(d_rot, cov7, 4.0) <= _HALVES_CHI2:
        return None
    return float(np.degrees(np.linalg.norm(d_rot))), float(np.linalg.norm(shift[3:6]))


def _halves_shift(passes: uncertainty.PassCovariance, prior_hessian: F64) -> F64 | None:
    """(p,) one-step estimate from the first half of the passes (in time: pass ids run in
    time order) minus that from the second half, None with fewer than four passes."""
    if passes.n_passes < 4:
        return None
    shift: F64 = -_split_step(passes, prior_hessian, passes.n_passes // 2)
    return shift


def _split_step(passes: uncertainty.PassCovariance, prior_hessian: F64, k: int) -> F64:
    """(p,) one-step estimate from the passes from ``k`` on (in time) minus that from the
    passes before it."""
    later = (np.arange(passes.n_passes) >= k).astype(np.int64)
    influences = uncertainty.group_influences(passes, later, prior_hessian)
    # influences[g]: the step that leaving group g out takes, i.e. towards the other group
    step: F64 = influences[0] - influences[1]
    return step


def _rotation_chi2(rotation_step: F64, cov7: F64, scale: float) -> float:
    """Chi-square of a rotation difference (3,) [rad] against ``scale`` times the rotation
    block of ``cov7``."""
    return float(rotation_step @ np.linalg.solve(scale * cov7[:3, :3], rotation_step))


def _turn_between_passes(passes: uncertainty.PassCovariance, prior_hessian: F64, cov7: F64,
                         data: _Selected, recording: Recording, estimate: Extrinsics,
                         config: CalibConfig) -> MountTurn | None:
    """Where the drives' halves disagree: the moment between two passes at which the
    rotations of the passes before and after differ most beyond the reported covariance,
    as a turn of the mount, when that is beyond ``_HALVES_CHI2`` with at least
    ``hypotheses.min_passes`` passes on each side; else None.

    Why: a turn that stage 6 did not see (its per-track rotations scatter by a degree, and
    a pitch or roll does not show in them at all) leaves a blend of two mounts, which the
    halves check only widens the uncertainty over (a simulated 4 deg re-aim between the
    third and the fourth of six passes: right, at 2.9 deg 1 sigma). Split where the step is,
    each side is one mount, and the later one is the radar as it is now.
    """
    n, least = passes.n_passes, config.hypotheses.min_passes
    best: tuple[float, int, F64] | None = None
    for k in range(least, n - least + 1):
        step = _split_step(passes, prior_hessian, k)
        # the difference of two part-estimates has G/k + G/(G-k) times the variance of
        # the whole
        chi2 = _rotation_chi2(step[:3], cov7, n / k + n / (n - k))
        if chi2 > _HALVES_CHI2 and (best is None or chi2 > best[0]):
            best = (chi2, k, step)
    if best is None:
        return None
    _, k, step = best
    stamps = recording.stamps_of(data.index)
    gap = (int(stamps[data.pass_id == k - 1].max()), int(stamps[data.pass_id == k].min()))
    local = recording.targets.positions_m[data.index]
    reach = float(np.hypot(local[:, 0], local[:, 1]).max()) + config.hypotheses.pass_margin_m
    at_ns = hypotheses.turn_moment_ns(recording.vehicle, estimate.translation_m[:2], reach,
                                      gap, config.sync.time_offset + estimate.time_offset_s)
    yaw, tilt = math.degrees(step[2]), math.degrees(math.hypot(step[0], step[1]))
    return MountTurn(at_ns, gap, yaw, k, n - k, tilt)


def _line_axis(world: F64, data: _Selected) -> tuple[F64, F64, float]:
    """Horizontal unit direction (3,) in which the fitted targets spread most (the road's,
    where they lie along one road), their information-weighted centre (3,) [m], and their
    spread across it [m] (1 sigma): small where every target lies along one road through
    the view."""
    weight = data.sqrt_weight ** 2
    centre = np.average(world, axis=0, weights=weight)
    values, axes = np.linalg.eigh(np.cov((world[:, :2] - centre[:2]).T, aweights=weight))
    return (np.array([axes[0, 1], axes[1, 1], 0.0]), centre,
            math.sqrt(max(float(values[0]), 0.0)))


#: Least share of the information each direction along the road must hold to count.
_DIRECTION_SHARE = 0.1


def _lane_separation(world: F64, velocity: F64, axis: F64, data: _Selected) -> float | None:
    """Distance [m] across the road ``axis`` between the mean positions of the targets
    seen driving one way and those seen driving the other; None where one way holds less
    than ``_DIRECTION_SHARE`` of the information (a one-way street)."""
    weight = data.sqrt_weight ** 2
    forward = velocity[:, :2] @ axis[:2] >= 0.0
    if min(weight[forward].sum(), weight[~forward].sum()) < _DIRECTION_SHARE * weight.sum():
        return None
    lateral = world[:, :2] @ np.array([-axis[1], axis[0]])
    return abs(float(np.average(lateral[forward], weights=weight[forward])
                     - np.average(lateral[~forward], weights=weight[~forward])))


def _position_spread(data: _Selected, poses: _Poses, offset_s: float) -> float:
    """RMS horizontal distance [m] of the vehicle positions behind the fit's targets from
    their information-weighted mean (at least a car length)."""
    pos = poses.at(data.times.frame_t + offset_s)[0][data.times.inverse, :2]
    weight = data.sqrt_weight ** 2
    mean = np.average(pos, axis=0, weights=weight)
    spread = math.sqrt(float(np.average(np.sum((pos - mean) ** 2, axis=1), weights=weight)))
    return max(spread, 5.0)


def _height_difference_shift(model: _Model, x: F64, jacobian: F64, sqrt_w: F64,
                             j_prior: F64) -> F64:
    """Change of the fitted parameters per metre of front/rear reflection height difference.

    The profile keeps one reflection height for every aspect, because a height that differs
    between the front and the rear is confounded with the radar's roll wherever the lanes
    towards the radar lie on one side of it and those away on the other (see
    ``core/reflection.py``). Real cars do differ (engine block and grille at the front, boot
    and bumper at the rear), and that difference tilts the fit by about the height
    difference over the lanes' lateral spread: decimetres over a few metres, i.e. half a
    degree, for a radar looking along a road (measured on the simulator: roll errors of
    0.4-0.55 deg on mid-block views, reported at 0.19-0.26 deg). Its effect is a "consider"
    term: the linearised shift of the solution for a height offset of cos(aspect), which the
    caller scales by ``refine.model_sigma_height_difference_m``. Over 108 simulated
    ten-minute runs (three scatter models) the 95 % rotation ellipsoid covered 94 / 89 / 91 %
    of the errors (interior / mixed / skin) without it and 100 / 92 / 91 % with 0.1 m; it
    adds about 0.05 deg where diverse views pin the tilt and 0.5 deg on mid-block views.
    The linearisation gives the direction of the tilt but, on a synthetic head-on scene,
    about a quarter of its size (the gate and weights of the later rounds follow the data).
    """
    return _height_shift(model, x, jacobian, sqrt_w, j_prior,
                         np.cos(model.geometry(x)['aspect']))


def _height_shift(model: _Model, x: F64, jacobian: F64, sqrt_w: F64, j_prior: F64,
                  offset_m: F64) -> F64:
    """Linearised change of the fitted parameters for the vehicle's targets raised by
    ``offset_m`` (n,) [m] each (a consider term, as ``_height_difference_shift``)."""
    d = model.data
    dz = np.zeros((d.index.size, 3))
    dz[:, 2] = -np.asarray(offset_m, float)
    dr = np.concatenate([(np.einsum('nij,nj->ni', d.whiten, dz) * d.sqrt_weight[:, None]).ravel(),
                         np.zeros(d.index.size)]) * sqrt_w
    jw = jacobian * sqrt_w[:, None]
    h = jw.T @ jw + j_prior.T @ j_prior
    shift: F64 = -np.linalg.solve(h, jw.T @ dr)
    return shift


#: How far the paper's stages may leave the radar along a direction the final fit's data do
#: not measure, in vehicle lengths (see ``_start_term``).
_START_ERROR_LENGTHS = 1.0


def _start_term(passes: uncertainty.PassCovariance, prior_hessian: F64,
                config: CalibConfig, start_sigma_m: float = _START_SIGMA_M) -> F64:
    """Covariance the start's own error adds where the data leave the horizontal position
    to the half-metre prior around the paper's estimate (``_START_SIGMA_M``).

    The prior keeps the fit near that estimate where the views say nothing, and its term in
    the covariance reports the half metre it assumes. But where the vehicle only drives
    straight along one road the paper's stages can be a car length off (tracks of a car
    reflecting at its front when it comes and its rear when it goes): a twentieth probe's
    radar looking along the road was 3.5-4 m off along the boresight at a reported 0.5 m,
    24 of 45 such drives outside two sigma. How much of the estimate the prior decides is
    H^-1 P; a start uncertain by a car length instead of the prior's half metre scales the
    prior's term H^-1 P H^-1 by their squared ratio, in the horizontal position only. Where
    the data measure the position (junctions, turns) it adds nothing.
    """
    scale2 = (_START_ERROR_LENGTHS * config.vehicle.length / start_sigma_m) ** 2
    p_xy = np.zeros_like(prior_hessian)
    p_xy[3:5, 3:5] = prior_hessian[3:5, 3:5]
    term: F64 = max(scale2 - 1.0, 0.0) * uncertainty.prior_part_covariance(
        passes, prior_hessian, p_xy)
    return term


def _pose_block(covariance: F64, estimate_tau: bool) -> F64:
    """The 7x7 [rotation vector, translation, clock offset] block of a full covariance
    (zero for the clock offset when it was not estimated)."""
    out = np.zeros((7, 7))
    n = 7 if estimate_tau else 6
    out[:n, :n] = covariance[:n, :n]
    return out


#: Clock offsets the first round leaves more uncertain than this are not estimated [s]:
#: normal drives pin it to 2-4 ms; where the vehicle keeps one speed through the view an
#: offset only moves it along its own travel, as a longer or shorter car would (the
#: profile's constant), and the fit slid 0.73 s to where other cars' targets were (an
#: independent recording of four straight passes: refused). Sigma of the hold [s].
_TAU_HOLD_SIGMA_S = 0.01
_TAU_HOLD_S = 1e-6


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


#: 1-sigma of the tilt prior from the road plane [deg]: the plane of the road users'
#: reflections is 0.1-0.5 deg off the road's (where a vehicle reflects changes with the
#: look-down angle), a cross slope adds up to 1; normal views pin the tilt to 0.05-0.2 deg
#: and are not moved by it.
_TILT_PRIOR_DEG = 1.0
#: How far the fit may tilt the radar from the road plane [deg], and across how much spread
#: of its targets about one road [m] (1 sigma) the vehicle's views count as one road, before
#: the tilt is held at the plane's (``_HELD_TILT_DEG``; see ``_refine_checked``). Junction
#: views spread 11-21 m and their fits stay within 0.93 deg of the plane (the bench's 33
#: drives); one road seen by a narrow beam spreads 3-4 m, one lane 0.6 m.
_TILT_MOVED_DEG = 0.75
_LINE_SPREAD_M = 5.0
_HELD_TILT_DEG = 0.1
#: Least separation [m] of the two directions' lanes the held plane's roll is judged over
#: (two lanes of one carriageway a car's width apart at the least).
_MIN_LANE_SEPARATION_M = 2.0
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


def _debiased_positions(sensor: F64, config: CalibConfig) -> F64:
    """Sensor-frame target positions with the bias of angular noise removed.

    The radar measures range, azimuth and elevation; noise n ~ N(0, s^2) on an angle
    shrinks the Cartesian position on average: E[cos(e + n)] = cos(e) exp(-s^2 / 2), the
    same for sin. With 1.5 deg of elevation noise that is 3.4e-4 of the range, 3 cm at
    100 m, a scale error that moves the radar along its boresight. Dividing by the expected
    shrink makes the positions unbiased.
    """
    cfg = config.refine
    s_el2 = math.radians(cfg.elevation_sigma_deg) ** 2
    s_az2 = math.radians(cfg.azimuth_sigma_deg) ** 2
    scale = np.array([math.exp(0.5 * (s_el2 + s_az2)), math.exp(0.5 * (s_el2 + s_az2)),
                      math.exp(0.5 * s_el2)])
    return sensor * scale


def _inside_elevation_view(pos: F64, yaw: F64, est: Extrinsics, fov: tuple[float, float],
                           config: CalibConfig) -> np.ndarray:
    """(n,) True where the whole vehicle and its mirror image below the road lie inside
    the elevation field of view.

    Where the field of view cuts off the lower part of the car (or its multipath image
    below the road), what is seen of it is higher on average, and more so the closer the
    car: the mean reflection height then changes with range, and a pitch error would be
    fitted to follow it (0.3-0.7 deg measured on the simulator). Such frames keep their
    horizontal and radial-velocity information but give no height information.
    """
    veh = config.vehicle
    x_lo, x_hi, _, _ = box_limits(veh)
    centre = pos.copy()
    centre[:, 0] += 0.5 * (x_lo + x_hi) * np.cos(yaw)
    centre[:, 1] += 0.5 * (x_lo + x_hi) * np.sin(yaw)
    road = pos[:, 2] - veh.ref_height
    ok = np.ones(pos.shape[0], bool)
    # the road under the vehicle's centre must be above the lower edge (a stricter test,
    # with the whole mirror image inside, drops the near passes that carry the pitch),
    # the roof below the upper one
    for dz, lower in ((0.0, True), (veh.height, False)):
        pt = centre.copy()
        pt[:, 2] = road + dz
        s = est.inverse_apply(pt)
        el = np.arcsin(np.clip(s[:, 2] / np.maximum(np.linalg.norm(s, axis=1), 1e-9), -1, 1))
        ok &= (el > fov[0]) if lower else (el < fov[1])
    return ok


def _slant_to_height(sensor: F64, height_m: F64, rotation: F64) -> F64:
    """A 2-D radar's targets (range and azimuth in its plane, z = 0) lifted out of the
    plane to ``height_m`` (n,) relative to the radar in the world, under ``rotation``.

    Its range is the slant range, so a target below the radar lies nearer horizontally, by
    height^2 / (2 range) (1.2 m at 15 m for a 6 m pole), a bias no reflection profile
    follows. The elevation e that puts the target at that height solves
    a cos e + b sin e = height / range, with (a, b) the world-vertical components of the
    azimuth's in-plane direction and of the plane's normal. The heights are the model's
    (the vehicle's plus the reflection prior) at the round's altitude, which the radial
    velocities fix: their line of sight dips by the same angle and shrinks them by its
    cosine.
    """
    rng = np.hypot(sensor[:, 0], sensor[:, 1])
    az = np.arctan2(sensor[:, 1], sensor[:, 0])
    a = rotation[2, 0] * np.cos(az) + rotation[2, 1] * np.sin(az)
    b = rotation[2, 2]
    norm = np.hypot(a, b)
    # sin(e + psi) = c / norm with psi = atan2(a, b); the root nearest the plane
    c = np.clip(height_m / np.maximum(rng, 1e-9) / norm, -_PLANAR_MAX_SIN, _PLANAR_MAX_SIN)
    e = np.arcsin(c) - np.arctan2(a, b)
    ce = np.cos(e)
    return np.column_stack([rng * ce * np.cos(az), rng * ce * np.sin(az), rng * np.sin(e)])


def _select(index: I64, times: _Times, est: Extrinsics, recording: Recording, poses: _Poses,
            scatter: F64, config: CalibConfig, fov: tuple[float, float]) -> _Selected:
    sensor = _debiased_positions(recording.targets.positions_m[index], config)
    pos, yaw, vel, _, _ = times.poses(poses, est.time_offset_s)
    # the model's target heights relative to the radar (the vehicle's plus the prior)
    above_radar = (pos[:, 2] + reflection_height_prior(config)[0] - config.vehicle.ref_height
                   - est.translation_m[2])
    if not recording.has_elevation:
        sensor = _slant_to_height(sensor, above_radar, est.rotation)
    x_lo, x_hi, _, _ = box_limits(config.vehicle)
    centre = pos - est.translation_m
    centre[:, 0] += 0.5 * (x_lo + x_hi) * np.cos(yaw)
    centre[:, 1] += 0.5 * (x_lo + x_hi) * np.sin(yaw)
    aspect = reflection.aspect_angles(centre, yaw)
    frame_index = recording.targets.frame_index[index]
    weight = _information_weights(frame_index, pos, aspect, config)
    pass_id = _passes(times.t_s, config.hypotheses.pass_gap_s)
    vertical_ok = _inside_elevation_view(pos, yaw, est, fov, config)
    whiten = _whitening(sensor, est.rotation, yaw, scatter, config, vertical_ok)
    # The v_r line of sight takes the target's height from the model; the reflectors'
    # height scatter then tilts it by dz/|d|: add that to the v_r noise.
    los = sensor @ est.rotation.T
    los[:, 2] = above_radar
    dist = np.linalg.norm(los, axis=1)
    unit = los / dist[:, None]
    v_along = np.einsum('ij,ij->i', vel, unit)
    dv_dh = (vel[:, 2] - v_along * unit[:, 2]) / dist
    sigma_v = np.sqrt(config.refine.velocity_sigma_mps ** 2 + (dv_dh * scatter[2]) ** 2)
    grade = poses.grade_at(times.frame_t + est.time_offset_s)[times.inverse]
    return _Selected(index, sensor, times, recording.targets.radial_velocity_mps[index],
                     np.sqrt(weight), pass_id, whiten, sigma_v, vertical_ok, grade)


def _scatter(g: dict[str, F64], floor_m: float, config: CalibConfig) -> F64:
    """Spread of the reflectors around the profile in the vehicle frame (x, y, z) for the
    next round's whitening, from the fit's geometry ``g`` (``_Model.geometry``): the robust
    spread (1.4826 MAD) of the position residuals minus the typical radar noise along that
    axis (range/azimuth horizontally, elevation vertically), floored."""
    c, s = g['c'], g['s']
    e = g['err']
    local = np.column_stack([c * e[:, 0] + s * e[:, 1], -s * e[:, 0] + c * e[:, 1], e[:, 2]])
    mad = 1.4826 * np.median(np.abs(local - np.median(local, axis=0)), axis=0)
    rng = g['range']
    cfg = config.refine
    noise_h = np.median(0.5 * (cfg.range_sigma_m ** 2
                               + (rng * math.radians(cfg.azimuth_sigma_deg)) ** 2))
    noise_v = np.median((rng * math.radians(cfg.elevation_sigma_deg)) ** 2)
    var = mad ** 2 - np.array([noise_h, noise_h, noise_v])
    return np.sqrt(np.maximum(var, (0.2 * floor_m) ** 2))


def _change(est: Extrinsics, rot: F64, trans: F64, tau: float) -> tuple[float, float, float]:
    """(rotation angle [rad], translation [m], clock offset [s]) between two estimates."""
    angle = float(np.linalg.norm(Rotation.from_matrix(rot @ est.rotation.T).as_rotvec()))
    return angle, float(np.linalg.norm(trans - est.translation_m)), abs(tau
                                                                        - est.time_offset_s)


# --- diagnostics --------------------------------------------------------------------------

def _diagnostics(model: _Model, x: F64, r: F64, data: _Selected,
                 pc: uncertainty.PassCovariance, cov7: F64, est: Extrinsics,
                 recording: Recording, poses: _Poses, config: CalibConfig, fit: _Fit,
                 rounds: int, scatter: F64) -> dict[str, Any]:
    g = model.geometry(x)
    n = data.index.size
    los, unit, err = g['los'], g['unit'], g['err']
    rng = g['range']
    # Residual components for the report: along the line of sight, across it (horizontal)
    # and vertical; azimuth is in the sensor frame.
    horiz = np.column_stack([-unit[:, 1], unit[:, 0], np.zeros(n)])
    horiz /= np.maximum(np.linalg.norm(horiz, axis=1), 1e-12)[:, None]
    along_los = np.einsum('ij,ij->i', err, unit)
    across_los = np.einsum('ij,ij->i', err, horiz)
    vel_res = g['v_pred'] - data.v_mps
    azimuth = np.arctan2(data.sensor_m[:, 1], data.sensor_m[:, 0])
    weight = data.sqrt_weight ** 2
    sig = uncertainty.sigma_summary(cov7, est.rotation)
    # Bearing of each target relative to the boresight's ground projection.
    bore = math.atan2(est.rotation[1, 0], est.rotation[0, 0])
    bearing = np.arctan2(los[:, 1], los[:, 0]) - bore
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    coverage = uncertainty.view_coverage(g['aspect'], bearing, weight)
    # The nearest the vehicle was seen: closer, it is below the radar's vertical view (a
    # steep or narrow beam leaves a blind zone of 15-20 m under a pole), and a drive
    # advised there would give nothing (seen on an independent recording: "about 11 m").
    nearest = float(np.percentile(np.hypot(*(g['pos'][:, :2] - est.translation_m[:2]).T), 2))
    candidates = _drive_candidates(recording, poses, est, g, data, coverage, bore, nearest)
    # The views decide how well the drives pin the position along the boresight; the
    # vehicle's own position error (what its fixes are worth, added to the covariance) no
    # drive takes away, and the data notes speak of it: drives are advised for the views'
    # part alone (a simulator's fixes taken as standalone GNSS had the tool blame 2 m on the
    # bearings and ask for more drives).
    fixes_sigma = recording.pose_sigma_m[0]
    views_along = math.sqrt(max(sig['sigma_along_boresight_m'] ** 2 - fixes_sigma ** 2, 0.0))
    vel = g['vel']
    headings = [math.atan2(float(np.sum(vel[m, 1])), float(np.sum(vel[m, 0])))
                for m in (data.pass_id == p for p in range(pc.n_passes)) if m.any()]
    advice = uncertainty.drive_advice(views_along, config.quality.max_boresight_sigma_m,
                                      coverage, candidates, bore, nearest, fixes_sigma,
                                      headings, _turn_ranges(g, data, est))
    passes = []
    i_t = slice(3, 6)
    t_target = data.times.t_s
    for p in range(pc.n_passes):
        m = data.pass_id == p
        if not m.any():
            continue
        vel = g['vel'][m]
        heading = math.atan2(float(np.sum(vel[:, 1])), float(np.sum(vel[:, 0])))
        passes.append({
            'pass': p,
            'start_s': float(t_target[m].min()), 'end_s': float(t_target[m].max()),
            'n_targets': int(m.sum()), 'weight': float(weight[m].sum()),
            'heading_compass': uncertainty.compass_name(heading),
            'heading_deg': float(np.degrees(heading)),
            'median_range_m': float(np.median(rng[m])),
            'bearing_deg': [float(np.degrees(bearing[m].min())),
                            float(np.degrees(bearing[m].max()))],
            'median_abs_along_los_m': float(np.median(np.abs(along_los[m]))),
            'median_along_los_m': float(np.median(along_los[m])),
            'median_across_los_m': float(np.median(across_los[m])),
            'median_vertical_m': float(np.median(err[m, 2])),
            'median_velocity_residual_mps': float(np.median(vel_res[m])),
            'influence_translation_m': [float(v) for v in pc.influences[p, i_t]],
            'influence_rotation_deg': [float(v) for v in np.degrees(pc.influences[p, :3])],
        })
    local = _vehicle_frame(g['world'], g['pos'], g['yaw'])
    return {
        **sig,
        'advice': advice,
        'passes': passes,
        'n_passes': pc.n_passes,
        'jackknife_t_scale': pc.t_scale,
        'rounds': rounds,
        'iterations': fit.iterations,
        'converged': fit.converged,
        'time_offset_s': est.time_offset_s,
        'scatter_sigma_m': [float(v) for v in scatter],
        'profile_harmonics': config.refine.profile_harmonics,
        'coverage': {'aspect_edges_deg': coverage.aspect_edges_deg,
                     'bearing_edges_deg': coverage.bearing_edges_deg,
                     'weights': coverage.weights,
                     'bearing_spread_deg': coverage.bearing_spread_deg},
        # Arrays for the report's figures (one entry per used target).
        'residuals': {
            'target_index': data.index, 'pass_id': data.pass_id, 'weight': weight,
            'range_m': rng, 'azimuth_rad': azimuth, 'aspect_rad': g['aspect'],
            'bearing_rad': bearing, 'along_los_m': along_los, 'across_los_m': across_los,
            'vertical_m': err[:, 2], 'velocity_mps': vel_res,
            'offset_vehicle_m': local,
        },
        'robust_weight_mean': float(np.mean(_robust(r, n)[0])),
    }


#: Largest yaw rate of a pose that shows a lane to drive again [rad/s].
_LANE_MAX_YAW_RATE_RPS = 0.2


#: Heading change within the view [rad] from which a pass counts as a turn through it.
_TURN_RAD = math.radians(45.0)


def _turn_ranges(g: dict[str, F64], data: _Selected, est: Extrinsics) -> list[float]:
    """Distance from the radar [m] of each pass that turned through the view, where its
    heading was halfway through the turn."""
    vel, pos, t = g['vel'], g['pos'], data.times.t_s
    ranges: list[float] = []
    for p in np.unique(data.pass_id[data.pass_id >= 0]):
        idx = np.flatnonzero(data.pass_id == p)
        idx = idx[np.argsort(t[idx], kind='stable')]
        heading = np.unwrap(np.arctan2(vel[idx, 1], vel[idx, 0]))
        if idx.size < 2 or abs(heading[-1] - heading[0]) < _TURN_RAD:
            continue
        mid = idx[int(np.argmin(np.abs(heading - 0.5 * (heading[0] + heading[-1]))))]
        ranges.append(float(np.hypot(*(pos[mid, :2] - est.translation_m[:2]))))
    return ranges


def _drive_candidates(recording: Recording, poses: _Poses, est: Extrinsics,
                      g: dict[str, F64], data: _Selected, coverage: uncertainty.ViewCoverage,
                      bore: float, nearest_m: float) -> list[uncertainty.DriveCandidate]:
    """Drives through the view ranked by the (aspect, bearing) diversity they would add.

    Candidates are the vehicle's own recorded positions inside the part of the view where it
    was seen (range and bearing span of the used targets, no nearer than ``nearest_m``):
    roads it can drive. Each is tried
    in both directions; an (aspect bin, bearing) pair scores by its angular distance to the
    bearings already seen at that aspect (saturating at 30 deg).
    """
    rng = g['range']
    bearing = np.arctan2(g['los'][:, 1], g['los'][:, 0]) - bore
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    r_max = float(np.percentile(rng, 98))
    b_lo, b_hi = float(np.percentile(bearing, 1)), float(np.percentile(bearing, 99))
    pts = recording.vehicle.positions_m
    yaw = recording.vehicle.yaw_rad
    rel = pts[:, :2] - est.translation_m[:2]
    p_rng = np.hypot(rel[:, 0], rel[:, 1])
    p_bear = (np.arctan2(rel[:, 1], rel[:, 0]) - bore + np.pi) % (2 * np.pi) - np.pi
    # where a drive is most useful: close enough for the bearing to change across the car,
    # far enough to see the whole car
    inside = ((p_rng <= min(r_max, 60.0)) & (p_rng >= max(10.0, nearest_m))
              & (p_bear >= b_lo - 0.1) & (p_bear <= b_hi + 0.1))
    # A heading met mid-turn is no lane's: a junction's turns pass through every diagonal,
    # and a twenty-fourth probe with only east-west and north-south roads was asked to drive
    # 'south-westbound ... on a lane already driven'. Lanes are where the vehicle drove
    # straight (or round a bend: 0.2 rad/s is a 50 m radius at 10 m/s).
    straight = np.abs(recording.vehicle.yaw_rate_rps) < _LANE_MAX_YAW_RATE_RPS
    if (inside & straight).any():
        inside &= straight
    if not inside.any():
        return []
    # thin to about one sample per 5 m of road per direction
    key = np.stack([np.floor(pts[inside, 0] / 5.0), np.floor(pts[inside, 1] / 5.0),
                    np.floor(((yaw[inside] + np.pi) % (2 * np.pi)) / (np.pi / 4))], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    sel = np.flatnonzero(inside)[first]
    a_edges = np.radians(coverage.aspect_edges_deg)
    seen_aspect = g['aspect']
    # where each direction was driven: a candidate driven the other way is one already
    # driven where a pose within a road's width heads that way too (the other carriageway)
    driven_key = np.unique(key, axis=0)
    out: list[uncertainty.DriveCandidate] = []
    for flip, driven in ((0.0, True), (np.pi, False)):
        heading = yaw[sel] + flip
        if flip:
            turned = np.column_stack([key[first, :2], np.floor(
                ((heading + np.pi) % (2 * np.pi)) / (np.pi / 4))])
            near = (np.abs(turned[:, None, :2] - driven_key[None, :, :2]).max(axis=2) <= 1.0)
            turn = (turned[:, None, 2] - driven_key[None, :, 2]) % 8
            already = (near & ((turn <= 1) | (turn == 7))).any(axis=1)
        else:
            already = np.ones(sel.size, bool)
        los_dir = np.arctan2(rel[sel, 1], rel[sel, 0])
        aspect = (los_dir + np.pi - heading + np.pi) % (2 * np.pi) - np.pi
        a_bin = np.searchsorted(a_edges, (aspect - a_edges[0]) % (2 * np.pi) + a_edges[0],
                                side='right') - 1
        s_bin = np.searchsorted(a_edges, (seen_aspect - a_edges[0]) % (2 * np.pi)
                                + a_edges[0], side='right') - 1
        # distance to the nearest bearing already seen at the same aspect bin (vectorised
        # over candidates x used targets, thinned to at most 2000 targets)
        step = max(1, bearing.size // 2000)
        sb, ss = bearing[::step], s_bin[::step]
        same = a_bin[:, None] == ss[None, :]
        dist = np.abs((p_bear[sel][:, None] - sb[None, :] + np.pi) % (2 * np.pi) - np.pi)
        dist = np.where(same, dist, np.inf).min(axis=1)
        gain = np.where(np.isfinite(dist), np.minimum(dist / np.radians(30.0), 1.0), 0.0)
        for i in np.argsort(-gain)[:3]:
            out.append(uncertainty.DriveCandidate(float(heading[i]), float(p_rng[sel][i]),
                                                  float(p_bear[sel][i]), float(gain[i]),
                                                  bool(driven or already[i])))
    out.sort(key=lambda c: -c.gain)
    # one suggestion per direction of travel
    unique: list[uncertainty.DriveCandidate] = []
    for cand in out:
        if all(abs((cand.heading_rad - u.heading_rad + np.pi) % (2 * np.pi) - np.pi) > 0.5
               for u in unique):
            unique.append(cand)
    return unique
