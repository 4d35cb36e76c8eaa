"""Every radar of one recording: ``radar-calib calibrate BAG --all-radars``.

A test site records all its radars in parallel while the calibration vehicle drives past
them all. Each radar topic is calibrated on its own (the same ``run_calibration`` as a single
radar, the topic chosen as if ``radar_topic`` named it), in parallel processes: the stages
are numpy-bound and hold the GIL between array operations, so threads would not overlap.

Each radar's result is named by its frame: the header ``frame_id`` of the topic's first
message (the frame other nodes know it by), or a name made from the topic when that is
empty or taken twice.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import BagReadError, CalibrationError, exit_code

if TYPE_CHECKING:
    from radar_calib_ros.io.bag import BagPaths

_LOG = logging.getLogger(__name__)

#: File name of the combined parameters file in the output directory.
COMBINED_FILE = 'all_radars.yaml'
#: Keys of a calibration that describe the transform (the combined file holds these).
TRANSFORM_KEYS = ('world_frame', 'radar_frame', 'epsg', 'translation', 'quaternion_xyzw',
                  'rpy_deg', 'latitude', 'longitude', 'altitude', 'boresight_azimuth_deg',
                  'stamp')
#: Keys of a calibration's quality that the combined file holds too: the radar's clock.
CLOCK_KEYS = ('time_offset_s', 'sync_time_offset_s')


@dataclass(frozen=True)
class RadarOutcome:
    """One radar's calibration run.

    calibration : the contract's result mapping, or None when the run failed; error: the
    reason (one line) and exit_code its code (0 ok, 1 cannot be calibrated, 2 bad input);
    summary : the one-screen summary lines; read_s / run_s : bag reading and pipeline time.
    """

    topic: str
    frame_id: str
    calibration: dict[str, Any] | None
    error: str | None
    exit_code: int
    summary: tuple[str, ...] = ()
    read_s: float = 0.0
    run_s: float = 0.0


def _same_topic(a: str, b: str) -> bool:
    return a.lstrip('/') == b.lstrip('/')


def ambiguous_radar_topics(bag: BagPaths, config: CalibConfig) -> list[str]:
    """The bag's radar topics when there are several and the parameters pick none, else [].

    Raises
    ------
    BagReadError
        The bag cannot be opened.
    """
    from radar_calib_ros.io.bag import radar_topics
    if 'radar_topic' in config.explicit:
        return []
    topics = radar_topics(bag, config.radar.velocity_field)
    if len(topics) > 1 and not any(_same_topic(t, config.radar_topic) for t in topics):
        return topics
    return []


def radar_frames(bag: BagPaths) -> dict[str, str]:
    """Radar topic -> the frame its result is for, sorted by topic: the messages' frame_id
    as TF has it (a frame with '/' keeps it: a carla-ros-bridge's 'ego_vehicle/radar_front'
    renamed would be a transform nobody looks up), or, where that is empty or shared by
    several topics, the topic made a name. A topic that repeats another's clouds in the
    same frame is left out (``_copied_topics``).

    Raises
    ------
    BagReadError
        The bag cannot be opened, or holds no radar topic.
    """
    from radar_calib_ros.io.bag import bag_label, radar_frame_ids
    found = radar_frame_ids(bag)
    if not found:
        raise BagReadError(f'no radar topic (PointCloud2 or RadarScan) in '
                           f'{bag_label(bag)!r}')
    for copy in _copied_topics(bag, found):
        del found[copy]
    names: dict[str, str] = {}
    # sorted by topic: the order the results are printed, written and combined in
    for topic, frame in sorted(found.items()):
        name = frame.strip().lstrip('/')
        if (not _safe(name) or _safe(name) in map(_safe, names.values())
                or list(found.values()).count(frame) > 1):
            name = _safe(topic)
            # said: the result's radar_frame is then no frame the radar publishes in (a
            # twenty-fifth probe's three radars all in 'radar' were renamed silently)
            _LOG.warning('radar topic %s: its messages\' frame_id %r is %s, so its result is '
                         'for frame %r; publish each radar in a frame of its own, or rename '
                         'the frame in the result', topic, frame,
                         'empty (or the topic has no message)' if not frame.strip()
                         else 'another radar\'s too', name)
        names[topic] = name
    return names


def _copied_topics(bag: BagPaths, found: Mapping[str, str]) -> list[str]:
    """The radar topics that repeat an earlier topic's clouds in the same frame (equal
    first messages), each said.

    Why: a forty-eighth probe's radar recorded on two topics (a relay, a remap) was
    calibrated twice under names made of the topics, and its own frame got no result.
    """
    from radar_calib_ros.io.bag import radar_fingerprints
    shared = [t for t, f in found.items() if f.strip() and list(found.values()).count(f) > 1]
    if not shared:
        return []
    prints = radar_fingerprints(bag, shared)
    first: dict[tuple[str, tuple[str, ...]], str] = {}
    copies = []
    for topic in sorted(shared):
        key = (found[topic], prints.get(topic, ()))
        if not key[1]:
            continue
        if key in first:
            copies.append(topic)
            _LOG.warning('radar topic %s carries the same clouds as %s (frame %r): the radar '
                         'is calibrated once, from %s', topic, first[key], found[topic],
                         first[key])
        else:
            first[key] = topic
    return copies


def _safe(name: str) -> str:
    """A frame or topic name as a file name and a parameter name: '/' and other
    separators become '_'."""
    return ''.join(c if c.isalnum() or c in '-_.' else '_' for c in name.strip('/')).strip('.')


@contextlib.contextmanager
def radar_named_records(frame_id: str) -> Iterator[None]:
    """Within it, every log record the handlers print begins with ``frame_id``.

    Why: the radars of an --all-radars run print their warnings side by side, and a
    forty-eighth probe could not tell which radar '... shifted by -0.20 s ...' was about."""
    prefix = frame_id.replace('%', '%%') + ': '

    class _Named(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            if not getattr(record, 'radar_named', False):
                record.msg = prefix + str(record.msg)
                record.radar_named = True
            return True

    named = _Named()
    handlers = list(logging.getLogger().handlers)
    for handler in handlers:
        handler.addFilter(named)
    try:
        yield
    finally:
        for handler in handlers:
            handler.removeFilter(named)


#: What a radar's advice to set ``sync.time_offset`` adds in an --all-radars run.
_OWN_CLOCK_NOTE = (' In an --all-radars run one parameters file serves every radar: set it '
                   'for this radar alone, calibrating it on its own with its topic named '
                   '(radar_topic) in a parameters file of its own.')


def _own_clock(text: str) -> str:
    """``text`` with ``_OWN_CLOCK_NOTE`` added where it asks to set ``sync.time_offset``:
    followed in the shared parameters file, a forty-eighth probe's -0.35 s for one radar
    put the next 4 m off, which then asked for +0.35 s."""
    return text + _OWN_CLOCK_NOTE if 'set sync.time_offset' in text.lower() else text


def _own_clock_advice(calibration: dict[str, Any]) -> None:
    """``_own_clock`` over the calibration's advice."""
    quality = calibration.get('quality') or {}
    if quality.get('advice'):
        quality['advice'] = [_own_clock(a) for a in quality['advice']]


def calibrate_topic(bag: BagPaths, params: str | None, topic: str, frame_id: str) -> RadarOutcome:
    """Calibrate one radar topic of a bag (runs in a worker process; never raises a
    CalibrationError, it is returned as the outcome's error)."""
    from radar_calib_ros.cli import summary_lines
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.pipeline import run_calibration
    try:
        config = CalibConfig.from_file(params) if params else CalibConfig()
        config = dataclasses.replace(config, radar=dataclasses.replace(config.radar,
                                                                       frame_id=frame_id))
        start = time.perf_counter()
        with radar_named_records(frame_id):
            recording = read_recording(bag, config, radar_topic=topic)
            read_s = time.perf_counter() - start
            result = run_calibration(recording, config)
        run_s = time.perf_counter() - start - read_s
    except CalibrationError as err:
        return RadarOutcome(topic, frame_id, None, _own_clock(str(err)), exit_code(err))
    calibration = result.calibration(config)
    _own_clock_advice(calibration)
    return RadarOutcome(topic, frame_id, calibration, None, 0,
                        tuple(summary_lines(calibration, result.stage_times_s, read_s,
                                            result.recording.sources, config.vehicle)),
                        read_s, run_s)


def calibrate_all_radars(bag: BagPaths, params: str | None = None, *,
                         jobs: int | None = None,
                         done: Callable[[RadarOutcome], None] | None = None,
                         begin: Callable[[dict[str, str]], None] | None = None,
                         ) -> list[RadarOutcome]:
    """Calibrate every radar topic of a bag, in parallel processes.

    Parameters
    ----------
    bag : str or Path, or a sequence of them
        A rosbag2 directory, or several read as one recording.
    params : str, optional
        ROS 2 parameters file for every radar (its ``radar_topic`` and ``radar.frame_id``
        are overridden per topic).
    jobs : int, optional
        Worker processes; default: one per radar, at most the number of CPUs.
    done : callable(RadarOutcome), optional
        Called once per radar in topic order, as soon as it and every radar before it have
        finished (an operator probe read the results in completion order, which changes
        from run to run and did not match the files' order).
    begin : callable(dict), optional
        Called with the radar topics and their frames (:func:`radar_frames`, in topic
        order) before any is calibrated.

    Returns
    -------
    list of RadarOutcome
        One per radar topic, in topic order.

    Raises
    ------
    BagReadError
        The bag cannot be opened or has no radar topic.
    ConfigError
        The parameters file is invalid (checked once, before any worker starts).
    """
    if params:
        CalibConfig.from_file(params)
    frames = radar_frames(bag)
    if begin is not None:
        begin(dict(frames))
    workers = max(1, min(len(frames), jobs or os.cpu_count() or 1))
    outcomes: dict[str, RadarOutcome] = {}
    order = list(frames)
    reported = 0

    def report_ready() -> None:
        # the finished radars at the head of the topic order, each once
        nonlocal reported
        while reported < len(order) and order[reported] in outcomes:
            if done is not None:
                done(outcomes[order[reported]])
            reported += 1

    if workers == 1:
        for topic, frame in frames.items():
            outcomes[topic] = calibrate_topic(bag, params, topic, frame)
            report_ready()
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(calibrate_topic, bag, params, topic, frame)
                       for topic, frame in frames.items()]
            for future in as_completed(futures):
                outcome = future.result()
                outcomes[outcome.topic] = outcome
                report_ready()
    return [outcomes[t] for t in order]


def combined_parameters(calibrations: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """One ROS 2 parameters file with every radar's transform, ready for ``/tf_static``.

    ``radar_frames`` lists the keys under ``calibrations``, each child frame as a
    parameter name ('/' made '_'); ``calibrations.<key>`` holds that radar's transform
    keys (parent ``world_frame``, child ``radar_frame`` as TF has it, ``translation``,
    ``quaternion_xyzw``, ...), as in a single result file without the quality figures
    (those stay in the per-radar files), and the radar's clock offset: ``time_offset_s``
    (to add to its stamps, in total) and ``sync_time_offset_s`` (the part given as
    ``sync.time_offset``). Each radar has a clock of its own, and a transform used at the
    wrong time is off by the speed of what it places times that (a seventy-sixth probe's
    0.15 s: its evaluation's r_i 68 -> 46 % with the combined file).
    """
    entries: dict[str, dict[str, Any]] = {}
    for frame, cal in calibrations.items():
        entry = {k: cal[k] for k in TRANSFORM_KEYS if k in cal}
        quality = cal.get('quality') or {}
        entry.update({k: quality[k] for k in CLOCK_KEYS if k in quality})
        entries[_safe(frame)] = entry
    return {'/**': {'ros__parameters': {'radar_frames': list(entries),
                                        'calibrations': entries}}}


def write_outcomes(out_dir: str | Path, outcomes: Sequence[RadarOutcome]) -> list[Path]:
    """Write ``<frame>.yaml`` per calibrated radar (the frame as a file name, '/' made
    '_') and the combined ``all_radars.yaml``; returns the files written (the combined one
    last, only when a radar succeeded)."""
    import yaml

    from radar_calib_ros.result import write_atomic, write_result_yaml
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    calibrations: dict[str, dict[str, Any]] = {}
    for outcome in outcomes:
        if outcome.calibration is None:
            continue
        path = out / f'{_safe(outcome.frame_id)}.yaml'
        write_result_yaml(path, outcome.calibration)
        written.append(path)
        calibrations[outcome.frame_id] = outcome.calibration
    if calibrations:
        path = out / COMBINED_FILE
        text = yaml.safe_dump(combined_parameters(calibrations), sort_keys=False)
        write_atomic(path, '# every radar of the recording, world -> radar (see radar_frames)\n'
                     + text)
        written.append(path)
    return written
