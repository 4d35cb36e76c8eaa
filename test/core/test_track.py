"""Stage 5: UKF (CTRA) + RTS smoother in the bird's-eye view."""
from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints

from radar_calib_ros.config import TrackConfig
from radar_calib_ros.core import track
from radar_calib_ros.core.ground_plane import level_rotation
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import Recording
from radar_calib_ros.types import GroundPlane, Targets, TrackedTargets, VehicleTrack

CFG = TrackConfig()


def _ctra_truth(rng: np.random.Generator, n: int, start: tuple[float, ...]) -> tuple[
        np.ndarray, np.ndarray]:
    """Times with jittered steps (and one dropped frame) and the true CTRA states."""
    steps = rng.uniform(0.06, 0.075, n - 1)
    if n > 2:
        steps[n // 2] *= 2.0
    times = np.concatenate([[0.0], np.cumsum(steps)])
    states = [np.array(start, float)]
    for dt in steps:
        states.append(track.ctra_transition(states[-1], dt))
    return times, np.array(states)


def test_batched_filter_equals_the_filterpy_reference() -> None:
    rng = np.random.default_rng(0)
    starts = [(0.0, 0.0, 0.3, 10.0, 0.2, 0.5), (50.0, 5.0, 3.1, 8.0, 0.15, -0.3),
              (-20.0, 3.0, -1.5, 1.0, -0.4, 0.0), (1.0, 2.0, 0.0, 5.0, 0.0, 0.0),
              (4.0, 4.0, 2.0, 6.0, 0.1, 0.0)]
    lengths = [45, 30, 25, 2, 1]
    times, centres = [], []
    for start, n in zip(starts, lengths):
        t, states = _ctra_truth(rng, n, start)
        times.append(t + rng.uniform(0.0, 100.0))
        centres.append(states[:, :2] + rng.normal(0.0, 0.7, (n, 2)))
    batched_x, batched_p = track.smooth_tracks(np.concatenate(times), np.concatenate(centres),
                                               np.array(lengths), CFG)
    lo = 0
    for t, z, n in zip(times, centres, lengths):
        ref_x, ref_p = track.smooth_track_reference(t, z, CFG)
        np.testing.assert_allclose(batched_x[lo:lo + n], ref_x, rtol=0, atol=1e-7)
        np.testing.assert_allclose(batched_p[lo:lo + n], ref_p, rtol=0, atol=1e-7)
        lo += n
    # the heading crossed +-pi (start yaw 3.1 turning left): wrapped, never a full turn
    assert np.all((batched_x[:, 2] >= -math.pi) & (batched_x[:, 2] < math.pi))


def test_smoothing_lowers_the_error_of_a_noisy_ctra_trajectory() -> None:
    rng = np.random.default_rng(1)
    times, truth = _ctra_truth(rng, 150, (10.0, -5.0, 0.8, 12.0, 0.25, -0.4))
    noisy = truth[:, :2] + rng.normal(0.0, 0.7, (150, 2))
    states, covariances = track.smooth_tracks(times, noisy, np.array([150]), CFG)
    raw = np.sqrt(np.mean(np.sum((noisy - truth[:, :2]) ** 2, axis=1)))
    smoothed = np.sqrt(np.mean(np.sum((states[:, :2] - truth[:, :2]) ** 2, axis=1)))
    assert smoothed < 0.4 * raw
    # the speed and heading come out too, and the covariance is a covariance
    assert np.median(np.abs(states[20:-20, 3] - truth[20:-20, 3])) < 0.5
    heading_error = np.abs(np.angle(np.exp(1j * (states[20:-20, 2] - truth[20:-20, 2]))))
    assert np.median(heading_error) < 0.05
    assert np.all(np.linalg.eigvalsh(covariances) > 0.0)


def _cv_model(q_density: float) -> track.MotionModel:
    """Linear constant velocity [x, y, vx, vy] with white acceleration."""

    def transition(states: np.ndarray, dt: np.ndarray) -> np.ndarray:
        dt = np.asarray(dt, float)
        out = np.array(states, float, copy=True)
        out[..., 0] += states[..., 2] * dt
        out[..., 1] += states[..., 3] * dt
        return out

    def noise(states: np.ndarray, dt: np.ndarray) -> np.ndarray:
        return _cv_q(np.broadcast_to(np.asarray(dt, float), states.shape[:-1]), q_density)

    return track.MotionModel(4, transition, noise, None)


def _cv_q(dt: np.ndarray, q: float) -> np.ndarray:
    out = np.zeros((*np.shape(dt), 4, 4))
    for i in (0, 1):
        out[..., i, i] = q * dt**3 / 3.0
        out[..., i, i + 2] = out[..., i + 2, i] = q * dt**2 / 2.0
        out[..., i + 2, i + 2] = q * dt
    return out


def test_ukf_on_a_linear_model_equals_the_linear_kalman_filter() -> None:
    """filterpy test_ukf_ekf_comparison idea: the unscented transform of a linear model is
    exact, so UKF + unscented RTS must equal KF + RTS (filterpy's KalmanFilter)."""
    rng = np.random.default_rng(2)
    n = 60
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 0.2, n - 1))])
    z = np.column_stack([3.0 * times, -2.0 * times + 0.3 * times**2])
    z += rng.normal(0.0, 0.5, z.shape)
    x0, p0 = np.array([0.0, 0.0, 2.0, -1.0]), np.diag([1.0, 1.0, 4.0, 4.0])
    r = np.eye(2) * 0.25
    model = _cv_model(0.8)
    ukf_x, ukf_p = track.batched_ukf_rts(times, z, np.array([n]), x0[None], p0[None], r, model)

    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.R = x0.copy(), p0.copy(), r
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    fs, qs = [np.eye(4)], [np.zeros((4, 4))]
    xs, ps = [x0.copy()], [p0.copy()]
    for k in range(1, n):
        dt = times[k] - times[k - 1]
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        q = _cv_q(np.array(dt), 0.8)
        kf.predict(F=f, Q=q)
        kf.update(z[k])
        fs.append(f)
        qs.append(q)
        xs.append(kf.x.copy())
        ps.append(kf.P.copy())
    # filterpy's KF smoother uses Fs[k + 1], Qs[k + 1] for the step k -> k + 1
    kf_x, kf_p, _, _ = kf.rts_smoother(np.array(xs), np.array(ps), Fs=fs, Qs=qs)
    np.testing.assert_allclose(ukf_x, kf_x, atol=1e-9)
    np.testing.assert_allclose(ukf_p, kf_p, atol=1e-9)


def test_merwe_weights_match_filterpy_and_sum_to_one() -> None:
    wm, wc, scale = track.merwe_weights(6)
    ref = MerweScaledSigmaPoints(6, alpha=track.ALPHA, beta=track.BETA, kappa=track.KAPPA)
    np.testing.assert_allclose(wm, ref.Wm)
    np.testing.assert_allclose(wc, ref.Wc)
    assert wm.sum() == pytest.approx(1.0)
    assert scale == pytest.approx(6.0)
    assert np.all(wm >= 0.0) and np.all(wc > 0.0)


def test_ctra_transition_known_answers() -> None:
    # straight, accelerating: s = v t + a t^2 / 2 along the heading
    s = track.ctra_transition(np.array([1.0, 2.0, math.pi / 2, 4.0, 0.0, 2.0]), 0.5)
    np.testing.assert_allclose(s, [1.0, 2.0 + 2.0 + 0.25, math.pi / 2, 5.0, 0.0, 2.0],
                               atol=1e-12)
    # constant turn: a quarter circle of radius v / w
    v, w = 10.0, 0.5
    s = track.ctra_transition(np.array([0.0, 0.0, 0.0, v, w, 0.0]), (math.pi / 2) / w)
    np.testing.assert_allclose(s[:3], [v / w, v / w, math.pi / 2], atol=1e-9)
    # the series branch and the closed form agree across the switch
    base = np.array([3.0, -1.0, 0.7, 12.0, 0.0, 1.5])
    below, above = base.copy(), base.copy()
    below[4], above[4] = 0.999e-4, 1.001e-4
    np.testing.assert_allclose(track.ctra_transition(below, 0.2),
                               track.ctra_transition(above, 0.2), atol=1e-6)
    # heading wrapped
    s = track.ctra_transition(np.array([0.0, 0.0, 3.1, 5.0, 1.0, 0.0]), 0.2)
    assert -math.pi <= s[2] < math.pi


def test_a_standing_object_keeps_a_valid_covariance() -> None:
    """Its heading is unobservable: the yaw variance is capped so the sigma points stay
    within a half turn and the covariance positive definite."""
    rng = np.random.default_rng(4)
    times = np.arange(300) / 15.0
    centres = np.array([40.0, 3.0]) + rng.normal(0.0, 0.3, (300, 2))
    states, covariances = track.smooth_tracks(times, centres, np.array([300]), CFG)
    assert np.all(np.linalg.eigvalsh(covariances) > 0.0)
    assert np.all(np.sqrt(covariances[:, 2, 2]) <= 1.0 + 1e-9)
    raw = np.sqrt(np.mean(np.sum((centres - [40.0, 3.0]) ** 2, axis=1)))
    smoothed = np.sqrt(np.mean(np.sum((states[:, :2] - [40.0, 3.0]) ** 2, axis=1)))
    assert smoothed < 0.7 * raw


def test_track_clusters_one_measurement_per_frame_in_the_levelled_view() -> None:
    rng = np.random.default_rng(5)
    n_frames = 40
    stamps = (1_000_000_000 + np.arange(n_frames) * 66_666_667).astype(np.int64)
    stamps[20:] += 66_666_667                       # a dropped radar cycle
    tilt = level_rotation(np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0]))
    positions, frames, tid = [], [], []
    for f in range(n_frames):
        for t, (x0, vy) in enumerate([(30.0, 8.0), (60.0, -6.0)]):
            k = 4
            centre = np.array([x0, -10.0 * np.sign(vy) + vy * f / 15.0, -5.0])
            positions.append(centre + rng.normal(0.0, 0.5, (k, 3)))
            frames.append(np.full(k, f))
            tid.append(np.full(k, t))
    levelled = np.concatenate(positions)
    sensor = levelled @ tilt                        # tilt.T applied: back to the sensor
    frame_index = np.concatenate(frames).astype(np.int64)
    track_id = np.concatenate(tid)
    track_id[:3] = -1                               # some noise targets
    targets = Targets(sensor, np.zeros(len(frame_index)), frame_index)
    vehicle = VehicleTrack(stamps[:2], np.zeros((2, 3)), np.zeros(2), np.zeros((2, 3)),
                           np.zeros(2))
    recording = Recording(stamps, targets, vehicle, LocalFrame(48.4, 9.9, 32632))
    ground = GroundPlane(normal=tilt.T @ [0.0, 0.0, 1.0], offset_m=-5.0,
                         rotation_level=tilt, density_threshold=1.0,
                         used=np.arange(3, dtype=np.int64))
    # target_index into the recording: give a shuffled subset to check the indexing
    order = rng.permutation(len(frame_index))
    tracked = TrackedTargets(order.astype(np.int64), track_id[order])
    tracks = track.track_clusters(recording, tracked, ground, CFG)
    assert [t.track_id for t in tracks] == [0, 1]
    for t in tracks:
        assert t.frame_index.tolist() == list(range(n_frames))
        np.testing.assert_array_equal(t.stamps_ns, stamps)
        for f in (5, 33):
            own = (frame_index == f) & (track_id == t.track_id)
            assert t.heights_m[f] == pytest.approx(levelled[own, 2].mean())
        assert t.states.shape == (n_frames, 6) and t.covariances.shape == (n_frames, 6, 6)
        np.testing.assert_array_equal(t.positions_m, t.states[:, :2])
    # the smoothed centre follows the levelled motion: 8 m/s along +y for track 0
    assert np.median(tracks[0].states[:, 3]) == pytest.approx(8.0, abs=0.5)
    assert np.median(np.cos(tracks[0].states[:, 2] - math.pi / 2)) > 0.99
    assert track.track_clusters(recording, TrackedTargets(np.arange(3), -np.ones(3, np.int64)),
                                ground, CFG) == []


def test_long_tracks_smoothed_in_segments_match_the_whole_track() -> None:
    rng = np.random.default_rng(6)
    n = 1400
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.06, 0.075, n - 1))])
    state, truth = np.array([0.0, 0.0, 0.3, 8.0, 0.0, 0.0]), []
    for k in range(n):
        state = state.copy()
        state[4], state[5] = 0.3 * math.sin(times[k] / 5.0), 0.5 * math.cos(times[k] / 3.0)
        truth.append(state)
        if k + 1 < n:
            state = track.ctra_transition(state, times[k + 1] - times[k])
    centres = np.array(truth)[:, :2] + rng.normal(0.0, 0.7, (n, 2))
    short_t, short_z = times[:300], centres[:300]
    states, covariances = track.smooth_tracks(
        np.concatenate([times, short_t]), np.concatenate([centres, short_z]),
        np.array([n, 300]), CFG)
    assert states.shape == (n + 300, 6) and covariances.shape == (n + 300, 6, 6)
    x0, p0 = track.initial_state(times, centres, CFG)
    whole, _ = track.batched_ukf_rts(times, centres, np.array([n]), x0[None], p0[None],
                                     np.eye(2) * CFG.measurement_sigma_m**2,
                                     track.ctra_model(CFG))
    np.testing.assert_allclose(states[:n, :2], whole[:, :2], atol=1e-6)
    short, _ = track.smooth_tracks(short_t, short_z, np.array([300]), CFG)
    np.testing.assert_allclose(states[n:], short, atol=1e-8)
