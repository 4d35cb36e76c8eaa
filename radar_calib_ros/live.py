"""The calibrator node's logic, without rclpy: buffer, trigger, outputs.

``node.py`` is a thin adapter: it hands every received message to :class:`LiveCalibrator`
and publishes the plain values this module returns (:class:`TransformOutput`,
:class:`DiagnosticStatusOutput`). Everything that can be wrong with live input is decided
here, so it is tested without a ROS install, with the rosbags message classes of ROS 2
Jazzy as input (the decoders read only attributes rclpy messages have as well).

Threading model (the node runs a multi-threaded executor): the subscription callbacks run
one at a time, while ``calibrate``, ``reset`` and ``save_recording`` may run in other
threads at the same time. Every access to the buffer holds ``_buffer_lock`` for a few
microseconds only: ``calibrate`` copies the buffer's lists under it
(``RecordingBuilder.snapshot``) and builds and calibrates outside it, so messages keep
being buffered meanwhile. ``_calibration_lock`` refuses a second concurrent ``calibrate``.

Stamps that jump backwards (a bag replayed in a loop, a restarted driver): **treated as a
new recording**. When one stream's header stamps go back by more than
``BACKWARD_TOLERANCE_NS`` and ``CONFIRM_MESSAGES`` consecutive messages agree, its new
messages are held while another stream goes on on its old stamps (up to
``AWAIT_RESTART_S``); once none does (the others jumped too, or went silent), the buffer is
emptied and refilled from the new stamps on; messages of the other streams still stamped
in the old recording are rejected as ``stale`` until their own stream has jumped back too.
Where the others go on and never jump, the stream's clock stepped (or it re-sent old
messages): what it held is buffered and the buffer kept. Rejecting the stale data
instead would freeze the node for good at the first loop of a replayed bag (every later
message would be older than the newest buffered one), so the latest loop is kept: a
calibration triggered after a full loop calibrates on it.
A single message stamped far off (a corrupt stamp) is not believed: it is held until
confirmed and otherwise rejected as ``stamp_outlier``, so one bad stamp can neither empty
the buffer nor push the ``buffer.max_duration`` window past the real data.
"""
from __future__ import annotations

import datetime as _dt
import logging
import math
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import CalibrationError, DecodeError, InsufficientDataError
from radar_calib_ros.io import messages as msgs
from radar_calib_ros.io.bag import write_bag
from radar_calib_ros.recording import RecordingBuilder
from radar_calib_ros.result import STAMP_FORMAT, load_result, parse_stamp, write_result_yaml
from radar_calib_ros.types import FixSample, OdomSample, QualityReport, RadarFrame

if TYPE_CHECKING:
    from radar_calib_ros.pipeline import CalibrationResult

    #: What ``run_calibration`` looks like (injectable for tests): called as
    #: ``run(recording, config, progress=progress)``.
    RunFn = Callable[..., CalibrationResult]

__all__ = ['CalibrationCancelled', 'DiagnosticStatusOutput', 'LiveCalibrator', 'LogFn',
           'LogForwarder', 'STREAMS', 'TransformOutput', 'TriggerOutcome']

_LOG = logging.getLogger(__name__)

#: ``log(severity, message)`` with severity one of 'debug', 'info', 'warn', 'error'.
LogFn = Callable[[str, str], None]

#: The three input streams, named as in the diagnostics counters.
STREAMS = ('radar', 'navsat', 'odom')

#: A stream going back in its own header stamps by more than this is a jump (less is
#: out-of-order delivery, accepted: the Recording is sorted when it is built).
BACKWARD_TOLERANCE_NS = 2_000_000_000
#: A stream going forward by more than this in one step is a jump too (a corrupt stamp or a
#: long outage); a confirmed forward jump is a gap, not a new recording.
FORWARD_GAP_NS = 120_000_000_000
#: Consecutive, mutually consistent messages that confirm a jump.
CONFIRM_MESSAGES = 3
#: After a new recording started, how long another stream may keep sending old stamps
#: before its next message is taken as it is [s, monotonic].
AWAIT_RESTART_S = 10.0
#: Repeated warnings of one kind are logged at most this often [s].
WARN_THROTTLE_S = 60.0
#: The buffer.max_duration window is enforced with this slack, so that the O(n) drop runs
#: once per slack span of data, not once per message.
_DURATION_SLACK = 0.02
#: When the memory bound is hit, the oldest data are dropped down to this fraction of it.
_MEMORY_REFILL = 0.9

Sample = RadarFrame | FixSample | OdomSample


class CalibrationCancelled(InsufficientDataError):
    """A running calibration was stopped because the node shuts down."""


@dataclass(frozen=True, slots=True)
class TransformOutput:
    """The calibration as a transform, world (parent) -> radar (child), plain values.

    translation_m : (x, y, z) of the radar in the world frame [m] (UTM easting, northing,
    ellipsoidal altitude); quaternion_xyzw : rotation sensor -> world; stamp_ns : when it
    was computed (the stamp of the published TransformStamped).
    """

    parent_frame: str
    child_frame: str
    translation_m: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]
    stamp_ns: int


@dataclass(frozen=True, slots=True)
class DiagnosticStatusOutput:
    """One diagnostic_msgs/DiagnosticStatus as plain values; level 'OK', 'WARN' or 'ERROR'."""

    name: str
    level: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...]


@dataclass(frozen=True, slots=True)
class TriggerOutcome:
    """Answer to a std_srvs/Trigger service; ``transform`` is set when there is a new
    calibration to publish."""

    success: bool
    message: str
    transform: TransformOutput | None = None


@dataclass(slots=True)
class _StreamState:
    """Stamp bookkeeping of one input stream (see the module docstring)."""

    last_ns: int | None = None
    held: list[tuple[int, Sample]] = field(default_factory=list)
    awaiting_since: float | None = None
    # a confirmed backward jump of this stream alone, held while the others continue
    pending_since: float | None = None
    seen_s: float | None = None


class LiveCalibrator:
    """Buffers decoded messages, calibrates on request, keeps the outputs.

    Parameters
    ----------
    config : CalibConfig
        Validated configuration (``CalibConfig.from_mapping``).
    log : LogFn
        Where log lines go; the node passes its rclpy logger.
    now_ns : callable() -> int, default=time.time_ns
        Clock for the stamp of a new calibration and for the receipt of each message (the
        node passes its ROS clock: replaying a bag with use_sim_time, the bag's record time).
    monotonic : callable() -> float, default=time.monotonic
        Clock for throttling warnings and for timeouts [s].
    run : callable(Recording, CalibConfig, progress=...) -> CalibrationResult, optional
        The pipeline, default ``pipeline.run_calibration`` (tests may pass a stand-in).
    name : str, default='radar_calib'
        Prefix of the diagnostic status names (the node passes its fully qualified name).

    Notes
    -----
    Memory: the buffer holds every target at the message's precision (16 bytes with its
    radial velocity in float32, 32 in float64) plus about 200 bytes per radar frame and
    120 / 400 bytes per fix / odometry sample; ``buffer.max_memory_mb`` bounds it. A
    calibration builds its arrays from a snapshot and needs about 8-9 times the buffer's
    memory while it runs (a probe's 10 minutes of an 800-target imaging radar: 161 MiB
    buffered, 1.3 GB at the peak), which the bound does not cover.
    """

    def __init__(self, config: CalibConfig, *, log: LogFn,
                 now_ns: Callable[[], int] = time.time_ns,
                 monotonic: Callable[[], float] = time.monotonic,
                 run: RunFn | None = None, name: str = 'radar_calib') -> None:
        if run is None:
            # imported here: the pipeline pulls in every stage (scipy, sklearn, filterpy)
            from radar_calib_ros.pipeline import run_calibration
            run = run_calibration
        self._config = config
        self._log = log
        self._now_ns = now_ns
        self._monotonic = monotonic
        self._run = run
        self._name = name
        self._buffer_lock = threading.Lock()
        self._calibration_lock = threading.Lock()
        self._builder = RecordingBuilder(config)
        self._streams = {stream: _StreamState() for stream in STREAMS}
        # each stream's (oldest, newest) buffered stamp: the window is held per stream, as
        # a radar's stamps may run on another clock than the vehicle's
        self._ranges: dict[str, tuple[int, int]] = {}
        # the frame of the buffered radar clouds (the first one's; see msgs.other_radar)
        self._radar_frame: str | None = None
        self.counters: Counter[str] = Counter()
        # the counters when the buffer was last emptied: a failure names what was lost
        # from the data it had, not since the start (a probe read an earlier replay's)
        self._counters_at_clear: Counter[str] = Counter()
        self._throttle: dict[str, list[float]] = {}
        self._last_rejection_s = -math.inf
        # when buffered or arriving data were last lost for another reason than the window
        # (buffer.max_duration) the user chose: no fix, the memory bound, a restart
        self._last_loss_s = -math.inf
        self._calibrating_since: float | None = None
        self._cancel = threading.Event()
        # outputs
        self._transform: TransformOutput | None = None
        self._calibration: dict[str, Any] | None = None
        self._source = ''
        self._failure: str | None = None
        self._file_problem: str | None = None

    # configuration ----------------------------------------------------------------------
    @property
    def config(self) -> CalibConfig:
        return self._config

    def update_config(self, config: CalibConfig) -> None:
        """Use a new configuration from now on (a running calibration keeps its own).

        The buffer keeps its samples: they are stored as decoded, before any parameter
        other than ``radar.velocity_field`` applies, so the next calibration uses the new
        values on all of them.
        """
        with self._buffer_lock:
            self._config = config
            self._enforce_bounds()

    # input ------------------------------------------------------------------------------
    def on_radar(self, msg: Any) -> bool:
        """Handle one sensor_msgs/PointCloud2; returns True when it was buffered (or held
        to confirm a stamp jump). Never raises for bad input: it is counted and logged."""
        self.counters['received.radar'] += 1
        try:
            frame = msgs.decode_pointcloud(msg, self._config.radar.velocity_field)
        except DecodeError as err:
            self._reject('radar', _decode_error_kind(err), f'radar PointCloud2 rejected: {err}')
            return False
        except Exception as err:  # noqa: BLE001 - see _internal_error
            return self._internal_error('radar', err)
        frame_id = str(getattr(msg.header, 'frame_id', '') or '')
        keep = msgs.radar_frame_to_keep(frame_id, self._radar_frame, self._config)
        other = msgs.other_radar(frame_id, keep)
        if other:
            self._reject('radar', 'other_frame', other)
            return False
        mismatch = msgs.frame_id_mismatch(frame_id, self._config.radar.frame_id)
        if mismatch:
            self._warn('radar.frame_id', mismatch)
        if frame.dropped_nonfinite and frame.invalid_declared:
            # is_dense false: the driver marks the points it has no detection for with NaN
            # (an imaging radar's fixed-size clouds do every scan), the message's own way
            # of saying so. Counted, not warned of: a probe's ARS548-like driver kept the
            # buffer diagnostic at WARN for the whole drive.
            self.counters['radar_targets.invalid'] += frame.dropped_nonfinite
        elif frame.dropped_nonfinite:
            self.counters['rejected.radar_targets.nonfinite'] += frame.dropped_nonfinite
            self._warn('radar.nonfinite', f'radar PointCloud2 with {frame.dropped_nonfinite} '
                       f'NaN/inf target(s) of {frame.dropped_nonfinite + len(frame.positions_m)}'
                       ': those targets were dropped, the others kept')
            self._last_rejection_s = self._monotonic()
        accepted = self._accept('radar', frame.stamp_ns, frame)
        if accepted:
            self._radar_frame = keep
        return accepted

    def on_navsat(self, msg: Any) -> bool:
        """Handle one sensor_msgs/NavSatFix (status < 0 is dropped and counted)."""
        self.counters['received.navsat'] += 1
        try:
            fix = msgs.decode_navsatfix(msg)
        except Exception as err:  # noqa: BLE001 - see _internal_error
            return self._internal_error('navsat', err)
        if fix.status < 0:
            self.counters['dropped.navsat.no_fix'] += 1
            self._last_loss_s = self._monotonic()
            self._warn('navsat.no_fix', 'NavSatFix without a fix (status < 0): dropped until '
                       'the receiver has a fix again', severity='info')
            return False
        if not all(math.isfinite(v) for v in (fix.lat_deg, fix.lon_deg, fix.alt_m)) or not (
                -90.0 <= fix.lat_deg <= 90.0 and -180.0 <= fix.lon_deg <= 180.0):
            self._reject('navsat', 'invalid', 'NavSatFix rejected: latitude/longitude/altitude'
                         f' {fix.lat_deg}, {fix.lon_deg}, {fix.alt_m} is not a position')
            return False
        return self._accept('navsat', fix.stamp_ns, fix)

    def on_odometry(self, msg: Any) -> bool:
        """Handle one nav_msgs/Odometry."""
        self.counters['received.odom'] += 1
        try:
            odom = msgs.decode_odometry(msg)
        except Exception as err:  # noqa: BLE001 - see _internal_error
            return self._internal_error('odom', err)
        values = (*odom.quaternion_xyzw, *odom.velocity_body_mps, odom.yaw_rate_rps)
        q_norm = math.sqrt(sum(v * v for v in odom.quaternion_xyzw))
        if not all(math.isfinite(v) for v in values) or not 0.5 < q_norm < 1.5:
            self._reject('odom', 'invalid', 'Odometry rejected: NaN/inf in its orientation or '
                         f'twist, or a quaternion of norm {q_norm:.3g}')
            return False
        return self._accept('odom', odom.stamp_ns, odom)

    def _accept(self, stream: str, stamp_ns: int, sample: Sample) -> bool:
        if stamp_ns <= 0:
            self._reject(stream, 'no_stamp', f'{stream} message without a header stamp '
                         f'({stamp_ns} ns) rejected: stamps are the time base')
            return False
        with self._buffer_lock:
            released = self._admit(stream, stamp_ns, sample)
            for source, stamp, item in released:
                self._add(source, stamp, item)
            if released:
                self._enforce_bounds()
            return bool(released) or bool(self._streams[stream].held)

    def _admit(self, stream: str, stamp_ns: int,
               sample: Sample) -> list[tuple[str, int, Sample]]:
        """Decide on one sample by its stamp (buffer lock held); returns what to buffer now
        as (stream, stamp, sample)."""
        state = self._streams[stream]
        state.seen_s = self._monotonic()
        if state.pending_since is None:
            return self._admit_one(stream, state, stamp_ns, sample)
        ended = self._pending(stream, state, stamp_ns, sample)
        if ended is None:
            return []
        return ended + self._admit_one(stream, state, stamp_ns, sample)

    def _admit_one(self, stream: str, state: _StreamState, stamp_ns: int,
                   sample: Sample) -> list[tuple[str, int, Sample]]:
        if state.awaiting_since is not None:
            waited = self._monotonic() - state.awaiting_since
            if (waited <= AWAIT_RESTART_S and self._newest_ns is not None
                    and stamp_ns > self._newest_ns + self._cross_tolerance_ns()):
                self._reject(stream, 'stale', f'{stream} message stamped before the new '
                             'recording started rejected (stale data of the previous loop)')
                return []
            state.awaiting_since = None
            state.last_ns = None
        if state.last_ns is None:
            state.last_ns = stamp_ns
            return [(stream, stamp_ns, sample)]
        if _continues(state.last_ns, stamp_ns):
            self._drop_held(stream, state)
            state.last_ns = max(state.last_ns, stamp_ns)
            return [(stream, stamp_ns, sample)]
        # a jump: hold the message until CONFIRM_MESSAGES consistent ones agree
        if state.held and not _continues(state.held[-1][0], stamp_ns):
            self._drop_held(stream, state)
        state.held.append((stamp_ns, sample))
        if len(state.held) < CONFIRM_MESSAGES:
            return []
        if stamp_ns < state.last_ns and self._others_continue(stream):
            # the other streams go on: a bag looping makes them jump back too within
            # moments; a step of this stream's clock alone (an NTP correction) or a burst
            # of its old messages re-sent does not, and must not empty the buffer (a
            # twenty-sixth probe: a radar clock stepped back 3 s lost the drive)
            state.pending_since = self._monotonic()
            return []
        held, state.held = state.held, []
        newest = max(stamp for stamp, _ in held)
        released = [(stream, stamp, item) for stamp, item in held]
        if stamp_ns < state.last_ns:
            released += self._start_new_recording(stream, state.last_ns - stamp_ns, newest)
        else:
            self._warn(f'{stream}.gap', f'{stream} stamps jumped forward by '
                       f'{(stamp_ns - state.last_ns) * 1e-9:.1f} s (an outage?): kept')
        state.last_ns = newest
        return released

    def _others_continue(self, stream: str) -> bool:
        """Whether another stream goes on on its clock: seen within AWAIT_RESTART_S and not
        itself waiting on a jump of its own."""
        now = self._monotonic()
        return any(state.seen_s is not None and now - state.seen_s <= AWAIT_RESTART_S
                   and state.pending_since is None and state.last_ns is not None
                   for other, state in self._streams.items() if other != stream)

    def _pending(self, stream: str, state: _StreamState, stamp_ns: int,
                 sample: Sample) -> list[tuple[str, int, Sample]] | None:
        """A message of a stream whose backward jump waits on the others (buffer lock
        held): None while it goes on holding, else what it held, to buffer before this
        message is decided on as any other."""
        assert state.last_ns is not None and state.pending_since is not None
        behind = stamp_ns < state.last_ns - BACKWARD_TOLERANCE_NS
        if behind and state.held and _continues(state.held[-1][0], stamp_ns) and (
                self._monotonic() - state.pending_since <= AWAIT_RESTART_S):
            state.held.append((stamp_ns, sample))
            return None
        # The others never followed (or this stream is back where it was): its clock
        # stepped back, or a burst of its old messages was re-sent; what it sent is kept,
        # and so is the buffer (the build tells a step of the radar's clock by the receipts)
        held, state.held, state.pending_since = state.held, [], None
        if held:
            jump_ns = state.last_ns - min(stamp for stamp, _ in held)
            state.last_ns = max([stamp_ns, *(stamp for stamp, _ in held)])
            self._warn(f'{stream}.step', f'{len(held)} {stream} message(s) stamped up to '
                       f'{jump_ns * 1e-9:.1f} s back while the other streams went on (a clock '
                       'correction, or old messages re-sent): kept, and the buffer too')
        return [(stream, stamp, item) for stamp, item in held]

    def _drop_held(self, stream: str, state: _StreamState) -> None:
        if state.held:
            self._reject(stream, 'stamp_outlier', f'{len(state.held)} {stream} message(s) with'
                         f' a stamp far from the stream ({state.held[0][0]} ns, last '
                         f'{state.last_ns} ns) rejected', count=len(state.held))
            state.held = []

    def _cross_tolerance_ns(self) -> int:
        return BACKWARD_TOLERANCE_NS + int(abs(self._config.sync.time_offset) * 1e9)

    def _start_new_recording(self, stream: str, jump_ns: int,
                             newest_ns: int) -> list[tuple[str, int, Sample]]:
        """Empty the buffer; returns the samples other streams held that belong to the new
        recording too (they jumped back with it but had not confirmed it yet)."""
        frames, fixes, odoms = self._builder.sample_counts()
        self._clear_buffer()
        self.counters['restarts'] += 1
        now = self._last_loss_s = self._monotonic()
        released: list[tuple[str, int, Sample]] = []
        for other, state in self._streams.items():
            if other == stream:
                continue
            state.pending_since = None
            if state.held and max(s for s, _ in state.held) <= (
                    newest_ns + self._cross_tolerance_ns()):
                released += [(other, s, item) for s, item in state.held]
                state.last_ns = max(s for s, _ in state.held)
                state.held, state.awaiting_since = [], None
            else:
                state.last_ns, state.held, state.awaiting_since = None, [], now
        self._warn('restart', f'{stream} stamps jumped back by {jump_ns * 1e-9:.1f} s (a bag '
                   'replayed in a loop, or a restarted driver): treating it as a new recording;'
                   f' the buffer was emptied ({frames} radar frames, {fixes} fixes, {odoms} '
                   'odometry samples dropped)')
        return released

    def _add(self, stream: str, stamp_ns: int, sample: Sample) -> None:
        # The node's clock is one clock for every stream, as a recorder's is: it shows radar
        # stamps seconds off the poses' or jumping (``clocks.receipt_checks``); a
        # sample held to confirm a jump counts as received when released, a moment late.
        added = True
        if isinstance(sample, RadarFrame):
            self._builder.add_radar_frame(sample)
        elif isinstance(sample, FixSample):
            added = self._builder.add_fix(sample)
        else:
            added = self._builder.add_odometry(sample)
        if added:
            now_ns = self._now_ns()
            if _clock_set(now_ns, stamp_ns):
                self._builder.note_receipt(stream, stamp_ns, now_ns)
            else:
                self.counters['receipts.clock_unset'] += 1
        self.counters[f'buffered.{stream}'] += 1
        lo, hi = self._ranges.get(stream, (stamp_ns, stamp_ns))
        self._ranges[stream] = (min(lo, stamp_ns), max(hi, stamp_ns))

    @property
    def _oldest_ns(self) -> int | None:
        """The oldest buffered stamp of any stream."""
        return min((lo for lo, _ in self._ranges.values()), default=None)

    @property
    def _newest_ns(self) -> int | None:
        """The newest buffered stamp of any stream."""
        return max((hi for _, hi in self._ranges.values()), default=None)

    def _enforce_bounds(self) -> None:
        """Drop the oldest data beyond buffer.max_duration or buffer.max_memory_mb, each
        stream by its own stamps: a radar on a clock of its own (an hour off, or counting
        from its boot, with sync.time_offset saying so) had every frame dropped on arrival
        by a window over all the streams' stamps (a twenty-sixth probe)."""
        if not self._ranges:
            return
        cfg = self._config.buffer
        max_span_ns = int(cfg.max_duration * 1e9)
        slack_ns = max(int(1e9), int(max_span_ns * _DURATION_SLACK))
        over = {stream: hi - max_span_ns for stream, (lo, hi) in self._ranges.items()
                if hi - lo > max_span_ns + slack_ns}
        for stream, cut_ns in over.items():
            self._drop_before(cut_ns, 'max_duration', stream)
        if over:
            self._warn('buffer.max_duration', f'buffer.max_duration ({cfg.max_duration:g} s) '
                       'reached: the oldest data are dropped from now on', severity='info')
        limit = cfg.max_memory_mb * 2**20
        nbytes = self._builder.nbytes()
        if nbytes > limit:
            keep = _MEMORY_REFILL * limit / nbytes
            span = max(hi - lo for lo, hi in self._ranges.values())
            for stream, (lo, hi) in list(self._ranges.items()):
                self._drop_before(hi - int((hi - lo) * keep), 'max_memory', stream)
            self._last_loss_s = self._monotonic()
            self._warn('buffer.max_memory', f'buffer.max_memory_mb ({cfg.max_memory_mb:g} MiB)'
                       f' reached at {span * 1e-9:.0f} s of data: the oldest data are dropped '
                       'from now on')

    def _drop_before(self, stamp_ns: int, reason: str, stream: str | None = None) -> None:
        before = self._builder.sample_counts()
        self._builder.drop_before(stamp_ns, stream)
        after = self._builder.sample_counts()
        for name, n_before, n_after in zip(STREAMS, before, after):
            if n_before > n_after:
                self.counters[f'dropped.{name}.{reason}'] += n_before - n_after
        self._ranges = self._builder.stamp_ranges_ns()

    def _clear_buffer(self) -> None:
        self._counters_at_clear = Counter(self.counters)
        counters = self._builder.counters
        self._builder = RecordingBuilder(self._config)
        self._builder.counters = counters
        self._ranges = {}
        self._radar_frame = None

    # services ---------------------------------------------------------------------------
    def calibrate(self) -> TriggerOutcome:
        """Run the pipeline on a snapshot of the buffer (the ``~/calibrate`` service).

        A second call while one runs is refused at once. On success the result file is
        written atomically and the new transform is returned for publishing.
        """
        if self._cancel.is_set():
            return TriggerOutcome(False, 'the node is shutting down')
        if not self._calibration_lock.acquire(blocking=False):
            started = self._calibrating_since
            age = f' (started {self._monotonic() - started:.0f} s ago)' if started else ''
            return TriggerOutcome(False, f'a calibration is already running{age}; call '
                                  '~/calibrate again when it has finished')
        try:
            self._calibrating_since = self._monotonic()
            return self._calibrate()
        finally:
            self._calibrating_since = None
            self._calibration_lock.release()

    def _calibrate(self) -> TriggerOutcome:
        config = self._config
        with self._buffer_lock:
            snapshot = self._builder.snapshot(config)
        frames, fixes, odoms = snapshot.sample_counts()
        start = time.perf_counter()
        try:
            recording = snapshot.build()
            result = self._run(recording, config, progress=self._progress)
            calibration = result.calibration(config)
        except CalibrationError as err:
            reason = err.reason if isinstance(err, InsufficientDataError) else str(err)
            # what the node refused on arrival is often the cause (every radar stamp 0, a
            # wrong radar.velocity_field): said with the reason (a twenty-sixth probe read
            # only 'no radar frame in the recording')
            if isinstance(err, CalibrationCancelled):
                # asked for (the node stopping): no failure to explain, nothing to blame
                self._log('warn', f'calibration cancelled: {reason}')
                return TriggerOutcome(False, f'calibration cancelled: {reason}')
            losses = self._losses()
            reason += (f' (messages the node refused or dropped since the buffer was last '
                       f'emptied: {losses})' if losses else '')
            self._failure = reason
            self._log('error', f'calibration failed: {reason} (buffer: {frames} radar frames, '
                      f'{fixes} fixes, {odoms} odometry samples)')
            return TriggerOutcome(False, f'calibration failed: {reason}')
        except Exception as err:  # noqa: BLE001 - a bug; see below
            # An exception out of a service callback stops rclpy's executor, i.e. the
            # roadside unit and the calibration it serves. The traceback is logged in full
            # and the caller told it is a bug; the node keeps serving the last calibration.
            reason = f'internal error (a bug, please report): {type(err).__name__}: {err}'
            self._failure = reason
            self._log('error', f'calibration failed with an {reason}\n{traceback.format_exc()}')
            return TriggerOutcome(False, f'calibration failed: {reason}')
        elapsed = time.perf_counter() - start
        # stamped with the calibration's own time, as the file says it: the node serves the
        # same TransformStamped after a restart (the node clock, under use_sim_time a bag's,
        # gave another stamp before the restart than after: a twenty-sixth probe)
        transform = _transform_from(calibration, _stamp_ns(calibration['stamp'])
                                    or self._now_ns())
        self._transform, self._calibration = transform, calibration
        self._failure = None
        summary = self._summary(calibration, result.quality, config) + self._bound_note()
        self._source = f'computed at {calibration["stamp"]}'
        try:
            write_result_yaml(config.output.path, calibration)
        except OSError as err:
            # the calibration is valid and published; only its file is missing
            self._file_problem = (f'result file {config.output.path!r} not written: '
                                  f'{err.strerror or err}')
            self._log('error', self._file_problem)
            summary += f'; WARNING: {self._file_problem}'
        else:
            self._file_problem = None
            self._source += f', written to {config.output.path}'
        self._log('info', f'{summary} ({elapsed:.1f} s on {frames} radar frames)')
        for line in result.quality.advice:
            # what `radar-calib calibrate` prints as warnings
            self._log('warn', line)
        return TriggerOutcome(True, summary, transform)

    def _progress(self, stage: str, fraction: float) -> None:
        """Pipeline progress hook: the one place a running calibration can be stopped."""
        if self._cancel.is_set():
            raise CalibrationCancelled('calibration', 'the node is shutting down')
        self._log('debug', f'calibrating: {stage} ({100 * fraction:.0f} %)')

    def cancel(self) -> None:
        """Make a running calibration stop before its next stage (node shutdown), and
        refuse new ones."""
        self._cancel.set()

    @staticmethod
    def _summary(calibration: Mapping[str, Any], quality: QualityReport,
                 config: CalibConfig) -> str:
        """One line: position, yaw, r_i, uncertainty (+ advice when the boresight is weak)."""
        east, north, alt = calibration['translation']
        text = (f'calibrated {calibration["radar_frame"]} in {calibration["world_frame"]} '
                f'(EPSG {calibration["epsg"]}): position E {east:.3f} N {north:.3f} alt '
                f'{alt:.3f} m, yaw {calibration["rpy_deg"][2]:.2f} deg (boresight '
                f'{calibration["boresight_azimuth_deg"]:.2f} deg from north), r_i '
                f'{quality.inlier_ratio:.2f}, 1-sigma {quality.sigma_translation_m:.3f} m '
                f'(along boresight {quality.sigma_along_boresight_m:.3f} m) / '
                f'{quality.sigma_rotation_deg:.2f} deg, {quality.passes} passes')
        notes = list(quality.extra.get('data_notes') or [])
        for note in notes:
            text += f'. {note}'
        drive_advice = quality.advice[len(notes):]
        if drive_advice and (quality.sigma_along_boresight_m
                             > config.quality.max_boresight_sigma_m):
            text += f'. {drive_advice[0]}'
        return text

    def _counters_since_clear(self) -> Counter[str]:
        """The counts since the buffer was last emptied (the start, ~/reset, a restart of
        the stamps): what the data a calibration ran on lost."""
        return self.counters - self._counters_at_clear

    def _bound_note(self) -> str:
        """A note for the answer where ``buffer.max_memory_mb`` dropped data since the buffer
        was last emptied: the drives in them are missing from the calibration, and its
        advice ('drive through the view at least 5 times') would blame the driver for it (a
        probe's 64 MiB bound kept 3 of 8 drives, and the answer said only that)."""
        frames = self._counters_since_clear().get('dropped.radar.max_memory', 0)
        if not frames:
            return ''
        return (f'. NOTE: buffer.max_memory_mb ({self._config.buffer.max_memory_mb:g} MiB) '
                f'dropped the oldest {frames} radar frames: the drives in them are not in this '
                'calibration; raise it to keep them (a calibration needs about 8-9 times the '
                'buffer\'s memory besides)')

    def reset(self) -> TriggerOutcome:
        """Empty the buffer (the ``~/reset`` service); counters and outputs are kept."""
        with self._buffer_lock:
            frames, fixes, odoms = self._builder.sample_counts()
            self._clear_buffer()
            for state in self._streams.values():
                state.last_ns, state.held, state.awaiting_since = None, [], None
            self.counters['resets'] += 1
        message = (f'buffer emptied: {frames} radar frames, {fixes} fixes, {odoms} odometry '
                   'samples dropped')
        self._log('info', message)
        return TriggerOutcome(True, message)

    def save_recording(self, path: str | Path | None = None) -> TriggerOutcome:
        """Write the buffer to a rosbag2 directory (mcap), the ``~/save_recording`` service.

        Radar targets are written as float64 fields exactly as buffered (before
        ``radar.velocity_sign``), fixes and odometry as received, so ``radar-calib
        calibrate`` on the bag, with the same parameters, gives the same calibration. Only
        what was buffered is written: rejected messages and NaN targets are not.

        Parameters
        ----------
        path : str or Path, optional
            Bag directory to create; default ``output.recording_dir/recording_<UTC time>``.
        """
        config = self._config
        with self._buffer_lock:
            snapshot = self._builder.snapshot(config)
        frames, fixes, odoms = snapshot.sample_counts()
        if frames + fixes + odoms == 0:
            return TriggerOutcome(False, 'the buffer is empty: nothing to save')
        if path is None:
            stamp = _dt.datetime.now(_dt.timezone.utc).strftime(STAMP_FORMAT)
            path = _unused_path(Path(config.output.recording_dir) / f'recording_{stamp}')
        path = Path(path)
        start = time.perf_counter()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            store = msgs.get_typestore()
            count = write_bag(path, _encode_samples(snapshot, config, store), storage='mcap',
                              typestore=store)
        except (CalibrationError, OSError) as err:
            message = f'recording not saved: {err}'
            self._log('error', message)
            return TriggerOutcome(False, message)
        message = (f'saved {count} messages ({frames} radar frames, {fixes} fixes, {odoms} '
                   f'odometry samples) to {path}')
        self._log('info', f'{message} in {time.perf_counter() - start:.1f} s')
        return TriggerOutcome(True, message)

    # result file ------------------------------------------------------------------------
    def load_result_file(self) -> TransformOutput | None:
        """Load and validate an existing result file at ``output.path`` (at start).

        Returns the transform to publish, or None when there is no file or it is not a
        valid calibration. A corrupt file is reported and left in place: only the next
        successful calibration replaces it.
        """
        path = Path(self._config.output.path)
        if not path.exists():
            self._log('info', f'no result file at {str(path)!r} yet: not calibrated')
            return None
        try:
            calibration = load_result(path)
            transform = _transform_from(calibration, _stamp_ns(calibration.get('stamp')) or
                                        self._now_ns(), self._config)
        except CalibrationError as err:
            # the error names the file already
            self._file_problem = (f'not a valid calibration: {err}; it is left in place and '
                                  'replaced only when a new calibration succeeds')
            self._log('error', self._file_problem)
            return None
        self._transform, self._calibration = transform, calibration
        self._file_problem = None
        self._source = f'loaded from {path} (computed at {calibration.get("stamp", "?")})'
        self._log('info', f'calibration {self._source}: {transform.parent_frame} -> '
                  f'{transform.child_frame} at {_fmt_vector(transform.translation_m)}')
        return transform

    # outputs ----------------------------------------------------------------------------
    @property
    def transform(self) -> TransformOutput | None:
        """The calibration currently served (None before the first one)."""
        return self._transform

    @property
    def calibration(self) -> dict[str, Any] | None:
        """The contract's result mapping currently served."""
        return self._calibration

    @property
    def calibrating(self) -> bool:
        return self._calibrating_since is not None

    def buffer_stats(self) -> dict[str, float]:
        """Buffered frames, targets, fixes, odometry samples, span [s] and memory [MiB]:
        what the buffer holds now (the counters say what arrived since the start)."""
        with self._buffer_lock:
            frames, fixes, odoms = self._builder.sample_counts()
            targets = self._builder.target_count()
            span = max(((hi - lo) * 1e-9 for lo, hi in self._ranges.values()), default=0.0)
            nbytes = self._builder.nbytes()
        return {'radar_frames': frames, 'targets': targets, 'fixes': fixes, 'odometry': odoms,
                'span_s': span, 'memory_mib': nbytes / 2**20}

    def diagnostics(self) -> tuple[DiagnosticStatusOutput, ...]:
        """The calibration's quality figures and the buffer's counters."""
        return self._calibration_status(), self._buffer_status()

    def _calibration_status(self) -> DiagnosticStatusOutput:
        name = f'{self._name}: calibration'
        hardware_id = self._config.radar.frame_id
        values: list[tuple[str, str]] = []
        if self._calibration is not None:
            values.extend(_flatten_values(
                {k: v for k, v in self._calibration.items() if k != 'quality'}))
            values.extend(_flatten_values(self._calibration.get('quality') or {}, 'quality.'))
        problems = [p for p in (self._failure and f'last calibration failed: {self._failure}',
                                self._file_problem) if p]
        if problems:
            serving = (f'; serving the calibration {self._source}' if self._transform
                       else '; no calibration is served')
            return DiagnosticStatusOutput(name, 'ERROR', '; '.join(problems) + serving,
                                          hardware_id, tuple(values))
        if self._transform is None:
            return DiagnosticStatusOutput(
                name, 'WARN', 'not calibrated yet: drive the calibration vehicle past the radar'
                ' (at least 3 passes) and call ~/calibrate', hardware_id, tuple(values))
        level, message = 'OK', f'calibration {self._source}'
        quality = (self._calibration or {}).get('quality') or {}
        sigma_along = (quality.get('sigma') or {}).get('along_boresight_m')
        limit = self._config.quality.max_boresight_sigma_m
        if isinstance(sigma_along, (int, float)) and sigma_along > limit:
            level = 'WARN'
            message += (f'; 1-sigma along the boresight {sigma_along:.3f} m > {limit:g} m')
            advice = quality.get('advice') or []
            if advice:
                message += f': {advice[0]}'
        return DiagnosticStatusOutput(name, level, message, hardware_id, tuple(values))

    def _buffer_status(self) -> DiagnosticStatusOutput:
        stats = self.buffer_stats()
        values = [(f'buffer.{key}', f'{value:.1f}' if isinstance(value, float) else str(value))
                  for key, value in stats.items()]
        values.append(('calibrating', 'yes' if self.calibrating else 'no'))
        counters = dict(self.counters)
        values.extend((key, str(counters[key])) for key in sorted(counters))
        rejected = {k: v for k, v in counters.items() if k.startswith('rejected.')}
        level, message = 'OK', (f'{stats["radar_frames"]} radar frames, {stats["fixes"]} fixes'
                                f', {stats["odometry"]} odometry samples over '
                                f'{stats["span_s"]:.0f} s ({stats["memory_mib"]:.1f} MiB)')
        now = self._monotonic()
        if now - self._last_rejection_s < WARN_THROTTLE_S:
            level = 'WARN'
            # the counters are totals since the start: said so (a probe read an outage
            # that had ended minutes before as this minute's)
            message += ('; bad input in the last minute (totals so far: ' + ', '.join(
                f'{k[len("rejected."):]}: {v}' for k, v in sorted(rejected.items())) + ')')
        if now - self._last_loss_s < WARN_THROTTLE_S:
            # the window's own drops (max_duration) are the buffer working as configured
            lost = {k: v for k, v in counters.items()
                    if k.startswith('dropped.') and not k.endswith('.max_duration')}
            if counters.get('restarts'):
                lost['restarts (buffer emptied)'] = counters['restarts']
            level = 'WARN'
            message += ('; data lost in the last minute (totals so far: ' + ', '.join(
                f'{k.removeprefix("dropped.")}: {v}' for k, v in sorted(lost.items())) + ')')
        return DiagnosticStatusOutput(f'{self._name}: buffer', level, message,
                                      self._config.radar.frame_id, tuple(values))

    # reporting --------------------------------------------------------------------------
    def _losses(self, most: int = 4) -> str:
        """The largest counts of messages refused or dropped since the buffer was last
        emptied (the start, ~/reset, a restart of the stamps), e.g. 'radar.no_stamp 5651'."""
        lost = sorted(((n, k.split('.', 1)[1]) for k, n in self._counters_since_clear().items()
                       if k.startswith(('rejected.', 'dropped.')) and n > 0), reverse=True)
        return ', '.join(f'{name} {n}' for n, name in lost[:most])

    def _reject(self, stream: str, kind: str, message: str, count: int = 1) -> None:
        self.counters[f'rejected.{stream}.{kind}'] += count
        self._last_rejection_s = self._monotonic()
        self._warn(f'{stream}.{kind}', message)

    def _internal_error(self, stream: str, err: Exception) -> bool:
        """A bug met by a message: counted and logged with its traceback, never raised.

        Style rule "catch CalibrationError only" has one exception here: an exception out of
        a subscription callback stops rclpy's executor, i.e. the roadside unit. The
        traceback is logged (once per throttle period) and the fuzz test asserts that the
        counter ``rejected.<stream>.internal_error`` stays zero.
        """
        self.counters[f'rejected.{stream}.internal_error'] += 1
        self._last_rejection_s = self._monotonic()
        if self._should_report(f'{stream}.internal_error'):
            _LOG.exception('bug while handling a %s message', stream)
            self._log('error', f'internal error while handling a {stream} message (a bug, '
                      f'please report): {type(err).__name__}: {err}')
        return False

    def _warn(self, kind: str, message: str, severity: str = 'warn') -> None:
        """Log once per kind, then at most every WARN_THROTTLE_S with the repeat count."""
        entry = self._throttle.get(kind)
        now = self._monotonic()
        if entry is None:
            self._throttle[kind] = [now, 0.0]
            self._log(severity, message)
            return
        entry[1] += 1
        if now - entry[0] >= WARN_THROTTLE_S:
            repeats = int(entry[1])
            entry[0], entry[1] = now, 0.0
            self._log(severity, f'{message} ({repeats} times since the last report)')

    def _should_report(self, kind: str) -> bool:
        entry = self._throttle.get(kind)
        now = self._monotonic()
        if entry is None or now - entry[0] >= WARN_THROTTLE_S:
            self._throttle[kind] = [now, 0.0]
            return True
        entry[1] += 1
        return False


class LogForwarder(logging.Handler):
    """Warnings and errors the pipeline logs through Python's ``logging`` (the
    ``radar_calib_ros`` loggers), passed to the node's log function.

    Why: the node logs through rclpy, but the stages log through ``logging``; with no
    handler configured, Python printed them bare on stderr, outside the node's log and
    /rosout (a probe's 'radar stamps shifted' line). Info and debug records stay out, as
    ``radar-calib`` shows them only with -v.
    """

    def __init__(self, log: LogFn) -> None:
        super().__init__(logging.WARNING)
        self._forward = log

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._forward('error' if record.levelno >= logging.ERROR else 'warn',
                          record.getMessage())
        except Exception:  # noqa: BLE001 - logging must never raise into the pipeline
            self.handleError(record)

    def install(self) -> LogForwarder:
        """Attach to the package's logger (undone by :meth:`remove`), and to those of its
        loggers that do not pass records up: ROS 2 launch's logger class (set for every
        logger made after ``import launch``, as launch_testing's pytest plugin does under
        ``colcon test``) makes each one with ``propagate = False``."""
        for logger in self._package_loggers():
            logger.addHandler(self)
        return self

    def remove(self) -> None:
        for logger in self._package_loggers():
            logger.removeHandler(self)

    @staticmethod
    def _package_loggers() -> list[logging.Logger]:
        package = logging.getLogger('radar_calib_ros')
        others = [logger for name, logger in list(logging.root.manager.loggerDict.items())
                  if name.startswith('radar_calib_ros.') and isinstance(logger, logging.Logger)
                  and not logger.propagate]
        return [package, *others]


# --- helpers -------------------------------------------------------------------------------

#: 2000-01-01 [ns]: a node clock before it, with header stamps after it, is not set yet.
_CLOCK_SET_NS = 946_684_800 * 10**9


def _clock_set(now_ns: int, stamp_ns: int) -> bool:
    """Whether the node's clock can time a message's receipt: a roadside host without a
    battery-backed clock before NTP, or use_sim_time before the first /clock, reads 0 (a
    twenty-sixth probe: such receipts read as every stream's stamps falling back by 55
    years, and the build failed on them)."""
    return now_ns > 0 and not now_ns < _CLOCK_SET_NS <= stamp_ns


def _continues(last_ns: int, stamp_ns: int) -> bool:
    """True when a stamp follows the previous one of its stream without a jump."""
    delta = stamp_ns - last_ns
    return -BACKWARD_TOLERANCE_NS <= delta <= FORWARD_GAP_NS


_DECODE_KINDS = (('fewer than', 'truncated'), ('point_step', 'point_step'),
                 ('velocity field', 'no_velocity_field'),
                 ('neither x/y/z', 'no_position_fields'), ('datatype', 'datatype'))


def _decode_error_kind(err: DecodeError) -> str:
    """Short kind of a PointCloud2 decoding problem, for counters and throttling."""
    text = str(err)
    for needle, kind in _DECODE_KINDS:
        if needle in text:
            return kind
    return 'undecodable'


def _transform_from(calibration: Mapping[str, Any], stamp_ns: int,
                    config: CalibConfig | None = None) -> TransformOutput:
    """TransformOutput of a result mapping (as written or loaded)."""
    world = calibration.get('world_frame') or (config.world.frame_id if config else 'utm')
    radar = calibration.get('radar_frame') or (config.radar.frame_id if config else 'radar')
    t = tuple(float(v) for v in calibration['translation'])
    q = np.asarray(calibration['quaternion_xyzw'], float)
    q = q / np.linalg.norm(q)  # a loaded file is unit to 1e-3 only
    return TransformOutput(str(world), str(radar), (t[0], t[1], t[2]),
                           (float(q[0]), float(q[1]), float(q[2]), float(q[3])), int(stamp_ns))


def _stamp_ns(stamp: Any) -> int | None:
    """ISO 8601 text (or a datetime, as YAML may parse it) -> ns since the epoch."""
    when = parse_stamp(stamp)
    if when is None:
        return None
    return int(when.timestamp()) * 1_000_000_000 + when.microsecond * 1000


def _fmt_vector(values: tuple[float, ...]) -> str:
    return '[' + ', '.join(f'{v:.3f}' for v in values) + ']'


def _flatten_values(mapping: Mapping[str, Any], prefix: str = '') -> list[tuple[str, str]]:
    """Nested mapping -> (key, text) pairs for DiagnosticStatus values."""
    out: list[tuple[str, str]] = []
    for key, value in mapping.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.extend(_flatten_values(value, name + '.'))
        elif isinstance(value, (list, tuple)):
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                out.append((name, '[' + ', '.join(f'{v:.9g}' for v in value) + ']'))
            else:
                out.append((name, ' '.join(str(v) for v in value)))
        elif isinstance(value, float):
            out.append((name, f'{value:.9g}'))
        else:
            out.append((name, str(value)))
    return out


def _unused_path(path: Path) -> Path:
    candidate, n = path, 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f'{path.name}_{n}')
    return candidate


def _encode_samples(builder: RecordingBuilder, config: CalibConfig,
                    store: Any) -> Iterator[tuple[str, str, int, object]]:
    """(topic, msgtype, record time, message) of every buffered sample, in stamp order.

    Topics are the configured (relative) names with a leading slash, which the offline
    tool matches against the same parameters file. The record time is when the node
    received the message (its header stamp where that is not known), as ``ros2 bag
    record`` would have written it: the offline tool's recorder's-clock checks (radar
    stamps seconds off the poses', a radar clock jump) then see what the node saw.
    """
    radar_received, pose_received = builder.receipt_times()
    radar_topic = '/' + config.radar_topic.lstrip('/')
    navsat_topic = '/' + config.navsat_topic.lstrip('/')
    odom_topic = '/' + config.odom_topic.lstrip('/')
    velocity_field = config.radar.velocity_field or 'velocity'
    # the fixes' own frame is not kept, only whether it named an antenna (the offline
    # tool's hint on vehicle.ref_height)
    fix_frame = 'gnss' if builder.counters.get('fix_frame_antenna') else 'base_link'
    for sample in builder.samples():
        if isinstance(sample, RadarFrame):
            msg = msgs.encode_pointcloud(store, sample.stamp_ns, config.radar.frame_id,
                                         sample.positions_m, sample.radial_velocity_mps,
                                         dtype=np.float64, velocity_field=velocity_field)
            yield (radar_topic, msgs.POINTCLOUD2,
                   radar_received.get(sample.stamp_ns, sample.stamp_ns), msg)
        elif isinstance(sample, FixSample):
            msg = msgs.encode_navsatfix(store, sample.stamp_ns, fix_frame, sample.lat_deg,
                                        sample.lon_deg, sample.alt_m, status=sample.status,
                                        position_sigma_m=sample.position_sigma_m)
            yield (navsat_topic, msgs.NAVSATFIX,
                   pose_received.get(sample.stamp_ns, sample.stamp_ns), msg)
        else:
            msg = msgs.encode_odometry(store, sample.stamp_ns, config.world.frame_id,
                                       'base_link', sample.position_m, sample.quaternion_xyzw,
                                       sample.velocity_body_mps, sample.yaw_rate_rps)
            yield (odom_topic, msgs.ODOMETRY,
                   pose_received.get(sample.stamp_ns, sample.stamp_ns), msg)


def replace_config(config: CalibConfig, **sections: Any) -> CalibConfig:
    """``dataclasses.replace`` on sections by dotted names, for tests and the node:
    ``replace_config(cfg, **{'buffer.max_duration': 60.0})``."""
    return config.replaced(sections)
