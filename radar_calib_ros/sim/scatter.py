"""Where on a road user the radar sees it: scattering regions per road user.

A road user's returns come from a few *regions* fixed to its body. Each frame, every
region offers one candidate reflection at a random point inside it (real scattering
centres flicker over a car's surface from frame to frame); the radar model then decides
from its strength, range, aspect and occlusion whether it is detected. A region has:

- a centre and half-extents in the vehicle frame (x forward from the reference point, the
  rear axle for vehicles and the centre otherwise; y left; z up from the road);
- a radar cross section [dBsm] and an aspect lobe: gain ``floor + (1 - floor) *
  max(cos(angle to lobe), 0) ** exp`` (linear power) against the bird's-eye direction
  towards the radar, omnidirectional when the lobe is zero. Faces facing away from the
  radar, and wheels on the far side, are thereby weak or invisible;
- a kind (:data:`KIND_NAMES`), and how its point moves: rigidly with the body, on a
  rolling wheel (micro-Doppler from ``omega x r``: from 0 at the contact patch to twice
  the speed at the top), or with swinging limbs;
- for multi-bounce regions, an extra path length: the wave enters under the car (wheel
  house, underbody), bounces between body and road, and returns later. Its target lies
  along the line of sight to the region's mirror image in the road, ``extra / 2`` beyond
  it: below the road and on the far side of the entry point, never on the radar's side.

Scatter models (issue 7): ``skin`` puts every return on the box faces that face the radar
and on the bumper corners (the natural first guess; at the true calibration about 40 %
of such targets fall inside the box, half the face returns leaving it through noise
alone). ``interior`` follows real car point clouds: wheels and wheel houses with
micro-Doppler, axles and underbody, the engine block behind the grille, seats seen
through the windows, the exhaust, mirrors outside the box, the bumper corners, weak skin,
and multi-bounce returns. ``mixed`` gives each road user its own blend: each region's
chance to offer a candidate is scaled by the road user's weight of the model it belongs to.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from radar_calib_ros.errors import ConfigError
from radar_calib_ros.sim.traffic import CYCLIST, PEDESTRIAN, TRUCK, RoadUsers

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

SCATTER_MODELS = ('skin', 'interior', 'mixed')
#: The model the simulator uses unless told otherwise: the one whose metrics at the true
#: calibration match the paper's Table I (test/sim/test_sim_scatter.py).
DEFAULT_SCATTER_MODEL = 'interior'

KIND_NAMES = ('static', 'face', 'corner', 'wheel', 'wheel_house', 'underbody', 'engine',
              'seat', 'exhaust', 'mirror', 'multibounce', 'body', 'limb', 'ghost_road',
              'ghost_wall', 'false_alarm')
(STATIC, FACE, CORNER, WHEEL, WHEEL_HOUSE, UNDERBODY, ENGINE, SEAT, EXHAUST, MIRROR,
 MULTIBOUNCE, BODY, LIMB, GHOST_ROAD, GHOST_WALL, FALSE_ALARM) = range(len(KIND_NAMES))


def check_scatter_model(model: str | None) -> str:
    """The model name to use (default for None); ConfigError for an unknown one."""
    if model is None:
        return DEFAULT_SCATTER_MODEL
    if model not in SCATTER_MODELS:
        raise ConfigError(f'unknown scatter model {model!r}; known: {", ".join(SCATTER_MODELS)}')
    return model


@dataclass(frozen=True)
class ScatterTemplates:
    """Scattering regions of every road user, concatenated (CSR by object id).

    Regions of object i are ``start[i]:start[i + 1]``. ``presence`` is the chance that a
    region offers a candidate in a frame (the blend of ``mixed``, below 1 for flickering
    details); ``skin_weight`` is each object's weight of the skin model.
    """

    start: I64
    centre: F64
    half: F64
    rcs_dbsm: F64
    lobe: F64
    lobe_exp: F64
    floor: F64
    kind: NDArray[np.int8]
    wheel_radius: F64
    limb: F64
    extra_path: F64
    presence: F64
    skin_weight: F64


_GLINT = 0.55


class _Regions:
    """Collects regions of one object (small Python lists; built once per road user)."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []

    def add(self, kind: int, centre: tuple[float, float, float],
            half: tuple[float, float, float], rcs: float, lobe: tuple[float, float] = (0, 0),
            exp: float = 1.0, floor_db: float = -40.0, wheel: float = 0.0, limb: float = 0.0,
            extra: tuple[float, float] = (0.0, 0.0), presence: float = 1.0,
            copies: int = 1) -> None:
        norm = math.hypot(*lobe)
        lx, ly = (lobe[0] / norm, lobe[1] / norm) if norm > 0 else (0.0, 0.0)
        row = (*centre, *half, rcs, lx, ly, exp, 10.0 ** (floor_db / 10.0), kind, wheel, limb,
               *extra, presence)
        self.rows.extend([row] * copies)


def _skin(r: _Regions, length: float, width: float, height: float, overhang: float,
          rcs_face: float, rcs_corner: float, presence: float, face_copies: int = 2,
          face_exp: float = 1.0) -> None:
    """Faces of the box (one region per face and copy) and the four bumper corners.

    ``face_exp`` sharpens the faces' lobe: 1 for the diffuse faces of the skin model,
    higher for real panels, which reflect back mostly when seen square-on."""
    x0, x1, hw = -overhang, length - overhang, 0.5 * width
    z_lo, z_hi = 0.25, 0.9 * height
    zc, hz = 0.5 * (z_lo + z_hi), 0.5 * (z_hi - z_lo)
    xc, hx = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    side_copies = face_copies + 1 if length > 3.0 else face_copies
    r.add(FACE, (x1, 0.0, zc), (0.0, hw * 0.95, hz), rcs_face, (1, 0), face_exp, -25.0,
          presence=presence, copies=face_copies)
    r.add(FACE, (x0, 0.0, zc), (0.0, hw * 0.95, hz), rcs_face, (-1, 0), face_exp, -25.0,
          presence=presence, copies=face_copies)
    r.add(FACE, (xc, hw, zc), (hx * 0.95, 0.0, hz), rcs_face, (0, 1), face_exp, -25.0,
          presence=presence, copies=side_copies)
    r.add(FACE, (xc, -hw, zc), (hx * 0.95, 0.0, hz), rcs_face, (0, -1), face_exp, -25.0,
          presence=presence, copies=side_copies)
    for sx, x in ((1.0, x1), (-1.0, x0)):
        for sy in (1.0, -1.0):
            r.add(CORNER, (x - sx * 0.08, sy * (hw - 0.08), 0.5), (0.08, 0.08, 0.12),
                  rcs_corner, (sx, sy), 1.0, -20.0, presence=presence)


def _car_interior(r: _Regions, length: float, width: float, height: float, overhang: float,
                  wheelbase: float, presence: float) -> None:
    """Real-car scattering: wheels, wheel houses, underbody, engine, seats, exhaust,
    mirrors, bumper corners, weak skin and multi-bounce (relative strengths in dBsm)."""
    hw = 0.5 * width
    track = hw - 0.24
    tyre = 0.31
    front = length - overhang
    for x in (0.0, wheelbase):
        for sy in (1.0, -1.0):
            r.add(WHEEL, (x, sy * track, tyre), (0.0, 0.0, 0.0), 1.0, (0, sy), 0.7, -9.0,
                  wheel=tyre, presence=presence)
            r.add(WHEEL_HOUSE, (x, sy * (track - 0.05), 0.62), (0.28, 0.1, 0.08), 1.5,
                  (0, sy), 0.5, -7.0, presence=presence)
    for fx in (0.2, 0.5, 0.8):
        r.add(UNDERBODY, (fx * wheelbase, 0.0, 0.25), (0.18 * wheelbase, hw - 0.45, 0.05),
              0.0, presence=presence)
    engine_x = wheelbase + 0.25 * (front - wheelbase)
    r.add(ENGINE, (engine_x, 0.0, 0.6), (0.3, 0.38, 0.15), 4.0, (1, 0), 0.5, -5.0,
          presence=presence)
    for sy in (1.0, -1.0):
        r.add(SEAT, (0.62 * wheelbase, sy * 0.38, 0.75), (0.18, 0.14, 0.15), -3.0, (0, 0),
              presence=presence * 0.8)
    r.add(SEAT, (0.18 * wheelbase, 0.0, 0.75), (0.18, 0.45, 0.15), -3.0, presence=presence * 0.8)
    r.add(EXHAUST, (-overhang + 0.25, -0.55 * hw, 0.28), (0.05, 0.05, 0.04), -4.0, (-1, 0),
          1.0, -15.0, presence=presence)
    mirror_x = front - 0.4 * length
    for sy in (1.0, -1.0):
        r.add(MIRROR, (mirror_x, sy * (hw + 0.11), 1.02), (0.05, 0.05, 0.04), -4.0,
              (0.5, 0.85 * sy), 0.5, -9.0, presence=presence)
    # plastic bumpers hide the corners from the radar; door panels glint square-on
    _skin(r, length, width, height, overhang, -4.0, -10.0, presence, face_copies=1,
          face_exp=8.0)
    for x, y in ((wheelbase, track - 0.05), (0.0, track - 0.05), (0.5 * wheelbase, 0.0)):
        for sy in ((1.0, -1.0) if y else (1.0,)):
            r.add(MULTIBOUNCE, (x, sy * y, 0.35), (0.15, 0.1, 0.05), -3.0,
                  extra=(0.5, 2.5), presence=presence * 0.7)


def _truck_interior(r: _Regions, length: float, width: float, height: float,
                    overhang: float, wheelbase: float, presence: float) -> None:
    hw = 0.5 * width
    track = hw - 0.3
    tyre = 0.5
    axles = [wheelbase, 0.0] + ([-1.35] if length > 9.0 else []) + (
        [-2.7] if length > 13.0 else [])
    for x in axles:
        for sy in (1.0, -1.0):
            r.add(WHEEL, (x, sy * track, tyre), (0.0, 0.0, 0.0), 4.0, (0, sy), 0.7, -9.0,
                  wheel=tyre, presence=presence)
    n_under = max(3, int(length / 2.5))
    for fx in np.linspace(-overhang + 1.0, length - overhang - 1.5, n_under):
        r.add(UNDERBODY, (float(fx), 0.0, 0.55), (0.8, hw - 0.5, 0.1), 6.0, presence=presence)
    front = length - overhang
    r.add(ENGINE, (front - 1.0, 0.0, 0.9), (0.4, 0.5, 0.25), 9.0, (1, 0), 0.5, -5.0,
          presence=presence)
    _skin(r, length, width, height, overhang, 3.0, 8.0, presence, face_copies=1)
    for x in (wheelbase, 0.0):
        for sy in (1.0, -1.0):
            r.add(MULTIBOUNCE, (x, sy * (track - 0.1), 0.6), (0.3, 0.15, 0.1), 2.0,
                  extra=(0.8, 3.5), presence=presence * 0.7)


def _object_regions(cls: int, length: float, width: float, height: float, overhang: float,
                    wheelbase: float, skin_weight: float) -> _Regions:
    r = _Regions()
    if cls == PEDESTRIAN:
        r.add(BODY, (0.0, 0.0, 0.62 * height), (0.1, 0.15, 0.22 * height), -10.0, limb=0.15)
        r.add(LIMB, (0.0, 0.0, 0.3 * height), (0.15, 0.12, 0.2 * height), -13.0, limb=1.0,
              presence=0.8)
        return r
    if cls == CYCLIST:
        for x in (-0.52, 0.53):
            r.add(WHEEL, (x, 0.0, 0.35), (0.0, 0.0, 0.0), -8.0, (0, 1), 0.0, 0.0, wheel=0.35)
        r.add(BODY, (0.0, 0.0, 1.2), (0.15, 0.18, 0.3), -7.0, limb=0.1)
        r.add(LIMB, (0.1, 0.0, 0.65), (0.15, 0.1, 0.2), -11.0, limb=0.8, presence=0.8)
        return r
    # scattering centres glint in and out with small changes of aspect: each region
    # offers a candidate in about half the frames
    interior = (1.0 - skin_weight) * _GLINT
    skin_weight = skin_weight * _GLINT
    if cls == TRUCK:
        if skin_weight > 0:
            _skin(r, length, width, height, overhang, 6.0, 10.0, skin_weight, face_copies=3)
        if interior > 0:
            _truck_interior(r, length, width, height, overhang, wheelbase, interior)
        return r
    if skin_weight > 0:
        _skin(r, length, width, height, overhang, 0.0, 3.0, skin_weight)
    if interior > 0:
        _car_interior(r, length, width, height, overhang, wheelbase, interior)
    return r


def build_templates(users: RoadUsers, model: str, rng: np.random.Generator) -> ScatterTemplates:
    """Scattering regions of every road user under a scatter model.

    Parameters
    ----------
    users : RoadUsers
    model : {'skin', 'interior', 'mixed'}
    rng : numpy.random.Generator
        Draws each road user's blend under ``mixed`` (skin weight uniform in [0, 1]).
    """
    model = check_scatter_model(model)
    n = len(users)
    if model == 'skin':
        weights = np.ones(n)
    elif model == 'interior':
        weights = np.zeros(n)
    else:
        weights = rng.uniform(0.0, 1.0, n)
    rows: list[tuple[float, ...]] = []
    start = np.zeros(n + 1, np.int64)
    cache: dict[tuple[float, ...], list[tuple[float, ...]]] = {}
    for i in range(n):
        key = (int(users.object_class[i]), float(users.length[i]), float(users.width[i]),
               float(users.height[i]), float(users.rear_overhang[i]),
               float(users.wheelbase[i]), float(weights[i]))
        regions = cache.get(key)
        if regions is None:
            regions = _object_regions(*key).rows  # type: ignore[arg-type]
            cache[key] = regions
        rows.extend(regions)
        start[i + 1] = len(rows)
    a = np.asarray(rows, float).reshape(-1, 17)
    return ScatterTemplates(
        start=start, centre=a[:, 0:3].copy(), half=a[:, 3:6].copy(), rcs_dbsm=a[:, 6].copy(),
        lobe=a[:, 7:9].copy(), lobe_exp=a[:, 9].copy(), floor=a[:, 10].copy(),
        kind=a[:, 11].astype(np.int8), wheel_radius=a[:, 12].copy(), limb=a[:, 13].copy(),
        extra_path=a[:, 14:16].copy(), presence=a[:, 16].copy(), skin_weight=weights)


@dataclass(frozen=True)
class Candidates:
    """Candidate reflections of road users in a batch of frames (before detection).

    frame : (m,) index of the frame in the batch; obj : (m,) object id; kind : (m,);
    point_m : (m, 3) world position of the reflecting point; velocity_mps : (m, 3) its
    world velocity; gain : (m,) aspect gain (linear); rcs_dbsm : (m,);
    extra_path_m : (m,) multi-bounce extra path (0 for direct returns).
    """

    frame: I64
    obj: I64
    kind: NDArray[np.int8]
    point_m: F64
    velocity_mps: F64
    gain: F64
    rcs_dbsm: F64
    extra_path_m: F64


def sample_candidates(templates: ScatterTemplates, frame: I64, obj: I64, ref_xy: F64,
                      heading: F64, speed: F64, yaw_rate: F64, ground_z: F64,
                      radar_xy: F64, rng: np.random.Generator,
                      ground_slope: tuple[float, float] = (0.0, 0.0)) -> Candidates:
    """Draw this batch's candidate reflections of the given road-user states.

    Parameters
    ----------
    frame, obj : ndarray of shape (n,)
        Frame index and object id of each road-user state.
    ref_xy : ndarray of shape (n, 2)
        Reference point in the world [m]; ``heading`` (n,) [rad], ``speed`` (n,) along the
        heading [m/s], ``yaw_rate`` (n,) [rad/s], ``ground_z`` (n,) road altitude under the
        reference point [m].
    radar_xy : ndarray of shape (2,)
        Radar position, for the aspect lobes.
    rng : numpy.random.Generator
    ground_slope : (dz/dx, dz/dy)
        Road gradient, so every point sits at its own road height.
    """
    counts = templates.start[obj + 1] - templates.start[obj]
    total = int(counts.sum())
    row = np.repeat(np.arange(obj.size), counts)
    first = np.repeat(templates.start[obj], counts)
    within = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    reg = first + within
    keep = rng.random(total) < templates.presence[reg]
    row, reg = row[keep], reg[keep]
    m = row.size
    c, s = np.cos(heading[row]), np.sin(heading[row])
    local = templates.centre[reg] + templates.half[reg] * rng.uniform(-1.0, 1.0, (m, 3))
    v = speed[row]
    # rolling wheels: a point on the disc at angle phi, radius rho; relative velocity
    # omega x r with omega = v / R about the axle (0 at the contact patch, 2v on top)
    wheel_r = templates.wheel_radius[reg]
    is_wheel = wheel_r > 0
    rel_vx = np.zeros(m)
    rel_vz = np.zeros(m)
    if np.any(is_wheel):
        k = np.flatnonzero(is_wheel)
        phi = rng.uniform(0.0, 2.0 * math.pi, k.size)
        rho = wheel_r[k] * np.sqrt(rng.uniform(0.1, 1.0, k.size))
        local[k, 0] += rho * np.cos(phi)
        local[k, 2] += rho * np.sin(phi)
        omega = v[k] / wheel_r[k]
        rel_vx[k] = omega * rho * np.sin(phi)
        rel_vz[k] = -omega * rho * np.cos(phi)
    limb = templates.limb[reg]
    if np.any(limb > 0):
        k = np.flatnonzero(limb > 0)
        rel_vx[k] += v[k] * limb[k] * rng.uniform(-1.0, 1.0, k.size)
    dx = c * local[:, 0] - s * local[:, 1]
    dy = s * local[:, 0] + c * local[:, 1]
    px = ref_xy[row, 0] + dx
    py = ref_xy[row, 1] + dy
    pz = ground_z[row] + ground_slope[0] * dx + ground_slope[1] * dy + local[:, 2]
    w = yaw_rate[row]
    # rigid body: v_ref along the heading + omega x r, plus the wheel / limb motion
    vx = v * c - w * dy + c * rel_vx
    vy = v * s + w * dx + s * rel_vx
    # on a slope the body climbs as it moves: every point's height follows the road under
    # it, so it rises by the gradient along its own horizontal motion
    vz = rel_vz + ground_slope[0] * vx + ground_slope[1] * vy
    # aspect: bird's-eye direction from the point to the radar, in the vehicle frame
    tx, ty = radar_xy[0] - px, radar_xy[1] - py
    norm = np.maximum(np.hypot(tx, ty), 1e-6)
    ax = (c * tx + s * ty) / norm
    ay = (-s * tx + c * ty) / norm
    lobe = templates.lobe[reg]
    cos_lobe = np.maximum(lobe[:, 0] * ax + lobe[:, 1] * ay, 0.0)
    omni = (lobe[:, 0] == 0) & (lobe[:, 1] == 0)
    floor = templates.floor[reg]
    gain = np.where(omni, 1.0, floor + (1.0 - floor) * cos_lobe ** templates.lobe_exp[reg])
    extra = np.zeros(m)
    mb = np.flatnonzero(templates.extra_path[reg, 1] > 0)
    if mb.size:
        lo, hi = templates.extra_path[reg[mb], 0], templates.extra_path[reg[mb], 1]
        extra[mb] = rng.uniform(lo, hi)
    return Candidates(frame[row], obj[row], templates.kind[reg],
                      np.column_stack([px, py, pz]), np.column_stack([vx, vy, vz]), gain,
                      templates.rcs_dbsm[reg], extra)
