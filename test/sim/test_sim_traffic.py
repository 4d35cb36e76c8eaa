"""Road geometry and traffic: fillets, lanes, signals, queues, the calibration drive."""
from __future__ import annotations

import math

import numpy as np
import pytest

from radar_calib_ros.sim.roads import DS_M, Junction, fillet_path, traffic_route
from radar_calib_ros.sim.scenario import get_scenario
from radar_calib_ros.sim.traffic import CAR, PEDESTRIAN, SignalPlan, simulate_traffic


def test_fillet_of_a_right_angle() -> None:
    """An L of two 50 m legs rounded with r = 10 m: arc length 50 + 50 - 2r + r pi/2,
    curvature 1/r on the arc, heading turned by exactly 90 deg."""
    r = 10.0
    path = fillet_path(np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 50.0]]), r)
    expected = 100.0 - 2 * r + r * math.pi / 2
    assert path.length_m == pytest.approx(expected, abs=DS_M)
    assert path.heading_rad[-1] - path.heading_rad[0] == pytest.approx(math.pi / 2, abs=1e-9)
    on_arc = path.curvature > 0
    assert np.allclose(path.curvature[on_arc], 1 / r)
    assert on_arc.sum() * DS_M == pytest.approx(r * math.pi / 2, abs=2 * DS_M)
    step = np.hypot(*np.diff(path.xy, axis=0).T)
    assert np.allclose(step, DS_M, atol=1e-3)
    # the arc's midpoint is r (sqrt 2 - 1) inside the corner
    mid = path.xy[np.argmin(np.hypot(path.xy[:, 0] - 50, path.xy[:, 1]))]
    assert math.hypot(mid[0] - 50, mid[1]) == pytest.approx(r * (math.sqrt(2) - 1), abs=0.1)


def test_routes_keep_to_their_side() -> None:
    for left_hand in (False, True):
        spec = get_scenario('baseline').junction
        from dataclasses import replace
        junction = Junction(replace(spec, left_hand=left_hand))
        route = traffic_route(junction, 0, 2, 0, 0, far_in_m=100.0, far_out_m=100.0)
        arm = junction.arms[0]
        start = route.path.xy[0]
        lateral = float((start - 100.0 * arm.u) @ arm.n)
        # inbound on the right of the travel direction (-u) with right-hand traffic
        travel = -arm.u
        right = np.array([travel[1], -travel[0]])
        side = float((start - 100.0 * arm.u) @ right)
        assert (side > 0) == (not left_hand)
        assert abs(lateral) == pytest.approx(0.5 * spec.lane_width_m)
        assert route.movement == 'straight'


def test_signals_cycle() -> None:
    plan = SignalPlan(np.array([0, 1, 0, 1]), 2, green_s=20.0, offset_s=0.0)
    assert list(plan.states(1.0)) == [0, 2, 0, 2]
    assert list(plan.states(21.0)) == [1, 2, 1, 2]
    assert list(plan.states(24.0)) == [2, 2, 2, 2]
    assert list(plan.states(26.0)) == [2, 0, 2, 0]
    off = SignalPlan(np.array([0, 1]), 2, 20.0, 0.0, off=True)
    assert list(off.states(5.0)) == [3, 3]


def test_traffic_queues_at_red_and_the_vehicle_passes() -> None:
    scenario = get_scenario('dense_traffic_steep_pitch')
    junction = Junction(scenario.junction)
    log = simulate_traffic(scenario, junction, 300.0, np.random.default_rng(0),
                           np.random.default_rng(1))
    users = log.users
    cls = users.object_class[log.ids]
    cars = cls == CAR
    # moving-class road users stand still at red lights and in queues
    standing = cars & (log.v < 0.05)
    assert standing.mean() > 0.1 * cars.mean()
    assert np.any(cls == PEDESTRIAN)
    assert np.max(log.v[cars]) < 16.7 * 1.4
    # never two cars of one lane on top of each other
    steps = np.searchsorted(log.step_start, np.arange(log.ids.size), side='right') - 1
    idx, frac = log.table.sample_index(users.route[log.ids], log.s)
    lane, u = log.table.lane_id[idx], log.table.lane_u[idx] + frac * DS_M
    sel = cars & (lane >= 0)
    order = np.lexsort((u[sel], lane[sel], steps[sel]))
    same = (np.diff(steps[sel][order]) == 0) & (np.diff(lane[sel][order]) == 0)
    assert np.min(np.diff(u[sel][order])[same]) > 1.0
    # the calibration vehicle passes through the junction, sometimes stopping
    t, s, v = log.vehicle_series(0)
    assert t[0] <= 0.0 <= 300.0 <= t[-1]
    crossings = [x for x in log.drive.pass_s[:, 1] if s[0] < x < s[-1]]
    assert len(crossings) >= 3
    assert np.any(v < 0.05)
    assert len(set(log.drive.movements[:len(crossings)])) >= 2
