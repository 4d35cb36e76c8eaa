"""Stage 6: hypotheses per track, the cluster filter, passes, and the exit-1 cases."""
from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from calib_scene import make_scene, with_hypotheses

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core import hypotheses, registration
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.types import Hypothesis


def _select(scene):  # type: ignore[no-untyped-def]
    hyps = hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          scene.config)
    return hyps, hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording,
                                             scene.ground, scene.config)


def test_noise_free_scene_recovers_the_transform() -> None:
    scene = make_scene(n_passes=5)
    hyps, selection = _select(scene)
    assert len(hyps) == 5
    level = scene.ground.rotation_level
    for h in hyps:
        # each hypothesis maps the levelled frame: truth = R_h @ R_level
        np.testing.assert_allclose(h.rotation @ level, scene.truth.rotation, atol=1e-9)
        np.testing.assert_allclose(h.translation_m, scene.truth.translation_m, atol=1e-8)
        assert h.rms_m < 1e-8
    est = selection.extrinsics
    assert float(registration.rotation_angle_deg(est.rotation, scene.truth.rotation)) < 1e-8
    np.testing.assert_allclose(est.translation_m, scene.truth.translation_m, atol=1e-8)
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    assert selection.n_passes == 5
    assert selection.n_correspondences == sum(h.n_correspondences for h in hyps)


def test_clock_offset_is_applied_before_interpolating() -> None:
    # radar stamps 80 ms late: at 6-12 m/s that is ~0.5-1 m along the path unless
    # sync.time_offset takes it back
    late = make_scene(n_passes=4, radar_stamp_shift_s=0.08)
    _, sel_wrong = _select(late)
    err_wrong = np.linalg.norm(sel_wrong.extrinsics.translation_m - late.truth.translation_m)
    cfg = late.config
    fixed = make_scene(n_passes=4, radar_stamp_shift_s=0.08,
                       config=type(cfg)(sync=type(cfg.sync)(time_offset=-0.08)))
    _, sel = _select(fixed)
    np.testing.assert_allclose(sel.extrinsics.translation_m, fixed.truth.translation_m,
                               atol=1e-8)
    assert err_wrong > 0.1


def test_decoys_are_rejected_and_fragments_merge_into_one_pass() -> None:
    scene = make_scene(n_passes=4, random_cars=15, split_pass=2, seed=3)
    hyps, selection = _select(scene)
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    assert len(selection.accepted_track_ids) == 5  # pass 2 is two fragments
    assert selection.n_passes == 4
    np.testing.assert_allclose(selection.extrinsics.translation_m,
                               scene.truth.translation_m, atol=1e-7)


def test_a_stop_in_view_splits_a_track_not_a_pass() -> None:
    # 12 s stopped at a light in view: two tracks far apart in time, one pass
    scene = make_scene(n_passes=3, stop_pass=1, stop_s=12.0)
    hyps, selection = _select(scene)
    assert len(selection.accepted_track_ids) == 4
    intervals = np.array([[t.stamps_ns[0], t.stamps_ns[-1]] for t in scene.tracks])
    assert hypotheses.merge_intervals_ns(intervals, 2.0).shape[0] == 4  # by time alone
    assert selection.n_passes == 3
    np.testing.assert_allclose(selection.extrinsics.translation_m,
                               scene.truth.translation_m, atol=1e-7)
    # ... while two passes with the vehicle parked far away in between stay two
    with pytest.raises(InsufficientDataError, match='seen in 2 passes'):
        _select(make_scene(n_passes=2, stop_pass=1))


def test_follower_cluster_loses_the_tie_on_timing() -> None:
    # every pass on the same lane, a car following 1.5 s behind: its hypotheses agree in
    # rotation as well as the vehicle's and span as many passes; only the timing (the
    # vehicle accelerates, so a lagged copy does not map rigidly) tells them apart
    scene = make_scene(n_passes=4, lanes=[0, 0, 0, 0], followers=1.5)
    hyps, selection = _select(scene)
    follower_ids = set(range(len(scene.tracks))) - set(scene.vehicle_track_ids)
    follower_labels = {int(selection.labels[i]) for i, h in enumerate(hyps)
                       if h.track_id in follower_ids}
    assert follower_labels and -1 not in follower_labels  # the decoys do form a cluster
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    np.testing.assert_allclose(selection.extrinsics.translation_m,
                               scene.truth.translation_m, atol=1e-7)


def test_a_look_alike_keeping_pace_on_every_pass_is_a_rival() -> None:
    """A car of the vehicle's size 11 m ahead of it on every pass (a convoy) agrees across
    passes as well as the vehicle does: the selection names it as a rival (the pipeline then
    refuses, a tenth probe's convoy having been 10.9 m off at a 0.5 m sigma); the follower
    that loses on timing, and chance decoys, are no rivals."""
    scene = make_scene(n_passes=4, lanes=[0, 0, 0, 0], escort_m=11.0)
    _, selection = _select(scene)
    assert len(selection.rivals) == 1
    distance, passes = selection.rivals[0]
    assert distance == pytest.approx(11.0, abs=0.5) and passes == 4
    for quiet in (make_scene(n_passes=4, lanes=[0, 0, 0, 0], followers=1.5),
                  make_scene(n_passes=4, random_cars=15, split_pass=2, seed=3)):
        assert _select(quiet)[1].rivals == ()


def test_a_longer_vehicle_kept_alongside_gives_way_to_the_one_that_fills_the_box() -> None:
    """A ten-metre truck kept alongside the vehicle on every pass agrees across passes as
    well as the vehicle does and, the vehicle hidden behind it on one pass, across more: the
    paper's rules take it, a lane off (a fifty-sixth probe: 4.8-5.2 m, exit 0). The
    vehicle's targets fill its box, the truck's spill beyond its ends: with the targets at
    hand the vehicle's group takes its place, and the selection says what it set aside."""
    scene = make_scene(n_passes=5, lanes=[0] * 5, beside_m=3.5, hidden_pass=2, seed=1)
    hyps = hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          scene.config)
    plain = hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                        scene.config)
    assert not set(plain.accepted_track_ids) & set(scene.vehicle_track_ids)
    assert plain.n_passes == 5 and plain.outfitted is None
    selection = hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                            scene.config, tracked=scene.tracked)
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    np.testing.assert_allclose(selection.extrinsics.translation_m, scene.truth.translation_m,
                               atol=1e-6)
    assert selection.outfitted is not None
    distance, passes, share, other = selection.outfitted
    assert distance == pytest.approx(3.5, abs=0.2) and passes == 5
    assert share > 0.8 and other < 0.5  # a sixth lie on its edge (the nearest point)
    assert selection.rivals == ()
    # where the vehicle is taken anyway, nothing is set aside
    seen = make_scene(n_passes=5, lanes=[0] * 5, beside_m=3.5, seed=1)
    assert hypotheses.prune_hypotheses(
        hypotheses.generate_hypotheses(seen.tracks, seen.recording, seen.ground, seen.config),
        seen.tracks, seen.recording, seen.ground, seen.config,
        tracked=seen.tracked).outfitted is None


def test_box_fit_tells_a_longer_vehicle_by_its_spill_not_a_smaller_one() -> None:
    """The contest's rule: far more of the winner's targets in the box, and the loser's
    lane holding the rest of a longer vehicle beyond the box's ends. A smaller vehicle fills
    the box as well and spills nothing, so it never out-fits the vehicle this way."""
    car = hypotheses.BoxFit(inside=0.72, spill=0.02)
    truck = hypotheses.BoxFit(inside=0.29, spill=0.25)
    small = hypotheses.BoxFit(inside=0.98, spill=0.0)
    assert car.beats(truck) and not truck.beats(car)
    assert not small.beats(car)
    assert not car.beats(hypotheses.BoxFit(inside=0.29, spill=0.1))  # no spill: not longer
    assert not car.beats(hypotheses.BoxFit(inside=0.6, spill=0.3))  # fills it about as well


def test_lowest_mean_angle_cluster_wins() -> None:
    # hand-made hypotheses: cluster A agrees to 0.2 deg, cluster B scatters by 3 deg
    scene = make_scene(n_passes=8, lanes=[0, 1, 2, 3, 0, 1, 2, 3])
    truth_bev = scene.truth.rotation @ scene.ground.rotation_level.T
    rng = np.random.default_rng(0)
    hyps = []
    for i, track in enumerate(scene.tracks):
        good = i % 2 == 0
        jitter = registration.yaw_rotation(np.radians(rng.normal(0, 0.2 if good else 3.0)))
        t = scene.truth.translation_m + (0.0 if good else 30.0) + rng.normal(0, 0.3, 3)
        hyps.append(Hypothesis(track.track_id, jitter @ truth_bev, t, 80, 0.2))
    cfg = with_hypotheses(scene.config, max_mean_angle_deg=10.0)
    selection = hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                            cfg)
    accepted = selection.accepted_label
    assert selection.mean_angles_deg[accepted] < 1.0
    assert max(selection.mean_angles_deg.values()) > 1.0
    assert set(selection.accepted_track_ids) == {t.track_id for i, t in
                                                 enumerate(scene.tracks) if i % 2 == 0}


def test_a_group_seen_on_many_more_passes_wins_over_a_tighter_one() -> None:
    """A car of the vehicle's size following it agrees only on the passes of one direction
    (3 of 8): its few hypotheses can agree in rotation better than the vehicle's 8. The
    paper's lowest mean angle picked it, and the vehicle was then refused as its rival (a
    thirty-ninth probe). The groups seen on about as many passes as the best contend; among
    them the lowest angle wins, ties going to more passes."""
    from types import SimpleNamespace

    def cluster(passes: int, angle: float, rms: float = 0.3) -> Any:
        return SimpleNamespace(n_passes=passes, mean_angle_deg=angle,
                               fit=SimpleNamespace(rms_m=rms))

    cfg = CalibConfig().hypotheses
    vehicle, follower = cluster(8, 1.6), cluster(3, 0.05)
    assert hypotheses._accepted_cluster([follower, vehicle], cfg) is vehicle
    # about as many passes: the paper's rule decides
    tighter = cluster(7, 0.05)
    assert hypotheses._accepted_cluster([vehicle, tighter], cfg) is tighter
    # within the angle tie, more passes, then the better fit
    close = cluster(7, 1.6 - 0.5 * cfg.angle_tie_deg)
    assert hypotheses._accepted_cluster([close, vehicle], cfg) is vehicle
    twin = cluster(8, 1.6, rms=0.2)
    assert hypotheses._accepted_cluster([vehicle, twin], cfg) is twin


def test_short_tracks_make_no_hypothesis() -> None:
    scene = make_scene(n_passes=3)
    n = min(t.stamps_ns.size for t in scene.tracks)
    cfg = with_hypotheses(scene.config, min_track_frames=n + 1)
    assert hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          cfg) == []
    cfg = with_hypotheses(scene.config, min_track_length_m=500.0)
    assert hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          cfg) == []
    # the reason names the tracks' lengths when most were too short (a narrow beam)
    longest = max(t.stamps_ns.size for t in scene.tracks)
    cfg = with_hypotheses(scene.config, min_track_frames=longest + 1)
    with pytest.raises(InsufficientDataError, match='never seen') as err:
        hypotheses.prune_hypotheses([], scene.tracks, scene.recording, scene.ground, cfg)
    assert f'(the longest {longest} frames)' in str(err.value)
    assert 'hypotheses.min_track_frames' in str(err.value)


def test_vehicle_never_seen_exits_with_reason() -> None:
    scene = make_scene(n_passes=3, random_cars=8, seed=1)
    others = tuple(t for t in scene.tracks if t.track_id not in scene.vehicle_track_ids)
    hyps = hypotheses.generate_hypotheses(others, scene.recording, scene.ground, scene.config)
    with pytest.raises(InsufficientDataError, match='never seen') as err:
        hypotheses.prune_hypotheses(hyps, others, scene.recording, scene.ground, scene.config)
    # long enough tracks of other cars: nothing said of short tracks, nor of the view, but
    # what else keeps a vehicle in view from a track (a fifty-fifth probe's single pass)
    assert 'shorter than that' not in str(err.value) and 'span only' not in str(err.value)
    assert 'only while turning close to the radar' in str(err.value)
    # a fan beam's +-8 deg: the reason names the narrow view
    rec = scene.recording
    az = np.degrees(np.arctan2(rec.targets.positions_m[:, 1], rec.targets.positions_m[:, 0]))
    inside = np.abs(az) < 8.0
    narrow = replace(rec, targets=replace(
        rec.targets, positions_m=rec.targets.positions_m[inside],
        radial_velocity_mps=rec.targets.radial_velocity_mps[inside],
        frame_index=rec.targets.frame_index[inside]))
    with pytest.raises(InsufficientDataError, match='span only -[78] to \\+[78] deg'):
        hypotheses.prune_hypotheses(hyps, others, narrow, scene.ground, scene.config)


def test_too_few_passes_exits_with_the_numbers() -> None:
    scene = make_scene(n_passes=2, split_pass=0)
    with pytest.raises(InsufficientDataError,
                       match='calibration vehicle seen in 2 passes, need at least 3'):
        _select(scene)


def test_disagreeing_hypotheses_exit() -> None:
    scene = make_scene(n_passes=4)
    truth_bev = scene.truth.rotation @ scene.ground.rotation_level.T
    # translations 20 m apart: no two agree
    hyps = [Hypothesis(t.track_id, truth_bev, scene.truth.translation_m + [20.0 * i, 0, 0],
                       80, 0.1) for i, t in enumerate(scene.tracks)]
    with pytest.raises(InsufficientDataError, match='hypotheses do not agree'):
        hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                    scene.config)
    # translations agree but each pass saw the world rotated by another 10 deg about the
    # sensor: every track fits its own hypothesis perfectly, no two agree in rotation
    tracks = []
    for i, t in enumerate(scene.tracks):
        rot = registration.yaw_rotation(np.radians(10.0 * i))[:2, :2]
        tracks.append(replace(t, positions_m=t.positions_m @ rot.T))
    tracks = tuple(tracks)
    hyps = hypotheses.generate_hypotheses(tracks, scene.recording, scene.ground, scene.config)
    assert len(hyps) == 4 and max(h.rms_m for h in hyps) < 1e-6
    with pytest.raises(InsufficientDataError, match='hypotheses do not agree: the cluster of 4 '
                       'hypotheses over 4 passes has only 1 that agree in rotation'):
        hypotheses.prune_hypotheses(hyps, tracks, scene.recording, scene.ground, scene.config)


def _vehicle_and_other_tracks(scene):  # type: ignore[no-untyped-def]
    vehicle = [t for t in scene.tracks if t.track_id in scene.vehicle_track_ids]
    others = [t for t in scene.tracks if t.track_id not in scene.vehicle_track_ids]
    return vehicle, others


def test_cluster_is_cut_to_its_consistent_core() -> None:
    # other cars' hypotheses land on the vehicle's translation (DBSCAN chains them in):
    # one with a rotation 20 deg off, others with the right rotation but tracks that do
    # not follow the vehicle's poses at all
    scene = make_scene(n_passes=4, random_cars=6, seed=7)
    truth_bev = scene.truth.rotation @ scene.ground.rotation_level.T
    vehicle, others = _vehicle_and_other_tracks(scene)
    t = scene.truth.translation_m
    hyps = [Hypothesis(v.track_id, truth_bev, t, 80, 0.0) for v in vehicle]
    hyps.append(Hypothesis(others[0].track_id,
                           registration.yaw_rotation(np.radians(20.0)) @ truth_bev, t, 80, 0.5))
    hyps += [Hypothesis(o.track_id, truth_bev, t + 0.5, 80, 0.5) for o in others[1:]]
    selection = hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                            scene.config)
    assert np.unique(selection.labels).tolist() == [0]  # one translation cluster
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    np.testing.assert_allclose(selection.extrinsics.translation_m, t, atol=1e-7)


def test_chance_cluster_of_other_cars_means_never_seen() -> None:
    # the vehicle is never tracked; other cars' hypotheses happen to agree over 3+ passes
    # but their tracks do not follow the vehicle's poses
    scene = make_scene(n_passes=5, random_cars=60, seed=8)
    truth_bev = scene.truth.rotation @ scene.ground.rotation_level.T
    _, others = _vehicle_and_other_tracks(scene)
    # only cars seen while the vehicle was parked out of view
    stamp0 = scene.recording.frame_stamps_ns[0] - 3_000_000  # frame times start at 3 ms
    others = [o for o in others if not any(
        lo - 1 < (o.stamps_ns[-1] - stamp0) * 1e-9 and (o.stamps_ns[0] - stamp0) * 1e-9 < hi + 1
        for lo, hi in scene.windows_s)]
    # ... and apart in time, so they count as separate passes
    apart: list = []
    for o in sorted(others, key=lambda o: o.stamps_ns[0]):
        if not apart or o.stamps_ns[0] - apart[-1].stamps_ns[-1] > 3e9:
            apart.append(o)
    others = apart
    assert len(others) >= 3
    hyps = [Hypothesis(o.track_id, truth_bev, scene.truth.translation_m, 80, 1.0)
            for o in others]
    with pytest.raises(InsufficientDataError, match='never seen clearly'):
        hypotheses.prune_hypotheses(hyps, tuple(others), scene.recording, scene.ground,
                                    scene.config)


def test_merge_intervals_boundaries() -> None:
    s = 1_000_000_000
    intervals = np.array([[10 * s, 12 * s], [0, 3 * s], [5 * s, 6 * s], [2 * s, 4 * s],
                          [14 * s, 15 * s]])
    merged = hypotheses.merge_intervals_ns(intervals, 2.0)
    # [0,3]+[2,4] overlap; 4 -> 5 is a 1 s gap; 6 -> 10 is 4 s; 12 -> 14 is exactly 2 s
    np.testing.assert_array_equal(merged, [[0, 6 * s], [10 * s, 15 * s]])
    assert hypotheses.merge_intervals_ns(intervals, 0.0).shape == (4, 2)
    assert hypotheses.merge_intervals_ns(np.zeros((0, 2), np.int64), 2.0).shape == (0, 2)
    # with the vehicle's away moments: only a gap holding one separates passes
    away = np.array([8 * s, 8 * s + 1])
    merged = hypotheses.merge_intervals_ns(intervals, 0.0, away)
    np.testing.assert_array_equal(merged, [[0, 6 * s], [10 * s, 15 * s]])
    merged = hypotheses.merge_intervals_ns(intervals, 0.0, np.zeros(0, np.int64))
    np.testing.assert_array_equal(merged, [[0, 15 * s]])


def test_a_u_turn_out_of_view_but_within_reach_starts_another_pass() -> None:
    """A straight road whose ends the radar cannot see: the vehicle drives through, turns
    round beyond the view but within its reach, and drives back. Two drives seen from
    opposite sides, not one; a 90 deg turn in between (the junction) keeps one pass."""
    from radar_calib_ros.types import VehicleTrack

    s = 1_000_000_000
    t = np.arange(0, 60, 0.1)
    stamps = (t * s).astype(np.int64)

    def track(yaw: np.ndarray) -> VehicleTrack:
        n = t.size
        return VehicleTrack(stamps, np.zeros((n, 3)), yaw, np.zeros((n, 3)), np.zeros(n))

    # in view 0-20 s and 40-60 s, never away in between (no away stamps)
    intervals = np.array([[0, 20 * s], [40 * s, 60 * s]])
    never_away = np.zeros(0, np.int64)
    u_turn = np.where(t < 25, 0.0, np.where(t > 35, np.pi, (t - 25) / 10 * np.pi))
    merged = hypotheses.merge_intervals_ns(intervals, 2.0, never_away, track(u_turn))
    np.testing.assert_array_equal(merged, intervals)
    # the same turn through +-pi wraps: the unwrapped change still counts
    wrapped = (u_turn + np.pi - 0.1) % (2 * np.pi) - np.pi
    merged = hypotheses.merge_intervals_ns(intervals, 2.0, never_away, track(wrapped))
    np.testing.assert_array_equal(merged, intervals)
    quarter = np.where(t < 25, 0.0, np.where(t > 35, np.pi / 2, (t - 25) / 20 * np.pi))
    merged = hypotheses.merge_intervals_ns(intervals, 2.0, never_away, track(quarter))
    np.testing.assert_array_equal(merged, [[0, 60 * s]])
    # without the vehicle, as before: one pass
    assert hypotheses.merge_intervals_ns(intervals, 2.0, never_away).shape == (1, 2)


def test_a_recording_spliced_from_drives_counts_each_drive() -> None:
    """Drives joined in one pose stream with a hole between them across which the vehicle
    jumps farther than it could drive (a sixty-ninth probe's 6.5 s and 139 m at 7 m/s, on
    another arm of the junction, within the radar's reach): two passes. A hole it drove
    across (fixes lost for 3 s at 10 m/s: 30 m) stays one drive."""
    from radar_calib_ros.types import VehicleTrack

    s = 1_000_000_000

    def drives(hole_s: float, jump_m: float, speed: float) -> VehicleTrack:
        t = np.concatenate([np.arange(0.0, 20.0, 0.1), np.arange(20.0, 40.0, 0.1) + hole_s])
        x = np.where(t < 20.0, speed * t, speed * (t - hole_s) + jump_m - speed * 0.1)
        n = t.size
        velocity = np.column_stack([np.full(n, speed), np.zeros(n), np.zeros(n)])
        return VehicleTrack((t * s).astype(np.int64), np.column_stack([x, np.zeros((n, 2))]),
                            np.zeros(n), velocity, np.zeros(n))

    spliced = drives(6.5, 139.0, 7.0)
    assert hypotheses.spliced_stamps_ns(spliced).size == 1
    away = hypotheses.away_stamps_ns(spliced, np.zeros(2), 500.0)   # never beyond reach
    intervals = np.array([[5 * s, 15 * s], [30 * s, 40 * s]])
    merged = hypotheses.merge_intervals_ns(intervals, 2.0, away, spliced)
    np.testing.assert_array_equal(merged, intervals)
    driven = drives(3.0, 10.0 * 3.0, 10.0)
    assert hypotheses.spliced_stamps_ns(driven).size == 0
    away = hypotheses.away_stamps_ns(driven, np.zeros(2), 500.0)
    assert hypotheses.merge_intervals_ns(intervals, 2.0, away, driven).shape == (1, 2)


def test_vehicle_view_passes_counts_the_passes_a_group_misses() -> None:
    # passes 0 and 1 on one lane, 2 and 3 on another: under the true calibration the
    # vehicle is in view in all four, and its own tracks follow it in all four; a group
    # of two of them (what a chance agreement of other road users looks like from the
    # vehicle's side) follows it in two
    scene = make_scene(n_passes=4, lanes=[0, 0, 1, 1])
    vehicle, _ = _vehicle_and_other_tracks(scene)
    corrs = hypotheses.track_correspondences(vehicle, scene.recording, scene.config)
    fit = registration.fit_yaw_translation(np.concatenate([c.source_m for c in corrs]),
                                           np.concatenate([c.target_m for c in corrs]))
    assert hypotheses.vehicle_view_passes(vehicle, fit, scene.tracks, scene.recording,
                                          scene.config) == (4, 4)
    assert hypotheses.vehicle_view_passes([vehicle[0], vehicle[2]], fit, scene.tracks,
                                          scene.recording, scene.config) == (4, 2)


def test_agreement_that_misses_most_passes_in_view_is_called_chance() -> None:
    # two tracks from two passes agree, but under their calibration the vehicle drove
    # through the view four times: not evidence that it was seen (contrast with
    # test_too_few_passes_exits_with_the_numbers, where it was in view only twice)
    scene = make_scene(n_passes=4, lanes=[0, 0, 1, 1])
    vehicle, _ = _vehicle_and_other_tracks(scene)
    group = (vehicle[0], vehicle[2])
    hyps = hypotheses.generate_hypotheses(group, scene.recording, scene.ground, scene.config)
    assert len(hyps) == 2
    with pytest.raises(InsufficientDataError,
                       match='no consistent calibration-vehicle track: 2 chance hypotheses .* '
                             r'in view in 4 passes and follows it in 2\)') as err:
        hypotheses.prune_hypotheses(hyps, group, scene.recording, scene.ground, scene.config)
    assert 'seen in' not in str(err.value)


def test_vehicle_never_in_view_is_not_reported_as_seen(tmp_path: Path) -> None:
    """The simulator's 'vehicle_never_in_view': other road users' tracks fit stretches of
    the vehicle's drive by chance; the exit-1 reason must not claim the vehicle was seen."""
    from radar_calib_ros.config import CalibConfig
    from radar_calib_ros.io.bag import read_recording
    from radar_calib_ros.pipeline import run_calibration
    from radar_calib_ros.sim import simulate

    sim = simulate(tmp_path / 'away', seed=1, duration_s=60.0,
                   scenario='vehicle_never_in_view')
    config = CalibConfig.from_file(sim.paths.params)
    with pytest.raises(InsufficientDataError) as err:
        run_calibration(read_recording(sim.paths.bag, config), config)
    reason = str(err.value)
    assert 'no consistent calibration-vehicle track' in reason
    assert 'vehicle seen' not in reason and 'vehicle was never seen' not in reason


def _skin_pass(config):  # type: ignore[no-untyped-def]
    """A car passing a radar at the origin (identity transform) 15 m off, on a straight
    east-bound lane, and the centroid of its faces that face the radar (the cluster
    centre of a car that reflects from its skin)."""
    x0, x1, y0, y1 = -config.vehicle.rear_overhang, \
        config.vehicle.length - config.vehicle.rear_overhang, \
        -0.5 * config.vehicle.width, 0.5 * config.vehicle.width
    centre = np.column_stack([np.linspace(-30.0, 30.0, 60), np.full(60, 15.0),
                              np.full(60, 0.5)])
    yaw = np.zeros(60)
    to_radar = -centre[:, :2]
    norm = np.hypot(to_radar[:, 0], to_radar[:, 1])
    w_end = (y1 - y0) * np.abs(to_radar[:, 0]) / norm
    w_side = (x1 - x0) * np.abs(to_radar[:, 1]) / norm
    faces = centre.copy()
    faces[:, 0] += w_end * 0.5 * (x1 - x0) * np.sign(to_radar[:, 0]) / (w_end + w_side)
    faces[:, 1] += w_side * 0.5 * (y1 - y0) * np.sign(to_radar[:, 1]) / (w_end + w_side)
    return centre, yaw, faces


def test_a_car_that_reflects_from_its_skin_is_fitted_at_its_faces() -> None:
    config = make_scene(n_passes=1).config
    centre, yaw, faces = _skin_pass(config)
    # the radar sees the faces: the centre assumption puts it ~1 m off, the faces' centroid
    # (placed around that first fit) brings it back to centimetres
    source = faces.copy()
    naive = registration.fit_yaw_translation(source, centre)

    def corr(src):  # type: ignore[no-untyped-def]
        return hypotheses.Correspondences(1, src, centre, np.arange(yaw.size), yaw)
    chosen = hypotheses.facing_radar(corr(source), config, keep_better=True).target_m
    fit = registration.fit_yaw_translation(source, chosen)
    assert np.linalg.norm(naive.translation_m[:2]) > 0.5
    assert np.linalg.norm(fit.translation_m[:2]) < 0.1
    assert fit.rms_m < naive.rms_m
    # a car that reflects from inside its footprint keeps the centre
    rng = np.random.default_rng(0)
    interior = centre + rng.normal(0.0, 0.3, centre.shape)
    kept = hypotheses.facing_radar(corr(interior), config, keep_better=True).target_m
    np.testing.assert_array_equal(kept, centre)


def test_a_long_vehicle_of_flat_panels_is_fitted_at_its_nearest_point() -> None:
    """A 12 m bus whose flat sides reflect like mirrors: the radar sees the point of its
    footprint nearest to it (a face's foot of the perpendicular, or a corner). The centre
    and the faces' centroid put the radar metres off; the nearest point, tried for long
    vehicles only, brings it back. A car's config does not try it."""
    bus = CalibConfig.from_mapping({'vehicle.length': 12.0, 'vehicle.width': 2.5,
                                    'vehicle.rear_overhang': 3.0})
    x0, x1 = -3.0, 9.0
    centre = np.column_stack([np.linspace(-40.0, 40.0, 80), np.full(80, 15.0),
                              np.full(80, 0.5)])
    yaw = np.zeros(80)
    middle = centre[:, :2] + [0.5 * (x0 + x1), 0.0]
    centre[:, :2] = middle
    nearest = centre.copy()
    nearest[:, 0] = np.clip(0.0, middle[:, 0] - 6.0, middle[:, 0] + 6.0)
    nearest[:, 1] = middle[:, 1] - 1.25

    def corr(src):  # type: ignore[no-untyped-def]
        return hypotheses.Correspondences(1, src, centre, np.arange(yaw.size), yaw)
    naive = registration.fit_yaw_translation(nearest, centre)
    chosen = hypotheses.facing_radar(corr(nearest), bus, keep_better=True).target_m
    fit = registration.fit_yaw_translation(nearest, chosen)
    assert np.linalg.norm(naive.translation_m[:2]) > 1.0
    assert np.linalg.norm(fit.translation_m[:2]) < 0.1
    car = hypotheses.facing_radar(corr(nearest), CalibConfig(), keep_better=True).target_m
    assert np.linalg.norm(registration.fit_yaw_translation(nearest, car).translation_m[:2]) > 0.5


def test_too_few_passes_names_the_drives_in_view_no_track_followed() -> None:
    # three drives through the view, the last one lost (hidden, below the view): the
    # refusal says when it was and which way the vehicle went, so it can be driven again
    scene = make_scene(n_passes=3)
    vehicle = [t for t in scene.tracks if t.track_id in scene.vehicle_track_ids]
    last = max(vehicle, key=lambda t: t.stamps_ns[0])
    kept = tuple(t for t in scene.tracks if t is not last)
    hyps = hypotheses.generate_hypotheses(kept, scene.recording, scene.ground, scene.config)
    with pytest.raises(InsufficientDataError, match='seen in 2 passes') as err:
        hypotheses.prune_hypotheses(hyps, kept, scene.recording, scene.ground, scene.config)
    message = str(err.value)
    assert 'no track followed it there' in message
    spans = [tuple(map(float, m)) for m in re.findall(r'(\d+)-(\d+) s [\w-]+bound', message)]
    assert len(spans) == 1
    t0 = int(scene.recording.vehicle.stamps_ns[0])
    lost = ((last.stamps_ns[0] - t0) * 1e-9, (last.stamps_ns[-1] - t0) * 1e-9)
    assert spans[0][0] <= lost[1] and spans[0][1] >= lost[0]
    # all drives followed: nothing added
    with pytest.raises(InsufficientDataError) as err:
        _select(make_scene(n_passes=2, split_pass=0))
    assert 'no track followed' not in str(err.value)


def test_hypotheses_of_one_pass_say_how_many_passes_there_were() -> None:
    """A recording whose tracks that fit the vehicle all lie in one pass (here one pass cut
    in two tracks): the reason says so, with the count (a fifty-fifth probe's two-pass
    recording was told 'a single pass fits any road user's track' without it)."""
    scene = make_scene(n_passes=1, seed=1, split_pass=0)
    hyps = hypotheses.generate_hypotheses(scene.tracks, scene.recording, scene.ground,
                                          scene.config)
    assert len(hyps) == 2
    with pytest.raises(InsufficientDataError, match='agrees with one from another pass') as err:
        hypotheses.prune_hypotheses(hyps, scene.tracks, scene.recording, scene.ground,
                                    scene.config)
    assert 'none of the 2 hypotheses (from up to 1 pass)' in str(err.value)


def test_a_loop_inside_the_view_counts_as_enough_passes() -> None:
    """A car looping inside the view (a car park) never leaves it: one pass however many
    loops, which a sixty-sixth probe's loops were refused for, 7 of 7. Tracked heading every
    way it is the vehicle (no other road user follows its poses through a full turn); half
    a loop is not enough, and the reason says how far round it was tracked."""
    scene = make_scene(n_passes=1, loop_radius_m=8.0, split_pass=0)
    hyps, selection = _select(scene)
    assert selection.n_passes == 1
    assert set(selection.accepted_track_ids) == set(scene.vehicle_track_ids)
    np.testing.assert_allclose(selection.extrinsics.translation_m,
                               scene.truth.translation_m, atol=1e-6)
    assert hypotheses.headings_seen(scene.tracks, scene.recording.vehicle, 0.0) == 12
    half = make_scene(n_passes=1, loop_radius_m=20.0, split_pass=0)
    with pytest.raises(InsufficientDataError,
                       match=r'a loop inside the view, tracked in [4-7] of 12 30-deg sectors, '
                             r'need 10'):
        _select(half)


def test_two_passes_turning_through_half_the_compass_are_enough() -> None:
    """At a junction the vehicle stops, turns and leaves inside the view, and its tracks
    agree on fewer passes than it drove (a sixty-seventh probe: 14 turning drives refused
    as 'seen in 2 passes'). Two passes that turned through half the compass or more are
    enough; two straight ones are not (``test_too_few_passes_exits_with_the_numbers``),
    nor is one such pass alone."""
    scene = make_scene(n_passes=2, loop_radius_m=20.0)
    _, selection = _select(scene)
    assert selection.n_passes == 2
    assert hypotheses.headings_seen(scene.tracks, scene.recording.vehicle, 0.0) >= 6
    np.testing.assert_allclose(selection.extrinsics.translation_m,
                               scene.truth.translation_m, atol=1e-6)
    with pytest.raises(InsufficientDataError):
        _select(make_scene(n_passes=1, loop_radius_m=20.0, split_pass=0))
