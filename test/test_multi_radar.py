"""Several radars in one recording: the simulator's 'three_radars' scenario and
``radar-calib calibrate --all-radars`` (CONTRACT.md "The offline tool")."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from radar_calib_ros.cli import main
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.evaluate import calibration_extrinsics
from radar_calib_ros.groundtruth import calibration_errors, load_ground_truth
from radar_calib_ros.io.bag import radar_frame_ids
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.multi_radar import TRANSFORM_KEYS, combined_parameters, radar_frames
from radar_calib_ros.result import load_result
from radar_calib_ros.sim import SimulationSummary, simulate

FRAMES = ['radar_1', 'radar_2', 'radar_3']


@pytest.fixture(scope='module')
def three(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulationSummary, Path]:
    """180 s past three radars (five or six passes each) and a parameters file that accepts
    two agreeing passes, so that each radar calibrates from this short drive. (At 150 s, one
    radar of some drives sees four passes and two of them are other road users that agree
    by chance: the tool rightly refuses it.)"""
    root = tmp_path_factory.mktemp('three')
    sim = simulate(root / 'bag', seed=5, duration_s=180.0, scenario='three_radars')
    params = yaml.safe_load(sim.paths.params.read_text())
    params['/**']['ros__parameters']['hypotheses'] = {'min_passes': 2}
    path = root / 'params_two_passes.yaml'
    path.write_text(yaml.safe_dump(params))
    return sim, path


def test_recording_holds_three_radars_with_their_own_truth(
        three: tuple[SimulationSummary, Path]) -> None:
    sim, _ = three
    bag = sim.paths.bag
    assert radar_frame_ids(bag) == {f'/{f}/points': f for f in FRAMES}
    assert list(sim.radars) == FRAMES
    truths = {f: load_ground_truth(bag, f) for f in FRAMES}
    assert all(t is not None and t['radar_frame'] == f for f, t in truths.items())
    # ground_truth.json stays a valid single-radar truth (radar_1's) listing all radars
    main_truth = load_ground_truth(bag)
    assert main_truth is not None
    assert main_truth['translation'] == truths['radar_1']['translation']
    assert [r['radar_frame'] for r in main_truth['radars']] == FRAMES
    assert load_ground_truth(bag, 'radar_9') is None
    positions = np.array([truths[f]['translation'] for f in FRAMES])
    spacing = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=-1)
    assert spacing[np.triu_indices(3, 1)].min() > 20.0      # three different poles
    for frame in FRAMES:
        with np.load(bag / f'ground_truth_targets_{frame}.npz') as npz:
            assert npz['is_calibration_vehicle'].sum() > 1000
    # no radar named in the parameters: the user must choose
    text = sim.paths.params.read_text()
    assert 'radar_topic' not in text and 'frame_id' not in text


def test_plain_calibrate_refuses_several_radars(three: tuple[SimulationSummary, Path],
                                                tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    sim, params = three
    out = tmp_path / 'result.yaml'
    code = main(['calibrate', str(sim.paths.bag), '--params', str(params), '--output',
                 str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert '--all-radars' in err and 'radar_topic' in err
    assert all(f'/{f}/points' in err for f in FRAMES)
    assert not out.exists()


def test_all_radars_calibrates_each_radar(three: tuple[SimulationSummary, Path],
                                          tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    sim, params = three
    out_dir = tmp_path / 'calibrations'
    code = main(['calibrate', str(sim.paths.bag), '--params', str(params), '--all-radars',
                 '--output-dir', str(out_dir), '--json', str(tmp_path / 'all.json'),
                 '--output', str(tmp_path / 'site' / 'radars.yaml'), '--jobs', '2'])
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert '3 of 3 radars calibrated' in stdout
    assert sorted(p.name for p in out_dir.iterdir()) == [
        'all_radars.yaml', 'radar_1.yaml', 'radar_2.yaml', 'radar_3.yaml']
    combined = yaml.safe_load((out_dir / 'all_radars.yaml').read_text())
    params_ = combined['/**']['ros__parameters']
    assert params_['radar_frames'] == FRAMES
    # --output, when named, gets the combined transforms too
    assert yaml.safe_load((tmp_path / 'site' / 'radars.yaml').read_text()) == combined
    as_json = json.loads((tmp_path / 'all.json').read_text())
    assert sorted(as_json) == FRAMES
    config = CalibConfig.from_file(params)
    for frame in FRAMES:
        result = load_result(out_dir / f'{frame}.yaml')
        assert result['radar_frame'] == frame and result['world_frame'] == 'utm'
        entry = params_['calibrations'][frame]
        assert set(entry) == set(TRANSFORM_KEYS) | {'time_offset_s', 'sync_time_offset_s'}
        assert entry['time_offset_s'] == result['quality']['time_offset_s']
        # evaluated from the combined file, the radar is where, and when, its own file says
        local = LocalFrame.at(result['latitude'], result['longitude'])
        own, combined_ = (calibration_extrinsics(c, local, config) for c in (result, entry))
        assert combined_.time_offset_s == own.time_offset_s
        assert np.allclose(combined_.translation_m, own.translation_m)
        assert entry['translation'] == pytest.approx(result['translation'])
        assert entry['quaternion_xyzw'] == pytest.approx(result['quaternion_xyzw'])
        assert as_json[frame]['translation'] == pytest.approx(result['translation'])
        # each result is its own radar's: decimetres from its truth, metres from the others
        errors = {f: calibration_errors(result, load_ground_truth(sim.paths.bag, f))
                  for f in FRAMES}
        assert errors[frame]['horizontal_m'] < 0.5
        assert errors[frame]['rotation_deg'] < 1.5
        assert min(e['horizontal_m'] for f, e in errors.items() if f != frame) > 20.0


def test_all_radars_bad_input_exits_2(tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    code = main(['calibrate', str(tmp_path / 'missing_bag'), '--all-radars', '--output-dir',
                 str(tmp_path / 'out')])
    assert code == 2
    assert capsys.readouterr().err.startswith('error: ')
    assert not (tmp_path / 'out').exists()


def test_all_radars_unwritable_output_exits_2_before_the_work(
        three: tuple[SimulationSummary, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    sim, params = three
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    code = main(['calibrate', str(sim.paths.bag), '--params', str(params), '--all-radars',
                 '--output-dir', str(tmp_path / 'out'), '--output', str(blocker / 'all.yaml')])
    assert code == 2
    assert 'cannot write the result' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_radar_frames_are_the_messages_frames_made_unique(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    """A frame with '/' (carla-ros-bridge: 'ego_vehicle/radar_front') stays as TF has it in
    the results; only file names and parameter keys make it 'ego_vehicle_radar_front'
    (a ninth probe's results named a frame no transform lookup would find). A frame shared
    or empty is replaced by the topic's name, and that is said."""
    found = {'/a/points': 'radar', '/b/points': 'radar', '/c/points': '', '/d/scan': 'x/y',
             '/e/scan': '/site/radar_e'}
    monkeypatch.setattr('radar_calib_ros.io.bag.radar_frame_ids', lambda bag: found)
    # the two in 'radar' are two radars: other clouds (a copy is one radar: test_bag.py)
    monkeypatch.setattr('radar_calib_ros.io.bag.radar_fingerprints',
                        lambda bag, topics: {t: (t,) for t in topics})
    with caplog.at_level('WARNING', logger='radar_calib_ros'):
        names = radar_frames('unused')
    assert names == {'/a/points': 'a_points', '/b/points': 'b_points', '/c/points': 'c_points',
                     '/d/scan': 'x/y', '/e/scan': 'site/radar_e'}
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 3 and "frame_id 'radar' is another radar's too" in said[0]
    assert "its result is for frame 'a_points'" in said[0] and "'' is empty" in said[2]
    from radar_calib_ros.multi_radar import RadarOutcome, write_outcomes
    cal = {k: 'x/y' if k == 'radar_frame' else k for k in TRANSFORM_KEYS}
    written = write_outcomes(tmp_path, [RadarOutcome('/d/scan', 'x/y', cal, None, 0)])
    assert [p.name for p in written] == ['x_y.yaml', 'all_radars.yaml']
    params = yaml.safe_load(written[1].read_text())['/**']['ros__parameters']
    assert params['radar_frames'] == ['x_y']
    assert params['calibrations']['x_y']['radar_frame'] == 'x/y'
    # evaluate finds it again by the frame it names
    from radar_calib_ros.result import _one_radar
    other = dict(params['calibrations']['x_y'], radar_frame='z')
    several = {'x_y': params['calibrations']['x_y'], 'z': other}
    assert _one_radar(several, 'x/y', tmp_path)['radar_frame'] == 'x/y'
    assert _one_radar(several, 'z', tmp_path) is other


def test_combined_parameters_hold_transforms_and_clocks() -> None:
    """The transforms and each radar's clock offset (a seventy-sixth probe's combined file
    dropped 0.15 s: r_i 68 -> 46 % on evaluation), not the quality figures."""
    cal = {k: k for k in TRANSFORM_KEYS} | {'quality': {'inlier_ratio': 0.9}}
    timed = {k: k for k in TRANSFORM_KEYS} | {'quality': {
        'inlier_ratio': 0.9, 'time_offset_s': 0.149, 'sync_time_offset_s': 0.1}}
    doc = combined_parameters({'r1': cal, 'r2': timed})
    params = doc['/**']['ros__parameters']
    assert params['radar_frames'] == ['r1', 'r2']
    assert params['calibrations']['r1'] == {k: k for k in TRANSFORM_KEYS}
    assert params['calibrations']['r2'] == {k: k for k in TRANSFORM_KEYS} | {
        'time_offset_s': 0.149, 'sync_time_offset_s': 0.1}


def test_evaluate_compares_each_radar_with_its_own_truth(
        three: tuple[SimulationSummary, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The 2nd and 3rd radar's evaluation took ground_truth.json, which is the 1st radar's,
    and so compared with no truth at all (an operator probe's N9). Each radar's own truth,
    written as its calibration, must evaluate to no error against the truth."""
    sim, params = three
    from radar_calib_ros.result import RESULT_KEYS, write_result_yaml
    for frame in FRAMES[1:]:
        truth = load_ground_truth(sim.paths.bag, frame)
        assert truth is not None
        calibration = tmp_path / f'{frame}.yaml'
        write_result_yaml(calibration, {k: truth[k] for k in RESULT_KEYS})
        report = tmp_path / f'{frame}.json'
        code = main(['evaluate', str(sim.paths.bag), '--params', str(params), '--calibration',
                     str(calibration), '--json', str(report)])
        assert code == 0, capsys.readouterr().err
        errors = json.loads(report.read_text())['ground_truth_errors']
        assert errors is not None, frame
        assert errors['horizontal_m'] < 1e-3 and errors['rotation_deg'] < 1e-3


def _fake_radars(monkeypatch: pytest.MonkeyPatch, found: dict[str, str],
                 failing: dict[str, str] | None = None) -> None:
    """--all-radars over the radar topics ``found`` (topic -> frame) with each radar's
    calibration faked: a result named after its frame and a one-line summary, or for the
    frames in ``failing`` the error given (exit 1); in threads instead of processes, so
    that the fake is called."""
    from concurrent.futures import ThreadPoolExecutor

    from radar_calib_ros import multi_radar
    monkeypatch.setattr('radar_calib_ros.io.bag.radar_frame_ids', lambda bag: found)

    def fake_calibrate(bag: str, params: str | None, topic: str,
                       frame_id: str) -> multi_radar.RadarOutcome:
        if failing and frame_id in failing:
            return multi_radar.RadarOutcome(topic, frame_id, None, failing[frame_id], 1, ())
        cal = {k: frame_id if k == 'radar_frame' else k for k in TRANSFORM_KEYS}
        cal['quality'] = {}
        return multi_radar.RadarOutcome(topic, frame_id, cal, None, 0, (
            f'summary {frame_id}', f'  advice: Drive across the view of {frame_id} again.',
            '  advice: The vehicle\'s fixes name a GNSS antenna\'s frame, yet vehicle.'
            'ref_height puts the point they describe at the axle.'))

    monkeypatch.setattr(multi_radar, 'calibrate_topic', fake_calibrate)
    monkeypatch.setattr(multi_radar, 'ProcessPoolExecutor', ThreadPoolExecutor)


def test_all_radars_prints_in_topic_order(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The radars finish in any order; the results are printed in topic order, the order of
    the files and of the combined parameters (an operator probe's N11: completion order,
    and a topics line in another)."""
    from radar_calib_ros import multi_radar
    _fake_radars(monkeypatch, {'/b/points': 'radar_b', '/a/points': 'radar_a',
                               '/c/points': 'radar_c'})
    # finishing last topic first
    monkeypatch.setattr(multi_radar, 'as_completed', lambda futures: list(reversed(futures)))
    bag = tmp_path / 'bag'
    bag.mkdir()
    code = main(['calibrate', str(bag), '--all-radars', '--output-dir', str(tmp_path / 'out'),
                 '--jobs', '3'])
    out = capsys.readouterr().out
    assert code == 0, out
    lines = out.splitlines()
    assert lines[0] == ('radar topics (3): /a/points (radar_a), /b/points (radar_b), '
                        '/c/points (radar_c)')
    blocks = [line for line in lines if line.endswith('s') and ': calibrated in' in line]
    assert [b.split()[0] for b in blocks] == ['/a/points', '/b/points', '/c/points']
    summaries = [line for line in lines if line.startswith('summary')]
    assert summaries == ['summary radar_a', 'summary radar_b', 'summary radar_c']
    # advice of the vehicle's, the same for every radar, is said in full once (a
    # seventy-sixth probe's ran to 39 repeats); each radar's own is said in full
    advice = [line for line in lines if line.startswith('  advice: ')]
    assert [a for a in advice if 'Drive across the view of' in a] == [
        f'  advice: Drive across the view of radar_{k} again.' for k in 'abc']
    gnss = [a for a in advice if 'GNSS antenna' in a]
    assert gnss[0].endswith('at the axle.') and gnss[1:] == [
        "  advice: as for radar_a above (The vehicle's fixes name a GNSS antenna's frame, "
        '...)'] * 2
    combined = yaml.safe_load((tmp_path / 'out' / 'all_radars.yaml').read_text())
    assert combined['/**']['ros__parameters']['radar_frames'] == ['radar_a', 'radar_b',
                                                                  'radar_c']


def test_all_radars_names_the_radars_left_out_in_its_last_line(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """One radar of three cannot be calibrated: the closing line names it with its reason
    (a forty-seventh probe read '3 of 4 radars calibrated' without which), exit 1."""
    _fake_radars(monkeypatch, {'/a/points': 'radar_a', '/b/points': 'radar_b',
                               '/c/points': 'radar_c'},
                 failing={'radar_b': 'read: no radar frame in the recording'})
    bag = tmp_path / 'bag'
    bag.mkdir()
    params = tmp_path / 'p.yaml'
    params.write_text("/**:\n  ros__parameters:\n    radar_topic: /a/points\n")
    code = main(['calibrate', str(bag), '--all-radars', '--output-dir', str(tmp_path / 'out'),
                 '--jobs', '2', '--params', str(params)])
    captured = capsys.readouterr()
    last = captured.out.splitlines()[-1]
    assert code == 1
    # the parameters' choice of one radar is not used, and said so
    assert f'(not used from {params}: radar_topic)' in captured.err
    assert last.startswith('2 of 3 radars calibrated')
    assert ('not calibrated: radar_b (/b/points: read: no radar frame in the recording)'
            in last), last


def test_an_all_radars_runs_warnings_name_their_radar_and_clock_advice_its_own_file(
        caplog: pytest.LogCaptureFixture) -> None:
    """Side by side, the radars' warnings begin with their frame (a forty-eighth probe could
    not tell which radar '... shifted by -0.20 s' was about); advice to set sync.time_offset
    says to do so in a parameters file of that radar's own (followed in the shared one, it
    put the next radar 4 m off)."""
    import logging

    from radar_calib_ros import multi_radar
    log = logging.getLogger('radar_calib_ros.pipeline')
    with caplog.at_level('WARNING'):
        with multi_radar.radar_named_records('radar_north'):
            log.warning('the hypotheses agree best with the radar stamps shifted by %+.2f s',
                        -0.2)
        log.warning('after the run')
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ['radar_north: the hypotheses agree best with the radar stamps '
                        'shifted by -0.20 s', 'after the run']
    calibration = {'quality': {'advice': ['Set sync.time_offset to -0.35 and calibrate again.',
                                          'Check vehicle.* before sync.time_offset.']}}
    multi_radar._own_clock_advice(calibration)
    first, second = calibration['quality']['advice']
    assert first.endswith('in a parameters file of its own.') and 'alone' in first
    assert second == 'Check vehicle.* before sync.time_offset.'
