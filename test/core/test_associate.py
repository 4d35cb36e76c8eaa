"""Stage 3: association of window clusters into tracks."""
from __future__ import annotations

import numpy as np

from radar_calib_ros.config import AssociateConfig, ClusterConfig
from radar_calib_ros.core.associate import associate_clusters
from radar_calib_ros.core.cluster import cluster_targets
from radar_calib_ros.types import Targets

DT = 1.0 / 15.0


def _scene(objects: list[dict], seed: int = 0) -> tuple[Targets, np.ndarray]:
    """Targets of moving objects: each dict has start, stop (frames), p0 (x, y), v (vx, vy)
    and optionally missing (frames without any target). Returns targets and object ids."""
    rng = np.random.default_rng(seed)
    positions, velocities, frames, owner = [], [], [], []
    for oid, obj in enumerate(objects):
        p0, v = np.asarray(obj['p0'], float), np.asarray(obj['v'], float)
        heading = v / np.linalg.norm(v)
        for f in range(obj['start'], obj['stop']):
            if f in obj.get('missing', ()):
                continue
            k = int(rng.integers(3, 7))
            centre = p0 + v * (f - obj['start']) * DT
            along = rng.uniform(-2.2, 2.2, k)
            across = rng.uniform(-0.8, 0.8, k)
            xy = centre + along[:, None] * heading + across[:, None] * heading[::-1] * [-1, 1]
            pos = np.column_stack([xy, rng.uniform(-6.0, -4.8, k)])
            sight = pos / np.linalg.norm(pos, axis=1)[:, None]
            positions.append(pos)
            velocities.append(sight[:, :2] @ v + rng.normal(0.0, 0.05, k))
            frames.append(np.full(k, f))
            owner.append(np.full(k, oid))
    targets = Targets(np.concatenate(positions), np.concatenate(velocities),
                      np.concatenate(frames).astype(np.int64))
    return targets, np.concatenate(owner)


def _track_ids(targets: Targets, cfg: AssociateConfig | None = None) -> np.ndarray:
    clusters = cluster_targets(targets, ClusterConfig())
    tracked = associate_clusters(targets, clusters, cfg or AssociateConfig())
    np.testing.assert_array_equal(tracked.target_index, np.arange(len(targets)))
    return tracked.track_id


def test_one_identity_through_a_pass_with_dropouts() -> None:
    # 8 s across the field of view at 12 m/s, with a 4-frame dropout (all targets lost)
    targets, _ = _scene([dict(start=0, stop=120, p0=(20.0, -30.0), v=(0.0, 12.0),
                              missing=range(60, 64))])
    track = _track_ids(targets)
    assert (track >= 0).mean() > 0.95
    assert np.unique(track[track >= 0]).size == 1


def test_two_cars_passing_each_other_keep_their_identities() -> None:
    # adjacent lanes along the line of sight: one receding, one approaching, side by side
    # (within eps) for several frames around x = 50 m; the radial velocity keeps them apart
    targets, owner = _scene([dict(start=0, stop=90, p0=(20.0, -1.6), v=(10.0, 0.0)),
                             dict(start=0, stop=90, p0=(80.0, 1.6), v=(-10.0, 0.0))])
    track = _track_ids(targets)
    ids = [np.unique(track[(owner == o) & (track >= 0)]) for o in (0, 1)]
    assert [i.size for i in ids] == [1, 1]
    assert ids[0][0] != ids[1][0]
    assert (track >= 0).mean() > 0.9


def test_a_new_object_is_not_tied_to_one_that_left() -> None:
    leave = dict(start=0, stop=50, p0=(30.0, -20.0), v=(0.0, 10.0))
    end = np.array([30.0, -20.0]) + np.array([0.0, 10.0]) * 49 * DT
    # appears 2 frames later but 12 m away from where the first would be
    elsewhere = dict(start=52, stop=100, p0=(30.0, end[1] + 12.0), v=(0.0, 10.0))
    # appears exactly where the first would be, but after a gap longer than max_gap_frames
    cfg = AssociateConfig(max_gap_frames=5)
    late_start = 50 + cfg.max_gap_frames + 6
    late = dict(start=late_start, stop=late_start + 40,
                p0=tuple(end + np.array([0.0, 10.0]) * (late_start - 49) * DT), v=(0.0, 10.0))
    for follower in (elsewhere, late):
        targets, owner = _scene([leave, follower], seed=1)
        track = _track_ids(targets, cfg)
        first = np.unique(track[(owner == 0) & (track >= 0)])
        second = np.unique(track[(owner == 1) & (track >= 0)])
        assert first.size == 1 and second.size == 1
        assert first[0] != second[0]


def test_a_short_gap_at_the_predicted_place_is_bridged() -> None:
    # the object unseen for max_gap_frames frames (no shared targets across the gap),
    # then back where its velocity puts it: one track; unseen one frame longer: two
    cfg = AssociateConfig(max_gap_frames=5)
    for unseen, n_tracks in ((cfg.max_gap_frames, 1), (cfg.max_gap_frames + 1, 2)):
        targets, _ = _scene([dict(start=0, stop=80, p0=(25.0, -25.0), v=(0.0, 11.0),
                                  missing=range(40, 40 + unseen))], seed=2)
        track = _track_ids(targets, cfg)
        assert np.unique(track[track >= 0]).size == n_tracks
    # with bridging disabled even a short gap splits the track
    targets, _ = _scene([dict(start=0, stop=80, p0=(25.0, -25.0), v=(0.0, 11.0),
                              missing=range(40, 43))], seed=2)
    track = _track_ids(targets, AssociateConfig(max_gap_frames=0))
    assert np.unique(track[track >= 0]).size == 2


def test_short_tracks_are_dropped_and_ids_are_dense() -> None:
    targets, owner = _scene([dict(start=0, stop=6, p0=(30.0, 0.0), v=(0.0, 10.0)),
                             dict(start=10, stop=60, p0=(60.0, -10.0), v=(0.0, 10.0)),
                             dict(start=20, stop=70, p0=(45.0, 10.0), v=(0.0, -10.0))])
    track = _track_ids(targets, AssociateConfig(min_track_frames=8))
    assert np.all(track[owner == 0] == -1)
    # numbered 0.. by first frame
    assert np.unique(track[owner == 1]).tolist() == [0]
    assert np.unique(track[owner == 2]).tolist() == [1]


def test_tracks_are_cut_where_their_stamps_jump() -> None:
    """A radar clock that jumps by an hour between two frames: association links the
    frames by number, the tracks are cut at the jump (the filter would otherwise predict
    over 3600 s and fail); small steps and the noise label -1 are kept."""
    from radar_calib_ros.core.associate import split_tracks_at_time_gaps

    s = 1_000_000_000
    # track 0: 0.0, 0.1, 0.2 s then 3600.3, 3600.4 s; track 1: 1.0, 2.5 s (1.5 s: kept);
    # noise; track 2 (targets out of order) jumps 5 s
    track = np.array([0, 0, 0, 0, 0, 1, 1, -1, 2, 2, 2])
    stamps = np.array([0, s // 10, s // 5, 3600 * s + 3 * s // 10, 3600 * s + 4 * s // 10,
                       s, 5 * s // 2, 7 * s, 20 * s, 10 * s, 11 * s])
    out = split_tracks_at_time_gaps(track, stamps)
    assert out[:3].tolist() == [0, 0, 0] and out[5:8].tolist() == [1, 1, -1]
    assert out[3] == out[4] and out[3] not in (0, 1, 2)
    assert out[9] == out[10] == 2 and out[8] not in (0, 1, 2, out[3])
    np.testing.assert_array_equal(split_tracks_at_time_gaps(track[:3], stamps[:3]), [0, 0, 0])
