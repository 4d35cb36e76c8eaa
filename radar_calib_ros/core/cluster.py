"""Stage 2: DBSCAN clustering of the moving targets over sliding windows of frames.

The paper accumulates three consecutive frames per clustering so that an object with a
single target per frame (a pedestrian, a far car) still reaches the minimum cluster size
of three, and extends the Euclidean distance by the radial velocity so that two objects
passing close to each other at different speeds stay apart:
``d^2 = |p_i - p_j|^2 + (velocity_weight * (v_i - v_j))^2``.

The window slides by one frame: window ``w`` holds frames ``w - K + 1 .. w``
(``K = accumulate_frames``), so every target belongs to ``K`` windows. The association
stage propagates identities from window ``w - 1`` to ``w`` through the targets the two
windows share; that is why all ``K`` labels of a target are kept.

All windows are clustered at once rather than by one DBSCAN call per window (13 500
calls of a library's per-call overhead would cost more than the clustering): a
``scipy.spatial.cKDTree`` finds every pair of targets within ``eps_m`` whose frames are
fewer than ``K`` apart in one bulk query per frame lag; each pair is then an edge in every
window that holds both targets. A node is one (target, window) membership; DBSCAN's core
points are the nodes with at least ``min_samples`` neighbours (itself included, as in
scikit-learn), clusters are the connected components of the core-core edges
(``scipy.sparse.csgraph``), and a border node joins the cluster of its nearest core
neighbour. That is DBSCAN per window, with ties of border points broken by distance
rather than by visiting order, which makes the labels independent of the order of the
targets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from radar_calib_ros.config import ClusterConfig
from radar_calib_ros.types import F64, I64, Targets

#: Windows clustered per bulk query: bounds the memory of the pair and edge arrays
#: (with 160 "moving" targets per frame, static clutter included, 500 windows give some
#: 2.5 million candidate pairs) ...
_CHUNK_FRAMES = 500
#: ... and at most about this many targets per chunk: a 4D imaging radar puts 100+ targets
#: on one car, every one within eps of the car's others, and 500 of its frames held over a
#: gigabyte of pairs.
_CHUNK_TARGETS = 40_000


@dataclass(frozen=True, slots=True)
class FrameClusters:
    """Clusters of every sliding window.

    labels : ndarray of shape (n, K), int64
        ``labels[i, k]`` is the cluster of target ``i`` in the window whose newest frame is
        ``frame_index[i] + k``; -1 = noise in that window (or no such window: windows end
        at the last frame that has a target).
    cluster_window : ndarray of shape (c,), int64
        Newest frame of each cluster's window; clusters are numbered in window order.
    centres_m : ndarray of shape (c, 3)
        Mean position of each cluster's targets (all frames of its window) [m].
    sizes : ndarray of shape (c,), int64
        Number of targets of each cluster.
    """

    labels: I64
    cluster_window: I64
    centres_m: F64
    sizes: I64

    def __post_init__(self) -> None:
        for array in (self.labels, self.cluster_window, self.centres_m, self.sizes):
            array.setflags(write=False)

    @property
    def accumulate_frames(self) -> int:
        """K, the number of frames per window."""
        return int(self.labels.shape[1])

    @property
    def n_clusters(self) -> int:
        """Number of clusters over all windows."""
        return int(self.cluster_window.shape[0])


def cluster_targets(targets: Targets, cfg: ClusterConfig) -> FrameClusters:
    """Cluster the moving targets of every window of ``accumulate_frames`` frames.

    Parameters
    ----------
    targets : Targets
        The moving targets (stage 1 output), in any order.
    cfg : ClusterConfig
        ``eps_m``, ``min_samples`` (itself included), ``accumulate_frames`` and
        ``velocity_weight`` [m per m/s].

    Returns
    -------
    FrameClusters
        Labels of each target in each of its windows, the window, centre and size of each
        cluster.

    Notes
    -----
    Memory and time grow with the number of target pairs within ``eps_m`` whose frames are
    fewer than ``accumulate_frames`` apart, never with the square of the number of targets:
    windows are processed in chunks of ``_CHUNK_FRAMES`` frames or ``_CHUNK_TARGETS``
    targets, whichever is fewer.

    References
    ----------
    method-paper.tex, section "Clustering and Association"; Schubert et al., "DBSCAN
    revisited" (2017).
    """
    n = len(targets)
    k_frames = cfg.accumulate_frames
    labels = np.full((n, k_frames), -1, dtype=np.int64)
    if n == 0:
        return FrameClusters(labels, np.zeros(0, np.int64), np.zeros((0, 3)),
                             np.zeros(0, np.int64))
    order = np.argsort(targets.frame_index, kind='stable')
    frames = targets.frame_index[order]
    windows: list[I64] = []
    n_labels = 0
    f_first, f_last = int(frames[0]), int(frames[-1])
    w0 = f_first
    while w0 <= f_last:
        start = int(np.searchsorted(frames, w0, side='left'))
        # up to the frame of the _CHUNK_TARGETS-th target from here (at least one frame)
        by_targets = (int(frames[start + _CHUNK_TARGETS]) if start + _CHUNK_TARGETS < n
                      else f_last + 1)
        w1 = min(w0 + _CHUNK_FRAMES, f_last + 1, max(w0 + 1, by_targets))
        lo = int(np.searchsorted(frames, w0 - k_frames + 1, side='left'))
        hi = int(np.searchsorted(frames, w1 - 1, side='right'))
        # The features and labels of a chunk's targets are gathered and written back per
        # chunk: all targets' sorted copies (four float64 and K int64 columns each) were
        # 350 MB for a dense imaging radar's 3.9 million moving targets.
        rows = order[lo:hi]
        features = np.empty((rows.size, 4))
        features[:, :3] = targets.positions_m[rows]
        features[:, 3] = cfg.velocity_weight * targets.radial_velocity_mps[rows]
        chunk_labels, chunk_windows = _cluster_windows(
            features, frames[lo:hi], w0, w1, k_frames, cfg.eps_m, cfg.min_samples)
        member = chunk_labels >= 0
        block = labels[rows]
        block[member] = chunk_labels[member] + n_labels
        labels[rows] = block
        windows.append(chunk_windows)
        n_labels += chunk_windows.shape[0]
        w0 = w1
    cluster_window = np.concatenate(windows) if windows else np.zeros(0, np.int64)
    member = labels >= 0
    owner = np.broadcast_to(np.arange(n)[:, None], labels.shape)[member]
    flat = labels[member]
    sizes = np.bincount(flat, minlength=n_labels).astype(np.int64)
    centres = np.column_stack([
        np.bincount(flat, weights=targets.positions_m[owner, axis], minlength=n_labels)
        for axis in range(3)]) / np.maximum(sizes, 1)[:, None]
    return FrameClusters(labels, cluster_window, centres, sizes)


def _cluster_windows(features: F64, frames: I64, w0: int, w1: int, k_frames: int,
                     eps_m: float, min_samples: int) -> tuple[I64, I64]:
    """DBSCAN of the windows ``w0 .. w1 - 1`` over targets sorted by frame.

    Returns the labels (m, K), numbered from 0 in window order, -1 for noise or for a
    membership whose window is outside ``[w0, w1)``, and the window of each label.
    """
    m = features.shape[0]
    if m == 0:
        return np.full((0, k_frames), -1, np.int64), np.zeros(0, np.int64)
    rel = (frames - frames[0]).astype(np.float64)
    # A fifth coordinate, frame * spacing, keeps frames apart: with spacing > eps /
    # sqrt(2K - 1), a ball of radius sqrt(eps^2 + ((K - 1) spacing)^2) holds every pair
    # within eps whose frames are up to K - 1 apart and none K or more apart. One bulk
    # query finds them all; the pairs beyond eps in the original distance are dropped.
    spacing = 1.05 * eps_m / np.sqrt(2.0 * k_frames - 1.0)
    radius = float(np.sqrt(eps_m**2 + ((k_frames - 1) * spacing) ** 2))
    coords = np.empty((m, 5))
    coords[:, :4] = features
    coords[:, 4] = rel * spacing
    pairs = cKDTree(coords).query_pairs(radius, output_type='ndarray').reshape(-1, 2)
    # query_pairs gives i < j, and targets are sorted by frame: j is never the earlier.
    first, second = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    lag_of = frames[second] - frames[first]
    in_reach = lag_of < k_frames
    first, second, lag_of = first[in_reach], second[in_reach], lag_of[in_reach]
    diff = features[first] - features[second]
    # Squared distances: the threshold and the nearest-core ordering need no square root.
    dist = np.einsum('ij,ij->i', diff, diff)
    near = dist <= eps_m * eps_m
    first, second, dist, lag_of = first[near], second[near], dist[near], lag_of[near]

    # Expand each pair into its edges: the pair (i, j) with frame_j = frame_i + lag is in
    # the windows frame_j + s for s = 0 .. K - 1 - lag, where i is at slot lag + s and j
    # at slot s (slot = window - own frame).
    edge_a: list[I64] = []
    edge_b: list[I64] = []
    edge_d: list[F64] = []
    for lag in range(k_frames):
        sel = lag_of == lag
        i, j, d = first[sel], second[sel], dist[sel]
        for s in range(k_frames - lag):
            window = frames[j] + s
            ok = (window >= w0) & (window < w1)
            edge_a.append(i[ok] * k_frames + lag + s)
            edge_b.append(j[ok] * k_frames + s)
            edge_d.append(d[ok])
    a = np.concatenate(edge_a)
    b = np.concatenate(edge_b)
    d = np.concatenate(edge_d)

    n_nodes = m * k_frames
    node_window = (frames[:, None] + np.arange(k_frames)[None, :]).ravel()
    valid = (node_window >= w0) & (node_window < w1)
    counts = 1 + np.bincount(a, minlength=n_nodes) + np.bincount(b, minlength=n_nodes)
    core = valid & (counts >= min_samples)

    both = core[a] & core[b]
    graph = coo_matrix((np.ones(int(both.sum()), np.int8), (a[both], b[both])),
                       shape=(n_nodes, n_nodes)).tocsr()
    _, component = connected_components(graph, directed=False)
    core_nodes = np.flatnonzero(core)
    unique_comp, core_label = np.unique(component[core_nodes], return_inverse=True)
    # Number clusters in window order so labels read chronologically.
    comp_window = np.zeros(unique_comp.shape[0], np.int64)
    comp_window[core_label] = node_window[core_nodes]
    renumber = np.empty_like(comp_window)
    by_window = np.argsort(comp_window, kind='stable')
    renumber[by_window] = np.arange(by_window.shape[0])
    node_label = np.full(n_nodes, -1, np.int64)
    node_label[core_nodes] = renumber[core_label]

    # Border nodes: not core, but within eps of a core node of the same window.
    a_to_b = core[a] & ~core[b] & valid[b]
    b_to_a = core[b] & ~core[a] & valid[a]
    border = np.concatenate([b[a_to_b], a[b_to_a]])
    via = np.concatenate([a[a_to_b], b[b_to_a]])
    via_d = np.concatenate([d[a_to_b], d[b_to_a]])
    if border.size:
        nearest = np.lexsort((via, via_d, border))
        border, via = border[nearest], via[nearest]
        first_of = np.r_[True, border[1:] != border[:-1]]
        node_label[border[first_of]] = node_label[via[first_of]]
    return node_label.reshape(m, k_frames), comp_window[by_window]
