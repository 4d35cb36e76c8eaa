"""radar-calib: the offline tool (CONTRACT.md "The offline tool").

Each command is a function returning an exit code; ``main`` wraps them:
0 success, 1 the data cannot be calibrated (with the reason, no result file),
2 bad usage or unreadable input, 130 interrupted. Errors are one ``error: ...`` line on
stderr; only bugs keep a traceback.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import stat
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from radar_calib_ros.config import CalibConfig, VehicleConfig
from radar_calib_ros.errors import CalibrationError, ResultFileError, exit_code

if TYPE_CHECKING:
    from radar_calib_ros.io.bag import BagPaths
    from radar_calib_ros.recording import Recording

_LOG = logging.getLogger('radar_calib_ros')
#: Where ``calibrate --all-radars`` writes its results unless --output-dir says.
DEFAULT_OUTPUT_DIR = 'radar_calibrations'


def _load_config(params: str | None) -> CalibConfig:
    return CalibConfig.from_file(params) if params else CalibConfig()


def _say_bags(bags: Sequence[str]) -> None:
    """Name the bags read together, so that a run over several is never mistaken for one
    over the first."""
    if len(bags) > 1:
        print(f'note: reading {len(bags)} bags as one recording: {", ".join(bags)}',
              file=sys.stderr)


class _Progress:
    """Progress on stderr: tqdm bars on a terminal (``'bars'``), nothing (``'off'``), or,
    where stderr is a log or a pipe (``'lines'``), a plain line now and then once a run has
    lasted ``quiet_s``: a headless run of a dense radar's recording printed nothing for
    1-7 minutes (a twenty-ninth probe), while short runs stay as quiet as before."""

    def __init__(self, mode: str, *, quiet_s: float = 10.0, every_s: float = 10.0,
                 clock: Any = time.monotonic) -> None:
        if mode not in ('bars', 'lines', 'off'):
            raise ValueError(f'progress mode {mode!r}')
        self.mode = mode
        self._bar: Any = None
        self._stage_bar: Any = None
        self._clock = clock
        self._start = clock()
        self._quiet_s = quiet_s
        self._every_s = every_s
        self._last_line: float | None = None

    @classmethod
    def for_stderr(cls, forced: bool | None) -> _Progress:
        """``--progress`` / ``--no-progress`` / neither (bars on a terminal, else lines)."""
        if forced is None:
            return cls('bars' if sys.stderr.isatty() else 'lines')
        return cls('bars' if forced else 'off')

    def _line(self, text: str, *, force: bool = False) -> None:
        now = self._clock()
        if now - self._start < self._quiet_s:
            return
        if not force and self._last_line is not None and now - self._last_line < self._every_s:
            return
        self._last_line = now
        print(f'progress: {text}, {now - self._start:.0f} s', file=sys.stderr, flush=True)

    def reading(self, done: int, total: int) -> None:
        if self.mode == 'lines':
            self._line(f'reading the recording, {done:,} of {total:,} messages')
        if self.mode != 'bars':
            return
        if self._bar is None:
            from tqdm import tqdm
            self._bar = tqdm(total=total, desc='reading', unit='msg', file=sys.stderr,
                             leave=False)
        self._bar.update(done - self._bar.n)

    def end_reading(self) -> None:
        """The recording is read (``evaluate`` and ``report`` run no stages to close it)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def stage(self, name: str, fraction: float) -> None:
        if self.mode == 'lines' and name != 'done':
            # every stage start once the run is long: the stages are few, and a line per
            # stage says where a slow run spends its time
            self._line(f'calibrating, stage {name} ({fraction:.0%} done)',
                       force=True)
        if self.mode != 'bars':
            return
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self._stage_bar is None:
            from tqdm import tqdm
            self._stage_bar = tqdm(total=100, desc='calibrating', file=sys.stderr,
                                   leave=False, bar_format='{desc}: {percentage:3.0f}%|{bar}|')
        self._stage_bar.set_description(f'calibrating ({name})')
        self._stage_bar.update(int(round(fraction * 100)) - self._stage_bar.n)
        if name == 'done':
            self._stage_bar.close()
            self._stage_bar = None


def calibrate_bag(bag: BagPaths, config: CalibConfig, *, progress: _Progress | None = None,
                  ) -> tuple[Any, float]:
    """Read a bag and run the pipeline; returns (CalibrationResult, read time [s])."""
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.pipeline import run_calibration
    start = time.perf_counter()
    recording = read_recording(bag, config,
                               progress=progress.reading if progress else None)
    read_s = time.perf_counter() - start
    result = run_calibration(recording, config,
                             progress=progress.stage if progress else None)
    return result, read_s


#: How an advice line of the summary begins (``summary_lines``).
_ADVICE_PREFIX = '  advice: '


def summary_lines(calibration: dict[str, Any], stage_times: dict[str, float] | None = None,
                  read_s: float | None = None,
                  sources: Mapping[str, str] | None = None,
                  vehicle: VehicleConfig | None = None) -> list[str]:
    """The one-screen summary of a calibration (with the topics it was read from, where
    given: a twenty-fifth probe's radar picked by type among a lidar's points was never
    named; and the vehicle's reference point the altitude rests on, where given)."""
    q = calibration.get('quality') or {}
    sigma = q.get('sigma') or {}
    e, n, alt = calibration['translation']
    r, p, y = calibration['rpy_deg']
    lines = [
        f'radar frame {calibration["radar_frame"]!r} in {calibration["world_frame"]} '
        f'(EPSG:{calibration["epsg"]})',
        f'  position   E {e:.3f}  N {n:.3f}  alt {alt:.3f} m',
        f'  lat/lon    {calibration["latitude"]:.8f}, {calibration["longitude"]:.8f}',
        f'  roll/pitch/yaw  {r:.3f} / {p:.3f} / {y:.3f} deg   boresight '
        f'{calibration["boresight_azimuth_deg"]:.2f} deg from true north',
    ]
    if vehicle is not None:
        # The data cannot show which point of the vehicle its pose describes: a roof
        # antenna's pose with a rear axle's vehicle.* put a thirty-first probe's radar 1.2 m
        # high, inside nothing and unnamed. Said beside the altitude, so that it is read.
        side = ('' if vehicle.ref_left == 0.0 else
                f', {abs(vehicle.ref_left):.2f} m {"left" if vehicle.ref_left > 0 else "right"}'
                ' of the centre line')
        lines.insert(2, f'  reference  pose point {vehicle.ref_height:.2f} m above the road, '
                     f'{vehicle.rear_overhang:.2f} m ahead of the rear bumper{side} '
                     '(vehicle.ref_height, rear_overhang'
                     + (', ref_left' if side else '') + '): the altitude rests on it')
    prior = q.get('reflection_height_prior_m')
    if isinstance(prior, list) and len(prior) == 2:
        lines.insert(3 if vehicle is not None else 2,
                     f'  heights    the vehicle\'s targets taken as {prior[0]:.2f} +- '
                     f'{prior[1]:.2f} m above the road on average (refine.reflection_height_m, '
                     'scaled with vehicle.height): the altitude rests on that too, one to one')
    if sources:
        lines.insert(1, '  topics     ' + ', '.join(
            f'{_ROLE_NAMES.get(role, role)} {topic}' for role, topic in sources.items()))
    if q:
        lines.append(
            f'  quality    r_i {100 * _num(q.get("inlier_ratio")):.1f} %  '
            f'delta_op {_num(q.get("outlier_distance_m")):.2f} m  '
            f'delta_p {_num(q.get("closest_target_offset_m")):.2f} m  '
            f'passes {q.get("passes")}  tracks {q.get("tracks_used")}  '
            f'clock offset {1000 * _num(q.get("time_offset_s")):.1f} ms'
            + (f' +- {1000 * _num(sigma["time_offset_s"]):.1f}' if 'time_offset_s' in sigma
               else ''))
        lines.append(
            f'  1-sigma    {_num(sigma.get("translation_m")):.3f} m (along boresight '
            f'{_num(sigma.get("along_boresight_m")):.3f}, across '
            f'{_num(sigma.get("across_boresight_m")):.3f}, vertical '
            f'{_num(sigma.get("vertical_m")):.3f})  rotation '
            f'{_num(sigma.get("rotation_deg")):.3f} deg')
    if stage_times:
        parts = [f'{k} {v:.2f}' for k, v in stage_times.items()]
        if read_s is not None:
            parts.insert(0, f'read {read_s:.2f}')
        lines.append('  time [s]   ' + '  '.join(parts))
    for advice in q.get('advice') or []:
        lines.append(f'{_ADVICE_PREFIX}{advice}')
    return lines


_ROLE_NAMES = {'radar': 'radar', 'navsat': 'NavSatFix', 'odom': 'Odometry'}


class _LoggedWarnings(logging.Handler):
    """The warnings the pipeline logged while it ran: the advice printed after the summary
    leaves those out, as they were said already (a nineteenth probe read the note on
    folded radial velocities twice)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.add(record.getMessage())


def _echo_advice(out: TextIO) -> bool:
    """Whether the summary's advice is repeated as warnings on stderr: only for someone
    watching a terminal while the summary goes elsewhere (each sentence was printed twice
    to a terminal, four paragraphs of advice among them). Not when the summary goes into
    a pipe: ``| cat``, ``| tee log`` or ``| less`` show it on the same terminal (a probe
    read every sentence twice there)."""
    if not sys.stderr.isatty() or (hasattr(out, 'isatty') and out.isatty()):
        return False
    try:
        return not stat.S_ISFIFO(os.fstat(out.fileno()).st_mode)
    except (AttributeError, OSError, ValueError):   # no file behind it (a StringIO)
        return True


def _num(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) else math.nan


def cmd_calibrate(args: argparse.Namespace, out: TextIO) -> int:
    from radar_calib_ros.result import write_result_json, write_result_yaml
    config = _load_config(args.params)
    if args.all_radars:
        return cmd_calibrate_all_radars(args, out)
    if args.output_dir is not None:
        raise ResultFileError('--output-dir goes with --all-radars (one result per radar); '
                              'for one radar give the result file with --output')
    if args.output is None and 'output.path' in config.explicit:
        print(f'note: output.path ({config.output.path}) is where the node writes its result; '
              'the offline tool writes result.yaml unless --output names another file',
              file=sys.stderr)
    args.output = args.output or 'result.yaml'
    _refuse_overwriting_inputs({'--output': args.output, '--json': args.json},
                               {'parameters file (--params)': args.params}, args.bag)
    _check_writable(args.output, args.json)
    _refuse_file_as_directory('--report', args.report)
    _say_bags(args.bag)
    config = _radar_of_frame(args.bag, config)
    _refuse_ambiguous_radar(args.bag, config)
    _warn_frame_id(args.bag, config)
    progress = _Progress.for_stderr(args.progress)
    logged = _LoggedWarnings()
    package_log = logging.getLogger('radar_calib_ros')
    package_log.addHandler(logged)
    try:
        result, read_s = calibrate_bag(args.bag, config, progress=progress)
    finally:
        package_log.removeHandler(logged)
    calibration = result.calibration(config)
    replaced = [p for p in (args.output, args.json) if p and Path(p).is_file()]
    write_result_yaml(args.output, calibration)
    if args.json:
        write_result_json(args.json, calibration)
    for line in summary_lines(calibration, result.stage_times_s, read_s,
                              result.recording.sources, config.vehicle):
        print(line, file=out)
    if _echo_advice(out):
        for advice in calibration['quality'].get('advice') or []:
            if advice not in logged.messages:
                print(f'warning: {advice}', file=sys.stderr)
    print(f'result written to {args.output}' + (f' and {args.json}' if args.json else '')
          + (f' (replacing the earlier {" and ".join(replaced)})' if replaced else ''),
          file=out)
    if args.report:
        from radar_calib_ros.io.bag import bag_label
        from radar_calib_ros.report import report_calibration
        start = time.perf_counter()
        files = report_calibration(args.report, result, config, calibration=calibration,
                                   truth=_ground_truth(args.bag, calibration['radar_frame']),
                                   source=bag_label(args.bag))
        print(f'report written to {files.html} ({len(files.figures)} figures, '
              f'{time.perf_counter() - start:.1f} s)', file=out)
    return 0


def _ground_truth(bags: Sequence[str], radar_frame: str | None = None
                  ) -> dict[str, Any] | None:
    """The simulator's ground truth next to a bag (the directory, or a metadata.yaml's
    directory) of the radar in ``radar_frame``, or None; a broken one is skipped with a
    warning, never used silently.

    The frame matters in a recording of several radars: its ground_truth.json is the first
    radar's, so an evaluation of the others compared with no truth (an operator probe's
    N9), or would have with the wrong one."""
    from radar_calib_ros.groundtruth import load_ground_truth
    # of several bags of one recording, the first's (a simulator writes one per recording)
    path = Path(bags[0])
    try:
        return load_ground_truth(path if path.is_dir() else path.parent,
                                 None if radar_frame is None else radar_frame.lstrip('/'))
    except (OSError, ValueError) as err:
        print(f'warning: ignoring the unreadable ground truth next to {path}: {err}',
              file=sys.stderr)
        return None


def cmd_evaluate(args: argparse.Namespace, out: TextIO) -> int:
    import json

    from radar_calib_ros.evaluate import evaluate_recording, evaluation_dict, format_evaluation
    from radar_calib_ros.result import write_atomic
    if args.strict and args.no_verdict:
        print('error: --strict judges the verdict, which --no-verdict leaves out',
              file=sys.stderr)
        return 2
    start = time.perf_counter()
    config = _load_config(args.params)
    _refuse_overwriting_inputs({'--json': args.json},
                               {'calibration file (--calibration)': args.calibration,
                                'parameters file (--params)': args.params}, args.bag)
    _check_writable(args.json)
    _say_bags(args.bag)
    calibration, recording = _calibrated_recording(args.bag, args.calibration, config,
                                                   _Progress.for_stderr(args.progress))
    read_s = time.perf_counter() - start
    evaluation = evaluate_recording(
        recording, calibration, config,
        truth=_ground_truth(args.bag, str(calibration.get('radar_frame', 'radar'))),
        agreement=not args.no_verdict)
    print(format_evaluation(evaluation), file=out)
    if args.json:
        write_atomic(args.json, json.dumps(evaluation_dict(evaluation), indent=2) + '\n')
    print(f'evaluated in {time.perf_counter() - start:.1f} s (reading {read_s:.1f} s)'
          + (f'; written to {args.json}' if args.json else ''), file=out)
    # an acceptance needs the calibration shown to hold: doubtful and cannot-tell are no
    # pass (a forty-first probe's 1 m altitude error passed as 'doubtful', a 3 deg yaw
    # error on two passes as 'cannot tell')
    if args.strict and evaluation.agreement is not None \
            and evaluation.agreement.verdict != 'holds':
        print(f'error: {evaluation.agreement.headline} (--strict: only a calibration that '
              'holds passes)', file=sys.stderr)
        return 1
    return 0


def cmd_report(args: argparse.Namespace, out: TextIO) -> int:
    from radar_calib_ros.io.bag import bag_label
    from radar_calib_ros.report import report_recording
    start = time.perf_counter()
    config = _load_config(args.params)
    _refuse_file_as_directory('--out', args.out)
    _say_bags(args.bag)
    calibration, recording = _calibrated_recording(args.bag, args.calibration, config,
                                                   _Progress.for_stderr(args.progress))
    files = report_recording(
        args.out, recording, calibration, config,
        truth=_ground_truth(args.bag, str(calibration.get('radar_frame', 'radar'))),
        source=bag_label(args.bag))
    print(f'report written to {files.html} ({len(files.figures)} figures, '
          f'{time.perf_counter() - start:.1f} s)', file=out)
    return 0


def _calibrated_recording(bag: BagPaths, calibration_path: str, config: CalibConfig,
                          progress: _Progress | None = None,
                          ) -> tuple[dict[str, Any], Recording]:
    """The calibration (of ``radar.frame_id`` where the file holds several radars') and the
    recording of that radar's topic (found by its frame where the parameters name none),
    for ``evaluate`` and ``report`` alike: ``report`` read the bag's only radar topic and
    refused one radar's result of ``--all-radars`` that ``evaluate`` took."""
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.result import load_result
    # a bad file fails before the bag is read
    calibration = load_result(calibration_path, config.radar.frame_id)
    topic = _topic_of_frame(bag, config, str(calibration.get('radar_frame')))
    recording = read_recording(bag, config, radar_topic=topic,
                               progress=progress.reading if progress else None)
    if progress:
        progress.end_reading()
    _warn_other_radar(bag, config, topic, str(calibration.get('radar_frame') or ''))
    return calibration, recording


def _warn_other_radar(bag: BagPaths, config: CalibConfig, topic: str | None,
                      result_frame: str) -> None:
    """Warn when the clouds read are in another frame than the result's radar: a result of
    another radar, evaluated without a word (a thirty-seventh probe's 'radar_north' result
    on a bag of 'radar' clouds)."""
    from radar_calib_ros.io.bag import configured_radar_frame_id
    read = configured_radar_frame_id(bag, config if topic is None else dataclasses.replace(
        config, radar_topic=topic)).lstrip('/')
    if read and result_frame and read != result_frame.lstrip('/'):
        print(f"warning: the result is of radar frame '{result_frame}' but the radar clouds "
              f"read are in frame '{read}': a result of another radar? The figures compare "
              'the two as if they were one.', file=sys.stderr)


def _radar_of_frame(bag: BagPaths, config: CalibConfig) -> CalibConfig:
    """Where the bag holds several radar topics and the parameters name none but set
    ``radar.frame_id``, the topic whose messages are in that frame (as ``evaluate`` finds
    it: a twenty-fifth probe's ``calibrate`` refused what ``evaluate`` took)."""
    if 'radar.frame_id' not in config.explicit:
        return config
    topic = _topic_of_frame(bag, config, config.radar.frame_id)
    if topic is None:
        return config
    return dataclasses.replace(config, radar_topic=topic,
                               explicit=config.explicit | {'radar_topic'})


def _refuse_ambiguous_radar(bag: BagPaths, config: CalibConfig) -> None:
    """Several radar topics and no ``radar_topic``: say how to choose (exit 2)."""
    from radar_calib_ros.errors import BagReadError
    from radar_calib_ros.multi_radar import ambiguous_radar_topics
    topics = ambiguous_radar_topics(bag, config)
    if topics:
        # a frame named that picks no topic, or two, is said as such (a forty-seventh and a
        # forty-eighth probe read 'the parameters name none' beside their radar.frame_id)
        named = ('the parameters name none'
                 if 'radar.frame_id' not in config.explicit else
                 f'radar.frame_id {config.radar.frame_id!r} is the frame of '
                 + _frame_matches(bag, config.radar.frame_id)
                 + ', and the parameters name no radar_topic')
        raise BagReadError(
            f'the bag has {len(topics)} radar topics ({", ".join(topics)}) and {named}: '
            'calibrate them all with `radar-calib calibrate BAG --all-radars`, or set '
            'radar_topic to one of them')


def _topics_in_frame(frames: Mapping[str, str], frame_id: str) -> list[str]:
    """The radar topics (of ``radar_frame_ids``) whose messages are in ``frame_id``."""
    return [topic for topic, frame in frames.items()
            if frame.lstrip('/') == frame_id.lstrip('/')]


def _frame_matches(bag: BagPaths, frame_id: str) -> str:
    """Which of the bag's radar topics are in ``frame_id``, in words."""
    from radar_calib_ros.io.bag import radar_frame_ids
    matching = _topics_in_frame(radar_frame_ids(bag), frame_id)
    if not matching:
        return 'none of them'
    return f'{len(matching)} of them ({", ".join(matching)})'


def _topic_of_frame(bag: BagPaths, config: CalibConfig, frame_id: str) -> str | None:
    """The radar topic whose messages are in ``frame_id``, where the parameters name none
    and the bag holds several radar topics (one radar's result of ``--all-radars``)."""
    from radar_calib_ros.io.bag import radar_frame_ids
    if 'radar_topic' in config.explicit:
        return None
    frames = radar_frame_ids(bag)
    matching = _topics_in_frame(frames, frame_id)
    return matching[0] if len(frames) > 1 and len(matching) == 1 else None


def _check_writable(*paths: str | None) -> None:
    """ResultFileError (exit 2) before the work, not a traceback after it, when a result
    could not be written: the nearest existing folder of each path must be a writable one
    (the missing ones below it are created when the result is written)."""
    for path in paths:
        if not path:
            continue
        target = Path(path).absolute()
        if target.is_dir():
            raise ResultFileError(f'cannot write the result to {path!r}: it is a directory')
        folder = target.parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
            raise ResultFileError(f'cannot write the result to {path!r}: {str(folder)!r} is '
                                  'not a writable folder')


def _refuse_file_as_directory(flag: str, path: str | None) -> None:
    """ResultFileError (exit 2) before the work when the report's directory is a file."""
    if path and Path(path).exists() and not Path(path).is_dir():
        raise ResultFileError(f'{flag} {path!r} is a file, not a directory: give the '
                              'directory for the figures and report.html')


#: Files of a rosbag2 recording an output must never replace.
_BAG_FILE_SUFFIXES = ('.mcap', '.db3', '.db3-wal', '.db3-shm')


def _refuse_overwriting_inputs(outputs: dict[str, str | None],
                               inputs: dict[str, str | None], bags: Sequence[str]) -> None:
    """ResultFileError (exit 2) before the work when an output would replace an input (the
    parameters or calibration file, a file of the bag) or another output: a probe's
    ``--output site.yaml`` with ``--params site.yaml`` replaced the site's parameters by
    the result, ``--output bag/metadata.yaml`` made the recording unreadable, ``--output
    same --json same`` left a result.yaml holding JSON."""
    from radar_calib_ros.result import is_stream

    def same(path: str) -> Path:
        return Path(os.path.realpath(path))

    bag_files: dict[Path, str] = {}
    for one in bags:
        root = same(one)
        if root.name == 'metadata.yaml' and root.is_file():
            root = root.parent    # the bag given by its metadata.yaml
        if root.is_file():
            bag_files[root] = one
        elif root.is_dir():
            bag_files.update({p: one for p in root.iterdir() if p.name == 'metadata.yaml'
                              or p.name.endswith(_BAG_FILE_SUFFIXES)})
    taken: dict[Path, str] = {}
    for flag, path in outputs.items():
        if not path or is_stream(path):
            continue   # unset, or a device or pipe (/dev/stdout): nothing to replace
        target = same(path)
        if target in taken:
            raise ResultFileError(f'{taken[target]} and {flag} name the same file {path!r}: '
                                  'give each its own')
        taken[target] = flag
        for role, source in inputs.items():
            if source and same(source) == target:
                raise ResultFileError(f'{flag} {path!r} is the {role}: writing there would '
                                      f'replace it; choose another {flag}')
        if target in bag_files:
            raise ResultFileError(f'{flag} {path!r} is a file of the recording '
                                  f'{bag_files[target]!r}: '
                                  f'writing there would destroy it; choose another {flag}')


def _warn_frame_id(bag: BagPaths, config: CalibConfig) -> None:
    """Warn when the radar topic's header frame_id is not ``radar.frame_id``."""
    from radar_calib_ros.io.bag import configured_radar_frame_id
    from radar_calib_ros.io.messages import frame_id_mismatch
    mismatch = frame_id_mismatch(configured_radar_frame_id(bag, config), config.radar.frame_id)
    if mismatch:
        print(f'warning: {mismatch}', file=sys.stderr)


def _note_unused_radar_choice(params: str | None) -> None:
    """Say that ``--all-radars`` takes every radar topic whatever the parameters choose:
    a forty-eighth probe's radar_topic and radar.frame_id went unused without a word."""
    if not params:
        return
    chosen = sorted({'radar_topic', 'radar.frame_id'} & CalibConfig.from_file(params).explicit)
    if chosen:
        print(f'note: --all-radars calibrates every radar topic, each under its own frame '
              f'(not used from {params}: {", ".join(chosen)})', file=sys.stderr)


def cmd_calibrate_all_radars(args: argparse.Namespace, out: TextIO) -> int:
    """``calibrate --all-radars``: every radar topic in parallel processes, one result per
    radar frame in ``--output-dir`` plus the combined ``all_radars.yaml``."""
    import json

    from radar_calib_ros.multi_radar import COMBINED_FILE, calibrate_all_radars, write_outcomes
    from radar_calib_ros.result import write_atomic
    if getattr(args, 'report', None):
        print('error: --report takes one radar; use `radar-calib report` per radar result',
              file=sys.stderr)
        return 2
    if args.jobs is not None and args.jobs < 1:
        raise ResultFileError(f'--jobs {args.jobs}: give at least 1 worker process')
    args.output_dir = args.output_dir or DEFAULT_OUTPUT_DIR
    _refuse_overwriting_inputs({'--output': args.output, '--json': args.json},
                               {'parameters file (--params)': args.params}, args.bag)
    _check_writable(args.output, args.json)
    _note_unused_radar_choice(args.params)
    _say_bags(args.bag)
    start = time.perf_counter()
    # advice said for an earlier radar (the vehicle's, the pose stream's) -> that radar:
    # each radar's summary repeated it in full (a seventy-sixth probe: 39 times a run)
    said: dict[str, str] = {}

    def done(outcome: Any) -> None:
        if outcome.calibration is None:
            print(f'{outcome.topic} ({outcome.frame_id}): error: {outcome.error}',
                  file=sys.stderr)
            return
        print(f'{outcome.topic} ({outcome.frame_id}): calibrated in '
              f'{outcome.read_s + outcome.run_s:.1f} s', file=out)
        for line in outcome.summary:
            print(_advice_said_before(line, outcome.frame_id, said), file=out)
        if _echo_advice(out):
            for advice in outcome.calibration['quality'].get('advice') or []:
                print(f'warning: {outcome.frame_id}: {advice}', file=sys.stderr)

    def begin(frames: dict[str, str]) -> None:
        # the order the results are printed, written and combined in
        print(f'radar topics ({len(frames)}): '
              + ', '.join(f'{topic} ({frame})' for topic, frame in frames.items()), file=out)

    outcomes = calibrate_all_radars(args.bag, args.params, jobs=args.jobs, done=done,
                                    begin=begin)
    written = write_outcomes(args.output_dir, outcomes)
    if args.output and written and written[-1].name == COMBINED_FILE:
        # a user who names --output expects the file there: the combined transforms
        write_atomic(args.output, written[-1].read_text())
        written.append(Path(args.output))
    if args.json:
        write_atomic(args.json, json.dumps({o.frame_id: o.calibration for o in outcomes
                                            if o.calibration is not None}, indent=2) + '\n')
        written.append(Path(args.json))
    ok = sum(o.calibration is not None for o in outcomes)
    # the ones left out named again at the end, where a user reads first (a forty-seventh
    # probe's '3 of 4 radars calibrated' said not which, and the files just lacked it)
    failed = [f'{o.frame_id} ({o.topic}: {o.error})' for o in outcomes if o.calibration is None]
    print(f'{ok} of {len(outcomes)} radars calibrated in {time.perf_counter() - start:.1f} s'
          + (f'; not calibrated: {"; ".join(failed)}' if failed else '')
          + (f'; written: {", ".join(str(p) for p in written)}' if written else ''), file=out)
    return max(o.exit_code for o in outcomes)


def _advice_said_before(line: str, frame_id: str, said: dict[str, str]) -> str:
    """``line`` of a radar's summary, or where it is advice an earlier radar's summary
    gave word for word (``said``: advice -> that radar's frame, updated here), a short
    pointer to it. The result files keep every radar's advice in full."""
    if not line.startswith(_ADVICE_PREFIX):
        return line
    text = line[len(_ADVICE_PREFIX):]
    first = said.setdefault(text, frame_id)
    if first == frame_id:
        return line
    words = ' '.join(text.split()[:8])
    return f'{_ADVICE_PREFIX}as for {first} above ({words} ...)'


def cmd_simulate(args: argparse.Namespace, out: TextIO) -> int:
    from radar_calib_ros.sim import simulate
    start = time.perf_counter()
    summary = simulate(args.out_bag, seed=args.seed, duration_s=args.duration,
                       storage=args.storage, scenario=args.scenario,
                       scatter_model=args.scatter_model, mount_seed=args.mount_seed,
                       max_unambiguous_velocity_mps=args.unambiguous_velocity,
                       mount_turn=None if args.mount_turn is None else tuple(args.mount_turn))
    mount = '' if args.mount_seed is None else f', mount seed {args.mount_seed}'
    if args.mount_turn is not None:
        mount += (f', mount turned {args.mount_turn[1]:+g} deg at {args.mount_turn[0]:g} s')
    # the drives the radar saw the vehicle on: a drive at the edge of the view may give it
    # no target (a probe read '3 passes' and then calibrate's 'seen in 2 passes')
    seen = sum(1 for p in summary.truth.get('passes', []) if p.get('n_targets', 1) > 0)
    print(f'simulated {args.scenario!r} ({args.duration:.0f} s, seed {args.seed}{mount}) into '
          f'{args.out_bag} in {time.perf_counter() - start:.1f} s: {summary.n_frames} radar '
          f'frames, {summary.n_targets} targets; the calibration vehicle drove through the '
          f'view {_times(summary.n_passes)}' + (
              f', {seen} of them with targets on it' if seen != summary.n_passes else ''),
          file=out)
    return 0


def _times(n: int) -> str:
    return {1: 'once', 2: 'twice'}.get(n, f'{n} times')


def cmd_demo(args: argparse.Namespace, out: TextIO) -> int:
    import shutil

    from radar_calib_ros.groundtruth import GROUND_TRUTH_FILE, load_ground_truth
    from radar_calib_ros.report import report_calibration
    from radar_calib_ros.result import write_result_yaml
    from radar_calib_ros.sim import simulate
    work = Path(args.out)
    bag = work / 'demo_bag'
    if bag.exists():
        if not (bag / GROUND_TRUTH_FILE).is_file():
            print(f'error: {bag} exists and is not a demo recording; choose another --out',
                  file=sys.stderr)
            return 2
        shutil.rmtree(bag)  # our own earlier demo recording: replace it
    # what simulate would refuse, refused before anything is said or done
    from radar_calib_ros.sim import check_duration
    from radar_calib_ros.sim.scenario import get_scenario
    get_scenario(args.scenario)
    check_duration(args.duration)
    print(f'1/4 simulating a {args.duration:.0f} s drive past a roadside radar '
          f'(scenario {args.scenario!r}, seed {args.seed}) ...', file=out)
    start = time.perf_counter()
    simulate(bag, seed=args.seed, duration_s=args.duration, scenario=args.scenario)
    params = bag / 'params.yaml'
    config = _load_config(str(params) if params.is_file() else None)
    print(f'2/4 calibrating {bag} ...', file=out)
    result, read_s = calibrate_bag(bag, config, progress=_Progress.for_stderr(None))
    calibration = result.calibration(config)
    write_result_yaml(work / 'result.yaml', calibration)
    print('3/4 result', file=out)
    for line in summary_lines(calibration, result.stage_times_s, read_s,
                              vehicle=config.vehicle):
        print(line, file=out)
    truth = load_ground_truth(bag)
    if truth is not None:
        print(_truth_table(calibration, truth, result), file=out)
    files = report_calibration(work / 'report', result, config, calibration=calibration,
                               truth=truth, source=str(bag))
    print(f'4/4 report: {files.html}', file=out)
    print(f'done in {time.perf_counter() - start:.1f} s; recording, result.yaml and report '
          f'in {work}/', file=out)
    return 0


def _truth_table(calibration: dict[str, Any], truth: dict[str, Any], result: Any) -> str:
    from radar_calib_ros.groundtruth import calibration_errors
    from radar_calib_ros.result import calibration_dict
    rows = ['', f'{"":<22}{"estimate":>14}{"truth":>14}{"error":>12}']
    for i, axis in enumerate(('easting [m]', 'northing [m]', 'altitude [m]')):
        est, tru = calibration['translation'][i], truth['translation'][i]
        rows.append(f'{axis:<22}{est:>14.3f}{tru:>14.3f}{est - tru:>12.3f}')
    for i, axis in enumerate(('roll [deg]', 'pitch [deg]', 'yaw [deg]')):
        est, tru = calibration['rpy_deg'][i], truth['rpy_deg'][i]
        rows.append(f'{axis:<22}{est:>14.3f}{tru:>14.3f}'
                    f'{(est - tru + 180.0) % 360.0 - 180.0:>12.3f}')
    est_dt = calibration['quality'].get('time_offset_s')
    if est_dt is not None and 'time_offset_s' in truth:
        rows.append(f'{"clock offset [ms]":<22}{1000 * est_dt:>14.1f}'
                    f'{1000 * truth["time_offset_s"]:>14.1f}'
                    f'{1000 * (est_dt - truth["time_offset_s"]):>12.1f}')
    err = calibration_errors(calibration, truth)
    rows.append(f'errors: horizontal {100 * err["horizontal_m"]:.1f} cm, vertical '
                f'{100 * err["vertical_m"]:.1f} cm, rotation {err["rotation_deg"]:.3f} deg')
    stages = []
    for name, ext in result.stage_extrinsics.items():
        e = calibration_errors(calibration_dict(ext, result.recording.frame), truth)
        stages.append(f'{name} {100 * e["horizontal_m"]:.1f} cm / {e["rotation_deg"]:.2f} deg')
    rows.append('after each stage (horizontal / rotation): ' + ', '.join(stages))
    return '\n'.join(rows)


def _add_recording_arguments(p: argparse.ArgumentParser, *, calibration: bool) -> None:
    """The recording (and, for commands that read one, the calibration file) and the
    parameters file, worded the same in every subcommand."""
    p.add_argument('bag', nargs='+', metavar='BAG',
                   help='rosbag2 directory (sqlite3 or mcap); several are read as one '
                   'recording (a drive split by a recorder restart, or the radar recorded at '
                   'the roadside and the vehicle\'s poses in the vehicle)')
    if calibration:
        p.add_argument('--calibration', required=True, metavar='RESULT',
                       help='result file of radar-calib calibrate (result.yaml or result.json)')
    p.add_argument('--params', help='ROS 2 parameters file (default: built-in defaults)')
    p.add_argument('--progress', action=argparse.BooleanOptionalAction, default=None,
                   help='progress bars on stderr (default: bars on a terminal; elsewhere, once '
                   'a run passes 10 s, a plain "progress:" line per stage and every 10 s '
                   'while reading; --no-progress: none)')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='radar-calib', description='Target-less geo-referenced radar calibration from a '
        'connected vehicle (offline tool; no ROS needed).')
    parser.add_argument('-v', '--verbose', action='store_true', help='log progress details')
    sub = parser.add_subparsers(dest='command', required=True)

    p = sub.add_parser('calibrate', help='calibrate a radar from a rosbag2 recording')
    _add_recording_arguments(p, calibration=False)
    p.add_argument('--output', default=None,
                   help='result file (default: result.yaml); with --all-radars, where a copy '
                   'of the combined all_radars.yaml goes')
    p.add_argument('--json', help='also write the result as JSON here')
    p.add_argument('--all-radars', action='store_true',
                   help='calibrate every radar topic of the recording, in parallel processes: '
                   'one result per radar frame in --output-dir plus all_radars.yaml with '
                   'every transform (--json then holds them all, keyed by frame)')
    p.add_argument('--output-dir', default=None, metavar='DIR',
                   help=f'with --all-radars: where the results go (default: '
                   f'{DEFAULT_OUTPUT_DIR})')
    p.add_argument('--jobs', type=int, default=None, metavar='N',
                   help='with --all-radars: worker processes (default: one per radar, at most '
                   'the number of CPUs)')
    p.add_argument('--report', metavar='DIR',
                   help='also write the report of this calibration run into DIR: every '
                   'figure of `radar-calib report` (on this recording) plus those only a '
                   'calibration run has: hypotheses, refinement residuals, reflection '
                   'profile, radial-velocity residuals')
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser(
        'evaluate', help="the paper's quality figures of a calibration on a second recording",
        description='Evaluate a calibration as the paper does: tracking only (no '
        're-calibration) on a second recording; tracks associated with the calibration '
        'vehicle by synchronised time, those more than 5 m from it on average dropped, the '
        'rest merged; r_i, delta_op and delta_p, overall and per range bin. Where the bag '
        "directory holds the simulator's ground_truth.json, also the position and rotation "
        'errors. Then a verdict: the radar fitted on this recording alone (the final '
        'refinement, started from the calibration) against the calibration, each axis in '
        'the uncertainty of both: holds, doubtful, does not hold, or cannot tell. Exit 1 when '
        'the vehicle is never seen (and with --strict unless the calibration holds), 2 on '
        'bad input.')
    _add_recording_arguments(p, calibration=True)
    p.add_argument('--json', help='also write the evaluation as JSON here')
    p.add_argument('--strict', action='store_true',
                   help="exit 1 unless the verdict is 'holds' (for acceptance scripts)")
    p.add_argument('--no-verdict', action='store_true',
                   help="the paper's figures only, without the fit behind the verdict "
                   '(about as long again as the tracking)')
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        'report', help='PNG figures and report.html of a calibration on a recording',
        description='Write PNG figures and a self-contained report.html for a calibration '
        'file on a recording, without re-calibrating (a run on a long recording takes '
        "minutes and would draw a different estimate from the file's): the bird's-eye view "
        "of a test track, delta_op and delta_p over range (the paper's evaluation on this "
        'recording) and the ground-plane fit. The hypotheses, the refinement residuals, the '
        'reflection profile and the radial-velocity residuals exist only inside a '
        'calibration run: get them with `radar-calib calibrate BAG --report DIR`.')
    _add_recording_arguments(p, calibration=True)
    p.add_argument('--out', required=True, metavar='DIR',
                   help='directory for the figures and report.html (created if missing)')
    p.set_defaults(func=cmd_report)

    p = sub.add_parser('simulate', help='write a synthetic recording with its ground truth')
    p.add_argument('out_bag', help='bag directory to create')
    p.add_argument('--seed', type=int, default=0,
                   help='varies the drive, traffic and noise (default: %(default)s)')
    p.add_argument('--duration', type=float, default=600.0,
                   help='seconds, 10-3600 (default: 600)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='rosbag2 storage (default: %(default)s)')
    p.add_argument('--scenario', default='baseline', metavar='NAME',
                   help='site and drive (default: %(default)s; an unknown name lists the '
                   'known ones)')
    p.add_argument('--scatter-model', default=None,
                   help='where on road users the radar sees them (skin, interior, mixed)')
    p.add_argument('--mount-seed', type=int, default=None,
                   help="moves the radar mount a little from the scenario's (default: as "
                        'described); --seed varies only the drive, traffic and noise, so '
                        'drives with one scenario and mount seed see the same radar')
    p.add_argument('--unambiguous-velocity', type=float, default=0.0, metavar='MPS',
                   help='fold radial velocities beyond +-MPS m/s, as a radar tuned for range '
                        'does (default: 0, no folding)')
    p.add_argument('--mount-turn', type=float, nargs=2, default=None,
                   metavar=('AT_S', 'YAW_DEG'),
                   help='the mount turns about the vertical by YAW_DEG (anticlockwise seen '
                        'from above) AT_S seconds into the recording, as when re-aimed; the '
                        'ground truth is the mount after it')
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser('demo',
                       help='simulate, calibrate, compare with the ground truth and report')
    p.add_argument('--seed', type=int, default=1,
                   help='varies the drive, traffic and noise (default: %(default)s)')
    p.add_argument('--duration', type=float, default=150.0,
                   help='seconds of simulated drive, 10-3600 (default: %(default)s)')
    p.add_argument('--scenario', default='baseline', metavar='NAME',
                   help='site and drive, as for simulate (default: %(default)s)')
    p.add_argument('--out', default='radar_calib_demo',
                   help='directory for the recording, result and report (default: %(default)s)')
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None, out: TextIO | None = None) -> int:
    """Run the tool; returns the exit code (0 ok, 1 cannot calibrate, 2 bad input)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as err:  # argparse: 0 for --help, 2 for bad usage
        return int(err.code or 0)
    fresh = not logging.getLogger().handlers   # not a host's (pytest's, an embedding's)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format='%(levelname)s %(name)s: %(message)s')
    if fresh and not args.verbose:
        # 'warning: ...' as the tool's own lines say it, not 'WARNING radar_calib_ros.io.bag:
        # ...' beside them (a probe's finding); -v keeps the logger names
        for handler in logging.getLogger().handlers:
            handler.setFormatter(_PlainFormatter())
    # one filter per handler: each passes a record the others have passed too
    filters = [(handler, _Once()) for handler in logging.getLogger().handlers]
    for handler, once in filters:
        handler.addFilter(once)
    try:
        return _run(args, out or _PipeSafe(sys.stdout))
    finally:
        for handler, once in filters:
            handler.removeFilter(once)


class _PlainFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f'{record.levelname.lower()}: {record.getMessage()}'


class _PipeSafe:
    """stdout that a reader gone away (``radar-calib calibrate BAG | head -3``) does not
    stop: the command goes on and writes its files, and its exit code says what it did.
    A broken pipe failed the run after the result was written (exit 2, 'cannot write
    None: Broken pipe', a probe's finding)."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self._gone = False

    def write(self, text: str) -> int:
        if not self._gone:
            try:
                self._stream.write(text)
                self._stream.flush()
            except BrokenPipeError:
                self._gone = True
                # the interpreter's own flush of stdout at exit must not fail either
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, self._stream.fileno())
                os.close(devnull)
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self._stream.isatty()

    def fileno(self) -> int:
        return self._stream.fileno()


class _Once(logging.Filter):
    """Lets each warning through once per run: the bag is opened by several steps (its
    radar frame, its radar topics, the reading), and a twenty-fifth probe read 'has no
    metadata.yaml' three times."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        key = (record.name, record.getMessage())
        if key in self._seen:
            return False
        self._seen.add(key)
        return True


def _run(args: argparse.Namespace, out: TextIO) -> int:
    try:
        return int(args.func(args, out))
    except CalibrationError as err:
        print(f'error: {err}', file=sys.stderr)
        return exit_code(err)
    except KeyboardInterrupt:
        print('error: interrupted', file=sys.stderr)
        return 130
    except OSError as err:  # a result, report or bag that cannot be written after all
        print(f'error: cannot write {err.filename!r}: {err.strerror or err}', file=sys.stderr)
        return 2
    except (ArithmeticError, ValueError) as err:  # numpy's LinAlgError is a ValueError
        # A numerical failure on data nothing above foresaw (a clock jump once made the
        # tracking filter's covariance indefinite): the data cannot be calibrated as they
        # are; say where, not a bare traceback (-v shows it).
        _LOG.debug('unexpected failure', exc_info=True)
        print(f'error: the calibration failed on these data ({type(err).__name__}: {err}); '
              'rerun with -v for the details and please report it with the recording',
              file=sys.stderr)
        return 1


def console_main() -> None:
    sys.exit(main())


if __name__ == '__main__':
    console_main()
