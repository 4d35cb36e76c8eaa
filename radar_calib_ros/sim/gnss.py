"""The calibration vehicle's GNSS/INS: NavSatFix and Odometry at 50 Hz.

An RTK receiver with an inertial unit: position noise ~2 cm horizontal (time-correlated,
as RTK errors are, plus a little white noise), ~3 cm vertical; heading noise ~0.1 deg;
occasional no-fix outages (status -1, the position drifting by metres meanwhile) during
which the INS keeps reporting orientation and twist while its position drifts. Positions
are the vehicle's reference point (rear axle, ``vehicle.ref_height`` above the road),
published as WGS 84 latitude / longitude / ellipsoidal altitude; Odometry carries UTM
coordinates, an ENU orientation against TRUE north (grid yaw + meridian convergence) with
the road's pitch and roll, and the body-frame twist.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.sim.scenario import VehicleSpec
from radar_calib_ros.sim.traffic import TrafficLog
from radar_calib_ros.sim.world import Ground

F64 = NDArray[np.float64]

#: GNSS/INS output rate [Hz].
RATE_HZ = 50.0


@dataclass(frozen=True)
class VehiclePoses:
    """True poses of the calibration vehicle's reference point at given times (local frame).

    position_m : (n, 3); yaw_rad : (n,) against the local grid; speed_mps, yaw_rate_rps :
    (n,); pitch_rad, roll_rad : (n,) from the road gradient (REP-103 signs).
    """

    time_s: F64
    position_m: F64
    yaw_rad: F64
    speed_mps: F64
    yaw_rate_rps: F64
    pitch_rad: F64
    roll_rad: F64


def vehicle_poses(log: TrafficLog, ground: Ground, vehicle: VehicleSpec,
                  times: F64) -> VehiclePoses:
    """The calibration vehicle's true poses at times within the recording."""
    s, v = log.vehicle_s_at(times)
    xy, yaw, speed, yaw_rate = log.poses(np.zeros(times.size, np.int64), s, v)
    z = ground.z(xy) + vehicle.ref_height
    sx, sy = ground.slope
    c, si = np.cos(yaw), np.sin(yaw)
    # uphill along the heading lifts the nose: negative pitch about y (REP-103)
    pitch = -np.arctan(sx * c + sy * si)
    roll = np.arctan(-sx * si + sy * c)
    return VehiclePoses(times, np.column_stack([xy, z]), yaw, speed, yaw_rate, pitch, roll)


@dataclass(frozen=True)
class GnssStreams:
    """What the GNSS/INS publishes (one row per 50 Hz epoch).

    status : (m,) NavSatStatus (2 RTK fix, -1 no fix); lat_deg, lon_deg, alt_m : (m,);
    odom_position_m : (m, 3) UTM; quaternion_xyzw : (m, 4) ENU vs true north;
    velocity_body_mps : (m, 3); yaw_rate_rps : (m,); outages_s : (k, 2) no-fix spans.
    """

    time_s: F64
    status: NDArray[np.int64]
    lat_deg: F64
    lon_deg: F64
    alt_m: F64
    odom_position_m: F64
    quaternion_xyzw: F64
    velocity_body_mps: F64
    yaw_rate_rps: F64
    outages_s: F64
    truth: VehiclePoses


def _ar1(n: int, sigma: float, tau_s: float, rng: np.random.Generator) -> F64:
    """Stationary first-order Gauss-Markov noise sampled at RATE_HZ."""
    a = math.exp(-1.0 / (RATE_HZ * tau_s))
    e = rng.normal(0.0, sigma, n)
    e[0] /= math.sqrt(1.0 - a * a)  # start in the stationary distribution
    return lfilter([math.sqrt(1.0 - a * a)], [1.0, -a], e)


def simulate_gnss(log: TrafficLog, frame: LocalFrame, ground: Ground, vehicle: VehicleSpec,
                  duration_s: float, rng: np.random.Generator) -> GnssStreams:
    """NavSatFix and Odometry contents at 50 Hz over ``[0, duration_s]``."""
    n = int(math.floor(duration_s * RATE_HZ)) + 1
    times = np.arange(n) / RATE_HZ
    truth = vehicle_poses(log, ground, vehicle, times)
    noise = np.column_stack([
        _ar1(n, 0.014, 12.0, rng) + rng.normal(0.0, 0.005, n),
        _ar1(n, 0.014, 12.0, rng) + rng.normal(0.0, 0.005, n),
        _ar1(n, 0.025, 20.0, rng) + rng.normal(0.0, 0.008, n)])
    measured = truth.position_m + noise
    # no-fix outages: the receiver keeps publishing, flagged, its solution wandering off
    status = np.full(n, 2, np.int64)
    outages = []
    for _ in range(int(rng.poisson(duration_s / 200.0))):
        t0 = float(rng.uniform(0.0, duration_s))
        t1 = t0 + float(rng.uniform(1.5, 6.0))
        sel = (times >= t0) & (times < t1)
        if not np.any(sel):
            continue
        outages.append((t0, min(t1, duration_s)))
        status[sel] = -1
        k = int(sel.sum())
        drift = np.cumsum(rng.normal(0.0, 0.15, (k, 3)), axis=0)
        measured[sel] += drift + rng.normal(0.0, 1.5, 3)
    lat, lon, alt = frame.local_to_geodetic(measured)
    # the INS dead-reckons through outages: a slowly growing position error only
    odom_local = truth.position_m + noise
    for t0, t1 in outages:
        sel = (times >= t0) & (times < t1)
        odom_local[sel, :2] += np.outer(times[sel] - t0, rng.normal(0.0, 0.05, 2))
    odom_utm = frame.local_to_utm(odom_local)
    heading_noise = _ar1(n, math.radians(0.08), 30.0, rng) + rng.normal(
        0.0, math.radians(0.03), n)
    lat_t, lon_t, _ = frame.local_to_geodetic(truth.position_m)
    yaw_true_north = truth.yaw_rad + frame.local_convergence_rad(lat_t, lon_t) + heading_noise
    quat = Rotation.from_euler('xyz', np.column_stack([
        truth.roll_rad + rng.normal(0.0, math.radians(0.05), n),
        truth.pitch_rad + rng.normal(0.0, math.radians(0.05), n),
        yaw_true_north])).as_quat()
    velocity_body = np.column_stack([truth.speed_mps + rng.normal(0.0, 0.02, n),
                                     rng.normal(0.0, 0.02, n), rng.normal(0.0, 0.02, n)])
    yaw_rate = truth.yaw_rate_rps + rng.normal(0.0, 0.003, n)
    return GnssStreams(times, status, lat, lon, alt, odom_utm, quat, velocity_body, yaw_rate,
                       np.asarray(outages, float).reshape(-1, 2), truth)
