"""Stage 3: association of the window clusters into tracks.

Consecutive windows share ``K - 1`` frames of targets (stage 2), so a cluster's identity
is propagated to the clusters of the next window that contain the same targets. The
proposed links are verified with the Hungarian algorithm on the distance between cluster
centres wherever they are not one-to-one (a cluster that splits or two that merge), and
gated by ``gate_m`` so that a jump between windows never continues a track.

A track whose object produced too few targets for one or more windows (a far or
occluded car) has no shared targets across the gap; its end is bridged to a new cluster
only if that cluster starts at most ``max_gap_frames`` windows later within ``gate_m`` of
where the track, continued at its last velocity, would be. A new object entering where
another left the view long ago, or somewhere else, starts a new track.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from radar_calib_ros.config import AssociateConfig
from radar_calib_ros.core.cluster import FrameClusters
from radar_calib_ros.types import F64, I64, Targets, TrackedTargets

#: Windows of a track's recent history used to estimate its velocity across a gap.
_VELOCITY_WINDOWS = 5
#: History (windows) after which a track counts as established in a merge conflict.
_AGE_WINDOWS = 10


def associate_clusters(targets: Targets, clusters: FrameClusters,
                       cfg: AssociateConfig) -> TrackedTargets:
    """Give every moving target the track of its cluster.

    Parameters
    ----------
    targets : Targets
        The moving targets that were clustered (same order as ``clusters.labels``).
    clusters : FrameClusters
        Stage 2 output.
    cfg : AssociateConfig
        ``gate_m`` (largest jump of a centre between windows, and largest miss of a gap
        prediction, both in the sensor's x-y plane), ``max_gap_frames``,
        ``min_track_frames``.

    Returns
    -------
    TrackedTargets
        ``target_index`` is ``arange(len(targets))`` (relative to the given targets);
        ``track_id`` numbers tracks 0.. in order of their first frame, -1 for targets in
        no cluster or in a track seen in fewer than ``min_track_frames`` frames.

    Notes
    -----
    A target is in ``K`` windows; it takes the track of its cluster in the window that
    ends at its own frame, else of the next window that clusters it (the first frame of an
    object reaches the minimum cluster size only with later frames).

    References
    ----------
    method-paper.tex, section "Clustering and Association".
    """
    n = len(targets)
    index = np.arange(n, dtype=np.int64)
    n_clusters = clusters.n_clusters
    if n_clusters == 0:
        return TrackedTargets(index, np.full(n, -1, np.int64))
    # Distances in the sensor's x-y plane: the height of a centre carries the elevation
    # noise (1-2 deg, metres at range; worst for the small clusters of a far car), and
    # the sensor's pitch and roll are small enough for x-y to stand in for the road.
    centres = clusters.centres_m[:, :2]
    window = clusters.cluster_window

    labels = clusters.labels
    # Only clusters holding targets of their window's newest frame ("live" clusters)
    # carry an identity: when an object's cloud splits along time, the part made of
    # older frames has no future and must not take the identity from the part that does.
    live = np.zeros(n_clusters, bool)
    live[labels[labels[:, 0] >= 0, 0]] = True
    prev, cur, shared = _shared_target_links(labels, n_clusters)
    near = np.linalg.norm(centres[prev] - centres[cur], axis=1) <= cfg.gate_m
    both_live = near & live[prev] & live[cur]
    predecessor = _one_to_one(prev[both_live], cur[both_live], centres, window, n_clusters,
                              cfg.gate_m)
    linked = np.flatnonzero(predecessor >= 0)
    chain = _components(predecessor[linked], linked, n_clusters)
    has_successor = np.zeros(n_clusters, bool)
    has_successor[predecessor[linked]] = True
    heads = np.flatnonzero(live & (predecessor < 0))
    tails = np.flatnonzero(live & ~has_successor)
    tail_b, head_b = _bridge_gaps(tails, heads, predecessor, centres, window, cfg)
    track_of_chain = _components(chain[tail_b], chain[head_b], int(chain.max()) + 1)
    track_of_cluster = np.where(live, track_of_chain[chain], -1)
    track_of_cluster = _attach_dead_clusters(track_of_cluster, live, prev[near], cur[near],
                                             shared[near])

    own = np.full(n, -1, np.int64)
    for slot in range(labels.shape[1]):
        free = (own < 0) & (labels[:, slot] >= 0)
        own[free] = labels[free, slot]
    track = np.where(own >= 0, track_of_cluster[np.maximum(own, 0)], -1)
    if (track >= 0).any():
        # Tracks are numbered by connected components; make them dense before filtering.
        _, dense = np.unique(track[track >= 0], return_inverse=True)
        track[track >= 0] = dense
    return TrackedTargets(index, _drop_short_tracks(track, targets.frame_index,
                                                    cfg.min_track_frames))


def _shared_target_links(labels: I64, n_clusters: int) -> tuple[I64, I64, I64]:
    """Unique (cluster in window w - 1, cluster in window w) pairs that share targets, and
    how many targets each pair shares."""
    prev_parts, cur_parts = [], []
    for slot in range(labels.shape[1] - 1):
        both = (labels[:, slot] >= 0) & (labels[:, slot + 1] >= 0)
        prev_parts.append(labels[both, slot])
        cur_parts.append(labels[both, slot + 1])
    if not prev_parts:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    key, shared = np.unique(np.concatenate(prev_parts) * n_clusters
                            + np.concatenate(cur_parts), return_counts=True)
    return key // n_clusters, key % n_clusters, shared.astype(np.int64)


def _attach_dead_clusters(track_of_cluster: I64, live: NDArray[np.bool_], prev: I64,
                          cur: I64, shared: I64) -> I64:
    """Give each cluster without newest-frame targets the track of the live cluster it
    shares most targets with in the previous window (else in the next): a target whose
    own window left it as noise falls back on such a cluster."""
    out = track_of_cluster.copy()
    for dead, other in ((cur, prev), (prev, cur)):
        ok = ~live[dead] & live[other] & (out[dead] < 0)
        d, o, s = dead[ok], other[ok], shared[ok]
        if d.size == 0:
            continue
        best = np.lexsort((-s, d))
        d, o = d[best], o[best]
        first = np.r_[True, d[1:] != d[:-1]]
        out[d[first]] = track_of_cluster[o[first]]
    return out


def _one_to_one(prev: I64, cur: I64, centres: F64, window: I64, n_clusters: int,
                gate_m: float) -> I64:
    """Predecessor of each cluster after keeping a one-to-one subset of the links.

    Links whose two clusters have no other link are kept as they are; the others (splits
    and merges) are resolved window by window, in time order, by the Hungarian algorithm
    on centre distance restricted to the proposed links. The cost is lowered by up to
    ``gate_m`` for an established predecessor (``_AGE_WINDOWS`` windows or more): when a
    car's cloud splits for a window and merges again, the merged cluster continues the
    car's long track rather than the fragment born at the split.
    """
    predecessor = np.full(n_clusters, -1, np.int64)
    out_degree = np.bincount(prev, minlength=n_clusters)
    in_degree = np.bincount(cur, minlength=n_clusters)
    simple = (out_degree[prev] == 1) & (in_degree[cur] == 1)
    predecessor[cur[simple]] = prev[simple]
    a_prev, a_cur = prev[~simple], cur[~simple]
    if a_prev.size == 0:
        return predecessor
    order = np.argsort(window[a_cur], kind='stable')
    a_prev, a_cur = a_prev[order], a_cur[order]
    a_dist = np.linalg.norm(centres[a_prev] - centres[a_cur], axis=1)
    w = window[a_cur]
    bounds = np.flatnonzero(np.r_[True, w[1:] != w[:-1], True]).tolist()
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        p = a_prev[lo:hi]
        age = _chain_age(p, predecessor)
        rows, cols = _assign(p, a_cur[lo:hi], a_dist[lo:hi] - gate_m * age / _AGE_WINDOWS)
        predecessor[cols] = rows
    return predecessor


def _chain_age(clusters: I64, predecessor: I64) -> I64:
    """Windows of history behind each cluster, counted up to ``_AGE_WINDOWS``."""
    ages = []
    # A few clusters per call: walking the pointers in Python beats ten numpy passes.
    for at in clusters.tolist():
        age = 0
        while age < _AGE_WINDOWS:
            at = int(predecessor[at])
            if at < 0:
                break
            age += 1
        ages.append(age)
    return np.asarray(ages, np.int64)


def _assign(rows_of_link: I64, cols_of_link: I64, cost_of_link: F64) -> tuple[I64, I64]:
    """Minimum-cost one-to-one subset of candidate links (Hungarian algorithm).

    Called once per ambiguous window, mostly with a handful of links: the bookkeeping is
    plain Python, which is several times faster than numpy's set routines at that size.
    """
    row_list, col_list = rows_of_link.tolist(), cols_of_link.tolist()
    rows, cols = sorted(set(row_list)), sorted(set(col_list))
    if len(rows) == 1 or len(cols) == 1:
        # One cluster on one side (a split or a merge): the cheapest link is the answer.
        best = int(np.argmin(cost_of_link))
        return rows_of_link[best:best + 1], cols_of_link[best:best + 1]
    row_at = {r: i for i, r in enumerate(rows)}
    col_at = {c: j for j, c in enumerate(cols)}
    # Non-candidates cost more than any set of candidates, so the assignment uses as many
    # candidate links as it can; assigned non-candidates are dropped afterwards.
    low, high = float(cost_of_link.min()), float(cost_of_link.max())
    forbidden = high + (high - low + 1.0) * (len(rows) + len(cols) + 1)
    cost = np.full((len(rows), len(cols)), forbidden)
    cost[[row_at[r] for r in row_list], [col_at[c] for c in col_list]] = cost_of_link
    r, c = linear_sum_assignment(cost)
    ok = cost[r, c] < forbidden
    return (np.asarray(rows, np.int64)[r[ok]], np.asarray(cols, np.int64)[c[ok]])


def _components(a: I64, b: I64, n: int) -> I64:
    """Connected-component label of each of ``n`` nodes joined by edges ``a - b``."""
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n)).tocsr()
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _bridge_gaps(tails: I64, heads: I64, predecessor: I64, centres: F64, window: I64,
                 cfg: AssociateConfig) -> tuple[I64, I64]:
    """One-to-one links from chain ends to chain starts across gaps of windows.

    A start is a candidate for an end when it lies 1 .. ``max_gap_frames + 1`` windows
    later (at most ``max_gap_frames`` frames unseen) and within ``gate_m`` of the end's
    centre continued at the chain's velocity.
    """
    empty = np.zeros(0, np.int64)
    if cfg.max_gap_frames == 0 or tails.size == 0 or heads.size == 0:
        return empty, empty
    # Velocity per window from up to _VELOCITY_WINDOWS clusters back along the chain.
    earlier = tails.copy()
    for _ in range(_VELOCITY_WINDOWS):
        back = predecessor[earlier]
        earlier = np.where(back >= 0, back, earlier)
    span = window[tails] - window[earlier]
    velocity = (centres[tails] - centres[earlier]) / np.maximum(span, 1)[:, None]

    # Candidates by one bulk radius query: each end continued 1 .. max_gap + 1 windows
    # ahead, against the starts, with the window as a third coordinate spaced wider than
    # the gate so that only starts in the predicted window can fall within it.
    gaps = np.arange(1, cfg.max_gap_frames + 2)
    of_tail = np.repeat(np.arange(tails.size), gaps.size)
    gap = np.tile(gaps, tails.size)
    spacing = 4.0 * cfg.gate_m
    first_window = int(window.min())
    predicted = np.column_stack([centres[tails[of_tail]] + velocity[of_tail] * gap[:, None],
                                 (window[tails[of_tail]] + gap - first_window) * spacing])
    starts = np.column_stack([centres[heads], (window[heads] - first_window) * spacing])
    pairs = cKDTree(predicted).sparse_distance_matrix(cKDTree(starts), cfg.gate_m,
                                                      output_type='ndarray')
    t = tails[of_tail[pairs['i']]]
    h = heads[pairs['j'].astype(np.int64)]
    miss = pairs['v'].astype(np.float64)
    if t.size == 0:
        return empty, empty
    out_degree = np.bincount(t, minlength=window.size)
    in_degree = np.bincount(h, minlength=window.size)
    simple = (out_degree[t] == 1) & (in_degree[h] == 1)
    keep_t, keep_h = [t[simple]], [h[simple]]
    t, h, miss = t[~simple], h[~simple], miss[~simple]
    if t.size:
        # Ambiguous candidates: one Hungarian problem per connected group of ends and
        # starts, on the miss distance of the prediction.
        ends, end_of = np.unique(t, return_inverse=True)
        starts, start_of = np.unique(h, return_inverse=True)
        group = _components(end_of, ends.size + start_of, ends.size + starts.size)[:ends.size]
        edge_group = group[end_of]
        order = np.argsort(edge_group, kind='stable')
        t, h, miss, edge_group = t[order], h[order], miss[order], edge_group[order]
        bounds = np.flatnonzero(np.r_[True, edge_group[1:] != edge_group[:-1], True])
        for a, b in zip(bounds[:-1], bounds[1:]):
            rows, cols = _assign(t[a:b], h[a:b], miss[a:b])
            keep_t.append(rows)
            keep_h.append(cols)
    return np.concatenate(keep_t), np.concatenate(keep_h)


def _drop_short_tracks(track: I64, frame_index: I64, min_frames: int) -> I64:
    """-1 for tracks seen in fewer than ``min_frames`` distinct frames; the rest renumbered
    0.. in order of their first frame."""
    member = np.flatnonzero(track >= 0)
    if member.size == 0:
        return track
    n_frames = int(frame_index.max()) + 1
    # Sorted unique (track, frame) keys: frames seen per track, first frame first.
    key = np.unique(track[member] * n_frames + frame_index[member])
    key_track = key // n_frames
    tracks, first, frames_seen = np.unique(key_track, return_index=True, return_counts=True)
    long_enough = frames_seen >= min_frames
    kept = tracks[long_enough]
    kept = kept[np.lexsort((kept, (key % n_frames)[first[long_enough]]))]
    renumber = np.full(int(track.max()) + 1, -1, np.int64)
    renumber[kept] = np.arange(kept.size)
    return np.where(track >= 0, renumber[np.maximum(track, 0)], -1)


#: Longest time between two measurements of one track [s]: association links clusters by
#: frame number, and frames far apart in time (a radar clock that jumps, a recording paused
#: and resumed) are not one motion. A track across a jump of an hour made the tracking
#: filter predict over 3600 s and fail.
MAX_TRACK_GAP_S = 2.0


def split_tracks_at_time_gaps(track_id: I64, target_stamps_ns: I64,
                              max_gap_s: float = MAX_TRACK_GAP_S) -> I64:
    """(m,) track ids with every track cut where its consecutive measurements are more
    than ``max_gap_s`` apart; -1 (no track) stays -1. The pieces get
    new ids after the existing ones; a track without such a gap keeps its id."""
    out = np.array(track_id, np.int64, copy=True)
    member = np.flatnonzero(out >= 0)
    if member.size < 2:
        return out
    order = member[np.lexsort((target_stamps_ns[member], out[member]))]
    ids, stamps = out[order], target_stamps_ns[order]
    step = np.diff(stamps)
    same = ids[1:] == ids[:-1]
    cut = same & (step > round(max_gap_s * 1e9))
    if not cut.any():
        return out
    piece = np.concatenate([[0], np.cumsum(cut)])
    # per track, the pieces after its first get new ids
    first_piece = piece[np.searchsorted(ids, ids, side='left')]
    later = piece > first_piece
    _, new_id = np.unique(piece[later], return_inverse=True)
    out[order[later]] = int(out.max()) + 1 + new_id.ravel()
    return out
