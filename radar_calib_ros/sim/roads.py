"""Road geometry of the simulated junction: lanes, filleted paths and routes.

Everything is in the site's local metric frame (x east, y north of the local grid, metres).
A junction is a set of arms leaving the centre at given directions; each arm carries
inbound and outbound lanes, a bike lane per side, kerbs and sidewalks. A *route* is the
path a road user's reference point follows (the rear axle for vehicles, so that the
heading is the path tangent, as for a non-slipping car), sampled every ``DS_M`` metres
along its arc length, and annotated per sample with the lane it occupies and the lane
coordinate ``u`` (metres, shared by every route using that lane), so that the traffic model
can find each road user's leader with one sort.

Paths are polylines whose corners are rounded by circular fillets: straight lanes, turns
of a given radius, U-turn loops. The curvature is therefore piecewise constant and the
yaw rate ``speed * curvature`` is exact for the sampled path.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Arc-length spacing of route samples [m].
DS_M = 0.25
#: Lane id of a path piece on which a road user has no leader (U-turn loops, sidewalks).
NO_LANE = -1


def unit(angle_rad: float) -> F64:
    """Unit vector of an ENU direction."""
    return np.array([math.cos(angle_rad), math.sin(angle_rad)])


def left_normal(angle_rad: float) -> F64:
    """Unit vector 90 deg counter-clockwise of an ENU direction."""
    return np.array([-math.sin(angle_rad), math.cos(angle_rad)])


def wrap_angle(angle: F64 | float) -> F64:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle, float) + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class SampledPath:
    """A path sampled every ``DS_M`` metres of arc length.

    xy : (n, 2) [m]; heading_rad : (n,) unwrapped ENU heading; curvature : (n,) [1/m]
    (positive = turning left); vertex_s : arc length of each input vertex (its fillet's
    midpoint when it was rounded) [m].
    """

    xy: F64
    heading_rad: F64
    curvature: F64
    vertex_s: F64

    @property
    def length_m(self) -> float:
        return float((self.xy.shape[0] - 1) * DS_M)


def fillet_path(vertices: F64, radii: F64 | float) -> SampledPath:
    """Sample a polyline whose interior corners are rounded with circular arcs.

    Parameters
    ----------
    vertices : ndarray of shape (m, 2)
        Corner points; consecutive duplicates are not allowed.
    radii : float or ndarray of shape (m,)
        Fillet radius wanted at each vertex (end vertices ignored). The radius shrinks
        where the neighbouring segments are too short to hold the arc: an interior segment
        lends each of its ends at most half its length, an end segment all of it.

    Returns
    -------
    SampledPath
    """
    p = np.asarray(vertices, float)
    m = p.shape[0]
    r_want = np.broadcast_to(np.asarray(radii, float), (m,))
    seg = np.diff(p, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    if np.any(seg_len < 1e-9):
        raise ValueError('fillet_path: consecutive vertices coincide')
    seg_dir = seg / seg_len[:, None]
    # primitives: ('line', start, heading, length) or ('arc', centre, radius, start angle,
    # sweep, heading0); collected with the arc length where each vertex lands
    prims: list[tuple[str, tuple[float, ...]]] = []
    vertex_s = np.zeros(m)
    cursor = p[0].copy()
    s = 0.0
    for i in range(1, m):
        d_in = seg_dir[i - 1]
        heading_in = math.atan2(d_in[1], d_in[0])
        if i == m - 1:
            length = float(np.hypot(*(p[i] - cursor)))
            if length > 1e-9:
                prims.append(('line', (cursor[0], cursor[1], heading_in, length)))
                s += length
            vertex_s[i] = s
            break
        d_out = seg_dir[i]
        turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(d_in @ d_out))
        if abs(turn) < 1e-9 or r_want[i] <= 0.0:
            length = float(np.hypot(*(p[i] - cursor)))
            if length > 1e-9:
                prims.append(('line', (cursor[0], cursor[1], heading_in, length)))
                s += length
            vertex_s[i] = s
            cursor = p[i].copy()
            continue
        half = math.tan(abs(turn) / 2.0)
        room_in = seg_len[i - 1] * (1.0 if i - 1 == 0 else 0.5)
        room_out = seg_len[i] * (1.0 if i + 1 == m - 1 else 0.5)
        tangent = min(r_want[i] * half, room_in, room_out,
                      float(np.hypot(*(p[i] - cursor))))
        radius = tangent / half
        a = p[i] - tangent * d_in
        length = float(np.hypot(*(a - cursor)))
        if length > 1e-9:
            prims.append(('line', (cursor[0], cursor[1], heading_in, length)))
            s += length
        side = 1.0 if turn > 0 else -1.0
        normal = np.array([-d_in[1], d_in[0]]) * side
        centre = a + radius * normal
        start_angle = math.atan2(a[1] - centre[1], a[0] - centre[0])
        prims.append(('arc', (centre[0], centre[1], radius, start_angle, turn, heading_in)))
        vertex_s[i] = s + 0.5 * radius * abs(turn)
        s += radius * abs(turn)
        cursor = p[i] + tangent * d_out
    starts = np.cumsum([0.0] + [_prim_length(pr) for pr in prims])
    total = starts[-1]
    n = int(math.floor(total / DS_M)) + 1
    grid = np.arange(n) * DS_M
    which = np.clip(np.searchsorted(starts, grid, side='right') - 1, 0, len(prims) - 1)
    xy = np.zeros((n, 2))
    heading = np.zeros(n)
    curvature = np.zeros(n)
    for k, (kind, par) in enumerate(prims):
        sel = which == k
        if not np.any(sel):
            continue
        ds = grid[sel] - starts[k]
        if kind == 'line':
            x0, y0, h, _ = par
            xy[sel, 0] = x0 + ds * math.cos(h)
            xy[sel, 1] = y0 + ds * math.sin(h)
            heading[sel] = h
        else:
            cx, cy, radius, a0, sweep, h0 = par
            sign = 1.0 if sweep > 0 else -1.0
            ang = a0 + sign * ds / radius
            xy[sel, 0] = cx + radius * np.cos(ang)
            xy[sel, 1] = cy + radius * np.sin(ang)
            heading[sel] = h0 + sign * ds / radius
            curvature[sel] = sign / radius
    heading = np.unwrap(heading)
    return SampledPath(xy, heading, curvature, vertex_s)


def _prim_length(prim: tuple[str, tuple[float, ...]]) -> float:
    kind, par = prim
    return par[3] if kind == 'line' else par[2] * abs(par[4])


# --- the junction -----------------------------------------------------------------------

@dataclass(frozen=True)
class JunctionSpec:
    """Layout of a signalised junction.

    arm_deg : outward direction of each arm (ENU, counter-clockwise from local east);
    phases : for each signal phase, the arms whose traffic has green in it;
    left_hand : traffic keeps left (UK, Australia, ...).
    """

    arm_deg: tuple[float, ...]
    phases: tuple[tuple[int, ...], ...]
    lanes_in: int = 2
    lanes_out: int = 2
    lane_width_m: float = 3.3
    left_hand: bool = False
    arm_length_m: float = 260.0
    crosswalk_m: float = 4.0


@dataclass(frozen=True)
class ArmGeometry:
    """Derived geometry of one arm: outward direction, left normal, stop-line distance."""

    angle_rad: float
    u: F64
    n: F64
    stop_m: float


class Junction:
    """Lane offsets, stop lines and lane ids of a :class:`JunctionSpec`.

    Lateral offsets are along each arm's left normal ``n`` (of its outward direction).
    With right-hand traffic outbound lanes lie at negative offsets and inbound lanes at
    positive ones; left-hand traffic mirrors that.
    """

    def __init__(self, spec: JunctionSpec) -> None:
        self.spec = spec
        w = spec.lane_width_m
        self.side = -1.0 if spec.left_hand else 1.0
        self.half_width_m = max(spec.lanes_in, spec.lanes_out) * w + 1.9
        arms = []
        angles = [math.radians(a) for a in spec.arm_deg]
        for k, a in enumerate(angles):
            need = 6.0
            for j, b in enumerate(angles):
                if j == k:
                    continue
                delta = float(wrap_angle(b - a))
                sin_d = abs(math.sin(delta))
                if sin_d < 0.25:
                    continue
                # where road j's edge crosses arm k's edge, measured along arm k
                reach = self.half_width_m / sin_d + self.half_width_m * abs(
                    math.cos(delta)) / sin_d
                if abs(delta) < math.pi / 2:
                    need = max(need, reach)
                else:
                    need = max(need, self.half_width_m / sin_d)
            stop = min(need + spec.crosswalk_m, 40.0)
            arms.append(ArmGeometry(a, unit(a), left_normal(a), stop))
        self.arms: tuple[ArmGeometry, ...] = tuple(arms)

    # offsets --------------------------------------------------------------------------------
    def inbound_offset(self, lane: int) -> float:
        return self.side * (lane + 0.5) * self.spec.lane_width_m

    def outbound_offset(self, lane: int) -> float:
        return -self.side * (lane + 0.5) * self.spec.lane_width_m

    def bike_offset(self, inbound: bool) -> float:
        base = (self.spec.lanes_in if inbound else self.spec.lanes_out) * self.spec.lane_width_m
        return (1.0 if inbound else -1.0) * self.side * (base + 0.9)

    def kerb_offset(self, inbound: bool) -> float:
        base = (self.spec.lanes_in if inbound else self.spec.lanes_out) * self.spec.lane_width_m
        return (1.0 if inbound else -1.0) * self.side * (base + 1.9)

    def sidewalk_offset(self, inbound: bool) -> float:
        """Centre of the sidewalk, behind a 2.2 m strip of parking bays along the kerb."""
        return self.kerb_offset(inbound) + (1.0 if inbound else -1.0) * self.side * 3.6

    def parking_offset(self, inbound: bool) -> float:
        return self.kerb_offset(inbound) + (1.0 if inbound else -1.0) * self.side * 1.2

    def facade_offset(self, inbound: bool) -> float:
        """Nearest a building front may come to the arm's centre line."""
        return self.kerb_offset(inbound) + (1.0 if inbound else -1.0) * self.side * 5.5

    # lane ids ---------------------------------------------------------------------------
    @staticmethod
    def lane_id(arm: int, inbound: bool, lane: int) -> int:
        """Lane ids: 16 per arm; 0-5 inbound lanes, 6 inbound bike, 8-13 outbound, 14 bike."""
        return arm * 16 + (0 if inbound else 8) + lane

    def bike_lane_id(self, arm: int, inbound: bool) -> int:
        return arm * 16 + (6 if inbound else 14)

    # movements --------------------------------------------------------------------------
    def turn_angle(self, entry: int, exit_: int) -> float:
        """Heading change of the movement entry -> exit [rad], positive = left."""
        a, b = self.arms[entry], self.arms[exit_]
        return float(wrap_angle(b.angle_rad - (a.angle_rad + math.pi)))

    def movement(self, entry: int, exit_: int) -> str:
        """'straight', 'left' or 'right'."""
        turn = self.turn_angle(entry, exit_)
        if abs(turn) < math.radians(40.0):
            return 'straight'
        return 'left' if turn > 0 else 'right'

    def lanes_for(self, entry: int, exit_: int) -> list[tuple[int, int]]:
        """Allowed (inbound lane, outbound lane) pairs of a movement.

        The turn across oncoming traffic (left with right-hand traffic) uses the inner
        lanes, the near-side turn the outer ones, straight traffic any lane.
        """
        move = self.movement(entry, exit_)
        n_in, n_out = self.spec.lanes_in, self.spec.lanes_out
        near_side = 'right' if self.side > 0 else 'left'
        if move == 'straight':
            return [(j, min(j, n_out - 1)) for j in range(n_in)]
        if move == near_side:
            return [(n_in - 1, n_out - 1)]
        return [(0, 0)]


@dataclass(frozen=True)
class Route:
    """One sampled route with its lane annotation.

    lane_id, lane_u : per sample; stop_s : arc length of its stop line (inf if none);
    signal_arm : arm whose signal governs the stop line (-1 none); stop_on_green : the road
    user waits while that arm has green (pedestrians crossing it) instead of while red.
    """

    path: SampledPath
    lane_id: I64
    lane_u: F64
    stop_s: F64 = field(default_factory=lambda: np.full(0, np.inf))
    signal_arm: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    stop_on_green: bool = False
    entry_arm: int = -1
    exit_arm: int = -1
    movement: str = ''

    @property
    def length_m(self) -> float:
        return self.path.length_m


def _annotate(n: int, pieces: list[tuple[float, float, int, float]]) -> tuple[I64, F64]:
    """Per-sample lane ids and coordinates from pieces (s0, s1, lane, s_of_u0)."""
    s = np.arange(n) * DS_M
    lane = np.full(n, NO_LANE, np.int64)
    u = np.zeros(n)
    for s0, s1, lid, s_ref in pieces:
        sel = (s >= s0) & (s < s1)
        lane[sel] = lid
        u[sel] = s[sel] - s_ref
    return lane, u


def traffic_route(j: Junction, entry: int, exit_: int, lane_in: int, lane_out: int, *,
                  far_in_m: float, far_out_m: float, radius_m: float | None = None,
                  bike: bool = False) -> Route:
    """The path of a vehicle (or a cyclist, ``bike=True``) through the junction."""
    a, b = j.arms[entry], j.arms[exit_]
    if bike:
        off_in, off_out = j.bike_offset(True), j.bike_offset(False)
        lid_in, lid_out = j.bike_lane_id(entry, True), j.bike_lane_id(exit_, False)
    else:
        off_in, off_out = j.inbound_offset(lane_in), j.outbound_offset(lane_out)
        lid_in, lid_out = j.lane_id(entry, True, lane_in), j.lane_id(exit_, False, lane_out)
    vertices, radii, i_stop, i_exit = _through_vertices(
        j, a, b, off_in, off_out, far_in_m, far_out_m, radius_m)
    path = fillet_path(vertices, radii)
    s_stop, s_exit = path.vertex_s[i_stop], path.vertex_s[i_exit]
    s_mid = 0.5 * (s_stop + s_exit)
    n = path.xy.shape[0]
    lane, u = _annotate(n, [(0.0, s_mid, lid_in, s_stop), (s_mid, np.inf, lid_out, s_exit)])
    return Route(path, lane, u, np.array([s_stop]), np.array([entry], np.int64),
                 entry_arm=entry, exit_arm=exit_, movement=j.movement(entry, exit_))


def _through_vertices(j: Junction, a: ArmGeometry, b: ArmGeometry, off_in: float,
                      off_out: float, far_in_m: float, far_out_m: float,
                      radius_m: float | None) -> tuple[F64, F64, int, int]:
    """Vertices (start, stop line, [corner], exit line, end) of a movement a -> b."""
    p_start = far_in_m * a.u + off_in * a.n
    p_stop = a.stop_m * a.u + off_in * a.n
    p_exit = b.stop_m * b.u + off_out * b.n
    p_end = far_out_m * b.u + off_out * b.n
    d_in, d_out = -a.u, b.u
    cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
    turn = math.atan2(cross, float(d_in @ d_out))
    if radius_m is None:
        radius_m = 9.0 if (turn < 0) == (j.side > 0) else 16.0
    corner = None
    if abs(cross) > 0.2:
        # p_stop + t d_in = p_exit - k d_out, t >= 0, k >= 0
        mat = np.column_stack([d_in, d_out])
        t, k = np.linalg.solve(mat, p_exit - p_stop)
        if t > 0.5 and k > 0.5:
            corner = p_stop + t * d_in
    if corner is None:
        vertices = np.array([p_start, p_stop, p_exit, p_end])
        radii = np.array([0.0, 40.0, 40.0, 0.0])
        return vertices, radii, 1, 2
    vertices = np.array([p_start, p_stop, corner, p_exit, p_end])
    radii = np.array([0.0, 0.0, radius_m, 0.0, 0.0])
    return vertices, radii, 1, 3


def pedestrian_route(j: Junction, arm: int, start_inbound_side: bool, far_m: float) -> Route:
    """A walk towards the junction on one sidewalk of an arm, across the arm on the
    crosswalk (waiting while the arm has green), and back out on the other sidewalk."""
    a = j.arms[arm]
    side_a = j.sidewalk_offset(start_inbound_side)
    side_b = j.sidewalk_offset(not start_inbound_side)
    cross = max(a.stop_m - 2.0, 3.0)
    vertices = np.array([far_m * a.u + side_a * a.n, cross * a.u + side_a * a.n,
                         cross * a.u + side_b * a.n, far_m * a.u + side_b * a.n])
    path = fillet_path(vertices, 1.0)
    # waiting point: the kerb, 0.6 m before the walk leaves the sidewalk
    kerb = j.kerb_offset(start_inbound_side)
    s_wait = path.vertex_s[1] + abs(side_a - kerb) - 0.6
    n = path.xy.shape[0]
    lane, u = np.full(n, NO_LANE, np.int64), np.zeros(n)
    return Route(path, lane, u, np.array([s_wait]), np.array([arm], np.int64),
                 stop_on_green=True, entry_arm=arm, exit_arm=arm, movement='crossing')


def chain_route(j: Junction, passes: list[tuple[int, int, int, int]], far_m: float,
                loop_m: float = 14.0) -> tuple[Route, F64]:
    """The calibration vehicle's drive: consecutive passes joined by U-turn loops.

    Parameters
    ----------
    passes : list of (entry arm, exit arm, inbound lane, outbound lane)
        Each pass enters where the previous one left (``entry[k+1] == exit[k]``).
    far_m : float
        Distance from the centre at which the vehicle turns round.

    Returns
    -------
    Route
        Lane annotation on the lanes it shares with traffic, ``NO_LANE`` in the loops; one
        stop line per pass.
    pass_s : ndarray of shape (k, 3)
        Arc length of each pass's start, stop line and end.
    """
    vertices: list[F64] = []
    radii: list[float] = []
    marks: list[tuple[int, int, int, int]] = []  # vertex index: start, stop, exit, end
    for k, (entry, exit_, lane_in, lane_out) in enumerate(passes):
        a, b = j.arms[entry], j.arms[exit_]
        off_in, off_out = j.inbound_offset(lane_in), j.outbound_offset(lane_out)
        v, r, i_stop, i_exit = _through_vertices(j, a, b, off_in, off_out, far_m, far_m, None)
        base = len(vertices)
        vertices.extend(v)
        radii.extend(r)
        marks.append((base, base + i_stop, base + i_exit, base + len(v) - 1))
        if k + 1 < len(passes):
            nxt_in = j.inbound_offset(passes[k + 1][2])
            away = float(np.sign(off_out - nxt_in))
            loop = [(far_m + 0.45 * loop_m) * b.u + (off_out + away * 4.0) * b.n,
                    (far_m + loop_m) * b.u + 0.5 * (off_out + nxt_in) * b.n,
                    (far_m + 0.45 * loop_m) * b.u + (nxt_in - away * 4.0) * b.n]
            vertices.extend(loop)
            radii.extend([4.5, 4.5, 4.5])
    verts = np.array(vertices)
    rad = np.array(radii)
    for k, (i_start, _, _, i_end) in enumerate(marks):
        # the loops join the lanes through rounded corners too
        rad[i_start] = 4.5 if k > 0 else 0.0
        rad[i_end] = 4.5 if k + 1 < len(marks) else 0.0
    path = fillet_path(verts, rad)
    pieces = []
    pass_s = np.zeros((len(passes), 3))
    for k, (entry, exit_, lane_in, lane_out) in enumerate(passes):
        i_start, i_stop, i_exit, i_end = marks[k]
        s_start, s_stop = path.vertex_s[i_start], path.vertex_s[i_stop]
        s_exit, s_end = path.vertex_s[i_exit], path.vertex_s[i_end]
        s_mid = 0.5 * (s_stop + s_exit)
        pieces.append((s_start, s_mid, j.lane_id(entry, True, lane_in), s_stop))
        pieces.append((s_mid, s_end, j.lane_id(exit_, False, lane_out), s_exit))
        pass_s[k] = (s_start, s_stop, s_end)
    n = path.xy.shape[0]
    lane, u = _annotate(n, pieces)
    entries = np.array([p[0] for p in passes], np.int64)
    return Route(path, lane, u, pass_s[:, 1].copy(), entries, movement='chain'), pass_s


def shuttle_route(j: Junction, arm: int, near_m: float, far_m: float, n_legs: int) -> Route:
    """Back and forth on one arm between ``near_m`` and ``far_m`` from the centre, turning
    round at both ends (the 'vehicle never in view' drive); no lanes, no signals."""
    a = j.arms[arm]
    off_out, off_in = j.outbound_offset(0), j.inbound_offset(0)
    away = float(np.sign(off_out - off_in))
    vertices: list[F64] = [near_m * a.u + off_out * a.n]
    for leg in range(n_legs):
        if leg % 2 == 0:
            vertices += [far_m * a.u + off_out * a.n,
                         (far_m + 6.0) * a.u + (off_out + away * 4.0) * a.n,
                         (far_m + 14.0) * a.u + 0.5 * (off_out + off_in) * a.n,
                         (far_m + 6.0) * a.u + (off_in - away * 4.0) * a.n]
        else:
            vertices += [near_m * a.u + off_in * a.n,
                         (near_m - 6.0) * a.u + (off_in - away * 4.0) * a.n,
                         (near_m - 14.0) * a.u + 0.5 * (off_out + off_in) * a.n,
                         (near_m - 6.0) * a.u + (off_out + away * 4.0) * a.n]
    verts = np.array(vertices)
    rad = np.full(len(vertices), 4.5)
    rad[0] = rad[-1] = 0.0
    path = fillet_path(verts, rad)
    n = path.xy.shape[0]
    return Route(path, np.full(n, NO_LANE, np.int64), np.zeros(n), np.full(0, np.inf),
                 np.zeros(0, np.int64), movement='shuttle')
