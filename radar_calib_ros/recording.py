"""The Recording: a whole calibration drive as a few columnar arrays.

One code path for both ways in: the offline tool feeds a ``RecordingBuilder`` the decoded
messages of a bag, the node feeds it the decoded messages as they arrive; both then call
``build()``. Decoding (``io.messages``) happens before, so the builder only stores numpy
chunks and turns fixes into the local metric frame once, vectorised, at build time.

What ``build()`` asks of the samples lives beside this module: the vehicle's track from
its fixes and Odometry, with the checks of that stream, in ``vehicle_track``; what the
recorder's receive times say about the clocks in ``clocks``. This one keeps the storage
(appending, dropping, snapshots), the radar frames' assembly and the ``Recording`` itself.
"""
from __future__ import annotations

import logging
import math
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from radar_calib_ros.clocks import (
    common_restart, jump_counters, radar_clock_step, receipt_checks, receipts_from,
    rejoin_shift, small_step_rejoin)
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core._angles import interp_angle
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.types import (
    F64, I64, FixSample, OdomSample, PoseSamples, RadarFrame, RadarView, Targets, VehicleTrack)
from radar_calib_ros.vehicle_track import (
    RTK_DECLARED_SIGMA_M, build_vehicle_track, declared_fix_sigma, on_centre_line)

__all__ = ['NOMINAL_FIX_SIGMA_M', 'RTK_DECLARED_SIGMA_M', 'Recording', 'RecordingBuilder',
           'interpolate_poses']

_LOG = logging.getLogger(__name__)


# rough per-sample Python overhead (list slots, tuple/object headers, boxed floats) [bytes]
_FRAME_OVERHEAD_BYTES = 200
_FIX_OVERHEAD_BYTES = 120
_ODOM_OVERHEAD_BYTES = 400

#: 1-sigma (horizontal, vertical) [m] assumed for fixes that declare no covariance, by the
#: augmentation their NavSatStatus names: RTK fixed (GBAS, status 2) 1-2 cm horizontal and
#: about half again vertical; SBAS (status 1) about half a metre; standalone GNSS (status 0)
#: a few metres. Typical receiver specifications, on the side of caution.
NOMINAL_FIX_SIGMA_M: dict[str, tuple[float, float]] = {
    'rtk': (0.02, 0.03), 'sbas': (0.6, 1.2), 'standalone': (2.0, 4.0)}
#: Most targets :meth:`Recording.view_sample_m` returns.
_VIEW_SAMPLE = 200_000
#: Targets faster than this [m/s] are the road users that outline the lower edge of the
#: radar's view (:meth:`Recording.radar_view`), where there are at least this many.
_VIEW_MOVING_MPS = 0.5
_VIEW_MIN_MOVING = 1000


def _view_stride(targets: Targets) -> int:
    """Every how many targets :meth:`Recording.view_sample_m` takes one."""
    return max(1, len(targets) // _VIEW_SAMPLE)


@dataclass(frozen=True, slots=True)
class Recording:
    """A calibration drive: radar frames and targets, vehicle poses, and what was dropped.

    frame_stamps_ns : (f,) sorted radar header stamps (``sync.time_offset`` NOT applied);
    targets : all finite targets, ``targets.frame_index`` indexes ``frame_stamps_ns``;
    vehicle : poses in ``frame`` (the local metric frame);
    counters : received / dropped counts by reason (e.g. ``fixes_no_fix``);
    fix_sigma_m : median 1-sigma (horizontal, vertical) the vehicle's fixes declare in their
        ``position_covariance`` [m], None when none declares one (``pose_sigma_m`` then
        assumes one);
    radar_clock_rejoin_ns : (f,) what to add to each frame's stamp to undo a step of the
        radar's clock under a second that the recorder's clock saw (``_small_clock_step``;
        zero on the side nearer the poses' clock); the pipeline tries it (such a step is
        not told from a transport latency that settled higher by the receipts alone).
        None without one.
    sources : the bag topic each role was read from (``'radar'``, ``'navsat'``, ``'odom'``);
        empty where the messages came otherwise (the node).
    """

    frame_stamps_ns: I64
    targets: Targets
    vehicle: VehicleTrack
    frame: LocalFrame
    radar_frame_id: str = 'radar'
    counters: dict[str, int] = field(default_factory=dict)
    fix_sigma_m: tuple[float, float] | None = None
    radar_clock_rejoin_ns: I64 | None = None
    sources: dict[str, str] = field(default_factory=dict)

    def view_sample_m(self) -> F64:
        """Up to about ``_VIEW_SAMPLE`` of the targets' sensor-frame positions, evenly
        strided: enough for the percentiles that outline the radar's view, without copies
        of every target (an imaging radar's 48 million took a gigabyte a percentile)."""
        sample: F64 = self.targets.positions_m[::_view_stride(self.targets)]
        return sample

    def radar_view(self) -> RadarView:
        """The radar's view from the data (see :class:`RadarView`); an empty recording's
        is unbounded."""
        pts = self.view_sample_m()
        if pts.shape[0] == 0:
            half = math.pi / 2
            return RadarView(math.inf, math.inf, (-math.pi, math.pi), (-half, half))
        rng = np.linalg.norm(pts, axis=1)
        az = np.percentile(np.arctan2(pts[:, 1], pts[:, 0]), [1.0, 99.0])
        elevation = np.arcsin(np.clip(pts[:, 2] / np.maximum(rng, 1e-9), -1, 1))
        el = np.percentile(elevation, [1.0, 99.0])
        # The lower edge where the road users show it, where that is higher: a strong
        # static reflector (a kerb, a sign's foot, the road near a pole) is detected further
        # below the boresight than a car's weaker points, and a view outlined by such clutter
        # takes a car's lower half, cut off near the radar, for seen. Clutter reaching 5 deg
        # below a +-10 deg radar's view (800 targets a frame, an imaging radar's) put our
        # baseline's radar 21 cm low and pitched 0.45 deg; outlined so, 9 cm and 0.26 deg.
        # the same targets as the sample's positions
        speed = np.abs(self.targets.radial_velocity_mps[::_view_stride(self.targets)])
        moving = speed > _VIEW_MOVING_MPS        # NaN: not moving
        if int(moving.sum()) >= _VIEW_MIN_MOVING:
            el[0] = max(float(el[0]), float(np.percentile(elevation[moving], 1.0)))
        return RadarView(float(np.percentile(rng, 99.0)),
                         float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 99.0)),
                         (float(az[0]), float(az[1])), (float(el[0]), float(el[1])))

    @property
    def pose_sigma_m(self) -> tuple[float, float]:
        """1-sigma (horizontal, vertical) of the vehicle's positions [m]: the fixes' own
        (``_fix_pose_sigma_m``), and where their latitude and longitude lie on a lattice
        with no Odometry to carry the motion between its steps, the lattice's
        (``vehicle_track._lattice_m``) with it."""
        horizontal, vertical = self._fix_pose_sigma_m
        lattice_m = 0.001 * self.counters.get('fix_lattice_sigma_mm', 0)
        return math.hypot(horizontal, lattice_m), vertical

    @property
    def _fix_pose_sigma_m(self) -> tuple[float, float]:
        """1-sigma (horizontal, vertical) of the vehicle's positions [m]: what the fixes
        declare, else what their NavSatStatus is known for (``NOMINAL_FIX_SIGMA_M``), and at
        least that below RTK.

        A driver that leaves the covariance unknown still has an error, and it passes one
        to one into the radar's position: leaving it out made the reported uncertainty
        smaller than with the same fixes declaring RTK's 2 cm (an independent recording:
        rotation sigma 0.158 deg against 0.203). Odometry alone is taken as RTK/INS, the
        set-up the tool is for."""
        nominal = NOMINAL_FIX_SIGMA_M[self.fix_grade]
        if self.fix_grade == 'rtk':
            declared = nominal if self.fix_sigma_m is None else self.fix_sigma_m
            if self.counters.get('fix_jumps') and not (
                    self.counters.get('fixes_silent_float_dropped')
                    or self.counters.get('odometry_silent_float_dropped')):
                # silent RTK float kept (``_fix_steps``): the fixes err by about half a jump
                half = 0.005 * self.counters['fix_jump_median_cm']
                return (max(declared[0], half), max(declared[1], 1.5 * half))
            return declared
        if self.fix_sigma_m is None:
            return nominal
        # an SBAS or standalone receiver cannot be centimetres, whatever its covariance says
        # (a probe's SBAS fixes declared a stale 2 cm: 74 cm off at 24 cm across)
        return (max(self.fix_sigma_m[0], nominal[0]), max(self.fix_sigma_m[1], nominal[1]))

    @property
    def _kept_fixes(self) -> int:
        return (self.counters.get('fixes', 0) - self.counters.get('fixes_no_fix', 0)
                - self.counters.get('fixes_invalid', 0)
                - self.counters.get('fixes_degraded_dropped', 0)
                - self.counters.get('fixes_silent_float_dropped', 0))

    @property
    def fix_status_counts(self) -> tuple[int, int, int]:
        """Fixes the vehicle track rests on: (all, standalone, SBAS), those left out as
        invalid or degraded (``_degraded_fixes``) not counted."""
        c = self.counters
        return (self._kept_fixes,
                c.get('fixes_unaugmented', 0) - c.get('fixes_unaugmented_dropped', 0),
                c.get('fixes_sbas', 0) - c.get('fixes_sbas_dropped', 0))

    @property
    def fix_status_unreported(self) -> bool:
        """True when every kept fix says NavSatStatus 0 while they declare RTK's accuracy
        (median horizontal 1-sigma at most ``RTK_DECLARED_SIGMA_M``).

        Status 0 (STATUS_FIX, unaugmented) is also the field's default: drivers that do not
        map RTK into it (some report RTK fixed, DGPS and standalone all as 0) and simulators
        leave it there, while the covariance they fill from the receiver's accuracy is
        information. A drive that mixes statuses uses them, and there a status 0 means the
        RTK solution was lost, whatever a stale covariance says."""
        kept, standalone, _ = self.fix_status_counts
        return (kept > 0 and standalone == kept and self.fix_sigma_m is not None
                and self.fix_sigma_m[0] <= RTK_DECLARED_SIGMA_M)

    @property
    def fix_grade(self) -> str:
        """'standalone', 'sbas' or 'rtk': what most of the kept fixes' status says ('rtk'
        without fixes, or where ``fix_status_unreported``)."""
        kept, standalone, sbas = self.fix_status_counts
        if kept > 0 and standalone > 0.5 * kept:
            return 'rtk' if self.fix_status_unreported else 'standalone'
        if kept > 0 and sbas > 0.5 * kept:
            return 'sbas'
        return 'rtk'

    @property
    def target_stamps_ns(self) -> I64:
        """(n,) header stamp of each target's frame."""
        return self.frame_stamps_ns[self.targets.frame_index]

    def stamps_of(self, index: NDArray[Any]) -> I64:
        """Header stamp of the frame of each target that ``index`` (indices or a mask)
        selects, without the stamps of every target (``target_stamps_ns``)."""
        stamps: I64 = self.frame_stamps_ns[self.targets.frame_index[index]]
        return stamps

    @property
    def has_elevation(self) -> bool:
        """False for a 2-D radar: (almost) every target at z = 0 in the sensor frame."""
        z = self.view_sample_m()[:, 2]
        return bool(z.size == 0 or np.mean(np.abs(z) < 1e-6) < 0.99)

    @property
    def duration_s(self) -> float:
        """Span of the radar frames [s]."""
        if self.frame_stamps_ns.size < 2:
            return 0.0
        return float(self.frame_stamps_ns[-1] - self.frame_stamps_ns[0]) * 1e-9


#: Elevations spread by less than this [deg] (99 % of the targets) are one elevation: no
#: radar measures angles that well, and a driver that writes a fixed elevation (the
#: mounting's nominal tilt, or a constant for 'none') reports none.
_CONSTANT_ELEVATION_SPREAD_DEG = 0.01


def _constant_elevation_deg(positions: F64) -> float | None:
    """The elevation [deg] every target lies at, where (almost) all lie at one other than
    0, else None (0 is a 2-D radar's own way to say it: ``Recording.has_elevation``).

    Why: a forty-ninth probe's radar that wrote -4 deg for every target put roll and pitch
    1.0-2.4 deg off at a reported 0.3-0.5 deg: its targets lay on a cone, taken for
    measured heights.
    """
    with np.errstate(over='ignore', invalid='ignore'):   # a corrupt cloud's huge values
        rng = np.linalg.norm(positions, axis=1)
    ok = np.isfinite(rng) & (rng > 0.1)
    if int(ok.sum()) < 100:
        return None
    elevation = np.degrees(np.arcsin(np.clip(positions[ok, 2] / rng[ok], -1.0, 1.0)))
    low, median, high = np.percentile(elevation, [0.5, 50.0, 99.5])
    if high - low >= _CONSTANT_ELEVATION_SPREAD_DEG or abs(median) < 1e-6:
        return None
    return float(median)


def _in_sensor_plane(positions: F64) -> F64:
    """Targets moved into the sensor's x-y plane at their range and azimuth (a 2-D radar's
    targets: ``Recording.has_elevation``)."""
    rng = np.linalg.norm(positions, axis=1)
    azimuth = np.arctan2(positions[:, 1], positions[:, 0])
    return np.column_stack([rng * np.cos(azimuth), rng * np.sin(azimuth), np.zeros_like(rng)])


def _narrowed(values: F64) -> NDArray[np.floating[Any]]:
    """``values`` as float32 where every one of them is a float32, else unchanged."""
    with np.errstate(over='ignore'):  # beyond float32's range: inf, unequal, kept wide
        narrow = values.astype(np.float32)
    return narrow if np.array_equal(narrow, values, equal_nan=True) else values


#: A NavSatFix header frame_id that names a GNSS antenna ('gnss', 'gps_link', 'antenna',
#: 'navsat_link'): the fixes are then most likely the antenna's position, whose height
#: above the road ``vehicle.ref_height`` must give (``pipeline._antenna_height_note``).
_ANTENNA_FRAME = re.compile(r'gnss|gps|antenna|navsat', re.IGNORECASE)


class RecordingBuilder:
    """Collects decoded samples (in any order) and builds a :class:`Recording`.

    Parameters
    ----------
    config : CalibConfig
        Uses ``world.epsg``, ``vehicle.odom_is_utm``, ``vehicle.min_heading_speed`` and
        ``radar.velocity_sign``.
    """

    def __init__(self, config: CalibConfig) -> None:
        self._config = config
        self._frame_stamps: list[int] = []
        self._frame_positions: list[F64] = []
        self._frame_velocities: list[F64] = []
        # (stamp, lat, lon, alt, status, sigma horizontal, sigma vertical)
        self._fixes: list[tuple[int, float, float, float, int, float, float]] = []
        # Odometry as flat tuples of numbers, not OdomSample objects: such tuples are not
        # tracked by Python's cyclic garbage collector, so a long buffer (90,000 samples in
        # 30 minutes) does not make every full collection in the node pause longer.
        self._odoms: list[tuple[float, ...]] = []
        self.counters: Counter[str] = Counter()
        # received - header stamp [ns] of each radar message and each pose message, in the
        # order received (a recorder's clock is one clock for both; see receipt_checks)
        self._radar_lag: list[int] = []
        self._radar_received: list[int] = []
        self._pose_lag: list[int] = []
        self._pose_received: list[int] = []
        self._pose_is_fix: list[bool] = []
        # kept current on every append so that the node can check its memory bound per message
        self._nbytes = 0

    # appending ---------------------------------------------------------------------------
    def add_radar_frame(self, frame: RadarFrame) -> None:
        """Append one decoded radar frame (an empty frame still counts as a cycle)."""
        n = frame.positions_m.shape[0]
        if frame.positions_m.shape != (n, 3) or frame.radial_velocity_mps.shape != (n,):
            raise ValueError('radar frame arrays must have shapes (n, 3) and (n,)')
        # Buffered as float32 where that loses nothing (float32 fields, as most PointCloud2
        # carry) and widened once in ``build``: an imaging radar's 6,500 targets a frame at
        # 15 Hz for eight minutes (an eighteenth probe) held 1.5 GB of float64 copies of
        # float32 values beside the recording.
        positions = _narrowed(np.asarray(frame.positions_m, np.float64))
        velocities = _narrowed(np.asarray(frame.radial_velocity_mps, np.float64))
        # No radar detects at its own antenna: targets at exactly (0, 0, 0) are the unused
        # slots of a fixed-size target list, zero-filled (an independent probe's: 81 % of
        # the 'moving' targets, named as rain)
        at_origin = ~np.any(positions != 0.0, axis=1)
        if at_origin.any():
            self.counters['targets_at_origin'] += int(at_origin.sum())
            positions, velocities = positions[~at_origin], velocities[~at_origin]
        cap = self._config.radar.max_targets_per_frame
        if 0 < cap < positions.shape[0]:
            # ``radar.max_targets_per_frame``: evenly over the frame's own list (drivers list
            # targets by range, azimuth or beam), so each kept one stands for its neighbours
            # there and a car keeps its share of them; the same targets every time.
            kept = np.arange(cap) * positions.shape[0] // cap
            self.counters['targets_thinned'] += positions.shape[0] - cap
            positions, velocities = positions[kept], velocities[kept]
        self._frame_stamps.append(int(frame.stamp_ns))
        self._frame_positions.append(positions)
        self._frame_velocities.append(velocities)
        self._nbytes += positions.nbytes + velocities.nbytes + _FRAME_OVERHEAD_BYTES
        self.counters['radar_frames'] += 1
        self.counters['targets'] += n
        if frame.dropped_nonfinite:
            self.counters['targets_nonfinite'] += frame.dropped_nonfinite
        if frame.velocity_components:
            self.counters['radar_frames_velocity_components'] += 1

    def note_receipt(self, role: str, stamp_ns: int, received_ns: int) -> None:
        """Record when a message of ``role`` ('radar', 'navsat' or 'odom') with this header
        stamp was received (a bag's record time): the two clocks' offset and jumps are
        judged on it at ``build``."""
        if role == 'radar':
            self._radar_lag.append(int(received_ns) - int(stamp_ns))
            self._radar_received.append(int(received_ns))
        else:
            self._pose_lag.append(int(received_ns) - int(stamp_ns))
            self._pose_received.append(int(received_ns))
            self._pose_is_fix.append(role == 'navsat')

    def add_fix(self, fix: FixSample) -> bool:
        """Append one NavSatFix; returns False (and counts why) when it is dropped."""
        self.counters['fixes'] += 1
        if fix.status < 0:
            self.counters['fixes_no_fix'] += 1
            return False
        if not all(math.isfinite(v) for v in (fix.lat_deg, fix.lon_deg, fix.alt_m)) or not (
                -90.0 <= fix.lat_deg <= 90.0 and -180.0 <= fix.lon_deg <= 180.0):
            self.counters['fixes_invalid'] += 1
            if not math.isfinite(fix.alt_m) and math.isfinite(fix.lat_deg + fix.lon_deg):
                self.counters['fixes_altitude_nan'] += 1
            return False
        if fix.lat_deg == 0.0 and fix.lon_deg == 0.0:
            # 'null island': a receiver without a solution yet writes zeros, often with
            # status 0 rather than -1; kept, it chose the UTM zone and skewed the headings
            # (a ninth probe's first two seconds)
            self.counters['fixes_invalid'] += 1
            self.counters['fixes_null_island'] += 1
            return False
        if fix.frame_id and 'fix_frame_checked' not in self.counters:
            self.counters['fix_frame_checked'] = 1
            if _ANTENNA_FRAME.search(fix.frame_id):
                self.counters['fix_frame_antenna'] = 1
        if fix.status == 0:  # STATUS_FIX: no RTK, SBAS or GBAS augmentation
            self.counters['fixes_unaugmented'] += 1
        elif fix.status == 1:  # STATUS_SBAS_FIX
            self.counters['fixes_sbas'] += 1
        self._fixes.append((int(fix.stamp_ns), fix.lat_deg, fix.lon_deg, fix.alt_m,
                            int(fix.status), *map(float, fix.position_sigma_m)))
        self._nbytes += _FIX_OVERHEAD_BYTES
        return True

    def add_odometry(self, odom: OdomSample) -> bool:
        """Append one Odometry sample; returns False (and counts why) when it is dropped."""
        self.counters['odometry'] += 1
        values = (*odom.quaternion_xyzw, *odom.velocity_body_mps, odom.yaw_rate_rps)
        q_norm = math.sqrt(sum(v * v for v in odom.quaternion_xyzw))
        if not all(math.isfinite(v) for v in values) or not 0.5 < q_norm < 1.5:
            self.counters['odometry_invalid'] += 1
            return False
        self._odoms.append((int(odom.stamp_ns), *map(float, odom.position_m), *map(
            float, odom.quaternion_xyzw), *map(float, odom.velocity_body_mps),
            float(odom.yaw_rate_rps)))
        self._nbytes += _ODOM_OVERHEAD_BYTES
        return True

    def drop_before(self, stamp_ns: int, role: str | None = None) -> int:
        """Drop every sample stamped before ``stamp_ns`` (of one ``role``, 'radar', 'navsat'
        or 'odom', where given: each stream's stamps may run on a clock of its own); returns
        how many were dropped."""
        dropped = 0
        if role in (None, 'radar'):
            keep_f = [i for i, s in enumerate(self._frame_stamps) if s >= stamp_ns]
            dropped += len(self._frame_stamps) - len(keep_f)
            if len(keep_f) < len(self._frame_stamps):
                self._frame_stamps = [self._frame_stamps[i] for i in keep_f]
                self._frame_positions = [self._frame_positions[i] for i in keep_f]
                self._frame_velocities = [self._frame_velocities[i] for i in keep_f]
            # receipts go with their samples (received - lag is the header stamp)
            keep = receipts_from(stamp_ns, self._radar_lag, self._radar_received)
            self._radar_lag = [self._radar_lag[i] for i in keep]
            self._radar_received = [self._radar_received[i] for i in keep]
        if role in (None, 'navsat'):
            n_fix = len(self._fixes)
            self._fixes = [f for f in self._fixes if f[0] >= stamp_ns]
            dropped += n_fix - len(self._fixes)
        if role in (None, 'odom'):
            n_odom = len(self._odoms)
            self._odoms = [o for o in self._odoms if o[0] >= stamp_ns]
            dropped += n_odom - len(self._odoms)
        if role != 'radar':
            keep = [i for i, (lag, rec, is_fix) in enumerate(zip(
                self._pose_lag, self._pose_received, self._pose_is_fix))
                if rec - lag >= stamp_ns or (role is not None and is_fix != (role == 'navsat'))]
            self._pose_lag = [self._pose_lag[i] for i in keep]
            self._pose_received = [self._pose_received[i] for i in keep]
            self._pose_is_fix = [self._pose_is_fix[i] for i in keep]
        self._nbytes = self._count_nbytes()
        return dropped

    def clear(self) -> None:
        """Forget every sample and counter."""
        self.__init__(self._config)  # type: ignore[misc]

    @property
    def n_frames(self) -> int:
        return len(self._frame_stamps)

    @property
    def n_poses(self) -> int:
        return len(self._fixes) + len(self._odoms)

    def stamp_range_ns(self) -> tuple[int, int] | None:
        """Earliest and latest stamp of any buffered sample."""
        ranges = self.stamp_ranges_ns().values()
        return (min(lo for lo, _ in ranges), max(hi for _, hi in ranges)) if ranges else None

    def stamp_ranges_ns(self) -> dict[str, tuple[int, int]]:
        """Earliest and latest stamp of each role ('radar', 'navsat', 'odom') that holds
        samples."""
        stamps = {'radar': self._frame_stamps, 'navsat': [int(f[0]) for f in self._fixes],
                  'odom': [int(o[0]) for o in self._odoms]}
        return {role: (min(s), max(s)) for role, s in stamps.items() if s}

    def nbytes(self) -> int:
        """Approximate memory held by the buffered samples [bytes] (O(1): kept current)."""
        return self._nbytes

    def _count_nbytes(self) -> int:
        arrays = sum(p.nbytes + v.nbytes for p, v in zip(self._frame_positions,
                                                         self._frame_velocities))
        return (arrays + _FRAME_OVERHEAD_BYTES * len(self._frame_stamps)
                + _FIX_OVERHEAD_BYTES * len(self._fixes)
                + _ODOM_OVERHEAD_BYTES * len(self._odoms))

    def sample_counts(self) -> tuple[int, int, int]:
        """Buffered (radar frames, fixes, odometry samples)."""
        return len(self._frame_stamps), len(self._fixes), len(self._odoms)

    def target_count(self) -> int:
        """Buffered radar targets (those of the frames still held)."""
        return sum(v.shape[0] for v in self._frame_velocities)

    def snapshot(self, config: CalibConfig | None = None) -> RecordingBuilder:
        """A copy that later appends and drops do not change, made in O(samples) list copies.

        The per-frame arrays are shared, not copied: nothing here ever writes into them. The
        node takes a snapshot under its buffer lock and builds and calibrates it outside, so
        subscriptions keep appending meanwhile. ``config`` replaces the one the copy builds
        with (the node's parameters may have changed since the samples arrived).
        """
        copy = RecordingBuilder(config if config is not None else self._config)
        copy._frame_stamps = list(self._frame_stamps)
        copy._frame_positions = list(self._frame_positions)
        copy._frame_velocities = list(self._frame_velocities)
        copy._fixes = list(self._fixes)
        copy._odoms = list(self._odoms)
        copy._radar_lag, copy._pose_lag = list(self._radar_lag), list(self._pose_lag)
        copy._radar_received = list(self._radar_received)
        copy._pose_received = list(self._pose_received)
        copy._pose_is_fix = list(self._pose_is_fix)
        copy.counters = Counter(self.counters)
        copy._nbytes = self._nbytes
        return copy

    def receipt_times(self) -> tuple[dict[int, int], dict[int, int]]:
        """When the buffered radar and pose messages were received, by header stamp:
        ({radar stamp: received}, {pose stamp: received}) [ns], the first receipt of a stamp
        (a scan published in pieces shares one). A saved bag takes them as record times, so
        that the recorder's-clock checks of ``build`` see there what they saw here."""
        def first(lags: list[int], received: list[int]) -> dict[int, int]:
            # reversed, so that the first receipt of a stamp is the one left in the dict
            return {rec - lag: rec for lag, rec in zip(lags[::-1], received[::-1])}
        return (first(self._radar_lag, self._radar_received),
                first(self._pose_lag, self._pose_received))

    def samples(self) -> Iterator[RadarFrame | FixSample | OdomSample]:
        """Every buffered sample, in stamp order (radar velocities as received, before
        ``radar.velocity_sign``; fixes with their status and covariance sigmas)."""
        items: list[tuple[int, int, int]] = []
        items.extend((s, 0, i) for i, s in enumerate(self._frame_stamps))
        items.extend((f[0], 1, i) for i, f in enumerate(self._fixes))
        items.extend((int(o[0]), 2, i) for i, o in enumerate(self._odoms))
        items.sort()
        for stamp, kind, i in items:
            if kind == 0:
                yield RadarFrame(stamp, self._frame_positions[i], self._frame_velocities[i])
            elif kind == 1:
                _, lat, lon, alt, status, sigma_h, sigma_v = self._fixes[i]
                yield FixSample(stamp, lat, lon, alt, status, (sigma_h, sigma_v))
            else:
                yield _odom_sample(self._odoms[i])

    # building ----------------------------------------------------------------------------
    def build(self) -> Recording:
        """The Recording of everything appended so far.

        Raises
        ------
        InsufficientDataError
            No radar frame, or no usable vehicle pose.
        ConfigError
            ``vehicle.odom_is_utm`` without ``world.epsg``.
        """
        if not self._frame_stamps:
            unset = self.counters.get('radar_stamps_unset', 0)
            raise InsufficientDataError('read', 'no radar frame in the recording' + (
                f': all {unset} radar messages carry header stamp 0 (a driver that does not '
                'stamp its scans); the calibration times every message by its header stamp, '
                'never by when it was received, so have the driver stamp each scan with its '
                'measurement time' if unset else ''))
        joined = self._joined_restarts()
        if joined is not None:
            return joined.build()
        rejoined = self._rejoined_radar_clock()
        if rejoined is not None:
            return rejoined.build()
        order = self._without_copies(
            np.argsort(np.asarray(self._frame_stamps, np.int64), kind='stable'))
        frame_stamps = np.asarray(self._frame_stamps, np.int64)[order]
        retimed = self._whole_scans_apart(order, frame_stamps)
        if retimed is not None:
            resort = np.argsort(retimed, kind='stable')
            order, frame_stamps = order[resort], retimed[resort]
        counts = np.array([self._frame_positions[i].shape[0] for i in order], np.int64)
        if counts.sum():
            positions = np.concatenate([self._frame_positions[i] for i in order],
                                       dtype=np.float64)
            velocities = np.concatenate([self._frame_velocities[i] for i in order],
                                        dtype=np.float64)
        else:
            positions, velocities = np.zeros((0, 3)), np.zeros(0)
        velocities *= self._config.radar.velocity_sign
        elevation_deg = _constant_elevation_deg(positions)
        if elevation_deg is not None:
            positions = _in_sensor_plane(positions)
            self.counters['radar_elevation_constant_mdeg'] = int(round(1000 * elevation_deg))
            _LOG.warning('every radar target lies at one elevation (%.2f deg): the radar '
                         'measures none, and its targets are taken as a 2-D radar\'s',
                         elevation_deg)
        # Some drivers publish one scan as several messages (sectors, or chunks of a long
        # target list) under one header stamp. They are one frame: taken apart, each
        # shows a part of the vehicle and the vehicle seems missed in most frames (an
        # independent recording with 5 parts per scan was refused for it).
        frame_stamps, message_frame = np.unique(frame_stamps, return_inverse=True)
        frame_index = np.repeat(message_frame.ravel().astype(np.int64), counts)
        targets = Targets(positions, velocities, frame_index)
        frame, vehicle = self._build_vehicle()
        counters = dict(self.counters)
        # The radar is paired with the poses' positions, which come from the fixes where
        # there are any: their receipts are the ones to judge the radar's stamps by (an
        # Odometry on a clock of its own, a node without use_sim_time, had the tool advise
        # a sync.time_offset of 1.76e9 s for a radar on the fixes' clock).
        pose_lag, pose_received = self._judging_pose_receipts()
        counters.update(receipt_checks(np.asarray(self._radar_lag, np.int64),
                                       np.asarray(self._radar_received, np.int64),
                                       pose_lag, pose_received))
        rejoin_ns = None
        if ('radar_stamp_jump_ms' in counters and len(self._radar_lag) == len(self._frame_stamps)):
            rejoin_ns = small_step_rejoin(np.asarray(self._radar_lag, np.int64),
                                          np.asarray(self._radar_received, np.int64),
                                          pose_lag, pose_received, order,
                                          message_frame.ravel(), frame_stamps.size)
        merged = int(order.size - frame_stamps.size)
        if merged:
            counters['radar_messages_merged'] = merged
            _LOG.warning('%d radar messages share their header stamp with another: each '
                         'stamp is taken as one scan (%d scans)', merged, frame_stamps.size)
        return Recording(frame_stamps, targets, vehicle, frame,
                         radar_frame_id=self._config.radar.frame_id, counters=counters,
                         fix_sigma_m=self._fix_sigma(), radar_clock_rejoin_ns=rejoin_ns)

    def _judging_pose_receipts(self) -> tuple[I64, I64]:
        """(lag, received) of the pose messages the radar's stamps are judged by: the fixes'
        where there are any (the poses' positions come from them), else the Odometry's; the
        Odometry's too where the fixes' stamps were found seconds off its own and moved onto
        its clock (``fix_stream_offset_ds``): the poses then run on that clock."""
        pose_lag = np.asarray(self._pose_lag, np.int64)
        pose_received = np.asarray(self._pose_received, np.int64)
        from_fixes = np.asarray(self._pose_is_fix, bool)
        if from_fixes.any() and from_fixes.size == pose_lag.size:
            judged = ~from_fixes if (self.counters.get('fix_stream_offset_ds')
                                     and not from_fixes.all()) else from_fixes
            pose_lag, pose_received = pose_lag[judged], pose_received[judged]
        return pose_lag, pose_received

    def _rejoined_radar_clock(self) -> RecordingBuilder | None:
        """A copy with the radar's header stamps on one side of a lasting step of its clock
        (``_RECEIPT_OFFSET_S`` or more, the radar's alone) moved by the step, else None.

        Why: a radar that reboots or loses its time sync mid-recording stamps the frames
        after it seconds off the ones before (an independent probe: +3 s at 560 s of 25
        minutes). Left so, the passes on one side were paired with poses 3 s off: 10 of 16
        drives went unused, blamed on traffic, and with a small constant offset on top the
        passes after the step, 36 m off, were taken for a second vehicle keeping pace (a
        'convoy', exit 1). The recorder's clock, one for every stream, shows the step to a
        few milliseconds (the receipt lag's medians on either side); the side whose stamps
        lie farther from the poses' is moved onto the other's clock, so one clock offset,
        which the fit still finds, holds throughout. A step of the recorder's own clock
        moves the poses' receipt lag alike and is left alone, and so are steps under a
        second: a transport latency that settles higher cannot be told from them, and
        there the fit's clock offset and drift absorb what is left.
        """
        if len(self._radar_lag) != len(self._frame_stamps) or len(self._frame_stamps) < 2:
            return None
        radar_lag = np.asarray(self._radar_lag, np.int64)
        radar_received = np.asarray(self._radar_received, np.int64)
        pose_lag, pose_received = self._judging_pose_receipts()
        step = radar_clock_step(radar_lag, radar_received, pose_lag, pose_received)
        if step is None:
            return None
        later, before_ns, after_ns = step
        move_later, shift = rejoin_shift(before_ns, after_ns, pose_lag)
        moved = later if move_later else ~later
        copy = self.snapshot()
        copy._frame_stamps = list(np.asarray(self._frame_stamps, np.int64) + shift * moved)
        copy._radar_lag = list(radar_lag - shift * moved)
        copy.counters.update(jump_counters(later, before_ns, after_ns, radar_received))
        copy.counters['radar_stamps_rejoined'] = int(moved.sum())
        copy.counters['radar_stamps_rejoined_later'] = int(move_later)
        _LOG.warning('the radar\'s header stamps jump by %+.1f s against the recorder\'s clock: '
                     'the %d frames %s it were moved onto the clock %s it',
                     -(after_ns - before_ns) * 1e-9, int(moved.sum()),
                     'after' if move_later else 'before', 'before' if move_later else 'after')
        return copy

    def _joined_restarts(self) -> RecordingBuilder | None:
        """A copy with the stamps after a restart of every stream's clock moved after the
        stamps before it (``_RESTART_GAP_S`` apart), else None when there is none.

        Why: a simulator reset mid-recording (Gazebo's world reset, CARLA restarted) sets
        every header stamp back to its start: sorted by stamp, the second drive lies over
        the first and each radar frame is paired with the pose of the other drive (an
        independent probe: 'no consistent track'). Told from the recorder's clock (every
        stream's stamps fall back by the same step at the same moment, unlike a radar clock
        that steps alone), the later part is shifted by one amount for every stream, so
        that within each part the streams keep their stamped relation exactly; the gap
        between the parts exceeds any ``sync.max_pose_gap``, so nothing is paired across.
        The receipts move by the gap too, so the receipt checks see the clocks as before.
        """
        radar_received = np.asarray(self._radar_received, np.int64)
        radar_lag = np.asarray(self._radar_lag, np.int64)
        is_fix = np.asarray(self._pose_is_fix, bool)
        pose_received = np.asarray(self._pose_received, np.int64)
        pose_lag = np.asarray(self._pose_lag, np.int64)
        if (radar_received.size != len(self._frame_stamps)
                or int(is_fix.sum()) != len(self._fixes)
                or int((~is_fix).sum()) != len(self._odoms)):
            return None  # samples appended without their receipts (a test's, a tool's)
        streams = [(radar_received, radar_lag), (pose_received[is_fix], pose_lag[is_fix]),
                   (pose_received[~is_fix], pose_lag[~is_fix])]
        restart = common_restart(streams)
        if restart is None:
            return None
        shift, gap, later = restart.shift_ns, restart.gap_ns, restart.later
        back_ns, at_ns = restart.back_ns, restart.at_ns
        copy = self.snapshot()
        copy._frame_stamps = [stamp + shift if moved else stamp
                              for stamp, moved in zip(self._frame_stamps, later[0])]
        copy._fixes = [(f[0] + shift, *f[1:]) if moved else f
                       for f, moved in zip(self._fixes, later[1])]
        copy._odoms = [(o[0] + shift, *o[1:]) if moved else o
                       for o, moved in zip(self._odoms, later[2])]
        copy._radar_received = list(radar_received + gap * later[0])
        copy._radar_lag = list(radar_lag + (gap - shift) * later[0])
        pose_later = np.zeros(is_fix.size, bool)
        pose_later[is_fix], pose_later[~is_fix] = later[1], later[2]
        copy._pose_received = list(pose_received + gap * pose_later)
        copy._pose_lag = list(pose_lag + (gap - shift) * pose_later)
        copy.counters['stamps_restarted'] += 1
        copy.counters.setdefault('stamps_restart_back_ms', int(round(np.median(back_ns) / 1e6)))
        copy.counters.setdefault('stamps_restart_at_s', int(round(
            (min(at_ns) - int(min(streams[0][0].min(), pose_received.min()))) * 1e-9)))
        _LOG.warning('every stream\'s header stamps fall back by %.1f s at once (a simulator '
                     'restarted?): the part after is taken after the part before',
                     np.median(back_ns) * 1e-9)
        return copy

    def _without_copies(self, order: I64) -> I64:
        """``order`` without the radar messages that repeat an earlier one exactly (same
        stamp, same targets), counted as ``radar_messages_duplicate``.

        Why: a topic recorded twice (two recorders, a bridge and the driver) doubles every
        scan; merged as the pieces of one scan, each target would count twice, and the note
        blamed a driver that publishes scans in pieces (an independent probe)."""
        stamps = np.asarray(self._frame_stamps, np.int64)[order]
        same = np.flatnonzero(stamps[1:] == stamps[:-1]) + 1
        if same.size == 0:
            return order
        drop = np.zeros(order.size, bool)
        for k in same:
            j = k - 1
            while j >= 0 and stamps[j] == stamps[k]:
                a, b = int(order[k]), int(order[j])
                if (not drop[j] and np.array_equal(self._frame_positions[a],
                                                   self._frame_positions[b])
                        and np.array_equal(self._frame_velocities[a],
                                           self._frame_velocities[b])):
                    drop[k] = True
                    break
                j -= 1
        if drop.any():
            self.counters['radar_messages_duplicate'] = int(drop.sum())
        return order[~drop]

    def _whole_scans_apart(self, order: I64, stamps: I64) -> I64 | None:
        """Header stamps (in ``order``) with the messages that share a stamp but each hold
        a whole scan moved apart in time, or None where the messages sharing stamps are the
        pieces of one scan (or none share one).

        Why: a driver that publishes its scans in batches may stamp every scan of a batch
        with the time it publishes (a twelfth probe: four 15 Hz scans under one stamp; as
        the pieces of one scan, the car in them smeared over 0.8 m: 23 cm off at 2.3 sigma,
        or no calibration), and one that re-uses a stale stamp gives two scans one stamp (an
        eleventh probe). Pieces (sectors, or chunks of a long list) are taken at one moment,
        whole scans one after another: the moving targets of the later lie further along
        their radial velocities (``_scans_apart_in_time``). Whole scans are then timed by
        their receipt where that tells them apart, else spread back from the stamp at the
        radar's scan interval (a batch is stamped when published, after its scans); a
        constant remainder is the clock offset the calibration estimates.
        """
        first = np.flatnonzero(np.diff(stamps) != 0) + 1
        starts = np.concatenate([[0], first])
        sizes = np.diff(np.concatenate([starts, [stamps.size]]))
        shared = starts[sizes > 1]
        if shared.size == 0:
            return None
        # the radar's scan interval: between distinct stamps, over the scans under one (a
        # median: a radar that fell silent for a while must not stretch it)
        interval = int(np.median(np.diff(stamps[starts])) // np.median(sizes)) if (
            starts.size > 1) else 0
        if interval <= 0:
            return None
        if not self._scans_apart_in_time(order, shared, sizes[sizes > 1], interval):
            return None
        n_shared = int(sizes[sizes > 1].sum())
        received = (np.asarray(self._radar_received, np.int64)
                    if len(self._radar_received) == len(self._frame_stamps) else None)
        out = stamps.copy()
        by_receipt = 0
        for start, size in zip(shared, sizes[sizes > 1]):
            rows = np.arange(start, start + size)
            if received is not None:
                apart = received[order[rows]] - received[order[rows[0]]]
                if np.all(np.diff(apart) >= interval // 2):
                    out[rows] = stamps[rows] + apart
                    by_receipt += int(size)
                    continue
            out[rows] = stamps[rows] - (size - 1 - np.arange(size)) * interval
        self.counters['radar_scans_shared_stamp'] = n_shared
        self.counters['radar_scans_shared_stamp_by_receipt'] = by_receipt
        self.counters['radar_scan_interval_ms'] = int(round(interval / 1e6))
        _LOG.warning('%d radar messages share their header stamp with another but each holds '
                     'a whole scan: moved apart in time', n_shared)
        return out

    def _scans_apart_in_time(self, order: I64, shared: I64, sizes: I64,
                             interval_ns: int) -> bool:
        """True when consecutive messages under one stamp were measured apart in time: a
        moving target's nearest twin in the message before (same radial velocity) lies
        nearer or further by its radial velocity times a scan interval (the median over up
        to ``_SHARED_GROUPS_CHECKED`` stamps at least ``_SHIFT_SHARE`` of the radar's scan
        interval ``interval_ns``); pieces of one scan, taken at one time, show no such
        shift (their targets differ, or are other points of the same objects at the same
        moment)."""
        sign = self._config.radar.velocity_sign
        pick = np.linspace(0, shared.size - 1, min(shared.size, _SHARED_GROUPS_CHECKED))
        shifts: list[F64] = []
        for g in np.unique(pick.astype(np.int64)):
            for k in range(int(sizes[g]) - 1):
                a, b = int(order[shared[g] + k]), int(order[shared[g] + k + 1])
                va, vb = sign * self._frame_velocities[a], sign * self._frame_velocities[b]
                fast_a, fast_b = np.abs(va) > _SHIFT_MIN_MPS, np.abs(vb) > _SHIFT_MIN_MPS
                if fast_a.sum() < 1 or fast_b.sum() < 1:
                    continue
                pa, pb = self._frame_positions[a][fast_a], self._frame_positions[b][fast_b]
                dist, near = cKDTree(pa).query(pb, distance_upper_bound=_SHIFT_MATCH_M)
                found = np.isfinite(dist)
                found[found] &= np.abs(vb[fast_b][found] - va[fast_a][near[found]]) < 0.5
                if found.any():
                    # corrupt clouds can hold finite but absurd ranges (1e308 m): inf there
                    with np.errstate(over='ignore', invalid='ignore'):
                        shifts.append((np.linalg.norm(pb[found], axis=1)
                                       - np.linalg.norm(pa[near[found]], axis=1))
                                      / vb[fast_b][found])
        if sum(d.size for d in shifts) < _SHIFT_MIN_PAIRS:
            return False
        return abs(float(np.median(np.concatenate(shifts)))) >= _SHIFT_SHARE * interval_ns * 1e-9

    def _fix_sigma(self) -> tuple[float, float] | None:
        """Median declared 1-sigma of the fixes (``vehicle_track.declared_fix_sigma``)."""
        return declared_fix_sigma(self._fix_rows()[1])

    def _fix_rows(self) -> tuple[I64, F64]:
        """The fixes as ``build_vehicle_track`` takes them: (n,) stamps and (n, 7) rows."""
        stamps = np.array([f[0] for f in self._fixes], np.int64)
        return stamps, np.array(self._fixes, dtype=np.float64).reshape(-1, 7)

    def _build_vehicle(self) -> tuple[LocalFrame, VehicleTrack]:
        """The local frame and the vehicle's track of the buffered fixes and Odometry
        (``vehicle_track.build_vehicle_track``; what its checks find goes to ``counters``)."""
        cfg = self._config
        odoms = [_odom_sample(o) for o in sorted(self._odoms, key=lambda o: o[0])]
        frame, vehicle = build_vehicle_track(
            *self._fix_rows(), odoms, epsg=cfg.world.epsg, odom_is_utm=cfg.vehicle.odom_is_utm,
            min_heading_speed=cfg.vehicle.min_heading_speed, counters=self.counters)
        return frame, on_centre_line(vehicle, cfg.vehicle.ref_left)


#: Radar messages under one stamp are whole scans taken apart in time when their moving
#: targets (faster than ``_SHIFT_MIN_MPS`` [m/s]) lie further along their radial velocity
#: than their twins (within ``_SHIFT_MATCH_M`` [m]) in the message before, by at least
#: ``_SHIFT_SHARE`` of a scan interval, judged on at least ``_SHIFT_MIN_PAIRS`` pairs of
#: up to ``_SHARED_GROUPS_CHECKED`` stamps (see ``RecordingBuilder._whole_scans_apart``).
_SHIFT_MIN_MPS = 2.0
_SHIFT_MATCH_M = 2.0
_SHIFT_SHARE = 0.3
_SHIFT_MIN_PAIRS = 30
_SHARED_GROUPS_CHECKED = 200


def _odom_sample(values: tuple[float, ...]) -> OdomSample:
    """OdomSample of a stored odometry tuple (stamp, position, quaternion, velocity, rate)."""
    v = values
    return OdomSample(int(v[0]), (v[1], v[2], v[3]), (v[4], v[5], v[6], v[7]),
                      (v[8], v[9], v[10]), v[11])


def interpolate_poses(vehicle: VehicleTrack, stamps_ns: I64, max_gap_s: float) -> PoseSamples:
    """Vehicle poses at arbitrary stamps: position and velocity linearly, heading on the
    circle, never the nearest sample (at 15 m/s, 10 ms is 15 cm).

    Parameters
    ----------
    vehicle : VehicleTrack
    stamps_ns : ndarray of shape (n,), int64 (radar stamps with any offset already added)
    max_gap_s : float
        Stamps inside a pose gap longer than this, or outside the pose stream, are invalid.
    """
    stamps_ns = np.asarray(stamps_ns, np.int64)
    t0 = vehicle.stamps_ns[0]
    tv = (vehicle.stamps_ns - t0) * 1e-9
    tq = (stamps_ns - t0) * 1e-9
    positions = np.column_stack([np.interp(tq, tv, vehicle.positions_m[:, i])
                                 for i in range(3)])
    velocities = np.column_stack([np.interp(tq, tv, vehicle.velocities_mps[:, i])
                                  for i in range(3)])
    yaw = interp_angle(tq, tv, vehicle.yaw_rad)
    yaw_rate = np.interp(tq, tv, vehicle.yaw_rate_rps)
    upper = np.clip(np.searchsorted(tv, tq, side='left'), 1, tv.size - 1)
    gap = tv[upper] - tv[upper - 1]
    valid = (tq >= tv[0]) & (tq <= tv[-1]) & (gap <= max_gap_s)
    return PoseSamples(positions, yaw, velocities, yaw_rate, valid)
