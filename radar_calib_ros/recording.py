"""The Recording: a whole calibration drive as a few columnar arrays.

One code path for both ways in: the offline tool feeds a ``RecordingBuilder`` the decoded
messages of a bag, the node feeds it the decoded messages as they arrive; both then call
``build()``. Decoding (``io.messages``) happens before, so the builder only stores numpy
chunks and turns fixes into the local metric frame once, vectorised, at build time.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core._angles import circular_mean, wrap_angle
from radar_calib_ros.errors import ConfigError, InsufficientDataError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.types import (
    F64, I64, FixSample, OdomSample, PoseSamples, RadarFrame, RadarView, Targets, VehicleTrack)

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
#: Largest median horizontal 1-sigma [m] that fixes which all say NavSatStatus 0 may declare
#: to be taken as RTK (see ``Recording.fix_status_unreported``): RTK fixed declares 1-3 cm,
#: float a decimetre or more, a standalone receiver metres.
RTK_DECLARED_SIGMA_M = 0.1
#: Most targets :meth:`Recording.view_sample_m` returns.
_VIEW_SAMPLE = 200_000


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
        sample: F64 = self.targets.positions_m[::max(1, len(self.targets) // _VIEW_SAMPLE)]
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
        el = np.percentile(np.arcsin(np.clip(pts[:, 2] / np.maximum(rng, 1e-9), -1, 1)),
                           [1.0, 99.0])
        return RadarView(float(np.percentile(rng, 99.0)),
                         float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 99.0)),
                         (float(az[0]), float(az[1])), (float(el[0]), float(el[1])))

    @property
    def pose_sigma_m(self) -> tuple[float, float]:
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


def _narrowed(values: F64) -> NDArray[np.floating[Any]]:
    """``values`` as float32 where every one of them is a float32, else unchanged."""
    with np.errstate(over='ignore'):  # beyond float32's range: inf, unequal, kept wide
        narrow = values.astype(np.float32)
    return narrow if np.array_equal(narrow, values, equal_nan=True) else values


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
        # order received (a recorder's clock is one clock for both; see _receipt_checks)
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
        self._frame_stamps.append(int(frame.stamp_ns))
        self._frame_positions.append(positions)
        self._frame_velocities.append(velocities)
        self._nbytes += positions.nbytes + velocities.nbytes + _FRAME_OVERHEAD_BYTES
        self.counters['radar_frames'] += 1
        self.counters['targets'] += n
        if frame.dropped_nonfinite:
            self.counters['targets_nonfinite'] += frame.dropped_nonfinite

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
            keep = _receipts_from(stamp_ns, self._radar_lag, self._radar_received)
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
        counters.update(_receipt_checks(np.asarray(self._radar_lag, np.int64),
                                        np.asarray(self._radar_received, np.int64),
                                        pose_lag, pose_received))
        rejoin_ns = None
        if ('radar_stamp_jump_ms' in counters and len(self._radar_lag) == len(self._frame_stamps)):
            small = _small_clock_step(np.asarray(self._radar_lag, np.int64),
                                      np.asarray(self._radar_received, np.int64),
                                      pose_lag, pose_received)
            if small is not None:
                _, _, later, before, after = small
                frame_later = np.zeros(frame_stamps.size, bool)
                np.logical_or.at(frame_later, message_frame.ravel(), later[order])
                move_later, shift = _rejoin_shift(before, after, pose_lag)
                moved = frame_later if move_later else ~frame_later
                rejoin_ns = shift * moved.astype(np.int64)
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
        where there are any (the poses' positions come from them), else the Odometry's."""
        pose_lag = np.asarray(self._pose_lag, np.int64)
        pose_received = np.asarray(self._pose_received, np.int64)
        from_fixes = np.asarray(self._pose_is_fix, bool)
        if from_fixes.any() and from_fixes.size == pose_lag.size:
            pose_lag, pose_received = pose_lag[from_fixes], pose_received[from_fixes]
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
        step = _radar_clock_step(radar_lag, radar_received, pose_lag, pose_received)
        if step is None:
            return None
        later, before_ns, after_ns = step
        move_later, shift = _rejoin_shift(before_ns, after_ns, pose_lag)
        moved = later if move_later else ~later
        copy = self.snapshot()
        copy._frame_stamps = list(np.asarray(self._frame_stamps, np.int64) + shift * moved)
        copy._radar_lag = list(radar_lag - shift * moved)
        copy.counters.update(_jump_counters(later, before_ns, after_ns, radar_received))
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
        steps = [_restart_step(received, lag) if received.size else None
                 for received, lag in streams]
        present = [step for (received, _), step in zip(streams, steps) if received.size]
        if any(step is None for step in present) or len(present) < 2:
            return None
        back_ns = [step[1] for step in present if step is not None]
        at_ns = [step[2] for step in present if step is not None]
        if (max(back_ns) - min(back_ns) > _RESTART_AGREE_S * 1e9
                or max(at_ns) - min(at_ns) > _RESTART_AGREE_S * 1e9):
            return None
        shift = int(np.median(back_ns)) + int(_RESTART_GAP_S * 1e9)
        gap = int(_RESTART_GAP_S * 1e9)
        later = [step[0] if step is not None else np.zeros(0, bool) for step in steps]
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
        """Median declared 1-sigma of the fixes (horizontal, vertical), None if none; the
        degraded ones the track leaves out (``_degraded_fixes``) not counted."""
        if not self._fixes:
            return None
        sigma = np.array([f[5:7] for f in self._fixes], np.float64)
        status = np.array([f[4] for f in self._fixes], np.float64)
        known = np.all(np.isfinite(sigma), axis=1) & ~_degraded_fixes(status, sigma[:, 0])
        if not known.any():
            return None
        h, v = np.median(sigma[known], axis=0)
        return float(h), float(v)

    def _build_vehicle(self) -> tuple[LocalFrame, VehicleTrack]:
        cfg = self._config
        odoms = [_odom_sample(o) for o in sorted(self._odoms, key=lambda o: o[0])]
        status_rtk = False
        if self._fixes:
            # Of fixes sharing a stamp the first received is kept (a stable sort by stamp
            # alone): a receiver at 20 Hz whose stamps have 0.1 s resolution gives pairs
            # 0.05 s apart under one stamp, and sorted by latitude as well, the later of a
            # pair was kept on every pass heading south or west, a lag that turned with the
            # heading (an eleventh probe: 25-30 cm along the boresight, outside 2 sigma).
            stamps = np.array([f[0] for f in self._fixes], np.int64)
            order = np.argsort(stamps, kind='stable')
            fixes = np.array(self._fixes, dtype=np.float64)[order]
            stamps, unique = np.unique(stamps[order], return_index=True)
            shared = _shared_stamps(fixes, unique)
            if shared:
                self.counters['fixes_stamp_shared'] = shared
            fixes = fixes[unique]
            self.counters.update(_unaugmented_stretches(stamps, fixes[:, 4]))
            degraded = _degraded_fixes(fixes[:, 4], fixes[:, 5])
            if degraded.any():
                self.counters['fixes_degraded_dropped'] = int(degraded.sum())
                self.counters['fixes_unaugmented_dropped'] = int(
                    np.count_nonzero(degraded & (fixes[:, 4] == 0)))
                self.counters['fixes_sbas_dropped'] = int(
                    np.count_nonzero(degraded & (fixes[:, 4] == 1)))
                stamps, fixes = stamps[~degraded], fixes[~degraded]
            declared = fixes[np.isfinite(fixes[:, 5]), 5]
            status_rtk = bool(np.mean(fixes[:, 4] >= 2) > 0.5 or (
                np.all(fixes[:, 4] == 0) and declared.size > 0
                and np.median(declared) <= RTK_DECLARED_SIGMA_M))
            lat, lon, alt = fixes[:, 1], fixes[:, 2], fixes[:, 3]
            frame = LocalFrame.at(lat[0], lon[0], cfg.world.epsg)
            positions = frame.geodetic_to_local(lat, lon, alt)
        elif odoms and cfg.vehicle.odom_is_utm:
            if not cfg.world.epsg:
                raise ConfigError('vehicle.odom_is_utm needs world.epsg (the UTM zone of the '
                                  'Odometry positions)')
            stamps, unique = np.unique(np.array([o.stamp_ns for o in odoms], np.int64),
                                       return_index=True)
            utm = np.array([odoms[i].position_m for i in unique], np.float64)
            _check_utm(utm, cfg.world.epsg)
            probe = LocalFrame(0.0, 0.0, cfg.world.epsg)
            lat0, lon0, _ = probe.utm_to_geodetic(utm[:1])
            frame = LocalFrame(float(lat0[0]), float(lon0[0]), cfg.world.epsg)
            positions = frame.utm_to_local(utm)
            lat, lon, _ = frame.utm_to_geodetic(utm)
        else:
            no_altitude = self.counters.get('fixes_altitude_nan', 0)
            no_fix = self.counters.get('fixes_no_fix', 0)
            reason = 'no valid NavSatFix'
            if no_altitude:
                reason += (f' ({no_altitude} of {self.counters["fixes"]} have a latitude and '
                           'longitude but no altitude (NaN): the radar\'s height needs the '
                           'vehicle\'s)')
            if no_fix and no_fix == self.counters.get('fixes', 0):
                reason += (f' (all {no_fix} report no fix, status -1: the receiver had no '
                           'solution during the whole recording)')
            if odoms:
                reason += ' (Odometry positions are used only with vehicle.odom_is_utm)'
            raise InsufficientDataError('read', f'no vehicle pose: {reason}')
        if stamps.size < 2:
            raise InsufficientDataError('read', f'only {stamps.size} vehicle pose(s)')
        t = (stamps - stamps[0]) * 1e-9
        raw_positions = positions
        if self._fixes and status_rtk:
            jitter = _stamp_jitter(t, positions)
            if jitter is not None:
                positions, along_m, spread_s = jitter
                self.counters['fix_stamp_jitter_ms'] = int(round(1000.0 * spread_s))
                self.counters['fix_stamp_jitter_cm'] = int(round(100.0 * along_m))
                _LOG.warning('the fixes scatter by %.0f cm along their travel only (%.0f ms of '
                             'their stamps): smoothed', 100.0 * along_m, 1000.0 * spread_s)
        o_stamps = np.array([o.stamp_ns for o in odoms], np.int64)
        if odoms and self._fixes:
            if o_stamps.max() < stamps[0] or o_stamps.min() > stamps[-1]:
                # Not one Odometry stamp within the fixes' span: the two are on different
                # clocks (a node without use_sim_time stamps wall-clock time beside a sim's),
                # and interpolated at the fixes' times the Odometry is its first or last
                # sample throughout. Left out, and said.
                apart_s = float(np.median(o_stamps) - np.median(stamps)) * 1e-9
                self.counters['odometry_other_clock_s'] = int(round(apart_s))
                _LOG.warning('the Odometry stamps lie %.1f s from the NavSatFix stamps and '
                             'never overlap them: the Odometry is left out', apart_s)
                odoms = []
        if odoms:
            q = np.array([o.quaternion_xyzw for o in odoms], np.float64)
            yaw_true = np.arctan2(2.0 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]),
                                  1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2))
            v_body = np.array([o.velocity_body_mps for o in odoms], np.float64)
            v_level = _level_twist(q, yaw_true, v_body)
            rate = np.array([o.yaw_rate_rps for o in odoms], np.float64)
            to = (o_stamps - stamps[0]) * 1e-9
            # over +-0.2 s; unchanged by a lag correction, which moves every fix alike
            measured = _position_velocities(t, positions)
            if self._fixes:
                against = _fix_lag(t, measured[:, :2], to, yaw_true, v_level, rate)
                lag_s = against.lag_s
                if against.lever_arm_m is not None:
                    forward, left = against.lever_arm_m
                    self.counters['fix_lever_arm_forward_cm'] = int(round(100.0 * forward))
                    self.counters['fix_lever_arm_left_cm'] = int(round(100.0 * left))
                    _LOG.warning('the NavSatFix positions describe a point %+.2f m forward and '
                                 '%+.2f m left of the Odometry\'s', forward, left)
                if lag_s:
                    # the fix stamped t shows where the vehicle was at t - lag
                    self.counters['fix_lag_ms'] = int(round(1000.0 * lag_s))
                    _LOG.warning('the NavSatFix stamps lag the Odometry\'s by %.0f ms: the '
                                 'fixes are taken at their stamp minus that', 1000.0 * lag_s)
                    stamps = stamps - int(round(lag_s * 1e9))
                    to = to + lag_s
            yaw_true_at = _interp_angle(t, to, yaw_true)
            # The checks differentiate over +-1 s, not the +-0.2 s the velocities use: a
            # standalone fix (metres of noise, 10 Hz) gives ~7 m/s of noise over 0.4 s and
            # would condemn a good twist, ~1.4 m/s over 2 s; a zero or mis-framed twist, or a
            # wrong heading, still misses by the speed.
            coarse = _position_velocities(t, positions[:, :2], _TWIST_CHECK_SPAN_S)
            vx = np.interp(t, to, v_level[:, 0])
            vy = np.interp(t, to, v_level[:, 1])
            yaw, offset = _checked_orientation(t, coarse, measured, positions, yaw_true_at, lat,
                                               lon, frame, cfg.vehicle.min_heading_speed,
                                               self.counters, vx, rtk=status_rtk)
            tilt_known = _tilted(q)
            if tilt_known and self.counters.get('odometry_orientation_replaced'):
                # An orientation that does not describe the travel (an INS's ECEF attitude,
                # another frame's) does not describe the tilt either: turned by it, the twist
                # lost 13 % of its speed into the vertical and was 'rescaled' (a tenth probe:
                # 2.8 m and 5 deg off). The body twist is taken as level, graded by the fixes.
                tilt_known = False
                v_level = v_body
                vx = np.interp(t, to, v_level[:, 0])
                vy = np.interp(t, to, v_level[:, 1])
            if not tilt_known:
                # a heading-only orientation on a grade: the fixes' climb tells the tilt
                level = _grade_cosine(t, positions, np.hypot(vx, vy), self._fix_sigma())
                vx, vy = vx * level, vy * level
            yaw_rate = np.interp(t, to, rate)
            twist_world = _turned(np.column_stack([vx, vy]), yaw)
            twist_turn = 0.0
            if offset:
                # an INS turned on its mount gives its twist in its own frame too: then the
                # heading as given turns it into the world, not the corrected one
                own_frame = _turned(np.column_stack([vx, vy]), yaw + offset)
                if _twist_mismatch(own_frame, coarse) < _twist_mismatch(twist_world, coarse):
                    twist_world, twist_turn = own_frame, offset
            velocities = _checked_twist(t, positions, measured, coarse, twist_world,
                                        np.column_stack([vx, vy]), self.counters, yaw_rate)
            if _slow_fixes(t, to):
                held = offset
                if self.counters.get('odometry_heading_wander_cdeg'):
                    # the wander followed at the fixes, at the Odometry's own stamps
                    wander = wrap_angle(frame.true_yaw_to_local(yaw_true_at, lat, lon)
                                        - offset - yaw)
                    held = offset + np.interp(to, t, wander)
                dense = _odometry_between_fixes(
                    t, positions, yaw, velocities, yaw_rate, to,
                    _odometry_heading(frame, yaw_true, np.interp(to, t, lat),
                                      np.interp(to, t, lon), held, self.counters, t, to,
                                      positions, v_level),
                    v_level, rate, twist_turn, self.counters)
                if dense is not None:
                    t_dense, positions, yaw, velocities, yaw_rate = dense
                    stamps = stamps[0] + np.round(t_dense * 1e9).astype(np.int64)
        else:
            velocities = _position_velocities(t, positions)
            yaw, yaw_rate = _course_over_ground(t, velocities, cfg.vehicle.min_heading_speed,
                                                self.counters, positions)
        # Positions from the Odometry alone (vehicle.odom_is_utm) come from the same GNSS
        # behind an INS: an RTK fix lost for float and regained moves them as it moves fixes
        # (a fifteenth probe: 0.30-0.87 m off against 0.01-0.09 m with the same jumps in
        # NavSatFix, where they were found), so they are searched alike.
        from_odometry = not self._fixes and bool(odoms)
        jittered = bool(self.counters.get('fix_stamp_jitter_ms'))
        if (status_rtk or from_odometry) and stamps.size == t.size:
            # (not where the Odometry's samples were added between slow fixes)
            twist = (velocities if odoms and not self.counters.get('odometry_twist_replaced')
                     else None)
            # jittered fixes are smoothed by now: the jumps are searched in the fixes
            # as stamped, across the travel only
            steps = _fix_steps(t, raw_positions if jittered else positions, twist,
                               across_only=jittered)
            if steps.times_s.size and from_odometry:
                self.counters['fix_jumps_in_odometry'] = 1
            if steps.times_s.size:
                self.counters['fix_jumps'] = int(steps.times_s.size)
                self.counters['fix_jump_max_cm'] = int(round(100.0 * steps.sizes_m.max()))
                self.counters['fix_jump_median_cm'] = int(round(
                    100.0 * np.median(steps.sizes_m)))
                self.counters['fix_jumps_first_s'] = int(steps.times_s[0])
                self.counters['fix_jumps_last_s'] = int(steps.times_s[-1])
            if steps.dropped.any():
                keep = ~steps.dropped
                self.counters['odometry_silent_float_dropped' if from_odometry else
                              'fixes_silent_float_dropped'] = int(steps.dropped.sum())
                stamps, positions, yaw = stamps[keep], positions[keep], np.asarray(yaw)[keep]
                velocities, yaw_rate = velocities[keep], np.asarray(yaw_rate)[keep]
        vehicle = VehicleTrack(stamps, positions, np.asarray(yaw, float), velocities,
                               np.asarray(yaw_rate, float))
        return frame, vehicle


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

#: Fixes slower than this (median interval) [s] are bridged by the Odometry's motion between
#: them; intervals longer than ``_BRIDGED_INTERVAL_S`` are not (an outage stays a gap).
_SLOW_FIX_INTERVAL_S = 0.3
_BRIDGED_INTERVAL_S = 2.5


#: Least jump of RTK fix positions between consecutive fixes taken as a fix lost or regained
#: [m], and in robust sigmas of the jump estimates (they scatter by ~1 cm at 20 Hz).
_FIX_STEP_MIN_M = 0.1
_FIX_STEP_SIGMAS = 6.0
#: Largest misfit of a window's parabola [m], or in medians of all windows', that still
#: measures a jump (a fix's noise is 1-2 cm).
_FIX_STEP_MISFIT_M = 0.03
_FIX_STEP_MISFIT_RATIO = 3.0
#: Largest change of velocity across a jump [m/s] (its two sides' parabolas at its middle):
#: a car brakes by less within a fix interval, a dead stop of a simulated one by more.
_FIX_STEP_RATE_MPS = 1.5
#: Fixes on each side of an interval its jump is measured from: at least this many, over
#: at least this span [s]; fixes slower than ``_FIX_STEP_MAX_INTERVAL_S`` are not searched
#: (a vehicle's own motion over seconds is no straight line).
_FIX_STEP_MIN_FIXES = 4
_FIX_STEP_MAX_FIXES = 16
_FIX_STEP_SPAN_S = 0.5
_FIX_STEP_MAX_INTERVAL_S = 0.2
#: Fixes this close to a jump [s] are left out with a float stretch (their velocities,
#: differenced over +-0.2 s, straddle the jump).
_FIX_STEP_MARGIN_S = 0.5
#: Largest share of the drive taken as RTK float between jumps: more, and which side of the
#: jumps is the fixed one is no longer clear.
_SILENT_FLOAT_MAX_SHARE = 0.4


@dataclass(frozen=True)
class FixSteps:
    """Jumps of the fix positions that the vehicle's motion does not explain.

    times_s : (j,) midpoints of the intervals where they happen [s, the fixes' time];
    sizes_m : (j,) horizontal size [m]; dropped : (n,) fixes taken as RTK float and left out.
    """

    times_s: F64
    sizes_m: F64
    dropped: np.ndarray


def _fix_steps(t: F64, positions: F64, twist: F64 | None,
               across_only: bool = False) -> FixSteps:
    """The jumps of fixes (n,) sorted by time, and the stretches between them taken as RTK
    float.

    Why: a receiver that loses its RTK fix for RTK float wanders by decimetres and jumps
    back when the fix returns; some drivers say so in neither the status nor the
    covariance (an eleventh probe: 23 cm along the boresight, no word). The jumps show: a
    parabola fitted to the fixes just before an interval and one fitted just after disagree
    at its middle by the jump, against ~1 cm of noise. With the Odometry's twist the
    vehicle's travel is taken out first (``twist``, world frame), so that only the jump and
    the twist's slow drift remain. The stretches between jumps alternate fixed and float;
    the float ones are taken as those that make the shorter share of the drive, and are
    dropped only while that share is clearly the smaller (``_SILENT_FLOAT_MAX_SHARE``). A
    jump missed (a float stretch that began where its error was small) flips the
    alternation after it; where that leaves no clearly smaller share, nothing is dropped,
    only said (on the eleventh probe's recordings about 97 % of the dropped fixes were
    float). ``across_only``: fixes whose stamps scatter (``_stamp_jitter``) scatter along
    the travel by decimetres, which would hide any jump there; across it they stay exact,
    so only the jumps' part across the travel is measured (a false fix of 0.7-1 m over a
    pass, missed in a sixteenth probe's jittered fixes: 0.13-0.78 m off).
    """
    none = FixSteps(np.empty(0), np.empty(0), np.zeros(t.size, bool))
    if t.size < 2:
        return none
    interval = float(np.median(np.diff(t)))
    if interval <= 0.0 or interval > _FIX_STEP_MAX_INTERVAL_S:
        return none
    # (capped: a 100 Hz stream's half-second windows would cost memory, not accuracy)
    k = min(max(_FIX_STEP_MIN_FIXES, math.ceil(_FIX_STEP_SPAN_S / interval)),
            _FIX_STEP_MAX_FIXES)
    if t.size < 2 * k + 1:
        return none
    q = positions[:, :2] if twist is None else positions[:, :2] - _travelled(t, twist)
    # a parabola through each window: constant acceleration (braking, a turn) leaves none
    # of itself in the jump, as a line would (4-5 cm at 3-8 m/s^2)
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    t_mean = tw.mean(axis=1)
    qw, design, coef = _window_quadratics(t, q, k, t_mean)
    misfit = np.sqrt(np.mean(np.sum((qw - design @ coef) ** 2, axis=2), axis=1))
    if across_only:
        # the travel's direction in each window from the fixes themselves (their scatter
        # is along it); what is measured is what lies across it
        _, _, path = _window_quadratics(t, positions[:, :2], k, t_mean)
        normal = path[:, 1, ::-1] * np.array([-1.0, 1.0])
        normal /= np.maximum(np.hypot(normal[:, 0], normal[:, 1]), 1e-9)[:, None]
        misfit = np.sqrt(np.mean(np.einsum('wkd,wd->wk', qw - design @ coef, normal) ** 2,
                                 axis=1))
    # interval i (fixes i, i+1): the window ending at fix i against the one starting at i+1
    i = np.arange(k - 1, t.size - k)
    before, after = i - k + 1, i + 1
    mid = 0.5 * (t[i] + t[i + 1])

    def at_mid(w: I64) -> F64:
        d = (mid - t_mean[w])[:, None]
        return coef[w, 0] + coef[w, 1] * d + coef[w, 2] * d ** 2

    def rate_at_mid(w: I64) -> F64:
        return coef[w, 1] + 2.0 * coef[w, 2] * (mid - t_mean[w])[:, None]

    jump = at_mid(after) - at_mid(before)
    rate_change = rate_at_mid(after) - rate_at_mid(before)
    if across_only:
        across = normal[before] + normal[after]
        across /= np.maximum(np.hypot(across[:, 0], across[:, 1]), 1e-9)[:, None]
        jump = across * np.einsum('ij,ij->i', jump, across)[:, None]
        rate_change = across * np.einsum('ij,ij->i', rate_change, across)[:, None]
    # a jump of the position leaves the velocity as it was
    steady = np.hypot(*rate_change.T) <= _FIX_STEP_RATE_MPS
    # A window across a gap (an outage, fixes already left out) measures no jump, nor one
    # that no parabola fits, nor a pair whose velocities differ: a step of the velocity (a
    # simulator's car stopping dead) bends the windows that straddle it, while either side
    # of a jump is smooth and at the same speed.
    span = 2.0 * k * interval
    fits = misfit <= max(_FIX_STEP_MISFIT_M, _FIX_STEP_MISFIT_RATIO * float(np.median(misfit)))
    whole = ((tw[before, -1] - tw[before, 0] <= span) & (tw[after, -1] - tw[after, 0] <= span)
             & (t[i + 1] - t[i] <= 3.0 * interval) & fits[before] & fits[after] & steady)
    if whole.sum() < 10:
        return none
    size = np.where(whole, np.hypot(jump[:, 0], jump[:, 1]), 0.0)
    spread = 1.4826 * np.median(np.abs(jump[whole] - np.median(jump[whole], axis=0)), axis=0)
    limit = max(_FIX_STEP_MIN_M, _FIX_STEP_SIGMAS * float(np.hypot(*spread)))
    # one jump shows in the k intervals on either side too: its own is the largest
    peak = ndimage.maximum_filter1d(size, 2 * k + 1, mode='constant') == size
    at = np.flatnonzero((size > limit) & peak)
    if at.size == 0:
        return none
    times, sizes = mid[at], size[at]
    # stretches between jumps, alternately fixed and float: the float ones the shorter share
    bounds = np.concatenate([[t[0]], times, [t[-1]]])
    lengths = np.diff(bounds)
    odd = lengths[1::2].sum()
    parity = 1 if odd <= lengths[0::2].sum() else 0
    share = lengths[parity::2].sum() / max(t[-1] - t[0], 1e-9)
    if share > _SILENT_FLOAT_MAX_SHARE:
        return FixSteps(times, sizes, np.zeros(t.size, bool))
    stretch = np.searchsorted(times, t)
    dropped = (stretch % 2) == parity
    near = np.abs(t[:, None] - times[None, :]).min(axis=1) <= _FIX_STEP_MARGIN_S
    return FixSteps(times, sizes, dropped | near)


#: Fixes are smoothed when their scatter from a quadratic over +-``_JITTER_HALF_SPAN_S``
#: along the travel (moving faster than ``_JITTER_MIN_SPEED_MPS``) is at least
#: ``_JITTER_ANISOTROPY`` times that across it, and amounts to ``_JITTER_MIN_S`` of their
#: stamps (1 sigma, robust). (At 10 ms a sixteenth probe's 20-40 ms delays, 7 ms of
#: spread, went unnamed, and their 20-30 cm of scatter along the travel were taken for
#: 144 RTK-float jumps; over 917 bench and probe recordings, 5 ms fires on none that 10
#: ms did not, but on these.)
_JITTER_HALF_SPAN_S = 1.0
#: (at most this many fixes either side: a 100 Hz stream's 201-fix windows cost seconds,
#: and 41 fixes average its scatter as well as 41 over +-1 s at 20 Hz)
_JITTER_MAX_HALF_FIXES = 20
_JITTER_MIN_SPEED_MPS = 3.0
_JITTER_ANISOTROPY = 3.0
_JITTER_MIN_S = 0.005
_JITTER_MIN_SAMPLES = 50


def _robust_sigma(x: F64) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _stamp_jitter(t: F64, positions: F64) -> tuple[F64, float, float] | None:
    """(positions smoothed, scatter along the travel [m], its spread in time [s]) where the
    fixes' stamps scatter, else None.

    Why: a driver that stamps each fix when it arrives rather than at the receiver's epoch
    (nmea_navsat_driver's default) adds the serial link's varying delay to every stamp. The
    positions are exact but each is placed up to a metre along the travel from where the
    vehicle was at its stamp (0.15 s at 12 m/s), while across the travel they lie on a
    smooth path to the millimetre; RTK float or a standalone fix errs in every direction
    alike. A fifteenth probe's fixes stamped 20-150 ms late: the radar 0.31-0.47 m off
    along its boresight with the Odometry, and with fixes alone 1-2 m high and 1.6-3.2 deg
    pitched (2.6 sigma), the vehicle recognised in 40 % of its frames, and the only word a
    wrong one (RTK float). A quadratic in time over +-``_JITTER_HALF_SPAN_S`` around each
    fix (the travel's constant acceleration; a turn's cubic term leaves the centre value
    alone in a symmetric window) gives the path; where the scatter is along it only, the
    fixes are replaced by it. The delay's mean is a latency like any other, found against
    the Odometry (``_fix_lag``) or by the final fit's clock offset.
    """
    n = t.size
    if n < 2:
        return None
    interval = float(np.median(np.diff(t)))
    if interval <= 0.0 or interval > _FIX_STEP_MAX_INTERVAL_S:
        return None
    m = min(max(2, int(round(_JITTER_HALF_SPAN_S / interval))), _JITTER_MAX_HALF_FIXES)
    k = 2 * m + 1
    if n < 4 * k:
        return None
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    _, _, coef = _window_quadratics(t, positions, k, tw[:, m])
    centre = np.arange(m, n - m)
    # a window across an outage measures nothing
    whole = tw[:, -1] - tw[:, 0] <= 2.0 * (k - 1) * interval
    value, rate = coef[:, 0, :], coef[:, 1, :2]
    speed = np.hypot(rate[:, 0], rate[:, 1])
    moving = whole & (speed > _JITTER_MIN_SPEED_MPS)
    if int(moving.sum()) < _JITTER_MIN_SAMPLES:
        return None
    heading = rate[moving] / speed[moving, None]
    residual = positions[centre[moving], :2] - value[moving, :2]
    along = np.einsum('ij,ij->i', residual, heading)
    across = residual[:, 1] * heading[:, 0] - residual[:, 0] * heading[:, 1]
    sigma_along, sigma_across = _robust_sigma(along), _robust_sigma(across)
    spread_s = _robust_sigma(along / speed[moving])
    if spread_s < _JITTER_MIN_S or sigma_along < _JITTER_ANISOTROPY * sigma_across:
        return None
    smoothed = np.array(positions, float, copy=True)
    smoothed[centre[whole]] = value[whole]
    return smoothed, sigma_along, spread_s


def _window_quadratics(t: F64, values: F64, k: int, origin: F64
                       ) -> tuple[F64, F64, F64]:
    """A quadratic in time fitted (least squares) to each run of ``k`` consecutive samples
    of ``values`` (n, d) at times ``t`` (n,), time counted from the window's ``origin``
    (n - k + 1,): the windows' values (w, k, d), design (w, k, 3) and coefficients
    (w, 3, d) (value, rate, half the acceleration at the origin)."""
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    vw = np.lib.stride_tricks.sliding_window_view(values, k, axis=0).transpose(0, 2, 1)
    dt = tw - origin[:, None]
    design = np.stack([np.ones_like(dt), dt, dt ** 2], axis=2)
    gram = np.einsum('wki,wkj->wij', design, design)
    # a window of samples at fewer than three times fits no quadratic (a stream whose
    # stamps were moved onto one instant): the identity keeps it solvable
    gram[(np.diff(tw, axis=1) != 0.0).sum(axis=1) < 2] += np.eye(3)
    coef = np.linalg.solve(gram, np.einsum('wki,wkd->wid', design, vw))
    return vw, design, coef


def _shared_stamps(fixes: F64, first: I64) -> int:
    """How many fixes (rows sorted by stamp, ``first`` the first row of each stamp) share
    their stamp with an earlier fix of another position (over 1 mm apart: a copy of the
    same fix, a topic recorded twice, is no loss)."""
    owner = np.repeat(first, np.diff(np.append(first, len(fixes))))
    moved = np.abs(fixes[:, 1:3] - fixes[owner, 1:3]).max(axis=1) > 1e-8
    return int(np.count_nonzero(moved))


def _slow_fixes(t: F64, to: F64) -> bool:
    """True when the fixes come slower than ``_SLOW_FIX_INTERVAL_S`` and the Odometry at
    least twice as fast within their span."""
    if t.size < 3:
        return False
    interval = float(np.median(np.diff(t)))
    inside = to[(to > t[0]) & (to < t[-1])]
    return (interval >= _SLOW_FIX_INTERVAL_S and inside.size >= 2 * t.size
            and float(np.median(np.diff(inside))) <= 0.5 * interval)


#: Largest median turn of a replaced Odometry heading from the course over ground, once its
#: constant offset is taken off, for it still to give the heading between fixes [rad].
_TURNED_MAP_SPREAD_RAD = math.radians(3.0)


def _dead_reckoned(times: F64, to: F64, twist: F64) -> tuple[F64, F64]:
    """(velocity, path from the first of ``times``): the world twist (sampled at ``to``) at
    ``times`` and its integral by trapezoids."""
    v = np.column_stack([np.interp(times, to, twist[:, i]) for i in range(2)])
    return v, _travelled(times, v)


def _travelled(times: F64, v: F64) -> F64:
    """(n, 2) path from the first of ``times``: horizontal velocities ``v`` at ``times``
    integrated by trapezoids."""
    return np.vstack([np.zeros((1, 2)), np.cumsum(
        0.5 * (v[1:, :2] + v[:-1, :2]) * np.diff(times)[:, None], axis=0)])


def _odometry_heading(frame: LocalFrame, yaw_true: F64, lat: F64, lon: F64,
                      offset: float | F64,
                      counters: Counter[str], t: F64, to: F64, positions: F64, v_level: F64
                      ) -> F64 | None:
    """The Odometry's heading at its own stamps as ``_checked_orientation`` read it (local
    grid, its offset taken off); where that replaced it by the course over ground, the
    Odometry's heading turned by the constant turn of its map frame when the fixes'
    ``positions`` (at ``t``) show one, else None.

    Why the second: a map frame turned against east (an HD map's, or a simulator's) is
    further off than ``_checked_orientation`` takes for an offset, but between fixes a
    second apart its turns are all there is (a probe's Odometry in a map frame turned 37 deg,
    beside 1 Hz fixes)."""
    if counters.get('odometry_orientation_compass'):
        return frame.true_yaw_to_local(np.pi / 2.0 - yaw_true, lat, lon)
    local = frame.true_yaw_to_local(yaw_true, lat, lon)
    if not counters.get('odometry_orientation_replaced'):
        return local - offset
    # the turn of the map frame: between consecutive fixes, the direction of their chord
    # against that of the twist integrated with the heading as given (exact for any path;
    # the course over ground at slow fixes is not the heading where the curvature changes)
    twist = _turned(v_level, local)
    times = np.union1d(t, to[(to > t[0]) & (to < t[-1])])
    _, travelled = _dead_reckoned(times, to, twist)
    reckoned = np.diff(travelled[np.searchsorted(times, t)], axis=0)
    chord = np.diff(positions[:, :2], axis=0)
    used = ((np.diff(t) <= _BRIDGED_INTERVAL_S)
            & (np.hypot(*chord.T) > _TWIST_CHECK_SPEED_MPS * np.diff(t)))
    if int(used.sum()) < _ORIENTATION_SAMPLES:
        return None
    turn = wrap_angle(np.arctan2(reckoned[used, 1], reckoned[used, 0])
                      - np.arctan2(chord[used, 1], chord[used, 0]))
    offset = float(circular_mean(turn))
    if float(np.median(np.abs(wrap_angle(turn - offset)))) > _TURNED_MAP_SPREAD_RAD:
        return None
    return local - offset


def _odometry_between_fixes(t: F64, positions: F64, yaw: F64, velocities: F64, yaw_rate: F64,
                            to: F64, heading: F64 | None, v_level: F64, rate: F64,
                            twist_turn: float, counters: Counter[str]
                            ) -> tuple[F64, F64, F64, F64, F64] | None:
    """(t, positions, yaw, velocities, yaw_rate) with the Odometry's samples added between
    fixes no more than ``_BRIDGED_INTERVAL_S`` apart, or None where its heading or twist
    was found unusable.

    Why: GNSS receivers give 1-2 Hz by default beside a 50-100 Hz INS. Linear between 1 Hz
    fixes, a car turning at 0.3 rad/s and 10 m/s is off its arc by up to 37 cm, and a gap
    of a second is more than ``sync.max_pose_gap`` allows (a probe's 1 Hz fixes were
    refused, and with the gap raised gave 19 cm against 11 cm at 10 Hz). Between two fixes
    the path is the Odometry's twist integrated from the first, its misclosure at the
    second spread linearly over the interval: the fixes stay exact, and a twist off by a
    scale, a grade or a small turn errs only by how much that error varies within one
    interval. Height is interpolated between the fixes (the twist's is not trusted).
    """
    if heading is None or counters.get('odometry_twist_replaced'):
        return None
    if counters.get('odometry_twist_in_parent_frame'):
        twist = v_level[:, :2]
    else:
        twist = _turned(v_level, heading + twist_turn)
    interval = np.diff(t)
    k = np.searchsorted(t, to, side='right') - 1
    inside = (k >= 0) & (k < t.size - 1)
    inside[inside] &= (to[inside] > t[k[inside]]) & (interval[k[inside]] <= _BRIDGED_INTERVAL_S)
    if not inside.any():
        return None
    added = np.flatnonzero(inside)
    times = np.concatenate([t, to[added]])
    order = np.argsort(times, kind='stable')
    times = times[order]
    is_fix = order < t.size
    v, travelled = _dead_reckoned(times, to, twist)
    misclosure = positions[:, :2] - travelled[is_fix]
    seg = np.clip(np.searchsorted(t, times, side='right') - 1, 0, t.size - 2)
    share = (times - t[seg]) / interval[seg]
    slope = (misclosure[seg + 1] - misclosure[seg]) / interval[seg][:, None]
    xy = travelled + misclosure[seg] + share[:, None] * (misclosure[seg + 1] - misclosure[seg])
    z = positions[seg, 2] + share * (positions[seg + 1, 2] - positions[seg, 2])
    vz = (positions[seg + 1, 2] - positions[seg, 2]) / interval[seg]
    out_positions = np.column_stack([xy, z])
    out_velocities = np.column_stack([v + slope, vz])
    out_yaw = np.empty(times.size)
    out_rate = np.empty(times.size)
    odom = ~is_fix
    out_yaw[odom] = heading[added]
    out_rate[odom] = rate[added]
    # at a fix the Odometry's heading too (a course over ground it replaced errs most at
    # the ends of the drive); one with no bridged interval on either side keeps what the
    # fixes alone gave
    bridged = np.zeros(t.size + 1, bool)
    bridged[1:-1] = interval <= _BRIDGED_INTERVAL_S
    alone = ~(bridged[:-1] | bridged[1:])
    fix_rows = np.flatnonzero(is_fix)
    out_yaw[is_fix] = np.where(alone, yaw, _interp_angle(t, to, heading))
    out_rate[is_fix] = np.where(alone, yaw_rate, np.interp(t, to, rate))
    out_positions[fix_rows] = positions
    # at a fix the misclosure's slope of a bridged interval beside it (an outage's one
    # trapezoid over seconds is no velocity)
    fix_seg = np.where(bridged[1:], np.arange(t.size), np.arange(t.size) - 1)[~alone]
    out_velocities[fix_rows[~alone], :2] = (
        v[fix_rows[~alone]] + (misclosure[fix_seg + 1] - misclosure[fix_seg])
        / interval[fix_seg][:, None])
    out_velocities[fix_rows[~alone], 2] = ((positions[fix_seg + 1, 2] - positions[fix_seg, 2])
                                           / interval[fix_seg])
    out_velocities[fix_rows[alone]] = velocities[alone]
    # sample stamps equal to a fix's would be duplicates once rounded to nanoseconds
    keep = np.ones(times.size, bool)
    keep[1:] = np.diff(np.round(times * 1e9)) > 0
    counters['poses_bridged_by_odometry'] = int(added.size)
    _LOG.info('the fixes come every %.2f s: the Odometry\'s %d samples between them give the '
              'path there', float(np.median(interval)), added.size)
    return (times[keep], out_positions[keep], out_yaw[keep], out_velocities[keep],
            out_rate[keep])


#: Where UTM coordinates can lie [m]: eastings within a zone (166-834 km at the equator,
#: the zone's overlap allowed for), northings from the equator (or its false northing).
_UTM_EASTING_M = (100_000.0, 900_000.0)
_UTM_NORTHING_M = (0.0, 10_000_000.0)


def _check_utm(utm: F64, epsg: int) -> None:
    """Raise ConfigError when Odometry positions taken as UTM (``vehicle.odom_is_utm``)
    cannot be: a local map frame's metres (Autoware's map is one MGRS grid square's, 0-100
    km) were placed 5000 km off at exit 0 with an 8 cm sigma (a tenth probe)."""
    east, north = np.median(utm[:, 0]), np.median(utm[:, 1])
    if not (_UTM_EASTING_M[0] <= east <= _UTM_EASTING_M[1]
            and _UTM_NORTHING_M[0] <= north <= _UTM_NORTHING_M[1]):
        raise ConfigError(
            f'vehicle.odom_is_utm: the Odometry positions (median E {east:.1f} m, N '
            f'{north:.1f} m) cannot be UTM coordinates of EPSG:{epsg} (eastings lie within '
            '100-900 km, northings within 0-10 000 km): they are in a local map frame (an '
            'MGRS grid square\'s, as Autoware\'s map is?). Record the NavSatFix, or publish '
            'the Odometry in UTM.')


def _turned(vectors: F64, angle_rad: F64 | float) -> F64:
    """(n, 2): the horizontal part of ``vectors`` (n, >=2) turned counter-clockwise by
    ``angle_rad`` (one angle, or one per row): a body-frame twist into the world by the
    heading."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.column_stack([c * vectors[:, 0] - s * vectors[:, 1],
                            s * vectors[:, 0] + c * vectors[:, 1]])


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
    yaw = _interp_angle(tq, tv, vehicle.yaw_rad)
    yaw_rate = np.interp(tq, tv, vehicle.yaw_rate_rps)
    upper = np.clip(np.searchsorted(tv, tq, side='left'), 1, tv.size - 1)
    gap = tv[upper] - tv[upper - 1]
    valid = (tq >= tv[0]) & (tq <= tv[-1]) & (gap <= max_gap_s)
    return PoseSamples(positions, yaw, velocities, yaw_rate, valid)


#: A lasting fall of a stream's header stamps against the recorder's clock of more than
#: this is a restart [s]; streams whose falls differ by less, and come this close in time,
#: fell together [s]; the gap left between the parts [s] (above any sync.max_pose_gap).
_RESTART_BACK_S = 5.0
_RESTART_AGREE_S = 2.0
_RESTART_GAP_S = 30.0


def _restart_step(received: I64, lag: I64) -> tuple[np.ndarray, int, int] | None:
    """(messages after the fall, fall [ns], when it came [recorder's ns]) of the largest
    lasting fall of one stream's header stamps against its receipts, or None.

    In receipt order the lag (received - stamp) jumps up by the fall (``_lag_step``)."""
    step = _lag_step(received, lag, _RESTART_BACK_S, rising_only=True)
    if step is None:
        return None
    later, before, after, at_ns = step
    return later, int(round(after - before)), at_ns


def _lag_step(received: I64, lag: I64, min_step_s: float, rising_only: bool = False
              ) -> tuple[np.ndarray, float, float, int] | None:
    """(messages after it, median lag before, after [ns], when it came [recorder's ns]) of
    the largest lasting step of one stream's receipt lag (received - header stamp) of at
    least ``min_step_s``, or None (``rising_only``: stamps that fall back).

    A median over ``_RECEIPT_WINDOW`` messages in receipt order ignores single late
    messages; the messages around the step then go to the side whose median lag their own
    is nearer (messages of the old clock still in flight, ``_step_sides``)."""
    w = _RECEIPT_WINDOW
    if received.size < 2 * w:
        return None
    order = np.argsort(received, kind='stable')
    ordered = lag[order].astype(np.float64)
    change = np.diff(ndimage.median_filter(ordered, size=w, mode='nearest'))
    k = int(np.argmax(change if rising_only else np.abs(change))) + 1
    before, after = float(np.median(ordered[:k])), float(np.median(ordered[k:]))
    step = after - before
    if min(abs(change[k - 1]), abs(step) if not rising_only else step) <= min_step_s * 1e9:
        return None
    return (_step_sides(order, ordered, k, before, after, w), before, after,
            int(received[order][k]))


def _step_sides(order: I64, ordered: F64, k: int, before: float, after: float,
                w: int) -> np.ndarray:
    """(n,) True for the messages after a step of their lag at ``k`` (in receipt order
    ``order``, lags ``ordered``): those from ``w`` before it on whose lag is nearer the
    median after it than the one before."""
    later_ordered = np.arange(ordered.size) >= max(0, k - w)
    later_ordered &= np.abs(ordered - after) < np.abs(ordered - before)
    later = np.zeros(ordered.size, bool)
    later[order] = later_ordered
    return later


def _receipts_from(stamp_ns: int, lags: list[int], received: list[int]) -> list[int]:
    """Indices of the receipts (lag, received) of the messages stamped at or after
    ``stamp_ns``."""
    return [i for i, (lag, rec) in enumerate(zip(lags, received)) if rec - lag >= stamp_ns]


#: Offset between the radar's and the poses' header stamps, as one recorder received them,
#: and a step of the radar's, worth naming [s] (transport latencies are milliseconds to a
#: few hundred); frames over which a step must persist.
_RECEIPT_OFFSET_S = 1.0
_RECEIPT_WINDOW = 15


def _radar_clock_step(radar_lag: I64, radar_received: I64, pose_lag: I64,
                      pose_received: I64 | None = None) -> tuple[np.ndarray, float, float] | None:
    """(messages after the step, median lag before, after [ns]) of the largest lasting step,
    ``_RECEIPT_OFFSET_S`` or more, of the radar stamps' receipt lag that the poses' lag does
    not share, or None. Messages near the step (in flight when it came) go to the side
    whose median lag their own is nearer."""
    step = _lag_step(radar_received, radar_lag, _RECEIPT_OFFSET_S)
    if step is None:
        return None
    later, before, after, at_ns = step
    if _pose_lag_stepped(pose_lag, pose_received, at_ns, after - before):
        return None
    return later, before, after


def _jump_counters(later: np.ndarray, before_ns: float, after_ns: float,
                   radar_received: I64) -> dict[str, int]:
    """'radar_stamp_jump_ms' (a lag that drops is a stamp that jumps forward) and
    'radar_stamp_jump_at_ms' (after the first radar message) of a step of the radar
    stamps' receipt lag from ``before_ns`` to ``after_ns``, ``later`` the messages after."""
    return {'radar_stamp_jump_ms': int(round(-(after_ns - before_ns) / 1e6)),
            'radar_stamp_jump_at_ms': int(
                (radar_received[later].min() - radar_received.min()) // 10**6)}


def _rejoin_shift(before_ns: float, after_ns: float, pose_lag: I64) -> tuple[bool, int]:
    """(whether the side after it moves, by how much [ns]) to undo a step of the radar
    stamps' receipt lag from ``before_ns`` to ``after_ns``: the side whose lag lies farther
    from the poses' moves onto the other's clock (a radar on GPS time that finds its sync
    keeps its later stamps; one that loses it, its earlier ones)."""
    pose_ns = float(np.median(pose_lag)) if pose_lag.size else before_ns
    move_later = abs(after_ns - pose_ns) >= abs(before_ns - pose_ns)
    shift = int(round(after_ns - before_ns))
    return move_later, shift if move_later else -shift


def _pose_lag_stepped(pose_lag: I64, pose_received: I64 | None, at_ns: int,
                      step_ns: float) -> bool:
    """Whether the poses' receipt lag steps alike (within half) at ``at_ns``: the
    recorder's own clock moved, not the radar's."""
    if pose_received is None or pose_received.size != pose_lag.size:
        return False
    before = pose_received < at_ns
    if before.sum() < _RECEIPT_WINDOW or (~before).sum() < _RECEIPT_WINDOW:
        return False
    pose_step = float(np.median(pose_lag[~before]) - np.median(pose_lag[before]))
    return abs(pose_step - step_ns) < 0.5 * abs(step_ns)


def _receipt_checks(radar_lag: I64, radar_received: I64, pose_lag: I64,
                    pose_received: I64 | None = None) -> dict[str, int]:
    """Counters from the receipt lags (received - header stamp, ns, in received order): the
    radar stamps' offset from the poses' ('radar_stamp_offset_ms': radar minus pose; the
    notes judge it against ``sync.time_offset``), and the largest lasting step of the lag
    ('radar_stamp_jump_ms', 'radar_stamp_jump_at_ms' after the first radar message).

    Why: a radar on GPS time and a vehicle on UTC are 18 s apart, a radar clock that loses
    its sync jumps; the stamps alone cannot tell a jump of 5 s from a pause in the data, the
    recorder's clock can."""
    out: dict[str, int] = {}
    if radar_lag.size < _RECEIPT_WINDOW or pose_lag.size < _RECEIPT_WINDOW:
        return out
    # A bag written by a converter may give every message one receive time (or a handful):
    # those receipts say nothing of the clocks (a twenty-fifth probe's were read as the
    # radar's stamps jumping by 188 s)
    for received in (radar_received, pose_received):
        if received is not None and np.unique(received).size < _RECEIPT_DISTINCT * received.size:
            return out
    # nor do receipts that pass at another pace than the stamps (a bag replayed faster than
    # it was recorded, without use_sim_time; messages fed as fast as they decode)
    if pose_received is not None and pose_received.size > 1:
        stamp_span = float(np.ptp(pose_received - pose_lag))
        if not 0.5 * stamp_span <= float(np.ptp(pose_received)) <= 2.0 * stamp_span:
            return out
    offset_ns = float(np.median(pose_lag) - np.median(radar_lag))
    out['radar_stamp_offset_ms'] = int(round(offset_ns / 1e6))
    step = _radar_clock_step(radar_lag, radar_received, pose_lag, pose_received)
    if step is not None:
        out.update(_jump_counters(*step, radar_received))
        return out
    step_at = _small_clock_step(radar_lag, radar_received, pose_lag, pose_received)
    if step_at is not None:
        out['radar_stamp_jump_ms'], out['radar_stamp_jump_at_ms'] = step_at[:2]
    return out


#: Fewest distinct receive times, as a fraction of the messages, for the receipts to count.
_RECEIPT_DISTINCT = 0.1
#: Messages on either side of a smaller step of the radar's clock (about 10 s at 15 Hz),
#: and the least such step named [s]: an NTP correction of a few hundred milliseconds.
_RECEIPT_STEP_WINDOW = 150
_RECEIPT_STEP_S = 0.15


def _small_clock_step(radar_lag: I64, radar_received: I64, pose_lag: I64,
                      pose_received: I64 | None
                      ) -> tuple[int, int, np.ndarray, float, float] | None:
    """(jump [ms], when [ms after the first radar message], the messages after it, the
    median lag before and after it [ns]) of a lasting step of the radar stamps' receipt lag
    below a second, or None.

    Why: an NTP correction steps the radar's clock by tenths of a second; the passes on one
    side are then paired with poses that far off, the clock offset the fit finds is a blend,
    and passes were lost without a word (an independent probe: +0.2 s, 2 of 6 passes). The
    lag's median over ``_RECEIPT_STEP_WINDOW`` messages is steady to a few milliseconds
    even under V2X latency jitter of a second, so a step of ``_RECEIPT_STEP_S`` stands out;
    where the poses' receipt lag steps alike, the recorder's clock moved, not the radar's.
    """
    w = _RECEIPT_STEP_WINDOW
    if radar_lag.size < 2 * w:
        return None
    order = np.argsort(radar_received, kind='stable')
    lag, received = radar_lag[order].astype(np.float64), radar_received[order]
    smooth = ndimage.median_filter(lag, size=w, mode='nearest')
    h = w // 2
    change = smooth[2 * h:] - smooth[:-2 * h]
    k = int(np.argmax(np.abs(change))) + h
    k = min(max(k, w), lag.size - w)
    before, after = float(np.median(lag[:k])), float(np.median(lag[k:]))
    step = after - before
    if abs(step) < _RECEIPT_STEP_S * 1e9:
        return None
    if _pose_lag_stepped(pose_lag, pose_received, int(received[k]), step):
        return None
    # a lag that drops is a stamp that jumps forward
    return (int(round(-step / 1e6)), int((received[k] - received[0]) // 10**6),
            _step_sides(order, lag, k, before, after, w), before, after)


def _unaugmented_stretches(stamps_ns: I64, status: F64) -> dict[str, int]:
    """Runs of consecutive standalone fixes (status 0) among fixes sorted by stamp: how
    many, and the longest [ms]. An RTK receiver that drops to a float or standalone
    solution for a while gives such runs; their error reaches the calibration unseen by
    the fit."""
    edges = np.diff(np.concatenate([[0], (status == 0).astype(np.int64), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    if starts.size == 0:
        return {}
    longest = int(np.max(stamps_ns[ends] - stamps_ns[starts])) // 1_000_000
    return {'fixes_unaugmented_stretches': int(starts.size),
            'fixes_unaugmented_longest_ms': longest}


#: A fix declaring more than this many times the horizontal sigma of the drive's best
#: quarter (and more than _DEGRADED_SIGMA_M) is degraded.
_DEGRADED_SIGMA_RATIO = 5.0
_DEGRADED_SIGMA_M = 0.1


#: Share of RTK fixes from which the others are left out. Not half: a drive 57 % in RTK
#: float (status 1) kept every fix, reported at SBAS's 0.6 m, 1.2 m and 4 deg for a
#: 0.33 m result (an eleventh probe), where the 43 % in RTK fixed held four minutes of
#: passes. A quarter of a calibration drive is still minutes; a drive with less RTK is
#: calibrated on what it has, and says so.
_DEGRADED_MIN_SHARE = 0.25


def _degraded_fixes(status: F64, sigma_h: F64) -> np.ndarray:
    """(n,) True for the fixes of a mostly-RTK drive where the receiver lost its solution:
    status 0 (no augmentation) while at least a quarter of the fixes are augmented, or a
    declared horizontal sigma far above that of the drive's best quarter. Their decimetres
    to metres would pass into the radar's position one to one (an independent recording
    with three 20 s RTK dropouts: 2.4 -> 15.4 cm); left out, their radar frames have no pose
    and wait for the passes with a good one. A drive with less than a quarter in RTK keeps
    everything (and a note says so): nothing better is there."""
    # SBAS (status 1) is decimetres to a metre as well: in an RTK drive it is a lost
    # solution too (or RTK float); in a drive mostly without RTK only the standalone fixes
    # are worse
    rtk = status >= 2
    augmented = status > 0
    if rtk.mean() >= _DEGRADED_MIN_SHARE:
        degraded = ~rtk
    elif augmented.mean() >= _DEGRADED_MIN_SHARE:
        degraded = ~augmented
    else:
        return np.zeros(status.size, bool)
    known = np.isfinite(sigma_h)
    if known.sum() >= 2:
        best = float(np.quantile(sigma_h[known], _DEGRADED_MIN_SHARE))
        limit = max(_DEGRADED_SIGMA_M, _DEGRADED_SIGMA_RATIO * best)
        degraded |= known & (sigma_h > limit)
    # at least two fixes must stay
    return degraded if (~degraded).sum() >= 2 else np.zeros(status.size, bool)


#: Median disagreement of the Odometry heading with the course over ground above which the
#: orientation is not the vehicle's [rad], and the least moving samples to judge it on.
_ORIENTATION_TOLERANCE_RAD = math.radians(20.0)
_ORIENTATION_SAMPLES = 10
#: Forward speed of the twist below which the vehicle is taken to reverse [m/s].
_REVERSE_TWIST_MPS = 0.5


def _checked_orientation(t: F64, coarse: F64, measured: F64, positions: F64, yaw_true: F64,
                         lat: F64, lon: F64, frame: LocalFrame, min_speed: float,
                         counters: Counter[str], forward_mps: F64 | None = None,
                         rtk: bool = False) -> tuple[F64, float]:
    """(n,) local-grid heading from the Odometry orientation where it describes the
    vehicle's travel (less its constant offset, returned too: ``_heading_offset``), else
    from a compass-convention reading of it, else from the course over ground.

    Why: the heading turns the vehicle's box and its body-frame twist. Drivers in the field
    write a compass heading (clockwise from north) into the quaternion, or leave it the
    identity; both were taken at their word, the twist then failed its check and was blamed
    (fourth probe: 22 cm and a 66 cm sigma). Where the vehicle moves (speed above
    ``min_speed``, over +-1 s) the course over ground is its heading: forwards, or backwards
    where the twist's forward speed ``forward_mps`` says the vehicle reversed (a shuttle
    that backs through the view half the time had its right orientation condemned and
    faced the wrong way: 3 m off, an independent probe). The orientation is judged against
    both readings of the course, with and without those reversals (a twist in the wrong
    frame has no meaningful sign), and the better one counts. ``coarse`` and ``measured``
    are the positions' velocities over +-1 s and +-0.2 s. With ``rtk`` fixes, whose course
    is good to a tenth of a degree, a slowly wandering offset is followed too
    (``_heading_wander``).
    """
    yaw = frame.true_yaw_to_local(yaw_true, lat, lon)
    moving = np.hypot(coarse[:, 0], coarse[:, 1]) > max(min_speed, 2.0)
    if int(moving.sum()) < _ORIENTATION_SAMPLES:
        return yaw, 0.0
    course = np.arctan2(coarse[moving, 1], coarse[moving, 0])
    courses = [course]
    if forward_mps is not None:
        backwards = np.asarray(forward_mps, float)[moving] < -_REVERSE_TWIST_MPS
        if backwards.any():
            courses.append(course + np.pi * backwards)

    def disagreement(heading: F64) -> float:
        return min(_median_turn(heading[moving], c) for c in courses)

    as_given = disagreement(yaw)
    if as_given <= _ORIENTATION_TOLERANCE_RAD:
        # straight stretches only where it matters: turning, a reference point ahead of the
        # rear axle moves off the car's heading (1-3 deg at the centre of a car in a
        # junction turn)
        rate = np.gradient(np.unwrap(yaw), t) if t.size > 1 else np.zeros_like(t)
        speed = np.hypot(coarse[moving, 0], coarse[moving, 1])
        turning = ((np.abs(rate[moving]) >= _STRAIGHT_RATE_RPS)
                   | (np.abs(rate[moving]) >= _STRAIGHT_CURVATURE_PER_M * speed))
        # the course is taken over +-_TWIST_CHECK_SPAN_S: straight where all of it is
        t_moving = t[moving]
        if t_moving.size > 1:
            step = float(np.median(np.diff(t_moving)))
            width = 2 * int(math.ceil(_TWIST_CHECK_SPAN_S / max(step, 1e-3))) + 1
            turning = ndimage.maximum_filter1d(turning.astype(np.int8), width) > 0
        straight = ~turning
        offset = _heading_offset(yaw[moving], courses, counters, t[moving], straight)
        best = min(courses, key=lambda c: _median_turn(yaw[moving], c))
        wander = (_heading_wander(t[moving][straight],
                                  wrap_angle(yaw[moving] - offset - best)[straight], t,
                                  counters) if rtk else None)
        if wander is not None:
            return yaw - offset - wander, offset
        return yaw - offset, offset
    compass = frame.true_yaw_to_local(np.pi / 2.0 - yaw_true, lat, lon)
    if disagreement(compass) <= _ORIENTATION_TOLERANCE_RAD:
        counters['odometry_orientation_compass'] = 1
        _LOG.warning('the Odometry orientation reads as a compass heading (clockwise from '
                     'north), not as REP-103 yaw (counter-clockwise from east): used so')
        return compass, 0.0
    counters['odometry_orientation_replaced'] = 1
    _LOG.warning('the Odometry orientation does not describe the vehicle\'s travel (median '
                 '%.0f deg off its course over ground): the heading is taken from the course '
                 'over ground instead', math.degrees(as_given))
    return _course_over_ground(t, measured, min_speed, counters, positions)[0], 0.0


def _median_turn(heading: F64, course: F64) -> float:
    """Median absolute angle between a heading and a course [rad]."""
    return float(np.median(np.abs(wrap_angle(heading - course))))


#: A constant heading offset of the Odometry against the course over ground smaller than
#: this is left alone [rad] where it can only be measured over turns as well (a reference
#: point ahead of the rear axle leaves the heading by a degree or more there).
_HEADING_OFFSET_MIN_RAD = math.radians(1.0)
#: Where straight stretches show it (``_HEADING_WANDER_BIN_S`` bins of at least
#: ``_HEADING_WANDER_MIN_SAMPLES`` straight moving samples, ``_HEADING_OFFSET_MIN_BINS`` of
#: them), an offset is taken off from this size [rad], or from ``_HEADING_OFFSET_SE``
#: standard errors of the bins' median if that is more.
_HEADING_OFFSET_STRAIGHT_MIN_RAD = math.radians(0.1)
_HEADING_OFFSET_MIN_BINS = 3
_HEADING_OFFSET_SE = 3.0


def _heading_offset(heading: F64, courses: list[F64], counters: Counter[str],
                    t: F64 | None = None, straight: np.ndarray | None = None) -> float:
    """The Odometry heading's constant offset from the vehicle's travel [rad], 0 where it
    is too small to be told from the course's own error.

    Why: an INS whose yaw is not aligned with the car (mounted turned, or the heading of
    ``imu_link`` rather than the vehicle) turns the vehicle's box and its twist by that
    angle; 12-20 deg went unnoticed below the 20 deg check and put an independent probe's
    radar 0.5 m off at twice its sigma. A car drives where it faces (no crab angle), so the
    median of heading minus course over the moving samples is the offset; of the two
    readings of the course (with and without reversals) the one the heading agrees with.
    On straight stretches (``straight``, at times ``t``) the course is the heading to a
    few hundredths of a degree with RTK, and there even a fraction of a degree counts: a
    fifteenth probe's INS turned by 0.7-1.0 deg, measured at 0.9-1.0 deg over all samples
    and left alone below the 1 deg that turns need, put the radar 0.22-0.40 m off across
    its boresight (2.2-2.8 sigma) and its yaw 0.55 deg, with no word (about 0.35 m and
    0.55 deg per degree). Straight, the offset is the median of 10 s bins' medians, and it
    is taken off where it exceeds both 0.1 deg and three standard errors of that median
    (the bins' spread: a standalone fix's course, or an INS that wanders, widens it).
    """
    best = min(courses, key=lambda c: _median_turn(heading, c))
    residual = wrap_angle(heading - best)
    offset, threshold = float(np.median(residual)), _HEADING_OFFSET_MIN_RAD
    if t is not None and straight is not None and straight.any():
        medians, _ = _heading_bins(t[straight], residual[straight])
        if medians.size >= _HEADING_OFFSET_MIN_BINS:
            offset = float(np.median(medians))
            # standard error of a median: 1.25 sigma / sqrt(n), sigma from the bins' MAD
            threshold = max(_HEADING_OFFSET_STRAIGHT_MIN_RAD, _HEADING_OFFSET_SE * 1.2533
                            * _robust_sigma(medians) / math.sqrt(medians.size))
    if abs(offset) < threshold:
        return 0.0
    counters['odometry_heading_offset_cdeg'] = int(round(100.0 * math.degrees(offset)))
    _LOG.warning('the Odometry heading is %.2f deg off the vehicle\'s course over ground '
                 'throughout: taken off', math.degrees(offset))
    return offset


#: The Odometry heading's offset from the course over ground, in medians over bins of this
#: length [s] with at least this many straight moving samples, is taken as varying (and
#: followed) when those medians span more than ``_HEADING_WANDER_MIN_RAD`` (medians beyond
#: ``_HEADING_WANDER_MAX_RAD`` left out); straight is below ``_STRAIGHT_RATE_RPS`` of yaw
#: rate.
_HEADING_WANDER_BIN_S = 10.0
_HEADING_WANDER_MIN_SAMPLES = 20
_HEADING_WANDER_MIN_RAD = math.radians(0.6)
_HEADING_WANDER_MAX_RAD = math.radians(5.0)
_STRAIGHT_RATE_RPS = 0.05
#: ... and below this curvature [1/m] (yaw rate over speed): a bend driven slowly turns
#: slower than the rate above, while its course still leaves the heading by the reference
#: point's distance ahead of the rear axle over the radius (1.2 deg on a 70 m bend: a
#: seventeenth probe's exact Odometry on a bend was called wandering by 0.3-0.6 deg). At
#: 200 m, 1.5 m ahead is 0.4 deg, under ``_HEADING_WANDER_MIN_RAD``.
_STRAIGHT_CURVATURE_PER_M = 1.0 / 200.0


def _heading_bins(t_straight: F64, residual: F64) -> tuple[F64, F64]:
    """(medians of ``residual``, mean times) over the ``_HEADING_WANDER_BIN_S`` bins of the
    straight moving samples ``t_straight`` that hold ``_HEADING_WANDER_MIN_SAMPLES`` or
    more (empty where none does)."""
    label = np.floor((t_straight - t_straight[0]) / _HEADING_WANDER_BIN_S).astype(np.int64)
    used = np.flatnonzero(np.bincount(label) >= _HEADING_WANDER_MIN_SAMPLES)
    if used.size == 0:
        return np.zeros(0), np.zeros(0)
    return (np.asarray(ndimage.median(residual, labels=label, index=used), float),
            np.asarray(ndimage.mean(t_straight, labels=label, index=used), float))


def _heading_wander(t_straight: F64, residual: F64, t: F64, counters: Counter[str]
                    ) -> F64 | None:
    """(n,) the slowly varying part of the Odometry heading's offset from the course over
    ground at ``t``, or None where it does not vary.

    Why: an INS without a second antenna holds its heading by its gyro between manoeuvres,
    and it wanders by a degree or two over minutes (a twelfth probe: +-2 deg over 300 s put
    the radar 1 m too high and its pitch 1.9 deg off, far outside 2 sigma, with no word; a
    constant offset is taken off by ``_heading_offset``). The heading turns the vehicle's
    box and its twist, whose direction the radial velocities read against the radar's
    rotation. A car drives where it faces, so on straight stretches the course over ground
    (RTK, +-1 s) shows the heading's error to a tenth of a degree; its medians over
    ``_HEADING_WANDER_BIN_S`` are interpolated between (turns, stops) and held beyond the
    ends. ``residual`` is heading minus course (the constant offset already off) at the
    straight moving samples ``t_straight``.
    """
    if t_straight.size < 2 * _HEADING_WANDER_MIN_SAMPLES:
        return None
    medians, centres = _heading_bins(t_straight, residual)
    if medians.size < 2:
        return None
    # a heading further off is no drift but a broken orientation (an INS still aligning
    # writes the identity): what judges the orientation as a whole sees to it
    small = np.abs(medians) <= _HEADING_WANDER_MAX_RAD
    if small.sum() < 3:
        return None
    # a drift over minutes, not one bin's (the edge of a stretch where the orientation was
    # the identity, or the wrong way round)
    medians = ndimage.median_filter(medians[small], size=3, mode='mirror')
    centres = centres[small]
    if float(medians.max() - medians.min()) < _HEADING_WANDER_MIN_RAD:
        return None
    counters['odometry_heading_wander_cdeg'] = int(round(100.0 * math.degrees(
        float(np.max(np.abs(medians))))))
    _LOG.warning('the Odometry heading wanders by up to %.1f deg from the vehicle\'s course '
                 'over ground: followed', math.degrees(float(np.max(np.abs(medians)))))
    return np.interp(t, centres, medians)


def _level_twist(quaternion_xyzw: F64, yaw: F64, v_body: F64) -> F64:
    """(n, 3) body-frame twists turned into the level frame that shares the vehicle's
    heading: rotated by the full orientation, then back by its yaw.

    Why: REP-105's twist is along the vehicle's own axes, so on a grade its x is the speed
    along the slope, and the horizontal speed is shorter by the cosine of the pitch (0.18 %
    at 6 %). The final refinement takes the speed at its word, and a speed that much too
    high was absorbed by the dip of the radial velocities' line of sight: an independent
    recording on a 6 % road along a mid-block view came out 50 cm high and 30-45 cm off
    across the boresight, well outside its sigma. A level orientation changes nothing.
    """
    rot = Rotation.from_quat(quaternion_xyzw)
    return Rotation.from_euler('z', -yaw[:, None]).apply(rot.apply(v_body))


#: Orientation tilt [rad] above which the quaternions are taken to carry pitch and roll
#: (an INS's attitude); a heading-only orientation is level to rounding.
_TILT_CARRIED_RAD = math.radians(0.05)
#: Vertical sigma of the fixes [m] up to which their climb is trusted for the grade
#: (RTK: 2-5 cm; a standalone fix's metres would invent grades), and the largest grade
#: taken from it (a steeper one is the noise of a slow vehicle's altitude).
_GRADE_FIX_SIGMA_M = 0.1
_GRADE_MAX = 0.15


def _tilted(quaternion_xyzw: F64) -> bool:
    """True when any orientation is tilted out of the level (pitch or roll carried)."""
    z_axis = Rotation.from_quat(quaternion_xyzw).apply([0.0, 0.0, 1.0])
    return bool(np.any(np.arccos(np.clip(z_axis[:, 2], -1.0, 1.0)) > _TILT_CARRIED_RAD))


def _grade_cosine(t: F64, positions: F64, speed: F64,
                  fix_sigma: tuple[float, float] | None) -> F64:
    """(n,) cosine of the vehicle's pitch on the road's grade, from the fixes' climb over
    +-1 s against the twist's speed along the slope, for a twist whose orientation is
    heading-only; ones where the fixes are too coarse to say (no declared sigma, or a
    vertical sigma above ``_GRADE_FIX_SIGMA_M``)."""
    if fix_sigma is None or not fix_sigma[1] <= _GRADE_FIX_SIGMA_M:
        return np.ones(t.size)
    climb = _finite_difference(t, positions[:, 2], _TWIST_CHECK_SPAN_S)
    sine = np.clip(climb / np.maximum(speed, 1e-9), -_GRADE_MAX, _GRADE_MAX)
    sine[speed < _TWIST_CHECK_SPEED_MPS] = 0.0
    return np.sqrt(1.0 - sine ** 2)


def _interp_angle(tq: F64, t: F64, angle: F64) -> F64:
    """Interpolate an angle series on the circle; result wrapped to [-pi, pi)."""
    unwrapped = np.unwrap(angle)
    return (np.interp(tq, t, unwrapped) + np.pi) % (2.0 * np.pi) - np.pi


#: The Odometry twist is trusted where it agrees with the motion of the positions to within
#: this (m/s) or this fraction of the median speed, whichever is larger (RTK positions
#: differentiated over 0.4 s: ~0.1 m/s; a standalone fix at 1 Hz: ~1 m/s).
_TWIST_TOLERANCE_MPS = 0.5
_TWIST_TOLERANCE_FRACTION = 0.2
#: Half span of the positions' differences the twist is judged against [s].
_TWIST_CHECK_SPAN_S = 1.0
#: Fewest samples of a moving vehicle (above this speed, m/s) to judge the twist on.
_TWIST_CHECK_SPEED_MPS = 2.0
_TWIST_CHECK_SAMPLES = 10


def _position_velocities(t: F64, positions: F64, half_span_s: float = 0.2) -> F64:
    """(n, k) velocities of positions (n, k) by central differences (``_finite_difference``)."""
    return np.column_stack([_finite_difference(t, positions[:, i], half_span_s)
                            for i in range(positions.shape[1])])


#: Latency of the fixes against the Odometry looked for [s] (a receiver at 1 Hz that stamps
#: on output, or an Odometry stamped as late: a ninth probe's 1 s), its grid step [s], the
#: smallest worth correcting [s] (a few centimetres of travel at urban speed), and how many
#: standard errors it must stand clear of zero.
_FIX_LAG_MAX_S = 1.2
_FIX_LAG_STEP_S = 0.01
_FIX_LAG_MIN_S = 0.02
_FIX_LAG_SIGMAS = 5.0
#: Fix velocities beyond this rate [Hz] add nothing to the lag's search (see ``_fix_lag``).
_FIX_LAG_RATE_HZ = 10.0
#: Grid steps between the lags searched first (see ``_fix_lag``).
_FIX_LAG_COARSE = 4


@dataclass(frozen=True)
class FixAgainstOdometry:
    """What the fixes' motion shows against the Odometry's (``_fix_lag``): the lag of their
    stamps [s] (0.0 when not clear), and the horizontal lever arm of the fixes' point from
    the Odometry's in the vehicle frame [m] (forward, left; None when not clear)."""

    lag_s: float = 0.0
    lever_arm_m: tuple[float, float] | None = None


#: A lever arm between the fixes' point and the Odometry's is reported when at least this
#: long [m] (a roof antenna above the rear axle: 1-2 m) and this many standard errors.
_LEVER_ARM_MIN_M = 0.3
_LEVER_ARM_SIGMAS = 5.0


def _lever_columns(rate: F64, heading: F64) -> F64:
    """(n, 2, 2): d(world velocity of a point)/d(lever arm forward, left) of a vehicle
    turning at ``rate`` [rad/s] on ``heading``: omega x l, turned into the world."""
    c, s = np.cos(heading), np.sin(heading)
    cols = np.empty((rate.size, 2, 2))
    cols[:, 0, 0], cols[:, 0, 1] = -rate * s, -rate * c
    cols[:, 1, 0], cols[:, 1, 1] = rate * c, -rate * s
    return cols


def _fix_lag(t: F64, v_fix: F64, to: F64, yaw: F64, v_level: F64,
             rate: F64 | None = None) -> FixAgainstOdometry:
    """Seconds by which the fixes' stamps lag the Odometry's, and the lever arm between
    the points the two describe, where the data show them clearly.

    Why the lag: a GNSS receiver that stamps a fix when it outputs it, not at its epoch, is
    50-200 ms late, while the INS beside it is on time. The fixes then place the vehicle
    that far behind itself along its path, an offset that turns with every pass and that
    no radar clock offset can take up (an independent recording: 0.73 m along the
    boresight, reported at 0.17 m, where the same data on one clock gave 0.34 m). The lag
    shows wherever the vehicle accelerates or turns: the fixes' velocity follows the
    Odometry's that much later. It is found on a grid of lags by least squares, refined by
    a parabola, and taken when it is at least ``_FIX_LAG_MIN_S`` and ``_FIX_LAG_SIGMAS``
    standard errors (the fixes' velocities over +-0.2 s are correlated over that span,
    which the error counts). A twist that does not describe the motion at all (zero,
    another frame, a compass heading) shows no clear minimum and is left to
    ``_checked_twist``.

    Why the lever arm: a NavSatFix of the roof antenna beside an Odometry of the rear axle
    (a tenth probe) moves faster on the outside of every turn (omega x l). Unmodelled, a
    lever arm 1 m forward passed for a fix lag of -46 ms and was 'corrected' in time. It
    is fitted with the lag (``rate``, the Odometry's yaw rate, makes it observable) and
    reported: the contract takes the fixes' point as the vehicle's reference point, and
    whether ``vehicle.*`` describes that point only the user knows.
    """
    if t.size < 50 or to.size < 50:
        return FixAgainstOdometry()
    v_odom = _turned(v_level, yaw)
    margin = _FIX_LAG_MAX_S + 0.2
    use = ((np.hypot(v_fix[:, 0], v_fix[:, 1]) > _TWIST_CHECK_SPEED_MPS)
           & (t - margin > to[0]) & (t + margin < to[-1]))
    if int(use.sum()) < 50:
        return FixAgainstOdometry()
    # Velocities over +-0.2 s are correlated over that span: every fifth of a 50 Hz drive
    # says as much and makes the two grid searches below five times cheaper (2.4 s of a
    # fifteen-minute recording's read otherwise)
    use = np.flatnonzero(use)
    use = use[::max(1, int(use.size / max(float(t[use[-1]] - t[use[0]]), 1e-9)
                           / _FIX_LAG_RATE_HZ))]
    tu, vu = t[use], v_fix[use]
    rate = np.zeros(to.size) if rate is None else rate
    unwrapped = np.unwrap(yaw)
    rate_hz = (tu.size - 1) / max(float(tu[-1] - tu[0]), 1e-9)
    correlated = max(1.0, 0.4 * rate_hz)

    def odom_at(tq: F64) -> F64:
        return np.column_stack([np.interp(tq, to, v_odom[:, i]) for i in range(2)])

    def matched_at(lag: float, with_arm: bool) -> tuple[F64, tuple[F64, F64] | None]:
        """The Odometry's velocity at the fixes' times minus ``lag``, turned by the angle
        that fits the fixes' best (an INS heading offset, ``_heading_offset``, must not
        pass for a lag: on a steady turn the two are one), plus (``with_arm``) the lever
        arm that fits best; also that lever arm and its (2, 2) normal matrix (None without
        one, or where the turns do not determine it)."""
        v = odom_at(tu - lag)
        angle = math.atan2(float(np.sum(v[:, 0] * vu[:, 1] - v[:, 1] * vu[:, 0])),
                           float(np.sum(v[:, 0] * vu[:, 0] + v[:, 1] * vu[:, 1])))
        v = _turned(v, angle)
        if not with_arm:
            return v, None
        cols = _lever_columns(np.interp(tu - lag, to, rate),
                              np.interp(tu - lag, to, unwrapped) + angle)
        normal = np.einsum('nki,nkj->ij', cols, cols)
        if np.linalg.cond(normal) > 1e8:
            return v, None
        arm = np.linalg.solve(normal, np.einsum('nki,nk->i', cols, vu - v))
        return v + cols @ arm, (arm, normal)

    lags = np.arange(-_FIX_LAG_MAX_S, _FIX_LAG_MAX_S + 1e-9, _FIX_LAG_STEP_S)
    speed = float(np.median(np.hypot(vu[:, 0], vu[:, 1])))
    tolerance = max(_TWIST_TOLERANCE_MPS, _TWIST_TOLERANCE_FRACTION * speed)

    def best_lag(with_arm: bool) -> float | None:
        """The lag of least misfit (a parabola through the grid's best three), None without
        a clear minimum. The grid is searched every ``_FIX_LAG_COARSE`` steps first, then
        step by step around the best of those (the misfit is smooth over a tenth of a
        second: a turn or a braking takes longer)."""
        def misfit(lag: float) -> float:
            return float(np.mean((vu - matched_at(lag, with_arm)[0]) ** 2))

        coarse = np.arange(0, lags.size, _FIX_LAG_COARSE)
        best = int(coarse[np.argmin([misfit(lags[i]) for i in coarse])])
        near = np.arange(max(best - _FIX_LAG_COARSE, 0),
                         min(best + _FIX_LAG_COARSE, lags.size - 1) + 1)
        cost = np.full(lags.size, np.inf)
        cost[near] = [misfit(lags[i]) for i in near]
        k = int(np.argmin(cost))
        while 0 < k < lags.size - 1:
            # on to the nearest local minimum should the search's edge hold the best
            for i in (k - 1, k + 1):
                if not np.isfinite(cost[i]):
                    cost[i] = misfit(lags[i])
            step = int(np.argmin(cost[k - 1:k + 2])) - 1
            if step == 0:
                break
            k += step
        if k in (0, lags.size - 1) or cost[k] > tolerance ** 2:
            return None
        curvature = cost[k - 1] - 2.0 * cost[k] + cost[k + 1]
        if curvature <= 0.0:
            return None
        return float(lags[k] + 0.5 * _FIX_LAG_STEP_S * (cost[k - 1] - cost[k + 1]) / curvature)

    # with a lever arm first; where none shows, the lag alone (a free lever arm of a few
    # centimetres moved the slow_gnss scenario's lag from 118 to 127 ms; the truth is 120)
    lever_arm = None
    lag = best_lag(True)
    if lag is not None:
        matched, fitted = matched_at(lag, True)
        if fitted is not None:
            arm, normal = fitted
            variance = float(np.mean((vu - matched) ** 2))
            arm_se = np.sqrt(np.diag(np.linalg.inv(normal)) * variance * correlated)
            length = float(np.hypot(*arm))
            if length >= _LEVER_ARM_MIN_M and length >= _LEVER_ARM_SIGMAS * float(
                    np.hypot(*arm_se)):
                lever_arm = (float(arm[0]), float(arm[1]))
            _LOG.debug('lever arm of the fixes from the Odometry %s +- %s m',
                       np.round(arm, 3), np.round(arm_se, 3))
    if lever_arm is None:
        lag = best_lag(False)
        if lag is None:
            return FixAgainstOdometry()
        matched, _ = matched_at(lag, False)
    residual = vu - matched
    variance = float(np.mean(residual ** 2))
    # standard error of a one-parameter least squares: residual variance over the summed
    # squared sensitivity (the Odometry's acceleration), with samples 0.4 s apart independent
    acc = np.column_stack([np.gradient(matched[:, i], tu) for i in range(2)])
    # the part of the lag's sensitivity that the turn's angle cannot take up: on a steady
    # circle the acceleration lies along the turn's (perpendicular to the velocity) and a
    # lag says nothing
    perp = np.column_stack([-matched[:, 1], matched[:, 0]])
    along_turn = float(np.sum(acc * perp)) ** 2 / max(float(np.sum(perp ** 2)), 1e-12)
    information = max(float(np.sum(acc ** 2)) - along_turn, 0.0) / correlated
    if information <= 0.0:
        return FixAgainstOdometry(0.0, lever_arm)
    se = math.sqrt(variance / information)
    if abs(lag) < _FIX_LAG_MIN_S or abs(lag) < _FIX_LAG_SIGMAS * se:
        _LOG.debug('fix lag against the Odometry %.1f +- %.1f ms: not taken', 1e3 * lag,
                   1e3 * se)
        return FixAgainstOdometry(0.0, lever_arm)
    _LOG.debug('fix lag against the Odometry %.1f +- %.1f ms', 1e3 * lag, 1e3 * se)
    return FixAgainstOdometry(lag, lever_arm)


#: A twist this many times the positions' speed is in km/h, give or take the tolerance.
_KMH_PER_MPS = 3.6
_KMH_TOLERANCE = 0.25


def _speed_ratio(twist_world: F64, velocities: F64, moving: np.ndarray) -> float:
    """Median ratio of a world twist's speed to the positions' ``velocities`` (over +-0.2 s:
    the +-1 s ones cut the corners of a turn) where moving (0 if never)."""
    speed = np.hypot(velocities[:, 0], velocities[:, 1])
    moving = moving & (speed > 0.0)
    if not moving.any():
        return 0.0
    return float(np.median(np.hypot(twist_world[moving, 0], twist_world[moving, 1])
                           / speed[moving]))


def _twist_mismatch(twist_world: F64, coarse: F64) -> float:
    """Median distance of a world twist from the positions' velocities where moving."""
    moving = np.hypot(coarse[:, 0], coarse[:, 1]) > _TWIST_CHECK_SPEED_MPS
    if not moving.any():
        return 0.0
    return float(np.median(np.linalg.norm(twist_world[moving] - coarse[moving], axis=1)))


def _checked_twist(t: F64, positions: F64, measured: F64, coarse: F64, twist_world: F64,
                   twist_as_given: F64, counters: Counter[str], yaw_rate: F64) -> F64:
    """(n, 3) vehicle velocities: the Odometry twist where it describes the motion of the
    positions, else what does; a twist speed clearly off the positions' is rescaled to them
    (``_speed_scale``).

    The radial-velocity constraint of the final refinement takes the vehicle's velocity at
    its word, so a twist that is not the vehicle's body-frame velocity would turn the
    radar's yaw. Drivers in the field get this wrong in two ways: the twist is left zero,
    or it is published in the parent (ENU) frame instead of ``child_frame_id`` as REP-105
    asks. Both are told from the positions' own motion; what matches is used (the ENU
    reading as it is, else the positions' central differences) and a warning says so.
    ``measured`` and ``coarse`` are the positions' velocities over +-0.2 s (3-D) and +-1 s
    (horizontal, the check's: see ``_build_vehicle``).
    """
    speed = np.hypot(coarse[:, 0], coarse[:, 1])
    moving = speed > _TWIST_CHECK_SPEED_MPS
    if int(moving.sum()) < _TWIST_CHECK_SAMPLES:
        return np.column_stack([twist_world, measured[:, 2]])
    tolerance = max(_TWIST_TOLERANCE_MPS,
                    _TWIST_TOLERANCE_FRACTION * float(np.median(speed[moving])))

    body, enu = _twist_mismatch(twist_world, coarse), _twist_mismatch(twist_as_given, coarse)
    if body <= tolerance:
        scale = _speed_scale(t, positions, twist_world, moving, yaw_rate)
        if scale != 1.0:
            counters['odometry_speed_scale_permille'] = int(round(1000.0 * (scale - 1.0)))
            _LOG.warning('the Odometry twist speed is %.1f %% off the positions\' on straight '
                         'driving: rescaled to them', 100.0 * (1.0 / scale - 1.0))
        return np.column_stack([scale * twist_world, measured[:, 2]])
    kmh = twist_world / _KMH_PER_MPS
    if (abs(_speed_ratio(twist_world, measured[:, :2], moving) - _KMH_PER_MPS) <= _KMH_TOLERANCE
            and _twist_mismatch(kmh, coarse) <= tolerance):
        # a driver that writes km/h (a tenth probe's): 3.6 times the fixes' speed, and
        # right once divided; better than the positions' differences, and said
        counters['odometry_twist_kmh'] = 1
        _LOG.warning('the Odometry twist is 3.6 times the positions\' speed: read as km/h')
        scale = _speed_scale(t, positions, kmh, moving, yaw_rate)
        return np.column_stack([scale * kmh, measured[:, 2]])
    if enu <= tolerance:
        counters['odometry_twist_in_parent_frame'] = 1
        _LOG.warning('the Odometry twist describes the vehicle\'s motion only read in the '
                     'parent (ENU) frame (median mismatch %.2f m/s, as the child frame %.2f '
                     'm/s): it is used so; REP-105 puts it in child_frame_id', enu, body)
        return np.column_stack([twist_as_given, measured[:, 2]])
    counters['odometry_twist_replaced'] = 1
    _LOG.warning('the Odometry twist does not describe the vehicle\'s motion (median mismatch '
                 '%.2f m/s against the positions, tolerance %.2f m/s): the velocity is taken '
                 'from the positions instead', body, tolerance)
    return measured


#: Straight driving for the speed-scale check [rad/s]; shortest straight stretch [s]; the
#: distance driven on such stretches needed to judge [m]; smallest correction.
_SCALE_STRAIGHT_RPS = 0.05
_SCALE_STRETCH_S = 5.0
_SCALE_DISTANCE_M = 100.0
_SCALE_MIN = 0.003
#: A gap between fixes this long ends a straight stretch [s] (fixes come at 1-50 Hz).
_SCALE_GAP_S = 2.5


def _speed_scale(t: F64, positions: F64, twist_world: F64, moving: np.ndarray,
                 yaw_rate: F64) -> float:
    """Factor that brings the twist's speed to the fixes' (1.0 when they agree).

    Why: the final refinement's radial-velocity fit takes the vehicle's speed at its word,
    and a speed 1 % off (wheel odometry) tilts the fitted pitch by about half a degree
    (seen on an independent recording), 0.3 % by about 0.15 deg. On every straight stretch
    of at least ``_SCALE_STRETCH_S`` the distance the fixes travelled (their path sampled
    once a second: 2 cm of RTK noise over 10 m steps adds nothing) is compared with the
    twist's speed integrated over the same time; the ratio of the sums is the scale, and
    the spread of the stretches' ratios its standard error. (A median of instantaneous
    speed ratios, used before, was itself 0.3 % off on our simulator's exact twist when
    the speed varied, and could only judge errors of 0.6 % and more; this estimate reads
    0.01-0.13 % there.) Corrected when off by ``_SCALE_MIN`` and three standard errors:
    standalone fixes are too noisy to say.
    """
    speed_twist = np.hypot(twist_world[:, 0], twist_world[:, 1])
    use = moving & (np.abs(yaw_rate) < _SCALE_STRAIGHT_RPS) & (speed_twist > 0.5)
    # A stretch ends where the fixes stop: across an outage the vehicle drove on unseen
    # (turned, looped) and the chord from the last fix to the next says nothing of its
    # path; a twenty-third probe's 4-8 s outages between passes read an exact twist as
    # 11-16 % off, 'rescaled' it, and failed the calibration.
    after_gap = np.concatenate([[True], np.diff(t) > _SCALE_GAP_S])
    start = use & (after_gap | ~np.concatenate([[False], use[:-1]]))
    end = use & np.concatenate([start[1:] | ~use[1:], [True]])
    paths, integrals = [], []
    for a, b in zip(np.flatnonzero(start), np.flatnonzero(end)):
        if t[b] - t[a] < _SCALE_STRETCH_S:
            continue
        idx = np.unique(np.concatenate([np.searchsorted(t, np.arange(t[a], t[b], 1.0)),
                                        [b]]))
        # pieces of about 10 s: their spread gives the standard error even on one stretch
        for piece in np.array_split(idx, max(1, round((t[b] - t[a]) / (2 * _SCALE_STRETCH_S)))):
            if piece.size < 2:
                continue
            step = np.diff(positions[piece, :2], axis=0)
            paths.append(float(np.sum(np.hypot(step[:, 0], step[:, 1]))))
            lo, hi = int(piece[0]), int(piece[-1]) + 1
            integrals.append(float(np.sum(0.5 * (speed_twist[lo + 1:hi]
                                                 + speed_twist[lo:hi - 1]) * np.diff(t[lo:hi]))))
    path, integral = np.array(paths), np.array(integrals)
    if path.size < 2 or integral.sum() < _SCALE_DISTANCE_M:
        return 1.0
    scale = float(path.sum() / integral.sum())
    # weighted spread of the stretches' ratios -> standard error of the ratio of sums
    ratio = path / integral
    weight = integral / integral.sum()
    spread = math.sqrt(float(np.sum(weight * (ratio - scale) ** 2)) / (1.0 - np.sum(weight ** 2)))
    se = spread * math.sqrt(float(np.sum(weight ** 2)))
    if abs(scale - 1.0) > max(_SCALE_MIN, 3.0 * se):
        return scale
    return 1.0


def _finite_difference(t: F64, x: F64, half_span_s: float = 0.2) -> F64:
    """Central difference over about +-half_span_s: RTK noise (~2 cm) differentiated over
    one 20 ms step would be ~1.4 m/s of noise; over 0.4 s it is ~0.07 m/s, while the lag
    on a 10 m/s, 15 m radius turn stays a few centimetres per second.

    Always at least one sample either side (one-sided only at the ends): with samples
    sparser than the span (fixes at 1-4 Hz) a forward difference is the velocity half an
    interval later, which the fix-lag check read as fixes 125-500 ms early and 'corrected'
    (a ninth probe: 0.66-1.1 m off along the boresight)."""
    if t.size < 2:
        return np.zeros_like(x)
    index = np.arange(t.size)
    lo = np.searchsorted(t, t - half_span_s, side='left')
    hi = np.searchsorted(t, t + half_span_s, side='right') - 1
    lo = np.minimum(lo, np.maximum(index - 1, 0))
    hi = np.maximum(hi, np.minimum(index + 1, t.size - 1))
    dt = t[hi] - t[lo]
    with np.errstate(divide='ignore', invalid='ignore'):
        v = np.where(dt > 0, (x[hi] - x[lo]) / dt, 0.0)
    return v


#: The course over ground is summed over the time the vehicle takes for this distance
#: [m] either side, within these bounds [s] (see ``_course_over_ground``).
_COURSE_SPAN_M = 2.0
_COURSE_HALF_SPAN_S = (0.2, 0.5)


def _course_over_ground(t: F64, velocities: F64, min_speed: float,
                        counters: Counter[str], positions: F64) -> tuple[F64, F64]:
    """Heading from the course over ground where the speed allows it, held (interpolated
    on the circle) across slow and stopped stretches where the course is noise.

    The course is the direction of the speed-weighted sum of the velocities of the usable
    samples within +-``_COURSE_SPAN_M`` of travel (+-0.2 to 0.5 s): right where the vehicle
    slows through ``min_speed`` a single 0.4 s difference spans only ~0.4 m, so 2 cm of RTK
    noise turns it by ~4 deg; the weighted sum leans on the faster neighbours instead. At
    speed the window shrinks: a car weaving in its lane (+-0.5 m over 25 m) turns its
    heading by +-7 deg within 2.5 s, which +-0.5 s flattened by a quarter (a twelfth
    probe's NavSatFix-only weaving: 21-35 cm along the boresight). A symmetric window adds
    no lag on a steady turn.
    """
    speed = np.hypot(velocities[:, 0], velocities[:, 1])
    good = speed >= min_speed
    weighted = np.where(good[:, None], velocities[:, :2] * speed[:, None], 0.0)
    sums = np.vstack([np.zeros((1, 2)), np.cumsum(weighted, axis=0)])
    half_span_s = np.clip(_COURSE_SPAN_M / np.maximum(speed, 1e-6), *_COURSE_HALF_SPAN_S)
    lo = np.searchsorted(t, t - half_span_s, side='left')
    hi = np.searchsorted(t, t + half_span_s, side='right')
    smoothed = sums[hi] - sums[lo]
    course = np.arctan2(smoothed[:, 1], smoothed[:, 0])
    course = course + np.pi * _reversing(t, course, good, speed, positions, counters)
    if good.sum() >= 2:
        yaw = _interp_angle(t, t[good], course[good])
    elif good.any():
        yaw = np.full_like(t, course[good][0])
    else:
        yaw = np.zeros_like(t)
    yaw_rate = _finite_difference(t, np.unwrap(yaw))
    return yaw, yaw_rate


#: A stop across which the course turns by more than this is a change of gear (a car cannot
#: turn while standing) [rad]; the most the vehicle may move during such a stop [m].
_REVERSE_FLIP_RAD = math.radians(135.0)
_REVERSE_STOP_MOVE_M = 3.0


def _reversing(t: F64, course: F64, good: np.ndarray, speed: F64, positions: F64,
               counters: Counter[str]) -> np.ndarray:
    """(n,) True where the vehicle, by its course over ground alone, drove backwards.

    Why: with fixes alone the heading is the course over ground, which points backwards
    while the vehicle reverses, and its box then faces the wrong way (a shuttle that backed
    through the view: 1.7-1.9 m off, outside 2 sigma, an independent probe). A car cannot
    turn while it stands, so a stop (or a slowing below ``min_speed``) across which the
    course turns by more than ``_REVERSE_FLIP_RAD`` while the vehicle stays within
    ``_REVERSE_STOP_MOVE_M`` is a change of gear: the runs of driving on either side face
    the same way, one of them backwards. Which one is told by distance driven: a calibration
    vehicle drives forwards most of the way (on a tie, the faster runs are the forward
    ones). Runs joined by no such stop keep their course.
    """
    reverse = np.zeros(t.size, bool)
    idx = np.flatnonzero(good)
    if idx.size < 2:
        return reverse
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    if starts.size < 2:
        return reverse
    turn = np.abs(wrap_angle(course[starts[1:]] - course[ends[:-1]]))
    moved = np.linalg.norm(positions[starts[1:], :2] - positions[ends[:-1], :2], axis=1)
    flip = (turn > _REVERSE_FLIP_RAD) & (moved < _REVERSE_STOP_MOVE_M)
    if not flip.any():
        return reverse
    # direction of each run within chains of runs joined by gear changes; a chain is broken
    # where the stop between runs says nothing (the vehicle moved, or the course went on)
    gear_change = np.concatenate([[False], flip])
    chain = np.cumsum(~gear_change)
    parity = np.cumsum(gear_change) % 2
    dt = np.gradient(t)
    distance = np.array([float(np.sum(speed[a:b + 1] * dt[a:b + 1]))
                         for a, b in zip(starts, ends)])
    duration = np.array([float(np.sum(dt[a:b + 1])) for a, b in zip(starts, ends)])
    backwards_run = np.zeros(starts.size, bool)
    for c in np.unique(chain[gear_change]):
        runs = np.flatnonzero(chain == c)
        odd = parity[runs] == 1
        d_odd, d_even = distance[runs][odd].sum(), distance[runs][~odd].sum()
        if math.isclose(d_odd, d_even, rel_tol=0.1):
            v_odd = d_odd / max(duration[runs][odd].sum(), 1e-9)
            v_even = d_even / max(duration[runs][~odd].sum(), 1e-9)
            odd_forward = v_odd > v_even
            counters['vehicle_reversed_ambiguous'] += 1
        else:
            odd_forward = d_odd > d_even
        backwards_run[runs] = odd != odd_forward
    for k in np.flatnonzero(backwards_run):
        reverse[starts[k]:ends[k] + 1] = True
    counters['vehicle_reversed_stretches'] += int(backwards_run.sum())
    counters['vehicle_reversed_m'] += int(round(float(distance[backwards_run].sum())))
    return reverse
