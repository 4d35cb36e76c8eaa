"""radar-calib: exit codes and one-line errors for bad input (no traceback)."""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pytest
import yaml

from radar_calib_ros.cli import main
from radar_calib_ros.config import CalibConfig


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    out = io.StringIO()
    code = main(argv, out=out)
    return code, out.getvalue(), capsys.readouterr().err


def test_missing_bag_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(['calibrate', str(tmp_path / 'nope'), '--output',
                         str(tmp_path / 'r.yaml')], capsys)
    assert code == 2
    assert err.startswith('error: ') and err.count('\n') == 1 and 'Traceback' not in err
    assert not (tmp_path / 'r.yaml').exists()


def test_directory_that_is_not_a_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / 'notabag').mkdir()
    (tmp_path / 'notabag' / 'x.txt').write_text('hello')
    code, _, err = _run(['calibrate', str(tmp_path / 'notabag')], capsys)
    assert code == 2 and 'error: ' in err


def test_a_numerical_failure_is_one_line_and_exit_1(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """An unforeseen numerical failure deep in the pipeline (a clock jump once made the
    tracking filter fail) ends in one line naming it, exit 1, no result file."""
    import numpy as np

    from radar_calib_ros import cli

    def fail(*args: object, **kwargs: object) -> None:
        raise np.linalg.LinAlgError('Matrix is not positive definite')

    monkeypatch.setattr(cli, '_refuse_ambiguous_radar', lambda *args: None)
    monkeypatch.setattr(cli, '_warn_frame_id', lambda *args: None)
    monkeypatch.setattr(cli, 'calibrate_bag', fail)
    code, _, err = _run(['calibrate', str(tmp_path), '--output', str(tmp_path / 'r.yaml')],
                        capsys)
    assert code == 1 and 'Traceback' not in err and err.count('\n') == 1
    assert 'LinAlgError: Matrix is not positive definite' in err
    assert not (tmp_path / 'r.yaml').exists()


def test_an_unwritable_result_path_exits_2_before_or_after_the_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Before the work where it can be told (a file where a folder should be), and in one
    line, not a traceback, where only the write finds out."""
    from radar_calib_ros import cli

    (tmp_path / 'file').write_text('')
    monkeypatch.setattr(cli, '_refuse_ambiguous_radar', lambda *args: None)
    monkeypatch.setattr(cli, '_warn_frame_id', lambda *args: None)
    worked: list[bool] = []
    monkeypatch.setattr(cli, 'calibrate_bag', lambda *a, **k: worked.append(True))
    for output in (tmp_path / 'file' / 'r.yaml', tmp_path):
        code, _, err = _run(['calibrate', str(tmp_path), '--output', str(output)], capsys)
        assert code == 2 and err.startswith("error: cannot write the result to ")
        assert 'Traceback' not in err and err.count('\n') == 1 and not worked

    def fail_to_write(*args: object, **kwargs: object) -> None:
        raise FileNotFoundError(2, 'No such file or directory', '/proc/x')

    monkeypatch.setattr(cli, 'calibrate_bag', fail_to_write)
    code, _, err = _run(['calibrate', str(tmp_path), '--output', str(tmp_path / 'r.yaml')],
                        capsys)
    assert code == 2 and err == "error: cannot write '/proc/x': No such file or directory\n"


def test_bad_params_file_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    vehicle: {lenght: 4.0}\n')
    code, _, err = _run(['calibrate', str(tmp_path), '--params', str(params)], capsys)
    assert code == 2 and "unknown parameter 'vehicle.lenght'" in err


def test_wrong_type_in_params_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    world.epsg: utm\n')
    code, _, err = _run(['calibrate', str(tmp_path), '--params', str(params)], capsys)
    assert code == 2 and "'world.epsg' must be int" in err


def test_bad_usage_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['calibrate']) == 2
    assert main(['no-such-command']) == 2
    assert main(['--help']) == 0
    capsys.readouterr()


def test_demo_end_to_end_against_ground_truth(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """The README's main job: simulate, calibrate, compare, report; then the same bag again
    through `calibrate --json`, whose result must agree with the ground truth."""
    import json

    from radar_calib_ros.groundtruth import calibration_errors, load_ground_truth
    from radar_calib_ros.result import load_result

    code, out, err = _run(['demo', '--out', str(tmp_path / 'demo'), '--duration', '150'],
                          capsys)
    assert code == 0, err
    assert 'errors: horizontal' in out and '4/4 report' in out
    assert (tmp_path / 'demo' / 'report' / 'report.html').is_file()
    bag = tmp_path / 'demo' / 'demo_bag'
    truth = load_ground_truth(bag)
    assert truth is not None
    estimate = load_result(tmp_path / 'demo' / 'result.yaml')
    errors = calibration_errors(estimate, truth)
    # the box it was made with, for evaluate on another recording
    assert set(estimate['quality']['vehicle']) == {'length', 'width', 'height',
                                                   'rear_overhang', 'ref_height'}
    # and its passes' part of the uncertainty, which evaluate judges the tilt by
    passes, sigma = estimate['quality']['sigma_passes'], estimate['quality']['sigma']
    assert set(passes) == {'along_boresight_m', 'across_boresight_m', 'vertical_m',
                           'roll_deg', 'pitch_deg', 'yaw_deg'}
    assert 0.0 < passes['pitch_deg'] <= sigma['pitch_deg']
    assert errors['horizontal_m'] < 0.10
    assert errors['vertical_m'] < 0.20
    assert errors['rotation_deg'] < 0.3

    code, out, err = _run(['calibrate', str(bag), '--params', str(bag / 'params.yaml'),
                           '--output', str(tmp_path / 'r.yaml'), '--json',
                           str(tmp_path / 'r.json')], capsys)
    assert code == 0, err
    as_json = json.loads((tmp_path / 'r.json').read_text())
    assert as_json['translation'] == pytest.approx(estimate['translation'], abs=1e-6)
    assert 'position' in out and 'result written to' in out

    # A radar that reports approach as positive (velocity_sign -1 read on this bag flips
    # every v_r): told from the vehicle's motion, flipped back, and said.
    params = yaml.safe_load((bag / 'params.yaml').read_text())
    params['/**']['ros__parameters'].setdefault('radar', {})['velocity_sign'] = -1.0
    (tmp_path / 'flipped.yaml').write_text(yaml.safe_dump(params))
    code, out, err = _run(['calibrate', str(bag), '--params', str(tmp_path / 'flipped.yaml'),
                           '--output', str(tmp_path / 'f.yaml')], capsys)
    assert code == 0, err
    assert 'opposite sign' in out + err and 'velocity_sign to 1' in out + err
    flipped = calibration_errors(load_result(tmp_path / 'f.yaml'), truth)
    assert flipped['horizontal_m'] < 0.10 and flipped['rotation_deg'] < 0.3


def test_folded_radial_velocities_are_unfolded_and_said(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        caplog: pytest.LogCaptureFixture) -> None:
    """A radar that folds radial velocities beyond +-5 m/s (half the vehicle's targets):
    the final fit used to run off by metres and ten degrees and exit 1. The note is said
    once on stderr: logged as the pipeline meets it, not printed again after the summary
    (a nineteenth probe read it twice)."""
    from radar_calib_ros.groundtruth import calibration_errors
    from radar_calib_ros.result import load_result
    from radar_calib_ros.sim import simulate
    bag = tmp_path / 'folded'
    summary = simulate(bag, seed=3, duration_s=150.0, max_unambiguous_velocity_mps=5.0)
    assert summary.truth['max_unambiguous_velocity_mps'] == 5.0
    code, out, err = _run(['calibrate', str(bag), '--params', str(bag / 'params.yaml'),
                           '--output', str(tmp_path / 'r.yaml')], capsys)
    assert code == 0, err
    assert 'fold over at +-5.0 m/s' in out + err
    logged = [r for r in caplog.records if 'fold over at' in r.getMessage()]
    assert len(logged) == 1 and logged[0].levelname == 'WARNING'
    assert 'fold over at' not in err   # not printed again as a warning: line
    errors = calibration_errors(load_result(tmp_path / 'r.yaml'), summary.truth)
    assert errors['horizontal_m'] < 0.10 and errors['rotation_deg'] < 0.3


def test_a_gnss_receiver_at_1_hz_beside_the_ins_calibrates(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The slow_gnss scenario: NavSatFix at 1 Hz, stamped 0.12 s late (on output), Odometry
    at 50 Hz. The default sync.max_pose_gap (0.5 s) is kept: the Odometry bridges the fixes,
    the fixes' lag is found and named, and the calibration lands as with fast fixes (it used
    to be refused: 'poses come every 1.00 s')."""
    import re

    from radar_calib_ros.groundtruth import calibration_errors
    from radar_calib_ros.result import load_result
    from radar_calib_ros.sim import simulate
    bag = tmp_path / 'slow'
    summary = simulate(bag, seed=3, duration_s=150.0, scenario='slow_gnss')
    code, out, err = _run(['calibrate', str(bag), '--params', str(bag / 'params.yaml'),
                           '--output', str(tmp_path / 'r.yaml')], capsys)
    assert code == 0, err
    lag = re.search(r"NavSatFix stamps lag the Odometry's by (-?\d+) ms", out + err)
    assert lag is not None and 60 <= int(lag.group(1)) <= 180, out + err
    errors = calibration_errors(load_result(tmp_path / 'r.yaml'), summary.truth)
    assert errors['horizontal_m'] < 0.10 and errors['rotation_deg'] < 0.3, errors
    # the summary's advice is said once, not again as warnings
    advice = [line[len('  advice: '):] for line in out.splitlines()
              if line.startswith('  advice: ')]
    assert not any(a in err for a in advice)


class _Stream(io.StringIO):
    def __init__(self, tty: bool) -> None:
        super().__init__()
        self._tty = tty

    def isatty(self) -> bool:
        return self._tty


@pytest.mark.parametrize('out_tty, err_tty, echoed', [
    (True, True, False), (False, True, True), (False, False, False), (True, False, False)])
def test_the_advice_reaches_a_terminal_once(monkeypatch: pytest.MonkeyPatch, out_tty: bool,
                                            err_tty: bool, echoed: bool) -> None:
    """The summary (stdout) carries the advice; it is repeated on stderr only for someone
    watching a terminal while the summary goes to a file or a pipe."""
    import sys

    from radar_calib_ros import cli
    monkeypatch.setattr(sys, 'stderr', _Stream(err_tty))
    assert cli._echo_advice(_Stream(out_tty)) is echoed


def test_vehicle_never_in_view_exits_1_without_result(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from radar_calib_ros.sim import simulate
    bag = tmp_path / 'never'
    simulate(bag, seed=3, duration_s=90.0, scenario='vehicle_never_in_view')
    # --no-progress: a slow machine's 'progress:' lines are not what this test counts
    code, _, err = _run(['calibrate', str(bag), '--params', str(bag / 'params.yaml'),
                         '--output', str(tmp_path / 'r.yaml'), '--no-progress'], capsys)
    assert code == 1
    assert err.startswith('error: ') and err.count('\n') == 1
    assert not (tmp_path / 'r.yaml').exists()


def test_a_radar_frame_id_unlike_the_parameter_is_warned(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    from radar_calib_ros import cli
    from radar_calib_ros.io import bag as bag_io

    config = CalibConfig()
    monkeypatch.setattr(bag_io, 'radar_frame_ids',
                        lambda path: {config.radar_topic: 'radar_front_link'})
    cli._warn_frame_id('some.bag', config)
    err = capsys.readouterr().err
    assert err.startswith("warning: the radar's messages are in frame 'radar_front_link'")
    assert 'set radar.frame_id: radar_front_link' in err
    # the topic named without its leading '/', as select_topics matches it
    bare = config.radar_topic.lstrip('/')
    monkeypatch.setattr(bag_io, 'radar_frame_ids',
                        lambda path: {bare: 'radar_front_link', '/other/points': 'radar'})
    cli._warn_frame_id('some.bag', config)
    assert "frame 'radar_front_link'" in capsys.readouterr().err
    # the same frame (a leading slash aside), or a header without one: nothing to say
    for same in ('/radar', 'radar', ''):
        monkeypatch.setattr(bag_io, 'radar_frame_ids',
                            lambda path, f=same: {config.radar_topic: f})
        cli._warn_frame_id('some.bag', config)
        assert capsys.readouterr().err == ''


def test_evaluate_finds_one_radars_topic_by_its_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """One radar's result of --all-radars on the bag of all of them: its radar_frame names
    the topic where the parameters do not; a topic the parameters name is kept."""
    from radar_calib_ros import cli
    from radar_calib_ros.io import bag as bag_io

    frames = {'/north/points': 'radar_ne', '/south/points': 'radar_sw'}
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: frames)
    assert cli._topic_of_frame('b', CalibConfig(), 'radar_sw') == '/south/points'
    assert cli._topic_of_frame('b', CalibConfig(), 'radar') is None
    named = CalibConfig.from_mapping({'radar_topic': '/north/points'})
    assert cli._topic_of_frame('b', named, 'radar_sw') is None


def test_evaluating_a_result_of_another_radar_frame_warns(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A result of radar frame 'radar_north' evaluated on a bag of 'radar' clouds (a
    thirty-seventh probe: evaluated without a word) warns; the same frame, or a header
    naming none, does not."""
    from radar_calib_ros import cli
    from radar_calib_ros.io import bag as bag_io

    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: {'/radar/points': 'radar'})
    config = CalibConfig.from_mapping({'radar_topic': '/radar/points'})
    cli._warn_other_radar('b', config, None, 'radar_north')
    err = capsys.readouterr().err
    assert "result is of radar frame 'radar_north'" in err and "in frame 'radar'" in err
    cli._warn_other_radar('b', config, None, '/radar')
    assert capsys.readouterr().err == ''
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: {'/radar/points': ''})
    cli._warn_other_radar('b', config, None, 'radar_north')
    assert capsys.readouterr().err == ''


def test_calibrate_finds_the_radar_of_the_frame_the_parameters_name(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Several radar topics, none named, radar.frame_id set: calibrate takes the topic in
    that frame, as evaluate does (it refused before: 'the parameters name none')."""
    from radar_calib_ros import cli
    from radar_calib_ros.io import bag as bag_io

    frames = {'/north/points': 'radar_ne', '/south/points': 'radar_sw'}
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: frames)
    by_frame = CalibConfig.from_mapping({'radar.frame_id': 'radar_sw'})
    chosen = cli._radar_of_frame('b', by_frame)
    assert chosen.radar_topic == '/south/points' and 'radar_topic' in chosen.explicit
    # the default frame, a frame no topic is in, or a topic already named: left alone
    assert cli._radar_of_frame('b', CalibConfig()) == CalibConfig()
    elsewhere = CalibConfig.from_mapping({'radar.frame_id': 'radar_x'})
    assert cli._radar_of_frame('b', elsewhere).radar_topic == CalibConfig().radar_topic
    named = CalibConfig.from_mapping({'radar.frame_id': 'radar_sw',
                                      'radar_topic': '/north/points'})
    assert cli._radar_of_frame('b', named).radar_topic == '/north/points'


def test_a_frame_that_picks_no_radar_topic_or_two_is_named_in_the_refusal(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Several radar topics, no radar_topic, radar.frame_id naming a frame no topic is in
    or two topics are in: the refusal says what the frame matched (it said 'the parameters
    name none' beside the frame they named, a forty-seventh and forty-eighth probe)."""
    from radar_calib_ros import cli, multi_radar
    from radar_calib_ros.errors import BagReadError
    from radar_calib_ros.io import bag as bag_io

    frames = {'/a/points': 'radar_east', '/b/points': 'radar_east', '/c/points': 'radar_w'}
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: frames)
    monkeypatch.setattr(multi_radar, 'ambiguous_radar_topics', lambda bag, config: list(frames))
    for frame, said in (('radar_east', "'radar_east' is the frame of 2 of them (/a/points, "
                                       '/b/points), and the parameters name no radar_topic'),
                        ('radar_x', "'radar_x' is the frame of none of them")):
        config = CalibConfig.from_mapping({'radar.frame_id': frame})
        with pytest.raises(BagReadError, match='3 radar topics') as err:
            cli._refuse_ambiguous_radar('b', config)
        assert said in str(err.value) and 'name none' not in str(err.value)
    with pytest.raises(BagReadError, match='the parameters name none'):
        cli._refuse_ambiguous_radar('b', CalibConfig())


def test_a_warning_said_by_several_steps_is_printed_once(
        capsys: pytest.CaptureFixture[str]) -> None:
    """The bag is opened by several steps of one run, each warning alike ('has no
    metadata.yaml' three times): a run lets each warning through once, and leaves no
    filter behind for the next run."""
    import logging

    from radar_calib_ros import cli

    def record(name: str, level: int, text: str) -> logging.LogRecord:
        return logging.LogRecord(name, level, __file__, 1, text, None, None)
    once = cli._Once()
    bag = 'radar_calib_ros.io.bag'
    assert once.filter(record(bag, logging.WARNING, 'no metadata.yaml'))
    assert not once.filter(record(bag, logging.WARNING, 'no metadata.yaml'))
    assert once.filter(record('radar_calib_ros.cli', logging.WARNING, 'no metadata.yaml'))
    assert once.filter(record(bag, logging.INFO, 'read'))
    assert once.filter(record(bag, logging.INFO, 'read'))
    handlers = logging.getLogger().handlers
    before = [list(h.filters) for h in handlers]
    assert main(['calibrate', 'no-such-bag']) == 2
    assert [list(h.filters) for h in handlers] == before


def test_report_reads_the_calibrated_radars_topic_as_evaluate_does(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """One radar's result of --all-radars (or the combined file with radar.frame_id set)
    on the bag of all the radars: report read the bag's radar topic by the parameters alone
    and refused (exit 2, several radar topics) what evaluate took."""
    from types import SimpleNamespace

    from radar_calib_ros import cli, report
    from radar_calib_ros import result as result_io
    from radar_calib_ros.io import bag as bag_io

    frames = {'/north/points': 'radar_ne', '/south/points': 'radar_sw'}
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: frames)
    read: list[str | None] = []
    monkeypatch.setattr(bag_io, 'read_recording', lambda bag, config, radar_topic=None,
                        progress=None: read.append(radar_topic))
    asked: list[str | None] = []

    def load(path: Any, radar_frame: str | None = None) -> dict[str, Any]:
        asked.append(radar_frame)
        return {'radar_frame': 'radar_sw'}
    monkeypatch.setattr(result_io, 'load_result', load)
    monkeypatch.setattr(report, 'report_recording',
                        lambda *a, **k: SimpleNamespace(html='report.html', figures=[]))
    params = tmp_path / 'p.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {'radar.frame_id':
                                                                  'radar_sw'}}}))
    argv = ['report', str(tmp_path / 'bag'), '--calibration', str(tmp_path / 'all.yaml'),
            '--params', str(params), '--out', str(tmp_path / 'out')]
    assert cli.main(argv) == 0
    assert read == ['/south/points'] and asked == ['radar_sw']


# --- outputs never replace inputs (an operator probe's findings) ------------------------

def _small_bag(tmp_path: Path) -> Path:
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    (bag / 'bag_0.mcap').write_bytes(b'x')
    return bag


@pytest.mark.parametrize('flags, inputs, named', [
    (['--output', 'site.yaml', '--params', 'site.yaml'], ['site.yaml'], 'parameters file'),
    (['--output', 'same.yaml', '--json', 'same.yaml'], [], 'name the same file'),
    (['--output', 'bag/metadata.yaml'], [], 'file of the recording'),
    (['--json', 'bag/bag_0.mcap'], [], 'file of the recording'),
    (['--output', 'bag/bag_0.mcap', '--bag-as-metadata'], [], 'file of the recording'),
    (['--output', 'link.yaml', '--params', 'site.yaml'], ['site.yaml', 'link.yaml'],
     'parameters file'),
])
def test_calibrate_refuses_outputs_that_would_replace_an_input(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        flags: list[str], inputs: list[str], named: str) -> None:
    monkeypatch.chdir(tmp_path)
    bag = _small_bag(tmp_path)
    before = {p: p.read_bytes() for p in bag.iterdir()}
    for name in inputs:
        if name == 'link.yaml':
            (tmp_path / name).symlink_to(tmp_path / 'site.yaml')
        else:
            (tmp_path / name).write_text('/**:\n  ros__parameters:\n    vehicle.length: 4.9\n')
    bag_arg = 'bag'
    if '--bag-as-metadata' in flags:   # the bag given by its metadata.yaml
        flags, bag_arg = [f for f in flags if f != '--bag-as-metadata'], 'bag/metadata.yaml'
    code, out, err = _run(['calibrate', bag_arg, *flags], capsys)
    assert code == 2 and named in err and err.count('\n') == 1 and out == ''
    assert {p: p.read_bytes() for p in bag.iterdir()} == before
    if inputs:
        assert 'vehicle.length' in (tmp_path / 'site.yaml').read_text()


def test_evaluate_refuses_its_json_onto_the_calibration(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / 'c.json').write_text('{"keep": 1}')
    code, _, err = _run(['evaluate', str(_small_bag(tmp_path)), '--calibration',
                         str(tmp_path / 'c.json'), '--json', str(tmp_path / 'c.json')], capsys)
    assert code == 2 and 'is the calibration file' in err
    assert (tmp_path / 'c.json').read_text() == '{"keep": 1}'


@pytest.mark.parametrize('command', ['evaluate', 'report'])
def test_evaluate_and_report_take_the_progress_options_of_calibrate(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        command: str) -> None:
    """A fifty-sixth probe's script passed --no-progress to every command, as calibrate
    takes it; evaluate refused it (exit 2). All three read a recording, and all three
    show (or, told so, do not show) its reading."""
    from radar_calib_ros import result as result_io
    from radar_calib_ros.errors import BagReadError
    from radar_calib_ros.io import bag as bag_io
    told: list[Any] = []

    def read(bag: Any, config: Any, radar_topic: Any = None, progress: Any = None) -> Any:
        told.append(progress)
        raise BagReadError('stop here: the options were taken')
    monkeypatch.setattr(bag_io, 'read_recording', read)
    monkeypatch.setattr(bag_io, 'radar_frame_ids', lambda path: {'/radar/points': 'radar'})
    monkeypatch.setattr(result_io, 'load_result',
                        lambda path, frame=None: {'radar_frame': 'radar'})
    tail = ['--out', str(tmp_path / 'o')] if command == 'report' else []
    for flag, mode in (('--no-progress', 'off'), ('--progress', 'bars')):
        (tmp_path / flag).mkdir()
        code, _, err = _run([command, str(_small_bag(tmp_path / flag)), '--calibration',
                             str(tmp_path / 'c.yaml'), flag, *tail], capsys)
        assert code == 2 and 'stop here' in err
        assert told[-1].__self__.mode == mode   # the reader's progress, as asked


def test_misplaced_options_are_refused(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    bag = str(_small_bag(tmp_path))
    code, _, err = _run(['calibrate', bag, '--output-dir', str(tmp_path / 'd')], capsys)
    assert code == 2 and '--output-dir goes with --all-radars' in err
    code, _, err = _run(['calibrate', bag, '--all-radars', '--jobs', '0'], capsys)
    assert code == 2 and '--jobs 0' in err
    (tmp_path / 'afile').write_text('x')
    code, _, err = _run(['report', bag, '--calibration', str(tmp_path / 'afile'), '--out',
                         str(tmp_path / 'afile')], capsys)
    assert code == 2 and 'is a file, not a directory' in err
    code, out, err = _run(['demo', '--duration', '5', '--out', str(tmp_path / 'demo')], capsys)
    assert code == 2 and 'outside [10, 3600]' in err and out == ''


def test_a_result_file_given_as_parameters_is_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from radar_calib_ros.io.geo import LocalFrame
    from radar_calib_ros.result import calibration_dict, write_result_yaml
    from radar_calib_ros.types import Extrinsics
    import numpy as np
    write_result_yaml(tmp_path / 'r.yaml', calibration_dict(
        Extrinsics(np.eye(3), np.array([1.0, 2.0, 500.0])), LocalFrame.at(48.4, 9.99)))
    code, _, err = _run(['calibrate', str(_small_bag(tmp_path)), '--params',
                         str(tmp_path / 'r.yaml')], capsys)
    assert code == 2 and 'is a result file of radar-calib calibrate, not a parameters' in err


def test_a_reader_gone_from_the_pipe_does_not_fail_the_run(tmp_path: Path) -> None:
    """`radar-calib ... | head -1`: the output written, exit code of the work, no 'Broken
    pipe' error after the result was written."""
    import os

    from radar_calib_ros.cli import _PipeSafe
    read_end, write_end = os.pipe()
    os.close(read_end)
    stream = os.fdopen(write_end, 'w')
    try:
        safe = _PipeSafe(stream)
        assert safe.write('summary\n') == len('summary\n')   # no BrokenPipeError
        assert safe.write('more\n') == len('more\n')
        stream.write('flushed at exit\n')
        stream.flush()     # stdout now leads to /dev/null: the interpreter's flush passes
    finally:
        stream.close()


def test_the_advice_is_not_repeated_into_a_pipe(monkeypatch: pytest.MonkeyPatch,
                                                tmp_path: Path) -> None:
    """`| cat` or `| tee log` show the summary on the same terminal: no second copy."""
    import os
    import sys

    from radar_calib_ros import cli
    monkeypatch.setattr(sys, 'stderr', _Stream(True))
    read_end, write_end = os.pipe()
    with os.fdopen(write_end, 'w') as pipe, open(tmp_path / 'log', 'w') as file:
        assert cli._echo_advice(pipe) is False
        assert cli._echo_advice(file) is True
    os.close(read_end)


def test_log_warnings_read_as_the_tools_own() -> None:
    import logging

    from radar_calib_ros.cli import _PlainFormatter
    record = logging.LogRecord('radar_calib_ros.io.bag', logging.WARNING, __file__, 1,
                               '%r has no metadata.yaml', ('bag',), None)
    assert _PlainFormatter().format(record) == "warning: 'bag' has no metadata.yaml"


def test_progress_off_a_terminal_is_a_line_now_and_then_once_a_run_is_long(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """stderr to a log or a pipe: nothing in the first 10 s (short runs stay quiet), then a
    line at each stage and every 10 s while reading; --no-progress: nothing at all."""
    import sys

    from radar_calib_ros import cli
    now = [0.0]
    err = _Stream(False)
    monkeypatch.setattr(sys, 'stderr', err)
    progress = cli._Progress('lines', clock=lambda: now[0])
    for t, done in ((1.0, 1000), (9.0, 9000), (11.0, 11000), (15.0, 15000), (22.0, 22000)):
        now[0] = t
        progress.reading(done, 40_000)
    for t, stage in ((23.0, 'moving'), (24.0, 'cluster'), (40.0, 'done')):
        now[0] = t
        progress.stage(stage, 0.5)
    lines = err.getvalue().splitlines()
    assert lines == [
        'progress: reading the recording, 11,000 of 40,000 messages, 11 s',
        'progress: reading the recording, 22,000 of 40,000 messages, 22 s',
        'progress: calibrating, stage moving (50% done), 23 s',
        'progress: calibrating, stage cluster (50% done), 24 s']
    monkeypatch.setattr(sys, 'stderr', _Stream(False))
    assert cli._Progress.for_stderr(None).mode == 'lines'
    assert cli._Progress.for_stderr(False).mode == 'off'
    assert cli._Progress.for_stderr(True).mode == 'bars'
    monkeypatch.setattr(sys, 'stderr', _Stream(True))
    assert cli._Progress.for_stderr(None).mode == 'bars'
    quiet = _Stream(False)
    monkeypatch.setattr(sys, 'stderr', quiet)
    off = cli._Progress('off', clock=lambda: now[0])
    now[0] = 100.0
    off.reading(1, 2)
    off.stage('refine', 0.8)
    assert quiet.getvalue() == ''
    with pytest.raises(ValueError):
        cli._Progress('loud')


def test_the_summary_says_which_point_of_the_vehicle_the_altitude_rests_on() -> None:
    """A roof antenna's pose with a rear axle's vehicle.* puts the radar metres high and the
    data cannot show it (a thirty-first probe): the summary names the point it assumed."""
    import dataclasses

    from radar_calib_ros.cli import summary_lines
    calibration = {'radar_frame': 'radar', 'world_frame': 'utm', 'epsg': 32632,
                   'translation': [1.0, 2.0, 3.0], 'rpy_deg': [0.0, 0.0, 0.0],
                   'latitude': 48.0, 'longitude': 11.0, 'boresight_azimuth_deg': 90.0}
    assert not any('reference' in line for line in summary_lines(calibration))
    vehicle = dataclasses.replace(CalibConfig().vehicle, ref_height=1.73, rear_overhang=2.55)
    lines = summary_lines(calibration, vehicle=vehicle)
    assert lines[1].startswith('  position') and lines[2] == (
        '  reference  pose point 1.73 m above the road, 2.55 m ahead of the rear bumper '
        '(vehicle.ref_height, rear_overhang): the altitude rests on it')
    # an antenna to one side of the centre line (vehicle.ref_left)
    right = dataclasses.replace(vehicle, ref_left=-0.4)
    assert summary_lines(calibration, vehicle=right)[2].endswith(
        '2.55 m ahead of the rear bumper, 0.40 m right of the centre line (vehicle.ref_height, '
        'rear_overhang, ref_left): the altitude rests on it')
    # and the vehicle's mean reflection height it assumed (a fortieth probe's van: 0.7 m low,
    # nothing said about heights)
    calibration['quality'] = {'reflection_height_prior_m': [0.35, 0.3]}
    lines = summary_lines(calibration, vehicle=vehicle)
    assert lines[3].startswith("  heights    the vehicle's targets taken as 0.35 +- 0.30 m "
                               'above the road on average (refine.reflection_height_m'), lines


def test_two_bags_of_one_drive_calibrate_as_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], drive: Any) -> None:
    """A drive whose recorder restarted halfway: both bags given together calibrate on
    every pass (a fiftieth probe had to copy their storage files into one folder)."""
    import json

    from rosbags.rosbag2 import Reader

    from radar_calib_ros.groundtruth import calibration_errors
    from radar_calib_ros.io.bag import write_bag
    summary, _ = drive
    with Reader(summary.paths.bag) as reader:
        items = [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]
    items.sort(key=lambda item: item[2])
    middle = (items[0][2] + items[-1][2]) // 2
    halves = [tmp_path / 'first', tmp_path / 'second']
    write_bag(halves[0], (i for i in items if i[2] < middle))
    write_bag(halves[1], (i for i in items if i[2] >= middle), storage='sqlite3')
    params = str(summary.paths.params)
    code, out, err = _run(['calibrate', *map(str, halves), '--params', params,
                           '--json', str(tmp_path / 'both.json'), '--output',
                           str(tmp_path / 'both.yaml'), '--no-progress'], capsys)
    assert code == 0, err
    assert f'note: reading 2 bags as one recording: {halves[0]}, {halves[1]}' in err
    both = json.loads((tmp_path / 'both.json').read_text())
    truth = json.loads(summary.paths.ground_truth.read_text())
    errors = calibration_errors(both, truth)
    assert errors['horizontal_m'] < 0.15 and errors['rotation_deg'] < 0.5
    code, _, err = _run(['calibrate', str(halves[0]), '--params', params, '--json',
                         str(tmp_path / 'first.json'), '--output',
                         str(tmp_path / 'first.yaml'), '--no-progress'], capsys)
    if code == 0:
        first = json.loads((tmp_path / 'first.json').read_text())
        assert both['quality']['passes'] > first['quality']['passes']
    else:
        assert code == 1 and 'pass' in err, err   # too few passes in half the drive
    # a result onto a file of the second bag is refused as onto the first's
    code, _, err = _run(['calibrate', *map(str, halves), '--params', params, '--output',
                         str(halves[1] / 'metadata.yaml')], capsys)
    assert code == 2 and f'file of the recording {str(halves[1])!r}' in err
