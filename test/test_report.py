"""radar-calib report and calibrate --report: every figure written as PNG, one offline page."""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from radar_calib_ros import cli, evaluate, report
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import ground_plane, reflection
from radar_calib_ros.groundtruth import load_ground_truth
from radar_calib_ros.pipeline import CalibrationResult
from radar_calib_ros.recording import Recording
from radar_calib_ros.result import utm_to_extrinsics, write_result_yaml
from radar_calib_ros.sim import SimulationSummary
from radar_calib_ros.types import (
    Extrinsics, Hypothesis, HypothesisSelection, QualityReport, Refinement)

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
EVALUATION_FIGURES = ('bev_track.png', 'outlier_distance.png', 'closest_offset.png',
                      'ground_plane.png')
RUN_FIGURES = ('hypotheses.png', 'refinement_residuals.png', 'reflection_profile.png',
               'velocity_residuals.png')


@pytest.fixture(scope='module')
def truth(sim: SimulationSummary) -> dict[str, Any]:
    doc = load_ground_truth(sim.paths.bag)
    assert doc is not None
    return doc


def _truth_calibration(truth: dict[str, Any]) -> dict[str, Any]:
    cal = {k: truth[k] for k in ('world_frame', 'radar_frame', 'epsg', 'translation',
                                 'quaternion_xyzw', 'rpy_deg', 'latitude', 'longitude',
                                 'altitude', 'boresight_azimuth_deg', 'stamp')}
    cal['quality'] = {'time_offset_s': truth['time_offset_s']}
    return cal


def _check_outputs(out_dir: Path, names: tuple[str, ...]) -> str:
    """Every PNG valid and not trivially small, and the page embedding and linking each."""
    page = (out_dir / 'report.html').read_text(encoding='utf-8')
    for name in names:
        data = (out_dir / name).read_bytes()
        assert data[:8] == PNG_MAGIC, name
        assert len(data) > 20_000, name   # an empty canvas is a few kB
        assert f'href="{name}"' in page and f'alt="{name}"' in page
    assert page.count('src="data:image/png;base64,') == len(names)
    # readable offline: nothing fetched from elsewhere, no script
    assert 'http://' not in page and 'https://' not in page and '<script' not in page
    return page


def _synthetic_run(recording: Recording, config: CalibConfig, extrinsics: Extrinsics,
                   ) -> tuple[HypothesisSelection, Refinement]:
    """A hypothesis selection and a refinement with the diagnostics the figures read."""
    rng = np.random.default_rng(3)
    t0 = np.asarray(extrinsics.translation_m, float)
    near = t0[:2] + rng.normal(0.0, 0.3, (6, 2))
    other = t0[:2] + [40.0, -30.0] + rng.normal(0.0, 0.5, (4, 2))
    noise = t0[:2] + rng.uniform(-120.0, 120.0, (20, 2))
    xy = np.concatenate([near, other, noise])
    hyps = tuple(Hypothesis(i, np.eye(3), np.array([x, y, t0[2]]), 50, 0.4)
                 for i, (x, y) in enumerate(xy))
    labels = np.array([0] * 6 + [1] * 4 + [-1] * 20, np.int64)
    selection = HypothesisSelection(hyps, labels, 0, {0: 0.4, 1: float('nan')},
                                    tuple(range(6)), extrinsics, 300,
                                    np.array([[0, 10], [20, 30]], np.int64))
    n = 3000
    aspect = rng.uniform(-np.pi, np.pi, n)
    coeffs = np.zeros(reflection.n_coefficients(4))
    idx = reflection.coefficient_index(4)
    coeffs[idx['a0']], coeffs[idx['a1']], coeffs[idx['c0']] = 1.45, 0.6, 0.3
    offsets = reflection.evaluate_profile(coeffs, aspect) + rng.normal(0.0, 0.6, (n, 3))
    velocity = rng.normal(0.0, 0.1, n)
    velocity[::10] += rng.normal(0.0, 3.0, velocity[::10].size)   # wheels
    residuals = {
        'target_index': np.arange(n), 'pass_id': np.repeat([0, 1], n // 2),
        'weight': np.ones(n), 'range_m': rng.uniform(10.0, 90.0, n),
        'azimuth_rad': rng.uniform(-0.8, 0.8, n), 'aspect_rad': aspect,
        'bearing_rad': rng.uniform(-0.8, 0.8, n), 'along_los_m': rng.normal(0.0, 0.6, n),
        'across_los_m': rng.normal(0.0, 0.4, n), 'vertical_m': rng.normal(0.0, 0.5, n),
        'velocity_mps': velocity, 'offset_vehicle_m': offsets}
    refinement = Refinement(extrinsics, np.eye(7) * 1e-4, n, 2, coeffs,
                            {'residuals': residuals, 'advice': []})
    del recording, config
    return selection, refinement


def _fake_result(recording: Recording, config: CalibConfig, truth: dict[str, Any],
                 with_refinement: bool = True) -> CalibrationResult:
    extrinsics = utm_to_extrinsics(Rotation.from_quat(truth['quaternion_xyzw']).as_matrix(),
                                   np.asarray(truth['translation']), recording.frame,
                                   truth['time_offset_s'])
    tracked = evaluate.track_targets(recording, config)
    ground = ground_plane.fit_ground_plane(recording.targets.positions_m[tracked.target_index],
                                           config.ground)
    selection, refinement = _synthetic_run(recording, config, extrinsics)
    quality = QualityReport(0.8, 0.3, 1.2, 6, 30, 300, 2, extrinsics.time_offset_s, 0.05,
                            0.04, 0.02, 0.03, 0.05, ('Drive the other way.',))
    return CalibrationResult(extrinsics, quality, recording, tracked, ground, (), selection,
                             refinement if with_refinement else None,
                             {'refine': extrinsics}, {'refine': 1.0})


def test_report_command_writes_the_evaluation_figures_without_recalibrating(
        sim: SimulationSummary, truth: dict[str, Any], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    def no_calibration(*args: Any, **kwargs: Any) -> None:
        raise AssertionError('report must not re-calibrate')

    monkeypatch.setattr('radar_calib_ros.pipeline.run_calibration', no_calibration)
    cal = tmp_path / 'result.yaml'
    write_result_yaml(cal, _truth_calibration(truth))
    out = io.StringIO()
    code = cli.main(['report', str(sim.paths.bag), '--calibration', str(cal), '--params',
                     str(sim.paths.params), '--out', str(tmp_path / 'rep')], out=out)
    assert code == 0, capsys.readouterr().err
    assert 'report written to' in out.getvalue()
    assert sorted(p.name for p in (tmp_path / 'rep').glob('*.png')) == sorted(
        EVALUATION_FIGURES)
    page = _check_outputs(tmp_path / 'rep', EVALUATION_FIGURES)
    assert 'Against the ground truth' in page and 'calibrate BAG --report DIR' in page
    # the verdict of a fit on the recording alone, as evaluate gives it (two passes here)
    assert 'Verdict: cannot tell whether the calibration holds' in page


def test_report_command_bad_input(sim: SimulationSummary, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('{translation: [1, 2]')
    code = cli.main(['report', str(sim.paths.bag), '--calibration', str(bad), '--out',
                     str(tmp_path / 'rep')], out=io.StringIO())
    err = capsys.readouterr().err
    assert code == 2 and err.startswith('error: ') and 'Traceback' not in err
    assert not (tmp_path / 'rep' / 'report.html').exists()
    assert cli.main(['report', str(sim.paths.bag), '--calibration', str(bad)]) == 2  # no --out


def test_calibrate_report_reuses_the_run(
        sim: SimulationSummary, config: CalibConfig, recording: Recording,
        truth: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    result = _fake_result(recording, config, truth)
    calls = []

    def calibrate_bag(bag: Any, cfg: CalibConfig, **kwargs: Any) -> tuple[Any, float]:
        calls.append(bag)
        return result, 0.1

    monkeypatch.setattr(cli, 'calibrate_bag', calibrate_bag)
    out = io.StringIO()
    code = cli.main(['calibrate', str(sim.paths.bag), '--params', str(sim.paths.params),
                     '--output', str(tmp_path / 'r.yaml'), '--no-progress', '--report',
                     str(tmp_path / 'rep')], out=out)
    assert code == 0, capsys.readouterr().err
    assert len(calls) == 1   # one calibration run, reused by the report
    assert (tmp_path / 'r.yaml').is_file()
    page = _check_outputs(tmp_path / 'rep', EVALUATION_FIGURES + RUN_FIGURES)
    assert 'Drive the other way.' in page        # the run's quality and advice
    assert 'Against the ground truth' in page


def test_report_without_refinement_leaves_its_figures_out(
        config: CalibConfig, recording: Recording, truth: dict[str, Any],
        tmp_path: Path) -> None:
    result = _fake_result(recording, config, truth, with_refinement=False)
    files = report.report_calibration(tmp_path, result, config)
    assert tuple(p.name for p in files.figures) == EVALUATION_FIGURES + ('hypotheses.png',)
    page = _check_outputs(tmp_path, EVALUATION_FIGURES + ('hypotheses.png',))
    assert 'refine.final is false' in page
    assert files.evaluation is not None and files.evaluation.errors is None


def test_figures_are_labelled(config: CalibConfig, recording: Recording,
                              truth: dict[str, Any]) -> None:
    """Each figure has a title and every axis with data a label with a unit."""
    from radar_calib_ros.report import figures
    result = _fake_result(recording, config, truth)
    ev = evaluate.evaluate_tracked(recording, result.tracked, _truth_calibration(truth), config)
    built = [figures.figure_bev_track(ev, config), figures.figure_outlier_distance(ev),
             figures.figure_closest_offset(ev, config.vehicle),
             figures.figure_ground_plane(recording.targets.positions_m[
                 result.tracked.target_index], result.ground, config),
             figures.figure_hypotheses(result.selection, result.extrinsics),
             figures.figure_refinement_residuals(result.refinement),
             figures.figure_reflection_profile(result.refinement, config.vehicle),
             figures.figure_velocity_residuals(result.refinement)]
    for fig in built:
        assert fig is not None
        titles = [fig.get_suptitle()] + [a.get_title() for a in fig.axes]
        assert any(titles)
        for ax in fig.axes:
            if not (ax.collections or ax.lines or ax.patches):
                continue
            label = ax.get_ylabel()
            assert label, titles
            if ax.get_label() != '<colorbar>':
                assert '[' in ax.get_xlabel() + label, (titles, ax.get_xlabel(), label)


def test_the_page_shows_the_verdict_with_each_difference(
        config: CalibConfig, recording: Recording, truth: dict[str, Any]) -> None:
    from dataclasses import replace

    from radar_calib_ros.evaluate import (AGREEMENT_COMPONENTS, Agreement, evaluate_tracked,
                                          track_targets)
    from radar_calib_ros.report import html
    ev = evaluate_tracked(recording, track_targets(recording, config),
                          _truth_calibration(truth), config)
    assert ev.agreement is None and html._agreement_section(ev) == ''
    differences = dict(zip(AGREEMENT_COMPONENTS, (0.012, -0.5, 0.03, 0.01, -0.02, 0.6)))
    sigmas = dict(zip(AGREEMENT_COMPONENTS, (0.1, 0.04, 0.4, 0.12, 0.38, 0.03)))
    agreement = Agreement('does not hold', 'a fit on this recording alone puts the radar '
                          '-50 cm across its boresight (12.5 sigma) from the calibration',
                          differences, sigmas, 6, 0.002)
    section = html._agreement_section(replace(ev, agreement=agreement))
    assert 'Verdict: the calibration does not hold on this recording' in section
    assert '12.5 sigma' in section
    assert '-50.0 (4.0)' in section and '+0.600 (0.030)' in section
