"""The clocks of a recording: what the recorder's receive times say about the header stamps.

A recorder stamps every message it receives with one clock, so the lag from each
message's header stamp to its receipt compares the radar's clock with the poses'. These
functions read it: the radar's stamps' offset from the poses' (``receipt_checks``), a
lasting step of the radar's clock alone (a reboot, a lost or regained sync:
``radar_clock_step``, under a second ``_small_clock_step``) and a restart of every
stream's clock at once (a simulator reset: ``common_restart``). They work on plain
arrays of lags and receive times; ``RecordingBuilder`` applies what they find to the
samples it holds.

Kept apart from ``recording.py``: the clocks are a question of their own, asked of the
receipts alone, and separate from both storing samples and building the vehicle's track.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from radar_calib_ros.core._splits import two_piece_rss
from radar_calib_ros.types import F64, I64

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


def receipts_from(stamp_ns: int, lags: list[int], received: list[int]) -> list[int]:
    """Indices of the receipts (lag, received) of the messages stamped at or after
    ``stamp_ns``."""
    return [i for i, (lag, rec) in enumerate(zip(lags, received)) if rec - lag >= stamp_ns]


#: Offset between the radar's and the poses' header stamps, as one recorder received them,
#: and a step of the radar's, worth naming [s] (transport latencies are milliseconds to a
#: few hundred); frames over which a step must persist.
_RECEIPT_OFFSET_S = 1.0
_RECEIPT_WINDOW = 15


def radar_clock_step(radar_lag: I64, radar_received: I64, pose_lag: I64,
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


def jump_counters(later: np.ndarray, before_ns: float, after_ns: float,
                  radar_received: I64) -> dict[str, int]:
    """'radar_stamp_jump_ms' (a lag that drops is a stamp that jumps forward) and
    'radar_stamp_jump_at_ms' (after the first radar message) of a step of the radar
    stamps' receipt lag from ``before_ns`` to ``after_ns``, ``later`` the messages after."""
    return {'radar_stamp_jump_ms': int(round(-(after_ns - before_ns) / 1e6)),
            'radar_stamp_jump_at_ms': int(
                (radar_received[later].min() - radar_received.min()) // 10**6)}


def rejoin_shift(before_ns: float, after_ns: float, pose_lag: I64) -> tuple[bool, int]:
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


def receipt_checks(radar_lag: I64, radar_received: I64, pose_lag: I64,
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
    step = radar_clock_step(radar_lag, radar_received, pose_lag, pose_received)
    if step is not None:
        out.update(jump_counters(*step, radar_received))
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
#: A step must leave under this share of the scatter a line leaves about the smoothed lag.
_STEP_OVER_LINE = 0.5


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
    # A radar clock that drifts (a free-running oscillator: 1000 ppm over six minutes is
    # 0.38 s) ramps the lag, whose halves differ by half the ramp wherever it is split; two
    # constant offsets then explain it no better than a line (a fifty-eighth probe's drift
    # was named a reboot's jump 10 s into the drive, in 4 runs of 4).
    # (what the best step leaves against what a line leaves)
    if (float(np.min(two_piece_rss(smooth)))
            >= _STEP_OVER_LINE ** 2 * _line_rss(received, smooth)):
        return None
    if _pose_lag_stepped(pose_lag, pose_received, int(received[k]), step):
        return None
    # a lag that drops is a stamp that jumps forward
    return (int(round(-step / 1e6)), int((received[k] - received[0]) // 10**6),
            _step_sides(order, lag, k, before, after, w), before, after)


def _line_rss(received: I64, values: F64) -> float:
    """The residual sum of squares of ``values`` about their least-squares line over the
    receive times (NaN where the numbers overflow: corrupted stamps)."""
    t = (received - received[0]).astype(np.float64) * 1e-9
    t -= t.mean()
    centred = values - values.mean()
    spread = float(np.dot(t, t))
    with np.errstate(all='ignore'):
        slope = float(np.dot(t, centred)) / spread if spread > 0 else 0.0
        return float(np.sum((centred - slope * t) ** 2))


@dataclass(frozen=True)
class Restart:
    """A restart of every stream's clock at once (``common_restart``).

    later : per stream (radar, fixes, Odometry) the messages after it, (0,) for a stream
        without messages; back_ns : how far each stream's stamps fell [ns]; at_ns : when
        each fall came [recorder's ns] (both of the streams with messages).
    """

    later: list[np.ndarray]
    back_ns: list[int]
    at_ns: list[int]

    @property
    def gap_ns(self) -> int:
        """The gap left between the parts [ns]."""
        return int(_RESTART_GAP_S * 1e9)

    @property
    def shift_ns(self) -> int:
        """What moves the stamps after the restart after those before it [ns]."""
        return int(np.median(self.back_ns)) + int(_RESTART_GAP_S * 1e9)


def common_restart(streams: list[tuple[I64, I64]]) -> Restart | None:
    """The restart of every stream (``(received, lag)`` of the radar, the fixes and the
    Odometry) at once, or None: each stream with messages has a lasting fall of its stamps
    (``_restart_step``), at least two have messages, and their falls agree in size and
    time to ``_RESTART_AGREE_S``."""
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
    later = [step[0] if step is not None else np.zeros(0, bool) for step in steps]
    return Restart(later, back_ns, at_ns)


def small_step_rejoin(radar_lag: I64, radar_received: I64, pose_lag: I64,
                      pose_received: I64 | None, order: I64, message_frame: I64,
                      n_frames: int) -> I64 | None:
    """(n_frames,) what to add to each frame's stamp to undo a step of the radar's clock
    under a second (``_small_clock_step``), or None without one; ``order`` the radar
    messages (in received order) by stamp, ``message_frame`` the frame of each of those."""
    small = _small_clock_step(radar_lag, radar_received, pose_lag, pose_received)
    if small is None:
        return None
    _, _, later, before, after = small
    frame_later = np.zeros(n_frames, bool)
    np.logical_or.at(frame_later, message_frame, later[order])
    move_later, shift = rejoin_shift(before, after, pose_lag)
    moved = frame_later if move_later else ~frame_later
    rejoin_ns: I64 = shift * moved.astype(np.int64)
    return rejoin_ns
