"""Radial velocities folded at the radar's unambiguous limit: found on the vehicle, unfolded."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import velocity_folding
from radar_calib_ros.groundtruth import load_ground_truth
from radar_calib_ros.recording import Recording
from radar_calib_ros.result import utm_to_extrinsics
from radar_calib_ros.sim import SimulationSummary
from radar_calib_ros.types import Extrinsics


@pytest.fixture(scope='module')
def truth(sim: SimulationSummary, recording: Recording) -> Extrinsics:
    """The true calibration in the recording's frame."""
    t = load_ground_truth(sim.paths.bag)
    assert t is not None
    return utm_to_extrinsics(Rotation.from_quat(t['quaternion_xyzw']).as_matrix(),
                             np.asarray(t['translation']), recording.frame,
                             t['time_offset_s'])


def _with_velocities(recording: Recording, v: np.ndarray) -> Recording:
    return replace(recording, targets=replace(recording.targets, radial_velocity_mps=v))


@pytest.mark.parametrize('period', [6.0, 9.0])
def test_a_fold_is_found_on_the_vehicle_and_undone(
        truth: Extrinsics, recording: Recording, config: CalibConfig,
        period: float) -> None:
    true_v = recording.targets.radial_velocity_mps
    folded = _with_velocities(recording, true_v - period * np.round(true_v / period))
    everything = np.arange(len(recording.targets))
    near, predicted = velocity_folding._near_vehicle(truth, recording, everything, config,
                                                     config.refine.gate_m)
    was_folded = np.abs(true_v[near]) > period / 2
    assert was_folded.mean() > 0.03   # the drive folds enough to matter
    found = velocity_folding.detect_folding(truth, folded, everything, config)
    assert found is not None and found.period_mps == pytest.approx(period, abs=0.02)
    unfolded, done = velocity_folding.unfold_radial_velocities(folded, truth,
                                                               everything, found, config)
    v = unfolded.targets.radial_velocity_mps
    # the vehicle's targets are back, to the period's precision, wherever its motion
    # predicts them within half a period (wheel micro-Doppler and ghosts may not be: they
    # land a period away, outliers either way), and the input stays as it was
    body = np.abs(true_v[near] - predicted) < period / 2 - 0.5
    assert body.mean() > 0.9
    assert np.mean(np.abs(v[near[body]] - true_v[near[body]]) < 0.03) > 0.995
    assert done.n_unfolded >= 0.97 * was_folded.sum()
    assert np.count_nonzero(v != folded.targets.radial_velocity_mps) == done.n_unfolded
    assert np.array_equal(folded.targets.radial_velocity_mps,
                          true_v - period * np.round(true_v / period))


def test_no_fold_is_found_where_there_is_none(
        truth: Extrinsics, recording: Recording, config: CalibConfig) -> None:
    everything = np.arange(len(recording.targets))
    assert velocity_folding.detect_folding(truth, recording, everything,
                                           config) is None
    # A tenth of the vehicle's targets off by one speed, regardless of their sign (another
    # car riding along, a bias): a peak, but not a fold, which brings speeds back from the
    # far end of the interval.
    near, _ = velocity_folding._near_vehicle(truth, recording, everything, config,
                                             config.refine.gate_m)
    rng = np.random.default_rng(3)
    decoys = rng.choice(near, near.size // 10, replace=False)
    v = recording.targets.radial_velocity_mps.copy()
    v[decoys] += 12.0
    assert velocity_folding.detect_folding(truth, _with_velocities(recording, v),
                                           everything, config) is None
    # nor under a calibration that puts the vehicle where nothing is
    away = replace(truth, translation_m=truth.translation_m + [40.0, 0, 0])
    period = 6.0
    v = recording.targets.radial_velocity_mps
    folded = _with_velocities(recording, v - period * np.round(v / period))
    assert velocity_folding.detect_folding(away, folded, everything, config) is None


def test_evaluate_unfolds_the_vehicles_velocities_at_the_calibration_under_test(
        truth: Extrinsics, recording: Recording, config: CalibConfig) -> None:
    """``calibrate`` unfolds folded radial velocities; ``evaluate`` must too before the fit
    that checks a calibration, or that fit follows them away (a seventy-third probe's radar
    folding at +-10 m/s: 'cannot tell', the fit 23-34 m off). It says so; unfolded data are
    left as they are."""
    from radar_calib_ros.evaluate import _unfolded
    from radar_calib_ros.pipeline import track_targets
    from radar_calib_ros.result import calibration_dict
    calibration = calibration_dict(truth, recording.frame)
    calibration['quality'] = {'time_offset_s': truth.time_offset_s}
    period = 9.0
    true_v = recording.targets.radial_velocity_mps
    folded = _with_velocities(recording, true_v - period * np.round(true_v / period))
    tracked = track_targets(folded, config)
    unfolded, note = _unfolded(folded, tracked, calibration, config)
    assert note is not None and 'fold over at +-4.5 m/s' in note
    changed = unfolded.targets.radial_velocity_mps != folded.targets.radial_velocity_mps
    assert changed.sum() > 100
    # (wheels' micro-Doppler and ghosts may land a period away, as in calibrate)
    assert np.mean(np.abs(unfolded.targets.radial_velocity_mps[changed]
                          - true_v[changed]) < 0.03) > 0.8
    same, none = _unfolded(recording, track_targets(recording, config), calibration, config)
    assert none is None and same is recording
