"""Scatter models (issue 7): where on the calibration vehicle its targets come from, and the
default model's metrics at the true calibration against the paper's Table I."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from radar_calib_ros import evaluate
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.io.bag import read_recording
from radar_calib_ros.result import load_result
from radar_calib_ros.sim import DEFAULT_SCATTER_MODEL, KIND_NAMES, SimulationSummary, simulate
from radar_calib_ros.sim.scatter import build_templates, check_scatter_model
from radar_calib_ros.sim.traffic import RoadUsers
from radar_calib_ros.errors import ConfigError
from radar_calib_ros.types import TrackedTargets
from sim_truth import load, metrics_at_truth

INTERIOR_KINDS = ('wheel', 'wheel_house', 'underbody', 'engine', 'seat', 'mirror',
                  'multibounce')


def _cal_kinds(sim: SimulationSummary) -> np.ndarray:
    _, z = load(sim.paths.bag)
    return z['scatter_kind'][z['is_calibration_vehicle']]


def test_models_differ_as_intended(model_sims: dict[str, SimulationSummary]) -> None:
    skin = _cal_kinds(model_sims['skin'])
    interior = _cal_kinds(model_sims['interior'])
    mixed = _cal_kinds(model_sims['mixed'])
    names = [KIND_NAMES[k] for k in np.unique(skin)]
    assert set(names) <= {'face', 'corner', 'ghost_road', 'ghost_wall'}
    inner = np.isin(interior, [KIND_NAMES.index(k) for k in INTERIOR_KINDS])
    assert inner.mean() > 0.6
    for kind in INTERIOR_KINDS:
        assert np.any(interior == KIND_NAMES.index(kind)), kind
    # the mixed blend of this vehicle holds some of both
    w = model_sims['mixed'].truth['calibration_vehicle_skin_weight']
    assert 0.0 <= w <= 1.0
    faces = np.isin(mixed, [KIND_NAMES.index('face'), KIND_NAMES.index('corner')]).mean()
    assert np.isin(interior, [KIND_NAMES.index('face'), KIND_NAMES.index('corner')]).mean(
    ) <= faces + 0.02 <= np.isin(skin, [KIND_NAMES.index('face'),
                                        KIND_NAMES.index('corner')]).mean() + 0.02
    # at the truth, a skin model puts about half its targets outside the box, the interior
    # model most inside: the problem issue 7 is about
    r_skin = metrics_at_truth(model_sims['skin'].paths.bag).inlier_ratio
    r_interior = metrics_at_truth(model_sims['interior'].paths.bag).inlier_ratio
    assert r_skin < 0.55 < 0.7 < r_interior


def test_models_share_the_drive(model_sims: dict[str, SimulationSummary]) -> None:
    """The model changes the reflections only: same radar mount, traffic and vehicle."""
    base = model_sims['skin']
    _, z0 = load(base.paths.bag)
    for model in ('interior', 'mixed'):
        sim = model_sims[model]
        assert sim.truth['translation'] == base.truth['translation']
        assert sim.truth['passes'][0]['t_stop_line_s'] == base.truth['passes'][0][
            't_stop_line_s']
        _, z = load(sim.paths.bag)
        np.testing.assert_array_equal(z['vehicle_position_m'], z0['vehicle_position_m'])
        np.testing.assert_array_equal(z['frame_stamp_ns'], z0['frame_stamp_ns'])
        assert sim.truth['scatter_model'] == model


def test_default_model_matches_table_one_at_the_truth(baseline_sim: SimulationSummary) -> None:
    """Paper Table I (real radars, their own calibration): r_i 60-79 %, delta_op 0.26-0.39 m,
    delta_p 1.10-1.71 m; at the truth r_i can only be higher. Computed by ``radar-calib
    evaluate``'s own protocol (stages 1-3, tracks within 5 m of the vehicle, merged) with
    the ground truth as the calibration."""
    assert baseline_sim.truth['scatter_model'] == DEFAULT_SCATTER_MODEL
    config = CalibConfig.from_file(baseline_sim.paths.params)
    recording = read_recording(baseline_sim.paths.bag, config)
    calibration = load_result(baseline_sim.paths.ground_truth)
    tracked = evaluate.track_targets(recording, config)
    full = evaluate.evaluate_tracked(recording, tracked, calibration, config)
    # The 5 m rule also keeps road users that pull away beside the vehicle at a light or
    # pass it (a radar sees them as one object for seconds): their targets lie metres
    # outside the box, and at a busy two-lane junction they, not the reflections, set
    # delta_op (Table I's delta_op says the paper's drives had almost none). The same
    # protocol on the tracker's own tracks with the other road users' targets taken out
    # measures where on the vehicle the radar sees it:
    _, z = load(baseline_sim.paths.bag)
    own = z['is_calibration_vehicle'][tracked.target_index]
    vehicle_only = TrackedTargets(tracked.target_index[own], tracked.track_id[own])
    ev = evaluate.evaluate_tracked(recording, vehicle_only, calibration, config)
    p = ev.paper
    assert p.n_targets > 2000 and p.n_frames > 300
    assert p.inlier_ratio >= 0.6
    assert p.outlier_distance_m <= 0.4
    assert 1.0 <= p.closest_target_offset_m <= 1.8
    # the protocol's own track choice found the vehicle (most of what it kept is the
    # vehicle's) and, with the others in, r_i still reads like Table I's
    kept = np.isin(tracked.track_id, full.vehicle_track_ids)
    assert own[kept].mean() > 0.7
    assert full.paper.inlier_ratio >= 0.6
    # and the npz-based figures (true poses at the true measurement times) agree
    m = metrics_at_truth(baseline_sim.paths.bag)
    assert abs(m.inlier_ratio - p.inlier_ratio) < 0.05
    assert abs(m.outlier_distance_m - p.outlier_distance_m) < 0.1


def test_vehicle_never_in_view_has_no_vehicle_targets(tmp_path: Path) -> None:
    sim = simulate(tmp_path / 'away', seed=2, duration_s=60.0, scenario='vehicle_never_in_view')
    _, z = load(sim.paths.bag)
    assert not np.any(z['is_calibration_vehicle'])
    assert np.any(z['object_id'] > 0)  # other traffic is seen
    assert sim.n_passes == 0 and sim.truth['n_calibration_vehicle_targets'] == 0


def test_calibration_vehicle_seen_in_several_passes(baseline_sim: SimulationSummary) -> None:
    passes = baseline_sim.truth['passes']
    assert baseline_sim.n_passes == len(passes) >= 4
    seen = [p for p in passes if p['n_targets'] > 30]
    assert len(seen) >= 3
    assert len({(p['entry_arm'], p['exit_arm']) for p in seen}) >= 3
    for p in passes:
        assert p['t_start_s'] <= p['t_stop_line_s'] <= p['t_end_s']


def test_unknown_model_is_a_config_error() -> None:
    assert check_scatter_model(None) == DEFAULT_SCATTER_MODEL
    with pytest.raises(ConfigError):
        check_scatter_model('chrome')


def test_mixed_blends_per_road_user() -> None:
    n = 50
    users = RoadUsers(np.full(n, 1, np.int8), np.zeros(n, np.int64), np.full(n, 4.5),
                      np.full(n, 1.8), np.full(n, 1.5), np.full(n, 1.0), np.full(n, 2.7),
                      np.zeros(n), np.ones(n), np.zeros(n))
    mixed = build_templates(users, 'mixed', np.random.default_rng(0))
    assert np.unique(mixed.skin_weight).size == n
    skin = build_templates(users, 'skin', np.random.default_rng(0))
    interior = build_templates(users, 'interior', np.random.default_rng(0))
    assert set(np.unique(skin.kind)) == {KIND_NAMES.index('face'), KIND_NAMES.index('corner')}
    assert KIND_NAMES.index('wheel') in set(np.unique(interior.kind))
    # a mixed road user carries both region sets, weighted by its blend
    first = slice(mixed.start[0], mixed.start[1])
    kinds = set(np.unique(mixed.kind[first]))
    assert KIND_NAMES.index('wheel') in kinds and KIND_NAMES.index('face') in kinds
