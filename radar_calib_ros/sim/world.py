"""The static world around the junction: road surface, buildings, poles, kerbs, parked cars.

Stationary scatterers make most of a roadside radar's targets. Each is a fixed point with
a radar cross section, an aspect lobe in the world (a facade reflects mostly towards the
road it faces, a kerb towards the carriageway) and a fluctuation type: steady (poles,
signal heads, signs: a few tenths of a dB) or Swerling I (everything rough). Building
fronts are also the walls that mirror moving road users into ghosts behind them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.sim.roads import Junction
from radar_calib_ros.sim.scenario import Scenario

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Ground:
    """The road surface: a plane ``z = alt0 + sx * x + sy * y`` (ellipsoidal altitude)."""

    alt0_m: float
    slope: tuple[float, float]

    def z(self, xy: F64) -> F64:
        xy = np.asarray(xy, float)
        return self.alt0_m + self.slope[0] * xy[..., 0] + self.slope[1] * xy[..., 1]

    @property
    def normal(self) -> F64:
        n = np.array([-self.slope[0], -self.slope[1], 1.0])
        return n / np.linalg.norm(n)


@dataclass(frozen=True)
class StaticScene:
    """Stationary scatterers and reflecting walls.

    point_m : (n, 3) world [m]; rcs_dbsm : (n,); lobe : (n, 2) world bird's-eye unit
    vector of strongest reflection, zero for omnidirectional; lobe_exp, floor : (n,);
    steady : (n,) True for non-fluctuating scatterers; walls : (w, 2, 2) bird's-eye end
    points of building fronts; wall_top_m : (w,) their top altitude.
    """

    ground: Ground
    point_m: F64
    rcs_dbsm: F64
    lobe: F64
    lobe_exp: F64
    floor: F64
    steady: NDArray[np.bool_]
    walls: F64
    wall_top_m: F64


class _Points:
    def __init__(self) -> None:
        self.rows: list[F64] = []

    def add(self, xy: F64, z: F64 | float, rcs: F64 | float, lobe: F64 | None = None,
            exp: float = 1.0, floor_db: float = -40.0, steady: bool = False) -> None:
        xy = np.atleast_2d(np.asarray(xy, float))
        n = xy.shape[0]
        lob = np.zeros((n, 2)) if lobe is None else np.broadcast_to(np.asarray(lobe, float),
                                                                    (n, 2))
        self.rows.append(np.column_stack([
            xy, np.broadcast_to(np.asarray(z, float), (n,)),
            np.broadcast_to(np.asarray(rcs, float), (n,)), lob, np.full(n, exp),
            np.full(n, 10.0 ** (floor_db / 10.0)), np.full(n, float(steady))]))


def build_scene(scenario: Scenario, junction: Junction, rng: np.random.Generator) -> StaticScene:
    """The static scatterers and walls of a scenario's junction (seeded).

    ``scenario.clutter_density`` scales the number of rough scatterers (facades, kerbs,
    vegetation) without changing the layout.
    """
    ground = Ground(scenario.site.ground_alt_m, scenario.site.slope)
    pts = _Points()
    walls: list[F64] = []
    tops: list[float] = []
    density = scenario.clutter_density
    parked_left = scenario.traffic.parked_cars
    n_arms = len(junction.arms)
    for k, arm in enumerate(junction.arms):
        u, n = arm.u, arm.n
        length = junction.spec.arm_length_m
        for inbound in (True, False):
            sgn = math.copysign(1.0, junction.kerb_offset(inbound))
            to_road = -sgn * n
            # kerb stones: weak, seen best square-on from the road
            d = np.arange(arm.stop_m + 1.0, min(length, 180.0), 1.5 / density)
            xy = d[:, None] * u + junction.kerb_offset(inbound) * n
            xy += rng.normal(0.0, 0.03, xy.shape)
            pts.add(xy, 0.12, rng.normal(-15.0, 3.0, d.size), to_road, 1.0, -12.0)
            # street lights and their foundations
            d = np.arange(arm.stop_m + 6.0 + rng.uniform(0, 20), min(length, 200.0), 32.0)
            xy = d[:, None] * u + (junction.kerb_offset(inbound) + sgn * 0.7) * n
            for z, rcs in ((0.4, 6.0), (2.2, 3.0), (4.6, 2.0)):
                pts.add(xy, z, rcs + rng.normal(0.0, 1.5, d.size), steady=True)
            # signal pole at the stop line and a sign further out
            xy = (arm.stop_m + 0.5) * u + (junction.kerb_offset(inbound) + sgn * 0.5) * n
            for z, rcs in ((0.5, 8.0), (2.6, 12.0), (3.8, 9.0)):
                pts.add(xy, z, rcs, steady=True)
            xy = (arm.stop_m + rng.uniform(15, 45)) * u + (
                junction.kerb_offset(inbound) + sgn * 0.6) * n
            pts.add(xy, 2.3, 10.0, -u if inbound else u, 1.0, -10.0, steady=True)
            # parked cars in the bays along the kerb
            n_here = int(round(parked_left / max(1, 2 * n_arms - 2 * k - (0 if inbound else 1))))
            parked_left -= n_here
            if n_here > 0:
                starts = arm.stop_m + 12.0 + np.sort(rng.choice(np.arange(0, 100, 6.0),
                                                                n_here, replace=False))
                for d0 in starts:
                    centre = (d0 + 2.3) * u + junction.parking_offset(inbound) * n
                    _parked_car(pts, centre, u, n, rng)
            # trees in the sidewalk (trunks; crowns sit above most radars' view)
            if rng.random() < 0.5:
                d = np.arange(arm.stop_m + 10.0 + rng.uniform(0, 8), min(length, 160.0), 11.0)
                xy = d[:, None] * u + (junction.sidewalk_offset(inbound) + sgn * 1.2) * n
                pts.add(xy, 1.2, rng.normal(-6.0, 2.0, d.size))
                for z in (3.5, 5.0):
                    keep = rng.random(d.size) < 0.6 * density
                    pts.add(xy[keep] + rng.normal(0, 1.0, (keep.sum(), 2)), z,
                            rng.normal(-13.0, 3.0, keep.sum()))
            # building fronts: blocks with gaps, set back behind the sidewalk
            d0 = arm.stop_m + rng.uniform(3.0, 9.0)
            far = rng.uniform(90.0, 170.0)
            while d0 < far:
                block = rng.uniform(14.0, 45.0)
                setback = junction.facade_offset(inbound) + sgn * rng.uniform(0.0, 6.0)
                top = rng.uniform(8.0, 20.0)
                a = d0 * u + setback * n
                b = (d0 + block) * u + setback * n
                walls.append(np.array([a, b]))
                tops.append(float(ground.z(0.5 * (a + b))) + top)
                along = np.arange(0.0, block, 1.7 / density)
                xy = a + along[:, None] * u
                for z in (0.8, 2.9, 5.6, 8.4):
                    if z > top:
                        continue
                    keep = rng.random(along.size) < 0.85
                    jitter = rng.normal(0.0, 0.15, (keep.sum(), 2))
                    pts.add(xy[keep] + jitter, z + rng.normal(0.0, 0.3, keep.sum()),
                            rng.normal(-1.0, 5.0, keep.sum()), to_road, 1.5, -20.0)
                d0 += block + rng.uniform(3.0, 14.0)
        # manhole covers and road marks on the carriageway
        d = rng.uniform(arm.stop_m, 150.0, 4)
        off = rng.uniform(-junction.half_width_m + 2.0, junction.half_width_m - 2.0, 4)
        pts.add(d[:, None] * u + off[:, None] * n, 0.02, rng.normal(-9.0, 2.0, 4), steady=True)
    a = np.concatenate(pts.rows)
    xy = a[:, 0:2]
    z = ground.z(xy) + a[:, 2]
    return StaticScene(ground, np.column_stack([xy, z]), a[:, 3].copy(), a[:, 4:6].copy(),
                       a[:, 6].copy(), a[:, 7].copy(), a[:, 8] > 0.5,
                       np.asarray(walls).reshape(-1, 2, 2), np.asarray(tops))


def _parked_car(pts: _Points, centre: F64, u: F64, n: F64, rng: np.random.Generator) -> None:
    """A parked car as a handful of fixed scattering points (wheels, body, corners)."""
    length, width = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.9)
    heading = u if rng.random() < 0.5 else -u
    side = np.array([-heading[1], heading[0]])
    local = np.array([
        [0.3 * length, 0.5 * width - 0.25, 0.3], [-0.3 * length, 0.5 * width - 0.25, 0.3],
        [0.3 * length, -0.5 * width + 0.25, 0.3], [-0.3 * length, -0.5 * width + 0.25, 0.3],
        [0.35 * length, 0.0, 0.6], [0.0, 0.0, 0.25], [0.1, 0.3, 0.8],
        [0.5 * length, 0.5 * width, 0.5], [-0.5 * length, 0.5 * width, 0.5],
        [0.5 * length, -0.5 * width, 0.5], [-0.5 * length, -0.5 * width, 0.5]])
    xy = centre + local[:, :1] * heading + local[:, 1:2] * side
    pts.add(xy, local[:, 2], rng.normal(0.0, 3.0, local.shape[0]))
