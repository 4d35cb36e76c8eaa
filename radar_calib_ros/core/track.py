"""Stage 5: tracking in the levelled bird's-eye view (UKF, CTRA model, RTS smoother).

Each track's targets are rotated by R_alpha_beta (stage 4), the height dropped, and
averaged per frame: the cluster centre is one measurement per frame, however many frames
of the sliding window its targets came from. The centre jumps as the set of reflecting
points changes, so it is filtered with an unscented Kalman filter over a constant turn
rate and acceleration (CTRA) model, state ``[x, y, yaw, v, yaw_rate, a]``, and smoothed
backwards with the unscented Rauch-Tung-Striebel smoother (Sarkka 2008). The time step
varies with the frame stamps (dropped frames, gaps in a track).

filterpy's ``UnscentedKalmanFilter`` is the reference (:func:`smooth_track_reference`).
The production path (:func:`smooth_tracks`) runs the same filter and smoother on all
tracks at once, step by step with numpy over the tracks (a 15-minute recording has
thousands of tracks and ~10^5 steps; filterpy takes ~0.25 ms per step). A test asserts
that both give the same numbers. Two filterpy details are matched on purpose:

* ``predict`` draws new sigma points from the predicted mean and covariance for the
  update, so with our linear measurement (the centre) the update equals a Kalman update;
* ``rts_smoother`` ignores ``Qs`` (rlabbe/filterpy#287) and adds a plain ``+=`` to the
  yaw: the reference therefore runs it one step at a time with ``Q`` set to the step's
  process noise, and wraps the yaw after each step.

Yaw is an angle throughout: sigma points, residuals and means go through
``core._angles`` (the filterpy hooks ``residual_x``, ``x_mean_fn``, ``state_add`` and the
sigma points' ``subtract``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from radar_calib_ros.config import TrackConfig
from radar_calib_ros.core._angles import wrap_angle
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import F64, I64, GroundPlane, SmoothedTrack, TrackedTargets

#: State dimension and the index of the angle in it: [x, y, yaw, v, yaw_rate, a].
DIM_X = 6
YAW = 2
#: Merwe scaled sigma points: alpha = 1, kappa = 0 give lambda = 0 and non-negative
#: weights (no negative central weight that could make a covariance indefinite), with the
#: points at +-sqrt(6) standard deviations.
ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0
#: Below this yaw rate [rad/s] the CTRA step uses its first-order series in the yaw rate
#: (the closed form divides by yaw_rate^2).
_SMALL_YAW_RATE = 1e-4
#: Initial state: heading and speed from the centre's displacement over this span [s].
_INIT_SPAN_S = 0.5
#: Initial standard deviations of speed [m/s], yaw rate [rad/s] and acceleration [m/s^2];
#: the heading's is 2 measurement sigmas over the initial displacement, within limits.
_INIT_SIGMA_V, _INIT_SIGMA_YAW_RATE, _INIT_SIGMA_A = 3.0, 0.5, 3.0
_INIT_SIGMA_YAW_MIN, _INIT_SIGMA_YAW_MAX = 0.05, 1.0
#: Largest yaw standard deviation after a predict or an update [rad]. A stopped or creeping
#: object's heading is unobservable and its variance would grow without bound; once the
#: sigma points (at +-sqrt(6) sigma) spread over more than a half turn, their wrapped
#: residuals no longer describe the covariance and it stops being positive definite.
_MAX_SIGMA_YAW = 1.0
#: Tracks longer than core + 2 overlaps are smoothed in overlapping segments
#: (see ``_segments``) [measurements].
_SEGMENT_CORE, _SEGMENT_OVERLAP = 512, 256


def track_clusters(recording: Recording, tracked: TrackedTargets, ground: GroundPlane,
                   cfg: TrackConfig) -> list[SmoothedTrack]:
    """Smoothed bird's-eye-view centre trajectory of every track.

    Parameters
    ----------
    recording : Recording
        Targets (sensor frame) and frame stamps.
    tracked : TrackedTargets
        Stages 1-3: ``target_index`` into ``recording.targets`` and ``track_id``
        (-1 = no track).
    ground : GroundPlane
        Stage 4: ``rotation_level`` levels the sensor frame.
    cfg : TrackConfig
        Process noise (``sigma_accel`` as jerk, ``sigma_yaw_accel``) and
        ``measurement_sigma_m`` of a centre.

    Returns
    -------
    list of SmoothedTrack
        One per track id present, in increasing id; ``heights_m`` is the mean levelled
        height of the track's targets per frame (not smoothed).

    References
    ----------
    method-paper.tex, section "Object Tracking".
    """
    member = tracked.track_id >= 0
    if not member.any():
        return []
    index = tracked.target_index[member]
    track_id = tracked.track_id[member]
    frames = recording.targets.frame_index[index]
    levelled = recording.targets.positions_m[index] @ ground.rotation_level.T
    n_frames = int(recording.frame_stamps_ns.shape[0])
    key = track_id * n_frames + frames
    order = np.argsort(key, kind='stable')
    unique_key, start, count = np.unique(key[order], return_index=True, return_counts=True)
    centres = np.add.reduceat(levelled[order], start, axis=0) / count[:, None]
    meas_track = unique_key // n_frames
    meas_frame = unique_key % n_frames
    stamps = recording.frame_stamps_ns[meas_frame]
    times_s = (stamps - stamps.min()) * 1e-9
    ids, first, lengths = np.unique(meas_track, return_index=True, return_counts=True)
    states, covariances = smooth_tracks(times_s, centres[:, :2], lengths, cfg)
    out = []
    for track, lo, n in zip(ids.tolist(), first.tolist(), lengths.tolist()):
        hi = lo + n
        out.append(SmoothedTrack(
            track_id=int(track), frame_index=meas_frame[lo:hi].copy(),
            stamps_ns=stamps[lo:hi].copy(), positions_m=states[lo:hi, :2].copy(),
            heights_m=centres[lo:hi, 2].copy(), states=states[lo:hi],
            covariances=covariances[lo:hi]))
    return out


# --- the model ----------------------------------------------------------------------------

def ctra_transition(states: F64, dt: F64 | float) -> F64:
    """Propagate CTRA states by ``dt``: exact integration of constant yaw rate and
    acceleration.

    Parameters
    ----------
    states : ndarray of shape (..., 6)
        ``[x, y, yaw, v, yaw_rate, a]`` [m, m, rad, m/s, rad/s, m/s^2].
    dt : float or ndarray broadcastable to ``states.shape[:-1]``
        Time step [s].

    Returns
    -------
    ndarray of shape (..., 6)
        The propagated states, yaw wrapped to [-pi, pi).
    """
    x, y, yaw, v, w, a = np.moveaxis(np.asarray(states, dtype=np.float64), -1, 0)
    t = np.broadcast_to(np.asarray(dt, dtype=np.float64), x.shape)
    yaw1 = yaw + w * t
    small = np.abs(w) < _SMALL_YAW_RATE
    w_safe = np.where(small, 1.0, w)
    s0, c0, s1, c1 = np.sin(yaw), np.cos(yaw), np.sin(yaw1), np.cos(yaw1)
    # Closed form: integral of (v + a t) [cos, sin](yaw + w t) dt over [0, T].
    dx_turn = ((v + a * t) * w_safe * s1 + a * c1 - v * w_safe * s0 - a * c0) / w_safe**2
    dy_turn = (-(v + a * t) * w_safe * c1 + a * s1 + v * w_safe * c0 - a * s0) / w_safe**2
    # First order in w: the closed form cancels catastrophically as w -> 0.
    along = v * t + 0.5 * a * t**2
    across = w * (0.5 * v * t**2 + a * t**3 / 3.0)
    dx_line = along * c0 - across * s0
    dy_line = along * s0 + across * c0
    return np.stack([x + np.where(small, dx_line, dx_turn),
                     y + np.where(small, dy_line, dy_turn),
                     wrap_angle(yaw1), v + a * t, w, a], axis=-1)


def ctra_process_noise(states: F64, dt: F64 | float, cfg: TrackConfig) -> F64:
    """Process noise of one CTRA step: white jerk along the heading, white yaw
    acceleration.

    The jerk drives the chain (distance along the heading, v, a) with the usual
    integrated-white-noise blocks; its distance term is also put across the heading, a
    small term that keeps the position covariance regular (the model has no lateral
    noise of its own: lateral motion comes from yaw).

    Parameters
    ----------
    states : ndarray of shape (..., 6)
        The state the step starts from (its yaw orients the along-track noise).
    dt : float or ndarray broadcastable to ``states.shape[:-1]``
    cfg : TrackConfig

    Returns
    -------
    ndarray of shape (..., 6, 6)
    """
    yaw = np.asarray(states, dtype=np.float64)[..., YAW]
    t = np.broadcast_to(np.asarray(dt, dtype=np.float64), yaw.shape)
    c, s = np.cos(yaw), np.sin(yaw)
    j2, r2 = cfg.sigma_accel**2, cfg.sigma_yaw_accel**2
    q_pp, q_pv, q_pa = j2 * t**5 / 20.0, j2 * t**4 / 8.0, j2 * t**3 / 6.0
    q_vv, q_va, q_aa = j2 * t**3 / 3.0, j2 * t**2 / 2.0, j2 * t
    q = np.zeros((*yaw.shape, DIM_X, DIM_X))
    q[..., 0, 0] = q[..., 1, 1] = q_pp
    q[..., 0, 3] = q[..., 3, 0] = c * q_pv
    q[..., 1, 3] = q[..., 3, 1] = s * q_pv
    q[..., 0, 5] = q[..., 5, 0] = c * q_pa
    q[..., 1, 5] = q[..., 5, 1] = s * q_pa
    q[..., 3, 3], q[..., 3, 5], q[..., 5, 3], q[..., 5, 5] = q_vv, q_va, q_va, q_aa
    q[..., 2, 2] = r2 * t**3 / 3.0
    q[..., 2, 4] = q[..., 4, 2] = r2 * t**2 / 2.0
    q[..., 4, 4] = r2 * t
    return q


def initial_state(times_s: F64, centres_m: F64, cfg: TrackConfig) -> tuple[F64, F64]:
    """Initial CTRA mean and covariance of a track from its first centres.

    Heading and speed come from the displacement between the first centre and the first
    one at least ``_INIT_SPAN_S`` later (or the last), yaw rate and acceleration start at
    zero.

    Parameters
    ----------
    times_s : ndarray of shape (k,)
    centres_m : ndarray of shape (k, 2)
    cfg : TrackConfig

    Returns
    -------
    (ndarray of shape (6,), ndarray of shape (6, 6))
    """
    j = int(np.searchsorted(times_s, times_s[0] + _INIT_SPAN_S, side='left'))
    j = min(j, times_s.shape[0] - 1)
    d = centres_m[j] - centres_m[0]
    span = float(times_s[j] - times_s[0])
    distance = float(np.hypot(d[0], d[1]))
    yaw = float(np.arctan2(d[1], d[0])) if distance > 0.0 else 0.0
    speed = distance / span if span > 0.0 else 0.0
    sigma_m = cfg.measurement_sigma_m
    sigma_yaw = float(np.clip(2.0 * sigma_m / max(distance, 1e-9), _INIT_SIGMA_YAW_MIN,
                              _INIT_SIGMA_YAW_MAX))
    mean = np.array([centres_m[0, 0], centres_m[0, 1], yaw, speed, 0.0, 0.0])
    cov = np.diag([sigma_m**2, sigma_m**2, sigma_yaw**2, _INIT_SIGMA_V**2,
                   _INIT_SIGMA_YAW_RATE**2, _INIT_SIGMA_A**2])
    return mean, cov


# --- the batched filter and smoother -------------------------------------------------------

@dataclass(frozen=True, slots=True)
class MotionModel:
    """What the batched UKF needs of a model (private to the tracking stage and tests).

    transition(states (..., n), dt) -> (..., n); process_noise(states (..., n), dt) ->
    (..., n, n), evaluated at the state the step starts from; angle: index of the angle
    in the state, or None.
    """

    dim: int
    transition: Callable[[F64, F64], F64]
    process_noise: Callable[[F64, F64], F64]
    angle: int | None


def ctra_model(cfg: TrackConfig) -> MotionModel:
    """The CTRA model with the configured process noise."""
    return MotionModel(DIM_X, ctra_transition,
                       lambda states, dt: ctra_process_noise(states, dt, cfg), YAW)


def merwe_weights(dim: int, alpha: float = ALPHA, beta: float = BETA,
                  kappa: float = KAPPA) -> tuple[F64, F64, float]:
    """Mean and covariance weights of Merwe's scaled sigma points, and lambda + n (the
    same numbers as filterpy's ``MerweScaledSigmaPoints``)."""
    lam = alpha**2 * (dim + kappa) - dim
    wm = np.full(2 * dim + 1, 0.5 / (dim + lam))
    wc = wm.copy()
    wm[0] = lam / (dim + lam)
    wc[0] = lam / (dim + lam) + (1.0 - alpha**2 + beta)
    return wm, wc, dim + lam


def smooth_tracks(times_s: F64, centres_m: F64, lengths: I64,
                  cfg: TrackConfig) -> tuple[F64, F64]:
    """UKF + unscented RTS smoother over many tracks at once (CTRA model).

    Parameters
    ----------
    times_s : ndarray of shape (m,)
        Measurement times, increasing within each track [s].
    centres_m : ndarray of shape (m, 2)
        Bird's-eye-view centres [m], the tracks one after another.
    lengths : ndarray of shape (t,), int
        Measurements per track (sum = m), each >= 1.
    cfg : TrackConfig

    Returns
    -------
    states : ndarray of shape (m, 6)
        Smoothed states, yaw wrapped to [-pi, pi).
    covariances : ndarray of shape (m, 6, 6)
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    starts = np.cumsum(lengths) - lengths
    # Segments: (first measurement, length, where its kept core starts in it, core length).
    seg_first, seg_len, core_at, core_len = _segments(starts, lengths)
    pick = np.concatenate([np.arange(a, a + n)
                           for a, n in zip(seg_first.tolist(), seg_len.tolist())])
    seg_times, seg_centres = times_s[pick], centres_m[pick]
    seg_starts = np.cumsum(seg_len) - seg_len
    init = [initial_state(seg_times[lo:lo + n], seg_centres[lo:lo + n], cfg)
            for lo, n in zip(seg_starts.tolist(), seg_len.tolist())]
    x0 = np.array([m for m, _ in init]).reshape(-1, DIM_X)
    p0 = np.array([c for _, c in init]).reshape(-1, DIM_X, DIM_X)
    r = np.eye(2) * cfg.measurement_sigma_m**2
    seg_x, seg_p = batched_ukf_rts(seg_times, seg_centres, seg_len, x0, p0, r, ctra_model(cfg))
    if seg_len.size == lengths.size:
        return seg_x, seg_p
    keep = np.concatenate([np.arange(lo + a, lo + a + n) for lo, a, n in zip(
        seg_starts.tolist(), core_at.tolist(), core_len.tolist())])
    return seg_x[keep], seg_p[keep]


def _segments(starts: I64, lengths: I64) -> tuple[I64, I64, I64, I64]:
    """Cut tracks longer than ``_SEGMENT_CORE + 2 * _SEGMENT_OVERLAP`` into overlapping
    segments.

    The batched filter takes one step per measurement of the longest track, each step
    costing the same fixed overhead however few tracks remain: a cluster of stationary
    clutter followed for minutes would take seconds alone. A segment is smoothed on its
    own with ``_SEGMENT_OVERLAP`` measurements either side of the core it contributes;
    for a moving object the smoother forgets its start within that margin (positions
    agree with the whole-track smoothing to ~1e-9 m at 256 steps, 1e-5 m at 128).
    """
    long_enough = _SEGMENT_CORE + 2 * _SEGMENT_OVERLAP
    firsts, lens, core_at, core_len = [], [], [], []
    for start, n in zip(starts.tolist(), lengths.tolist()):
        if n <= long_enough:
            firsts.append(start)
            lens.append(n)
            core_at.append(0)
            core_len.append(n)
            continue
        for core in range(0, n, _SEGMENT_CORE):
            lo = max(0, core - _SEGMENT_OVERLAP)
            hi = min(n, core + _SEGMENT_CORE + _SEGMENT_OVERLAP)
            firsts.append(start + lo)
            lens.append(hi - lo)
            core_at.append(core - lo)
            core_len.append(min(_SEGMENT_CORE, n - core))
    return (np.asarray(firsts, np.int64), np.asarray(lens, np.int64),
            np.asarray(core_at, np.int64), np.asarray(core_len, np.int64))


def batched_ukf_rts(times_s: F64, measurements: F64, lengths: I64, x0: F64, p0: F64,
                    r: F64, model: MotionModel) -> tuple[F64, F64]:
    """Unscented Kalman filter and RTS smoother, vectorised over tracks.

    The measurement is the first ``measurements.shape[1]`` state entries (linear; no
    angle among them). Step ``k`` of every track still running is done in one set of
    array operations; tracks are ordered by length so those still running are a prefix.

    Parameters
    ----------
    times_s : ndarray of shape (m,)
    measurements : ndarray of shape (m, d)
    lengths : ndarray of shape (t,)
    x0, p0 : ndarray of shape (t, n) and (t, n, n)
        State at each track's first measurement (that measurement is not applied again).
    r : ndarray of shape (d, d)
        Measurement noise.
    model : MotionModel

    Returns
    -------
    states, covariances : ndarray of shape (m, n) and (m, n, n)
        Smoothed, in the input order.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    n_x, n_z = model.dim, measurements.shape[1]
    m = int(lengths.sum())
    wm, wc, scale = merwe_weights(n_x)
    by_length = np.argsort(-lengths, kind='stable')
    sorted_lengths = lengths[by_length]
    starts = (np.cumsum(lengths) - lengths)[by_length]
    # running[k] = number of tracks with more than k measurements (a prefix of by_length).
    running = np.searchsorted(-sorted_lengths, -np.arange(int(sorted_lengths[0]) + 1),
                              side='left') if m else np.zeros(1, np.int64)

    # One state and one covariance array, filtered forward, then smoothed in place going
    # backward (step k needs the filtered k and the smoothed k + 1): on a long recording
    # they are the biggest arrays of the stage, so there are no copies and no stored
    # process noise (it is recomputed from the same filtered state).
    x = np.empty((m, n_x))
    p = np.empty((m, n_x, n_x))
    first = starts
    x[first] = x0[by_length]
    p[first] = p0[by_length]
    for k in range(1, int(sorted_lengths[0]) if m else 0):
        idx = starts[:running[k]] + k
        prev = idx - 1
        dt = times_s[idx] - times_s[prev]
        x_prior, p_prior = _predict(x[prev], p[prev], dt, model.process_noise(x[prev], dt),
                                    model, wm, wc, scale)
        if model.angle is not None:
            p_prior = cap_angle_variance(p_prior, model.angle)
        x_post, p_post = _update(x_prior, p_prior, measurements[idx], r, model.angle, n_z)
        if model.angle is not None:
            p_post = cap_angle_variance(p_post, model.angle)
        x[idx], p[idx] = x_post, p_post

    for k in range(int(sorted_lengths[0]) - 2 if m else -1, -1, -1):
        idx = starts[:running[k + 1]] + k
        nxt = idx + 1
        dt = times_s[nxt] - times_s[idx]
        x_f, p_f = x[idx], p[idx]
        sigmas = _sigma_points(x_f, p_f, scale, model.angle)
        sigmas_f = model.transition(sigmas, dt[:, None])
        x_b, p_b = _unscented_transform(sigmas_f, wm, wc, model.process_noise(x_f, dt),
                                        model.angle)
        dx = _residual(sigmas, x_f[:, None, :], model.angle)
        db = _residual(sigmas_f, x_b[:, None, :], model.angle)
        gain = _weighted_outer(wc, dx, db) @ np.linalg.inv(p_b)
        x_s = x_f + (gain @ _residual(x[nxt], x_b, model.angle)[:, :, None])[:, :, 0]
        if model.angle is not None:
            x_s[:, model.angle] = wrap_angle(x_s[:, model.angle])
        p[idx] = p_f + gain @ (p[nxt] - p_b) @ np.swapaxes(gain, -1, -2)
        x[idx] = x_s
    return x, p


def cap_angle_variance(p: F64, angle: int, max_sigma: float = _MAX_SIGMA_YAW) -> F64:
    """Scale the angle's row and column of covariances (..., n, n) so that its standard
    deviation is at most ``max_sigma``; correlations are kept and the result stays
    positive definite (a congruence with a positive diagonal matrix)."""
    var = p[..., angle, angle]
    factor = np.sqrt(np.minimum(1.0, max_sigma**2 / np.maximum(var, 1e-300)))
    scale = np.ones(p.shape[:-1])
    scale[..., angle] = factor
    return p * scale[..., :, None] * scale[..., None, :]


def _weighted_outer(w: F64, a: F64, b: F64) -> F64:
    """sum_s w[s] a[t, s, :] outer b[t, s, :] for each t, as one batched matrix product."""
    return np.swapaxes(a * w[:, None], -1, -2) @ b


def _residual(a: F64, b: F64, angle: int | None) -> F64:
    d = a - b
    if angle is not None:
        d[..., angle] = wrap_angle(d[..., angle])
    return d


def _sigma_points(x: F64, p: F64, scale: float, angle: int | None) -> F64:
    """(t, 2n+1, n) sigma points, filterpy's order: mean, mean + rows of U, mean - rows
    of U, with U the upper Cholesky factor of scale * P (the rows of U are the columns of
    numpy's lower factor)."""
    offsets = np.swapaxes(np.linalg.cholesky(scale * p), -1, -2)
    sigmas = np.concatenate([x[:, None, :], x[:, None, :] + offsets,
                             x[:, None, :] - offsets], axis=1)
    if angle is not None:
        sigmas[..., angle] = wrap_angle(sigmas[..., angle])
    return sigmas


def _unscented_transform(sigmas: F64, wm: F64, wc: F64, noise: F64,
                         angle: int | None) -> tuple[F64, F64]:
    """Weighted mean (circular for the angle) and covariance of sigma points + noise."""
    mean = wm @ sigmas
    if angle is not None:
        mean[:, angle] = np.arctan2(np.sin(sigmas[..., angle]) @ wm,
                                    np.cos(sigmas[..., angle]) @ wm)
    y = _residual(sigmas, mean[:, None, :], angle)
    return mean, _weighted_outer(wc, y, y) + noise


def _predict(x: F64, p: F64, dt: F64, q: F64, model: MotionModel, wm: F64, wc: F64,
             scale: float) -> tuple[F64, F64]:
    sigmas = _sigma_points(x, p, scale, model.angle)
    return _unscented_transform(model.transition(sigmas, dt[:, None]), wm, wc, q,
                                model.angle)


def _update(x: F64, p: F64, z: F64, r: F64, angle: int | None, n_z: int) -> tuple[F64, F64]:
    """Measurement update with the first ``n_z`` state entries measured.

    filterpy passes fresh sigma points of the prior through h. For a linear h they are
    symmetric about the mean and reproduce the covariance, so the predicted measurement is
    ``x[:n_z]``, S is ``P[:n_z, :n_z] + R`` and the cross covariance ``P[:, :n_z]``:
    the Kalman update, exactly, as long as the angle's sigma points stay within a half
    turn of the mean (wrapped residuals equal the offsets), which the variance cap keeps.
    """
    s = p[:, :n_z, :n_z] + r
    gain = p[:, :, :n_z] @ np.linalg.inv(s)
    x_new = x + (gain @ (z - x[:, :n_z])[:, :, None])[:, :, 0]
    if angle is not None:
        x_new[:, angle] = wrap_angle(x_new[:, angle])
    return x_new, p - gain @ s @ np.swapaxes(gain, -1, -2)


# --- the filterpy reference ------------------------------------------------------------------

def smooth_track_reference(times_s: F64, centres_m: F64, cfg: TrackConfig,
                           model: MotionModel | None = None,
                           x0: F64 | None = None, p0: F64 | None = None) -> tuple[F64, F64]:
    """The same filter and smoother for one track with filterpy (slow; for tests).

    Parameters
    ----------
    times_s : ndarray of shape (k,)
    centres_m : ndarray of shape (k, 2)
    cfg : TrackConfig
    model : MotionModel, optional
        Default: the CTRA model of ``cfg``.
    x0, p0 : ndarray, optional
        Initial state; default :func:`initial_state`.

    Returns
    -------
    states, covariances : ndarray of shape (k, n) and (k, n, n)
    """
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    model = model if model is not None else ctra_model(cfg)
    if x0 is None or p0 is None:
        x0, p0 = initial_state(times_s, centres_m, cfg)
    angle = model.angle

    def residual_x(a: F64, b: F64) -> F64:
        return _residual(np.asarray(a, float), np.asarray(b, float), angle)

    def state_add(a: F64, b: F64) -> F64:
        out = np.asarray(a, float) + b
        if angle is not None:
            out[angle] = wrap_angle(out[angle])
        return out

    def x_mean(sigmas: F64, wm: F64) -> F64:
        mean = np.dot(wm, sigmas)
        if angle is not None:
            mean[angle] = np.arctan2(np.dot(wm, np.sin(sigmas[:, angle])),
                                     np.dot(wm, np.cos(sigmas[:, angle])))
        return mean

    n_z = centres_m.shape[1]
    points = MerweScaledSigmaPoints(model.dim, alpha=ALPHA, beta=BETA, kappa=KAPPA,
                                    subtract=residual_x)
    ukf = UnscentedKalmanFilter(
        dim_x=model.dim, dim_z=n_z, dt=1.0, hx=lambda s: s[:n_z],
        fx=lambda s, dt: model.transition(s, dt), points=points, x_mean_fn=x_mean,
        residual_x=residual_x, state_add=state_add)
    ukf.x, ukf.P = np.array(x0, float), np.array(p0, float)
    ukf.R = np.eye(n_z) * cfg.measurement_sigma_m**2
    k_steps = times_s.shape[0]
    xs = np.empty((k_steps, model.dim))
    ps = np.empty((k_steps, model.dim, model.dim))
    qs = np.zeros((k_steps, model.dim, model.dim))
    xs[0], ps[0] = ukf.x, ukf.P
    for k in range(1, k_steps):
        dt = float(times_s[k] - times_s[k - 1])
        # predict() takes no Q: set it for this step's dt (and heading).
        qs[k] = ukf.Q = model.process_noise(ukf.x, dt)
        ukf.predict(dt=dt)
        if angle is not None:
            # the same cap on the prior; update() uses the sigma points predict() drew
            ukf.P = cap_angle_variance(ukf.P, angle)
            ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
        ukf.update(centres_m[k])
        if angle is not None:
            ukf.P = cap_angle_variance(ukf.P, angle)
        xs[k], ps[k] = ukf.x, ukf.P
    smoothed_x, smoothed_p = xs.copy(), ps.copy()
    for k in range(k_steps - 2, -1, -1):
        # rts_smoother ignores Qs and uses self.Q: one backward step per call, Q set.
        ukf.Q = qs[k + 1]
        pair_x = np.array([xs[k], smoothed_x[k + 1]])
        pair_p = np.array([ps[k], smoothed_p[k + 1]])
        step_x, step_p, _ = ukf.rts_smoother(pair_x, pair_p,
                                             dts=[float(times_s[k + 1] - times_s[k])] * 2)
        smoothed_x[k], smoothed_p[k] = step_x[0], step_p[0]
        if angle is not None:
            smoothed_x[k, angle] = wrap_angle(smoothed_x[k, angle])
    return smoothed_x, smoothed_p
