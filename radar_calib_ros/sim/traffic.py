"""Road users on the junction: lanes, signals, queues and the calibration drive.

Every road user follows one route (``roads.Route``) with the Intelligent Driver Model
(Treiber, Hennecke and Helbing 2000): it keeps its desired speed on a free road, slows for
curves ahead, follows its leader in the same lane and stops at its stop line while its
signal says so, which makes queues at red lights. Pedestrians wait at the kerb while the
arm they cross has green. All road users advance together, one vectorised step of ``DT_S``
per iteration; a step's acceleration is constant, so a road user's arc length between
steps is the exact quadratic through the logged (s, v) pairs (:meth:`TrafficLog.states_at`).

The calibration vehicle (object id 0) drives a chain of passes through the junction,
joined by U-turns far down the arms, among the traffic and under the same rules.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.sim.roads import (
    DS_M, NO_LANE, Junction, Route, chain_route, pedestrian_route, shuttle_route,
    traffic_route)
from radar_calib_ros.sim.scenario import Scenario

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Traffic step [s].
DT_S = 0.2
#: Seconds simulated before t = 0, so the junction is busy when the recording starts.
WARMUP_S = 90.0
#: Recordings shorter than this are compressed drives (see ``plan_drive``) [s].
SHORT_S = 240.0

#: Object classes (``object_class`` codes in the ground truth).
CLASS_NAMES = ('clutter', 'car', 'truck', 'cyclist', 'pedestrian', 'false_alarm')
CAR, TRUCK, CYCLIST, PEDESTRIAN = 1, 2, 3, 4

# IDM parameters per class: desired speed mean/sd [m/s], max accel, comfortable decel
# [m/s^2], time headway [s], jam distance [m], lateral acceleration in curves [m/s^2]
# (class means: each driver draws its own around them, ``_driver``)
_IDM = {
    CAR: (13.0, 1.5, 1.5, 2.0, 1.2, 2.0, 2.2),
    TRUCK: (11.0, 1.0, 0.8, 1.5, 1.6, 3.0, 1.5),
    CYCLIST: (5.0, 0.8, 1.0, 1.5, 1.0, 1.0, 2.0),
    PEDESTRIAN: (1.35, 0.2, 0.8, 1.5, 0.5, 0.3, 3.0),
}


def _merge_lanes(lane: I64, u: F64) -> tuple[I64, F64]:
    """Per sample of one route: the exit lane it is about to join inside the junction (past
    its stop line, ``u > 0`` on the inbound lane) and its coordinate on that lane."""
    merge_lane = np.full(lane.size, NO_LANE, np.int64)
    merge_u = np.zeros(lane.size)
    change = np.flatnonzero((lane[1:] != lane[:-1]) & (lane[1:] != NO_LANE)
                            & (lane[:-1] != NO_LANE)) + 1
    for c in change:
        inside = np.arange(c - 1, -1, -1)
        inside = inside[(lane[inside] == lane[c - 1]) & (u[inside] > 0.0)]
        merge_lane[inside] = lane[c]
        merge_u[inside] = u[c] - (c - inside) * DS_M
    return merge_lane, merge_u


@dataclass(frozen=True)
class RouteTable:
    """All routes concatenated: per-sample arrays plus per-route offsets.

    The speed limit ``v_lim`` combines the curve limit of each sample with braking at
    ``b`` = 1.5 m/s^2 towards the slower samples ahead (a reverse cumulative minimum).
    """

    routes: tuple[Route, ...]
    offset: I64
    n_samples: I64
    xy: F64
    heading: F64
    curvature: F64
    lane_id: I64
    lane_u: F64
    v_lim: F64
    stop_key: F64
    stop_arm: I64
    stop_on_green: NDArray[np.bool_]
    #: inside the junction (past the stop line, before the route joins its exit lane): the
    #: exit lane and the coordinate there (negative: before joining), else NO_LANE / 0
    merge_lane: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    merge_u: F64 = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def build(cls, routes: list[Route], caps: list[F64 | float],
              a_lat: list[float] | None = None, brake: float = 1.5) -> RouteTable:
        """Concatenate routes; ``caps`` are speed caps (per route or per sample) and
        ``a_lat`` the lateral acceleration accepted in curves per route (default 2.2)."""
        n = np.array([r.path.xy.shape[0] for r in routes], np.int64)
        offset = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
        v_lims = []
        lateral = a_lat if a_lat is not None else [2.2] * len(routes)
        for route, cap, a_lat_route in zip(routes, caps, lateral):
            kappa = np.abs(route.path.curvature)
            with np.errstate(divide='ignore'):
                vc = np.where(kappa > 1e-6, np.sqrt(a_lat_route / np.maximum(kappa, 1e-9)),
                              30.0)
            vc = np.minimum(vc, cap)
            s = np.arange(vc.size) * DS_M
            v2 = np.minimum.accumulate((vc ** 2 + 2.0 * brake * s)[::-1])[::-1] - 2 * brake * s
            v_lims.append(np.sqrt(np.maximum(v2, 0.0)))
        keys, arms, green = [], [], []
        for k, route in enumerate(routes):
            for s_stop, arm in zip(route.stop_s, route.signal_arm):
                keys.append(k * 1e6 + float(s_stop))
                arms.append(int(arm))
                green.append(route.stop_on_green)
        order = np.argsort(keys) if keys else np.zeros(0, np.int64)
        merges = [_merge_lanes(r.lane_id, r.lane_u) for r in routes]
        return cls(tuple(routes), offset, n,
                   np.concatenate([r.path.xy for r in routes]),
                   np.concatenate([r.path.heading_rad for r in routes]),
                   np.concatenate([r.path.curvature for r in routes]),
                   np.concatenate([r.lane_id for r in routes]),
                   np.concatenate([r.lane_u for r in routes]),
                   np.concatenate(v_lims),
                   np.asarray(keys, float)[order], np.asarray(arms, np.int64)[order],
                   np.asarray(green, bool)[order],
                   np.concatenate([m[0] for m in merges]),
                   np.concatenate([m[1] for m in merges]))

    def sample_index(self, route: I64, s: F64) -> tuple[I64, F64]:
        """(global index of the sample at or before s, fraction to the next) per object."""
        pos = np.clip(s / DS_M, 0.0, (self.n_samples[route] - 1).astype(float) - 1e-9)
        i0 = np.floor(pos).astype(np.int64)
        return self.offset[route] + i0, pos - i0

    def lookup(self, route: I64, s: F64) -> tuple[F64, F64, F64]:
        """(xy (n, 2), heading (n,), curvature (n,)) at arc lengths, interpolated."""
        idx, frac = self.sample_index(route, s)
        xy = self.xy[idx] + (self.xy[idx + 1] - self.xy[idx]) * frac[:, None]
        heading = self.heading[idx] + (self.heading[idx + 1] - self.heading[idx]) * frac
        return xy, heading, self.curvature[idx]


@dataclass(frozen=True)
class SignalPlan:
    """Fixed-time signals: phases in turn, each green, amber 3 s, all-red 2 s; or switched
    off (flashing amber: nobody is held, pedestrians cross at will)."""

    arm_phase: I64
    n_phases: int
    green_s: float
    offset_s: float
    amber_s: float = 3.0
    all_red_s: float = 2.0
    off: bool = False

    def states(self, t: float) -> I64:
        """Per arm: 0 green, 1 amber, 2 red, 3 off (flashing amber) at time t."""
        if self.off:
            return np.full(self.arm_phase.size, 3, np.int64)
        slot = self.green_s + self.amber_s + self.all_red_s
        tau = (t + self.offset_s) % (slot * self.n_phases)
        phase = int(tau // slot)
        within = tau - phase * slot
        state = 0 if within < self.green_s else (1 if within < self.green_s + self.amber_s
                                                 else 2)
        out = np.full(self.arm_phase.size, 2, np.int64)
        out[self.arm_phase == phase] = state
        out[self.arm_phase < 0] = 0
        return out

    def states_at(self, times: F64, arms: I64) -> I64:
        """The state of ``arms[i]``'s signal at ``times[i]`` (vectorised :meth:`states`)."""
        times = np.asarray(times, float)
        arms = np.asarray(arms, np.int64)
        if self.off:
            return np.full(arms.size, 3, np.int64)
        slot = self.green_s + self.amber_s + self.all_red_s
        tau = (times + self.offset_s) % (slot * self.n_phases)
        phase = np.floor(tau / slot).astype(np.int64)
        within = tau - phase * slot
        state = np.where(within < self.green_s, 0, np.where(
            within < self.green_s + self.amber_s, 1, 2))
        arm_phase = self.arm_phase[arms]
        return np.where(arm_phase < 0, 0, np.where(arm_phase == phase, state, 2))


@dataclass(frozen=True)
class RoadUsers:
    """Static attributes per object id (id 0 is the calibration vehicle)."""

    object_class: NDArray[np.int8]
    route: I64
    length: F64
    width: F64
    height: F64
    rear_overhang: F64
    wheelbase: F64
    wobble_amp: F64
    wobble_k: F64
    wobble_phase: F64

    def __len__(self) -> int:
        return int(self.route.size)


@dataclass(frozen=True)
class CalibrationDrive:
    """The calibration vehicle's planned passes (entry arm, exit arm, lanes, movement)
    and the arc lengths of each pass's start, stop line and end on its route."""

    passes: tuple[tuple[int, int, int, int], ...]
    movements: tuple[str, ...]
    pass_s: F64
    far_m: float
    mode: str


@dataclass(frozen=True)
class TrafficLog:
    """Every road user's arc length and speed at every step.

    Rows of step k are ``rows[step_start[k]:step_start[k + 1]]``, sorted by id; step k is
    at time ``t0_s + k * DT_S``.
    """

    t0_s: float
    step_start: I64
    ids: I64
    s: F64
    v: F64
    users: RoadUsers
    table: RouteTable
    drive: CalibrationDrive
    signals: SignalPlan

    @property
    def n_steps(self) -> int:
        return int(self.step_start.size - 1)

    def states_at(self, t: float) -> tuple[I64, F64, F64]:
        """(ids, s, v) of the road users present at time t (between two logged steps)."""
        k = int(math.floor((t - self.t0_s) / DT_S))
        k = min(max(k, 0), self.n_steps - 2)
        tau = min(max(t - (self.t0_s + k * DT_S), 0.0), DT_S)
        a0, a1 = self.step_start[k], self.step_start[k + 1]
        b0, b1 = a1, self.step_start[k + 2]
        ids0, ids1 = self.ids[a0:a1], self.ids[b0:b1]
        pos = np.searchsorted(ids1, ids0)
        pos = np.minimum(pos, max(ids1.size - 1, 0))
        both = ids1[pos] == ids0 if ids1.size else np.zeros(ids0.size, bool)
        i0 = np.flatnonzero(both) + a0
        i1 = pos[both] + b0
        v0, v1 = self.v[i0], self.v[i1]
        acc = (v1 - v0) / DT_S
        return self.ids[i0], self.s[i0] + v0 * tau + 0.5 * acc * tau ** 2, v0 + acc * tau

    def poses(self, ids: I64, s: F64, v: F64) -> tuple[F64, F64, F64, F64]:
        """(xy (n, 2), heading (n,), speed (n,), yaw rate (n,)) of road users' reference
        points.

        Drivers do not hold the lane centre: each road user weaves by ``w(s) = A sin(k s +
        phase)`` across its path. The pose is that of the weaving point p(s) = c(s) + w n(s)
        exactly: its heading is the direction of dp/ds = t (1 - kappa w) + w' n (the rear
        axle moves along the heading, no side slip), its speed v |dp/ds|, and its yaw rate
        v d(heading)/ds (kappa piecewise constant).
        """
        users = self.users
        route = users.route[ids]
        xy, heading, kappa = self.table.lookup(route, s)
        amp, k, ph = users.wobble_amp[ids], users.wobble_k[ids], users.wobble_phase[ids]
        arg = k * s + ph
        w = amp * np.sin(arg)
        w1 = amp * k * np.cos(arg)
        w2 = -amp * k * k * np.sin(arg)
        normal = np.column_stack([-np.sin(heading), np.cos(heading)])
        xy = xy + w[:, None] * normal
        along = 1.0 - kappa * w
        norm2 = along * along + w1 * w1
        heading = heading + np.arctan2(w1, along)
        speed = v * np.sqrt(norm2)
        yaw_rate = v * (kappa + (along * w2 + kappa * w1 * w1) / norm2)
        return xy, heading, speed, yaw_rate

    def vehicle_series(self, object_id: int = 0) -> tuple[F64, F64, F64]:
        """(times, s, v) of one road user at every step it was present."""
        rows = np.flatnonzero(self.ids == object_id)
        steps = np.searchsorted(self.step_start, rows, side='right') - 1
        return self.t0_s + steps * DT_S, self.s[rows], self.v[rows]

    def vehicle_s_at(self, t: F64, object_id: int = 0) -> tuple[F64, F64]:
        """(s, v) of one road user at many times (constant acceleration between steps)."""
        times, s, v = self.vehicle_series(object_id)
        k = np.clip(np.searchsorted(times, t, side='right') - 1, 0, times.size - 2)
        tau = np.clip(t - times[k], 0.0, DT_S)
        acc = (v[k + 1] - v[k]) / DT_S
        return s[k] + v[k] * tau + 0.5 * acc * tau ** 2, v[k] + acc * tau


# --- the calibration drive --------------------------------------------------------------

def plan_drive(junction: Junction, scenario: Scenario, duration_s: float,
               rng: np.random.Generator) -> tuple[Route, CalibrationDrive, F64]:
    """The calibration vehicle's route, its passes and per-sample speed caps.

    The number of passes aimed at grows with the duration (one a minute, at least 4, at
    most 15); the U-turn distance shrinks for short recordings so that they still hold at
    least four passes. More passes are planned than fit: the recording just ends.
    """
    spec = scenario.drive
    n_arms = len(junction.arms)
    n_target = int(np.clip(round(duration_s / 60.0), 4, 15))
    slot = duration_s / n_target
    far = float(np.clip((slot * 6.5 - 70.0) / 2.0, 28.0, 230.0))
    if spec.mode == 'away':
        near = 205.0
        legs = int(math.ceil(duration_s * 14.0 / 110.0)) + 3
        route = shuttle_route(junction, spec.focus_arm, near, near + 95.0, legs)
        caps = np.full(route.path.xy.shape[0], float(rng.uniform(*spec.speed_mps)))
        drive = CalibrationDrive((), (), np.zeros((0, 3)), near, 'away')
        return route, drive, caps
    n_plan = n_target + 6
    passes: list[tuple[int, int, int, int]] = []
    used: dict[tuple[int, int], int] = {}
    entry = spec.focus_arm if spec.mode == 'arm' else int(rng.integers(n_arms))
    for k in range(n_plan):
        exits = [b for b in range(n_arms) if b != entry]
        if spec.mode == 'arm' and entry != spec.focus_arm:
            exits = [spec.focus_arm]
        score = np.array([used.get((entry, b), 0) + rng.uniform(0.0, 0.9) for b in exits])
        exit_ = exits[int(np.argmin(score))]
        used[(entry, exit_)] = used.get((entry, exit_), 0) + 1
        lanes = junction.lanes_for(entry, exit_)
        lane_in, lane_out = lanes[int(rng.integers(len(lanes)))]
        passes.append((entry, exit_, lane_in, lane_out))
        entry = exit_
    route, pass_s = chain_route(junction, passes, far)
    s = np.arange(route.path.xy.shape[0]) * DS_M
    speeds = rng.uniform(*spec.speed_mps, size=len(passes))
    which = np.clip(np.searchsorted(pass_s[:, 0], s, side='right') - 1, 0, len(passes) - 1)
    caps = speeds[which]
    movements = tuple(junction.movement(e, x) for e, x, _, _ in passes)
    return route, CalibrationDrive(tuple(passes), movements, pass_s, far, spec.mode), caps


# --- the traffic simulation -------------------------------------------------------------

@dataclass
class _Source:
    """A place where road users of one kind appear (Poisson arrivals)."""

    kind: int
    lane: int
    routes: list[int]
    weights: F64
    rate_hz: float
    next_t: float


def simulate_traffic(scenario: Scenario, junction: Junction, duration_s: float,
                     rng: np.random.Generator, drive_rng: np.random.Generator) -> TrafficLog:
    """Run the traffic from ``-WARMUP_S`` to ``duration_s`` (+ a margin).

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the traffic (arrivals, classes, sizes, desired speeds).
    drive_rng : numpy.random.Generator
        Draws the calibration drive, so that it does not change with the traffic density.
    """
    spec = scenario.traffic
    arm_len = junction.spec.arm_length_m
    routes: list[Route] = []
    caps: list[F64 | float] = []
    cal_route, drive, cal_caps = plan_drive(junction, scenario, duration_s, drive_rng)
    routes.append(cal_route)
    caps.append(cal_caps)
    # in its U-turns the calibration vehicle's driver accepts a little more lateral
    # acceleration in a short (compressed) drive
    a_lat = [3.5 if duration_s < SHORT_S else 2.5]
    sources: list[_Source] = []
    n_arms = len(junction.arms)
    lane_rate = spec.vehicles_per_lane_h / 3600.0
    for a in range(n_arms):
        for lane in range(junction.spec.lanes_in):
            ids, weights = [], []
            for b in range(n_arms):
                if b == a:
                    continue
                for lane_in, lane_out in junction.lanes_for(a, b):
                    if lane_in != lane:
                        continue
                    routes.append(traffic_route(junction, a, b, lane_in, lane_out,
                                                far_in_m=arm_len, far_out_m=arm_len))
                    caps.append(16.7)
                    a_lat.append(2.2)
                    ids.append(len(routes) - 1)
                    weights.append(0.6 if junction.movement(a, b) == 'straight' else 0.25)
            if ids:
                w = np.asarray(weights) / np.sum(weights)
                sources.append(_Source(CAR, junction.lane_id(a, True, lane), ids, w, lane_rate,
                                       0.0))
        bike_ids, bike_w = [], []
        near_side = 'right' if not junction.spec.left_hand else 'left'
        for b in range(n_arms):
            move = junction.movement(a, b) if b != a else ''
            if move in ('straight', near_side):
                routes.append(traffic_route(junction, a, b, 0, 0, far_in_m=min(arm_len, 160.0),
                                            far_out_m=min(arm_len, 160.0), bike=True))
                caps.append(7.0)
                a_lat.append(2.0)
                bike_ids.append(len(routes) - 1)
                bike_w.append(1.0)
        if bike_ids and spec.cyclists_per_arm_h > 0:
            sources.append(_Source(CYCLIST, junction.bike_lane_id(a, True), bike_ids,
                                   np.asarray(bike_w) / len(bike_w),
                                   spec.cyclists_per_arm_h / 3600.0, 0.0))
        for side in (True, False):
            routes.append(pedestrian_route(junction, a, side, 90.0))
            caps.append(2.0)
            a_lat.append(3.0)
            if spec.pedestrians_per_arm_h > 0:
                sources.append(_Source(PEDESTRIAN, NO_LANE, [len(routes) - 1], np.ones(1),
                                       spec.pedestrians_per_arm_h / 7200.0, 0.0))
    table = RouteTable.build(routes, caps, a_lat)
    for src in sources:
        src.next_t = -WARMUP_S + float(rng.exponential(1.0 / src.rate_hz))
    arm_phase = np.full(n_arms, -1, np.int64)
    for p, arms in enumerate(junction.spec.phases):
        arm_phase[list(arms)] = p
    # a short recording is a compressed drive: signals off (as at night), so that even
    # 90 s hold four passes; long ones have queues at red lights
    signals = SignalPlan(arm_phase, len(junction.spec.phases), spec.green_s,
                         float(rng.uniform(0.0, 100.0)), off=duration_s < SHORT_S)
    return _run(scenario, table, sources, signals, drive, duration_s, rng)


def _new_user(kind: int, rng: np.random.Generator) -> tuple[float, ...]:
    """(length, width, height, rear overhang, wheelbase, wobble amp, wavelength) of one
    road user; vehicles' reference point is the rear axle, others' the centre."""
    if kind == CAR:
        if rng.random() < 0.18:  # vans and SUVs
            length, width, height = rng.uniform(4.6, 5.4), rng.uniform(1.85, 2.05), \
                rng.uniform(1.75, 2.2)
        else:
            length, width, height = rng.uniform(3.8, 5.0), rng.uniform(1.68, 1.92), \
                rng.uniform(1.38, 1.6)
        overhang = length * rng.uniform(0.19, 0.23)
        wheelbase = length * rng.uniform(0.57, 0.62)
        return length, width, height, overhang, wheelbase, rng.uniform(0.03, 0.25), \
            rng.uniform(60.0, 220.0)
    if kind == TRUCK:
        length = rng.uniform(7.0, 16.5)
        overhang = rng.uniform(1.2, 3.2) if length < 12 else rng.uniform(3.0, 4.5)
        wheelbase = length - overhang - rng.uniform(1.2, 1.6)
        return length, rng.uniform(2.4, 2.55), rng.uniform(3.0, 4.0), overhang, wheelbase, \
            rng.uniform(0.03, 0.15), rng.uniform(100.0, 300.0)
    if kind == CYCLIST:
        return 1.8, 0.6, 1.75, 0.9, 1.05, rng.uniform(0.05, 0.2), rng.uniform(15.0, 40.0)
    return 0.5, 0.55, rng.uniform(1.55, 1.9), 0.25, 0.0, rng.uniform(0.02, 0.1), \
        rng.uniform(6.0, 12.0)


def _run(scenario: Scenario, table: RouteTable, sources: list[_Source], signals: SignalPlan,
         drive: CalibrationDrive, duration_s: float, rng: np.random.Generator) -> TrafficLog:
    veh = scenario.vehicle
    n_steps = int(math.ceil((WARMUP_S + duration_s + 2.0) / DT_S)) + 2
    t0 = -WARMUP_S
    cal_step = int(math.floor(WARMUP_S / DT_S)) - 2  # present a little before t = 0
    # static attributes, grown as road users appear
    attrs: dict[str, list[float]] = {k: [] for k in (
        'cls', 'route', 'length', 'width', 'height', 'overhang', 'wheelbase', 'wob_amp',
        'wob_k', 'wob_phase', 'v0', 'amax', 'b', 'T', 's0', 'react')}

    def add(kind: int, route: int, dims: tuple[float, ...], v0: float) -> int:
        amax, b, headway, s0, react = _driver(kind, rng)
        for key, value in zip(('cls', 'route', 'length', 'width', 'height', 'overhang',
                               'wheelbase', 'wob_amp'), (kind, route, *dims[:6])):
            attrs[key].append(value)
        attrs['wob_k'].append(2.0 * math.pi / dims[6])
        attrs['wob_phase'].append(float(rng.uniform(0.0, 2.0 * math.pi)))
        attrs['v0'].append(v0)
        attrs['amax'].append(amax)
        attrs['b'].append(b)
        attrs['T'].append(headway)
        attrs['s0'].append(s0)
        attrs['react'].append(react)
        return len(attrs['cls']) - 1

    # id 0: the calibration vehicle (its wobble is drawn too: a real driver)
    add(CAR, 0, (veh.length, veh.width, veh.height, veh.rear_overhang, veh.wheelbase,
                 float(rng.uniform(0.05, 0.18)), float(rng.uniform(80.0, 200.0))), 30.0)
    act_id = np.zeros(0, np.int64)
    act_s = np.zeros(0)
    act_v = np.zeros(0)
    lead_in = 12.0 if duration_s < SHORT_S else 30.0
    cal_start_s = float(drive.pass_s[0, 1] - lead_in) if drive.pass_s.size else 0.0
    cal_start_s = max(cal_start_s, 0.0)
    log_ids: list[I64] = []
    log_s: list[F64] = []
    log_v: list[F64] = []
    step_start = np.zeros(n_steps + 1, np.int64)
    count = 0
    a_arr = {k: np.zeros(0) for k in ('route', 'length', 'overhang', 'v0', 'amax', 'b', 'T',
                                      's0', 'cls', 'react')}
    stale = True
    for k in range(n_steps):
        t = t0 + k * DT_S
        # arrivals
        for src in sources:
            while src.next_t <= t:
                src.next_t += float(rng.exponential(1.0 / src.rate_hz))
                kind = src.kind
                if kind == CAR and rng.random() < scenario.traffic.truck_share:
                    kind = TRUCK
                route = src.routes[int(rng.choice(len(src.routes), p=src.weights))]
                dims = _new_user(kind, rng)
                room = math.inf
                if src.lane != NO_LANE and act_id.size:
                    routes_now = np.asarray(attrs['route'], np.int64)[act_id]
                    idx, _ = table.sample_index(routes_now, act_s)
                    on_lane = table.lane_id[idx] == src.lane
                    if np.any(on_lane):
                        u_min = np.min(table.lane_u[idx][on_lane]
                                       - np.asarray(attrs['overhang'])[act_id][on_lane])
                        u_start = table.lane_u[table.offset[route]]
                        room = float(u_min - (u_start + dims[0]))
                        if room < 3.0:
                            continue  # the lane is backed up to its end: no room
                mean_v0, sd_v0 = _IDM[kind][0], _IDM[kind][1]
                v0 = float(np.clip(rng.normal(mean_v0, sd_v0), 0.5 * mean_v0, 1.35 * mean_v0))
                new = add(kind, route, dims, v0)
                act_id = np.append(act_id, new)
                act_s = np.append(act_s, 0.0)
                act_v = np.append(act_v, min(v0, float(table.v_lim[table.offset[route]]),
                                             _stoppable_speed(room)))
                stale = True
        if k == cal_step:
            # the calibration vehicle joins where its drive begins (before the recording
            # starts); road users standing in its place leave, and it comes in no faster
            # than it can stop behind the next one
            act_id, act_s, act_v, room = _make_room(table, attrs, act_id, act_s, act_v,
                                                    cal_start_s)
            act_id = np.append(act_id, 0)
            act_s = np.append(act_s, cal_start_s)
            act_v = np.append(act_v, min(8.0, _stoppable_speed(room)))
            order = np.argsort(act_id, kind='stable')
            act_id, act_s, act_v = act_id[order], act_s[order], act_v[order]
            stale = True
        if stale:
            for key in a_arr:
                a_arr[key] = np.asarray(attrs[key], float)[act_id]
            stale = False
        # log this step (sorted by id: arrivals get increasing ids)
        step_start[k] = count
        log_ids.append(act_id.copy())
        log_s.append(act_s.copy())
        log_v.append(act_v.copy())
        count += act_id.size
        if act_id.size == 0:
            continue
        act_s, act_v = _idm_step(table, signals, a_arr, act_s, act_v, t)
        done = act_s >= table.n_samples[a_arr['route'].astype(np.int64)] * DS_M - 1.0
        if np.any(done):
            keep = ~done
            act_id, act_s, act_v = act_id[keep], act_s[keep], act_v[keep]
            for key in a_arr:
                a_arr[key] = a_arr[key][keep]
    step_start[n_steps] = count
    users = RoadUsers(
        object_class=np.asarray(attrs['cls'], np.int8),
        route=np.asarray(attrs['route'], np.int64),
        length=np.asarray(attrs['length']), width=np.asarray(attrs['width']),
        height=np.asarray(attrs['height']), rear_overhang=np.asarray(attrs['overhang']),
        wheelbase=np.asarray(attrs['wheelbase']), wobble_amp=np.asarray(attrs['wob_amp']),
        wobble_k=np.asarray(attrs['wob_k']), wobble_phase=np.asarray(attrs['wob_phase']))
    return TrafficLog(t0, step_start, np.concatenate(log_ids), np.concatenate(log_s),
                      np.concatenate(log_v), users, table, drive, signals)


def _stoppable_speed(room_m: float) -> float:
    """Entry speed [m/s] that can stop within ``room_m`` of free lane ahead at a firm
    3 m/s^2, keeping 2 m (a road user must not appear on top of a queue)."""
    return math.sqrt(2.0 * 3.0 * max(room_m - 2.0, 0.0))


def _make_room(table: RouteTable, attrs: dict[str, list[float]], act_id: I64, act_s: F64,
               act_v: F64, s_start: float) -> tuple[I64, F64, F64, float]:
    """Drop the active road users whose bodies lie where the calibration vehicle (id 0,
    route 0) starts, at arc length ``s_start``; also the free lane ahead of it [m]."""
    idx0, frac0 = table.sample_index(np.zeros(1, np.int64), np.array([s_start]))
    lane0 = table.lane_id[idx0[0]]
    if lane0 == NO_LANE or act_id.size == 0:
        return act_id, act_s, act_v, math.inf
    u0 = float(table.lane_u[idx0[0]] + frac0[0] * DS_M)
    rear0, front0 = u0 - attrs['overhang'][0], u0 + attrs['length'][0] - attrs['overhang'][0]
    routes = np.asarray(attrs['route'], np.int64)[act_id]
    idx, frac = table.sample_index(routes, act_s)
    on = table.lane_id[idx] == lane0
    u = table.lane_u[idx] + frac * DS_M
    overhang = np.asarray(attrs['overhang'])[act_id]
    rear, front = u - overhang, u - overhang + np.asarray(attrs['length'])[act_id]
    clash = on & (rear < front0 + 3.0) & (front > rear0 - 3.0)
    keep = ~clash
    ahead = on & keep & (rear >= front0)
    room = float(np.min(rear[ahead]) - front0) if np.any(ahead) else math.inf
    return act_id[keep], act_s[keep], act_v[keep], room


def _driver(kind: int, rng: np.random.Generator) -> tuple[float, float, float, float, float]:
    """One driver's (max accel, comfortable decel, time headway, jam distance, reaction
    time) around the class means of ``_IDM``.

    Drivers differ: with one set of constants every car pulls away from a stop line in
    lockstep with its neighbour in the next lane, and a radar (and the paper's evaluation,
    which keeps every track within 5 m of the vehicle) sees the two as one object for
    seconds. Real start-up: perception-reaction times of ~0.5-2.5 s (median ~1 s),
    accelerations spread by about a quarter.
    """
    _, amax, _, b, headway, s0, _ = _IDM[kind]
    spread = np.exp(rng.normal(0.0, 0.22, 2))
    react = float(np.clip(rng.lognormal(math.log(1.0), 0.4), 0.4, 2.5))
    return (float(amax * spread[0]), float(b * spread[1]),
            float(headway * rng.uniform(0.8, 1.3)), float(s0 * rng.uniform(0.8, 1.4)), react)


def _idm_step(table: RouteTable, signals: SignalPlan, a: dict[str, F64], s: F64, v: F64,
              t: float) -> tuple[F64, F64]:
    """One IDM step of every road user (leaders in the lane, stop lines, curve limits)."""
    route = a['route'].astype(np.int64)
    front = a['length'] - a['overhang']
    idx, frac = table.sample_index(route, s)
    lane = table.lane_id[idx]
    u = table.lane_u[idx] + frac * DS_M
    gap = np.full(s.size, np.inf)
    v_lead = np.zeros(s.size)
    # leader: the next road user ahead in the same lane (one lexsort). Inside the junction
    # a road user also queues on the exit lane it is about to join, so two flows merging
    # into one lane take turns instead of driving into each other.
    m_lane = table.merge_lane[idx]
    m_u = table.merge_u[idx] + frac * DS_M
    who = np.concatenate([np.flatnonzero(lane != NO_LANE), np.flatnonzero(m_lane != NO_LANE)])
    e_lane = np.concatenate([lane[lane != NO_LANE], m_lane[m_lane != NO_LANE]])
    e_u = np.concatenate([u[lane != NO_LANE], m_u[m_lane != NO_LANE]])
    if who.size > 1:
        order = np.lexsort((e_u, e_lane))
        same = e_lane[order[1:]] == e_lane[order[:-1]]
        me_e, ahead_e = order[:-1][same], order[1:][same]
        me, ahead = who[me_e], who[ahead_e]
        entry_gap = e_u[ahead_e] - a['overhang'][ahead] - (e_u[me_e] + front[me])
        # the nearest leader over both of a road user's entries
        first = np.lexsort((entry_gap, me))
        first = first[np.concatenate([[True], me[first][1:] != me[first][:-1]])[:first.size]]
        gap[me[first]] = entry_gap[first]
        v_lead[me[first]] = v[ahead[first]]
    # stop lines whose signal holds this road user
    if table.stop_key.size:
        key = route * 1e6 + s + front + 0.05
        j = np.searchsorted(table.stop_key, key)
        has = j < table.stop_key.size
        jj = np.minimum(j, table.stop_key.size - 1)
        has &= np.floor(table.stop_key[jj] / 1e6 + 1e-9).astype(np.int64) == route
        if np.any(has):
            arm = table.stop_arm[jj]
            state = signals.states_at(np.full(s.size, t), arm)
            # at a light that has just turned green each driver starts after its own
            # perception-reaction time (stopping for amber and red stays as timed)
            starting = (state == 0) & (signals.states_at(t - a['react'], arm) == 2)
            state = np.where(starting, 2, state)
            dist = table.stop_key[jj] - key + 0.05
            on_green = table.stop_on_green[jj]
            can_stop = dist > v * v / (2.0 * 3.5)
            hold = np.where(on_green, state <= 1, (state == 2) | ((state == 1) & can_stop))
            hold &= has & (dist < 120.0)
            closer = hold & (dist < gap)
            gap[closer] = dist[closer]
            v_lead[closer] = 0.0
    # desired speed: the class/driver speed, capped by the curve limit two seconds ahead
    ahead_idx, _ = table.sample_index(route, s + 2.0 * v + 2.0)
    v0 = np.maximum(np.minimum(a['v0'], table.v_lim[ahead_idx]), 0.3)
    amax, b, headway, s0 = a['amax'], a['b'], a['T'], a['s0']
    dv = v - v_lead
    s_star = s0 + np.maximum(0.0, v * headway + v * dv / (2.0 * np.sqrt(amax * b)))
    interaction = (s_star / np.maximum(gap, 0.1)) ** 2
    acc = amax * (1.0 - (v / v0) ** 4 - np.where(np.isfinite(gap), interaction, 0.0))
    acc = np.clip(acc, -9.0, amax)
    v_new = np.maximum(v + acc * DT_S, 0.0)
    return s + 0.5 * (v + v_new) * DT_S, v_new
