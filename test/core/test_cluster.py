"""Stage 2: DBSCAN over sliding windows of frames, distance extended by radial velocity."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.cluster import DBSCAN

from radar_calib_ros.config import ClusterConfig
from radar_calib_ros.core.cluster import cluster_targets
from radar_calib_ros.types import Targets


def _targets(positions: np.ndarray, velocities: np.ndarray, frames: np.ndarray) -> Targets:
    return Targets(np.asarray(positions, float).reshape(-1, 3), np.asarray(velocities, float),
                   np.asarray(frames, np.int64))


def _random_scene(rng: np.random.Generator, n_frames: int = 30) -> Targets:
    positions, velocities, frames = [], [], []
    for f in range(n_frames):
        k = int(rng.integers(3, 30))
        centres = rng.uniform(-15.0, 15.0, (4, 3))
        which = rng.integers(0, 4, k)
        positions.append(centres[which] + rng.normal(0.0, 1.0, (k, 3)))
        velocities.append(which + rng.normal(0.0, 0.8, k))
        frames.append(np.full(k, f))
    order = rng.permutation(sum(len(x) for x in frames))
    return _targets(np.concatenate(positions)[order], np.concatenate(velocities)[order],
                    np.concatenate(frames)[order])


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal up to relabelling (noise -1 must stay noise)."""
    if not np.array_equal(a < 0, b < 0):
        return False
    pairs = set(zip(a[a >= 0].tolist(), b[b >= 0].tolist()))
    return len(pairs) == len(set(a[a >= 0].tolist())) == len(set(b[b >= 0].tolist()))


@pytest.mark.parametrize('k_frames', [1, 3])
def test_each_window_is_dbscan_of_its_frames(k_frames: int) -> None:
    """Known answer: scikit-learn's DBSCAN on each window's targets, with the velocity as a
    fourth coordinate scaled by velocity_weight. Core points, noise and the partition of
    core points must agree (border points may go to either of two touching clusters)."""
    targets = _random_scene(np.random.default_rng(0))
    cfg = ClusterConfig(eps_m=2.0, velocity_weight=0.7, min_samples=3,
                        accumulate_frames=k_frames)
    clusters = cluster_targets(targets, cfg)
    assert clusters.labels.shape == (len(targets), k_frames)
    for window in range(int(targets.frame_index.max()) + 1):
        members = np.flatnonzero((targets.frame_index <= window)
                                 & (targets.frame_index > window - k_frames))
        slot = window - targets.frame_index[members]
        ours = clusters.labels[members, slot]
        features = np.column_stack([targets.positions_m[members],
                                    0.7 * targets.radial_velocity_mps[members]])
        reference = DBSCAN(eps=2.0, min_samples=3).fit(features)
        core = np.zeros(members.size, bool)
        core[reference.core_sample_indices_] = True
        assert np.array_equal(ours < 0, reference.labels_ < 0)
        assert _same_partition(ours[core], reference.labels_[core])
        assert np.all(clusters.cluster_window[ours[ours >= 0]] == window)
    # windows end at the last frame: slots past it are unlabelled
    last = targets.frame_index.max()
    beyond = targets.frame_index[:, None] + np.arange(k_frames) > last
    assert np.all(clusters.labels[beyond] == -1)


def _passing_cars(velocity_weight: float) -> tuple[Targets, np.ndarray, np.ndarray]:
    """Two cars on the same line of sight, one approaching at 10 m/s and one receding at
    10 m/s, crossing at x = 40 m around frame 15 (they overlap for several frames)."""
    rng = np.random.default_rng(3)
    positions, velocities, frames, car = [], [], [], []
    dt = 1.0 / 15.0
    for f in range(30):
        for c, (x0, v) in enumerate([(30.0, 10.0), (50.0, -10.0)]):
            x = x0 + v * f * dt
            k = 5
            pos = np.column_stack([x + rng.uniform(-2.0, 2.0, k),
                                   rng.uniform(-0.8, 0.8, k), rng.uniform(-6.0, -5.0, k)])
            positions.append(pos)
            velocities.append(v + rng.normal(0.0, 0.1, k))
            frames.append(np.full(k, f))
            car.append(np.full(k, c))
    targets = _targets(np.concatenate(positions), np.concatenate(velocities),
                       np.concatenate(frames))
    labels = cluster_targets(targets, ClusterConfig(eps_m=2.0, velocity_weight=velocity_weight,
                                                    min_samples=3, accumulate_frames=3)).labels
    return targets, np.concatenate(car), labels


def test_two_cars_passing_each_other_stay_apart() -> None:
    targets, car, labels = _passing_cars(velocity_weight=1.0)
    # they do overlap in space: at frame 15 the two clouds share x
    f15 = targets.frame_index == 15
    x0 = targets.positions_m[f15 & (car == 0), 0]
    x1 = targets.positions_m[f15 & (car == 1), 0]
    assert x0.max() > x1.min() and x1.max() > x0.min()
    clustered = labels >= 0
    for label in np.unique(labels[clustered]):
        owners = np.unique(np.broadcast_to(car[:, None], labels.shape)[labels == label])
        assert owners.size == 1, f'cluster {label} mixes both cars'
    # and most targets of both cars are clustered in their own window
    assert (labels[:, 0] >= 0).mean() > 0.9


def test_without_the_velocity_term_the_crossing_cars_merge() -> None:
    _, car, labels = _passing_cars(velocity_weight=0.0)
    mixed = [label for label in np.unique(labels[labels >= 0]) if np.unique(
        np.broadcast_to(car[:, None], labels.shape)[labels == label]).size > 1]
    assert mixed


def test_accumulation_clusters_an_object_with_one_target_per_frame() -> None:
    frames = np.arange(6)
    positions = np.column_stack([20.0 + 0.3 * frames, np.zeros(6), np.zeros(6)])
    targets = _targets(positions, np.full(6, 4.5), frames)
    accumulated = cluster_targets(targets, ClusterConfig(accumulate_frames=3, min_samples=3))
    single = cluster_targets(targets, ClusterConfig(accumulate_frames=1, min_samples=3))
    assert np.all(single.labels == -1)
    # from the third frame on, each target's own window holds three targets
    assert np.all(accumulated.labels[2:, 0] >= 0)
    assert np.all(accumulated.labels[:2, 0] == -1)
    assert np.all(accumulated.sizes == 3)


def test_eps_boundary_is_inclusive() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0 + 1e-9, 0.0, 0.0]])
    targets = _targets(positions, np.zeros(3), np.zeros(3))
    cfg = ClusterConfig(eps_m=2.0, min_samples=2, accumulate_frames=1)
    labels = cluster_targets(targets, cfg).labels[:, 0]
    # exactly eps apart: neighbours (scikit-learn's convention too)
    assert labels[0] == labels[1] >= 0
    # a hair beyond eps from its nearest neighbour: noise
    assert labels[2] == -1


def test_centres_sizes_and_empty_input() -> None:
    targets = _random_scene(np.random.default_rng(1), n_frames=10)
    clusters = cluster_targets(targets, ClusterConfig())
    for label in range(clusters.n_clusters):
        owner = np.flatnonzero((clusters.labels == label).any(axis=1))
        assert clusters.sizes[label] == owner.size
        np.testing.assert_allclose(clusters.centres_m[label],
                                   targets.positions_m[owner].mean(axis=0))
    assert np.all(np.diff(clusters.cluster_window) >= 0)
    empty = cluster_targets(_targets(np.zeros((0, 3)), np.zeros(0), np.zeros(0)),
                            ClusterConfig())
    assert empty.labels.shape == (0, 3) and empty.n_clusters == 0
    with pytest.raises(ValueError):
        clusters.labels[0, 0] = 5


@settings(deadline=None, max_examples=25)
@given(st.integers(min_value=0, max_value=2**31 - 1))
def test_labels_invariant_under_permutation_of_targets(seed: int) -> None:
    rng = np.random.default_rng(seed)
    targets = _random_scene(rng, n_frames=8)
    perm = rng.permutation(len(targets))
    cfg = ClusterConfig(eps_m=2.0, velocity_weight=0.5)
    base = cluster_targets(targets, cfg).labels
    permuted = cluster_targets(targets.subset(perm), cfg).labels
    for slot in range(cfg.accumulate_frames):
        assert _same_partition(base[perm, slot], permuted[:, slot])


@pytest.mark.parametrize('chunk_targets', [25, 60, 10**9])
def test_chunks_by_target_count_give_the_same_clusters(
        chunk_targets: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Dense frames (a 4D imaging radar) are clustered in chunks of fewer frames so the
    pair arrays stay bounded; the windows are independent, so the clusters are the same as
    in one chunk, including those of the windows at the chunks' edges."""
    from radar_calib_ros.core import cluster

    targets = _random_scene(np.random.default_rng(3), n_frames=40)
    cfg = ClusterConfig()
    monkeypatch.setattr(cluster, '_CHUNK_FRAMES', 10**9)
    monkeypatch.setattr(cluster, '_CHUNK_TARGETS', 10**9)
    whole = cluster_targets(targets, cfg)
    monkeypatch.setattr(cluster, '_CHUNK_TARGETS', chunk_targets)
    chunked = cluster_targets(targets, cfg)
    assert whole.centres_m.shape[0] > 40
    np.testing.assert_array_equal(chunked.labels, whole.labels)
    np.testing.assert_array_equal(chunked.cluster_window, whole.cluster_window)
    np.testing.assert_allclose(chunked.centres_m, whole.centres_m)
