"""V2X as vehicles send it (sim/v2x.py): ETSI CAM generation rules and the GNSS/odometry error model.

CAM tests drive exact, noise-free trajectories whose CAM instants follow by hand from EN 302 637-2
clause 6.1.3. Statistical tests isolate one error component (all others zero) and use fixed seeds; each
tolerance is 4 standard errors of the estimate, derived beside the assertion.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sim.errors import SimulationError
from sim.v2x import CamSpec, GnssSpec, GnssTrack, cam_generation, ideal_gnss, measure_gnss

DT_S = 0.1  # 10 Hz fixes


def straight(speed_mps: float, duration_s: float = 30.0) -> tuple[np.ndarray, ...]:
    """A drive east at a constant speed: t, position (N, 3), yaw, speed."""
    t = np.round(np.arange(0.0, duration_s + DT_S / 2, DT_S), 9)
    position = np.column_stack([speed_mps * t, np.zeros_like(t), np.zeros_like(t)])
    return t, position, np.zeros_like(t), np.full_like(t, speed_mps)


def integrate(t: np.ndarray, speed: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Positions (N, 3) of a vehicle driving with the given speed and yaw profile (forward Euler)."""
    step = np.column_stack([np.cos(yaw), np.sin(yaw)]) * (speed * DT_S)[:, None]
    xy = np.vstack([[0.0, 0.0], np.cumsum(step[:-1], axis=0)])
    return np.column_stack([xy, np.zeros(len(t))])


def intervals(t: np.ndarray, idx: np.ndarray) -> np.ndarray:
    return np.round(np.diff(t[idx]), 6)


def only(**fields: object) -> GnssSpec:
    """A receiver with every error off except the given fields."""
    return replace(GnssSpec.perfect(), **fields)  # type: ignore[arg-type]


def city_drive(duration_s: float = 300.0) -> tuple[np.ndarray, ...]:
    """Speeds 0-14 m/s with stops, turns both ways: t, position, yaw, speed."""
    t = np.round(np.arange(0.0, duration_s, DT_S), 9)
    speed = np.clip(7.0 + 8.0 * np.sin(2 * math.pi * t / 45.0), 0.0, None)
    yaw = np.cumsum(0.25 * np.sin(2 * math.pi * t / 23.0) * DT_S * (speed > 0.5))
    return t, integrate(t, speed, yaw), yaw, speed


# ---------------------------------------------------------------- CAM generation (EN 302 637-2 6.1.3)


def test_fast_straight_drive_triggers_by_position_every_0_3_s() -> None:
    # 14 m/s: 4.2 m > 4 m after 0.3 s (0.2 s gives 2.8 m); the check period rounds 4/14 = 0.29 s up.
    t, position, yaw, speed = straight(14.0)
    idx = cam_generation(t, position, yaw, speed, CamSpec())
    assert idx[0] == 0
    assert np.all(intervals(t, idx) == 0.3)


def test_slow_straight_drive_sends_at_1_hz() -> None:
    # 2 m/s: 4 m takes 2 s > T_GenCamMax, so only condition 2 fires, every T_GenCamMax = 1 s.
    t, position, yaw, speed = straight(2.0)
    idx = cam_generation(t, position, yaw, speed, CamSpec())
    assert np.all(intervals(t, idx) == 1.0)
    assert len(idx) == 31


def test_turn_triggers_by_heading() -> None:
    # 2 m/s, turning at 25 deg/s from t = 5 s to 8 s: 5 deg > 4 deg after 0.2 s (0.4 m, speed constant).
    t = np.round(np.arange(0.0, 15.0, DT_S), 9)
    speed = np.full_like(t, 2.0)
    yaw = np.radians(25.0) * np.clip(t - 5.0, 0.0, 3.0)
    idx = cam_generation(t, integrate(t, speed, yaw), yaw, speed, CamSpec())
    cam_t = t[idx]
    in_turn = cam_t[(cam_t >= 5.0) & (cam_t <= 8.0 + 1e-9)]
    assert np.all(np.round(np.diff(in_turn), 6) == 0.2)
    assert len(in_turn) == 16  # 5.0 (timed), then 5.2 ... 8.0
    # After the turn: N_GenCam = 3 timed CAMs at the last interval, then 1 Hz again.
    after = np.round(cam_t[cam_t > 8.0 + 1e-9] - 8.0, 6)
    assert list(after[:5]) == [0.2, 0.4, 0.6, 1.6, 2.6]


def test_acceleration_triggers_by_speed() -> None:
    # From 2 m/s at 3 m/s^2 for 2 s: 0.6 m/s > 0.5 m/s after 0.2 s, while moving <= 1.6 m and not turning.
    t = np.round(np.arange(0.0, 12.0, DT_S), 9)
    speed = 2.0 + 3.0 * np.clip(t - 5.0, 0.0, 2.0)
    yaw = np.zeros_like(t)
    idx = cam_generation(t, integrate(t, speed, yaw), yaw, speed, CamSpec())
    cam_t = t[idx]
    accelerating = cam_t[(cam_t >= 5.0) & (cam_t <= 7.0 + 1e-9)]
    assert np.all(np.round(np.diff(accelerating), 6) == 0.2)
    assert len(accelerating) == 11


def test_n_gen_cam_rule_keeps_the_dynamic_interval_for_three_timed_cams() -> None:
    # Position triggers every 0.3 s until t = 3 s, then the position freezes (speed and heading unchanged,
    # so no condition 1): T_GenCam stays 0.3 s for N_GenCam = 3 timed CAMs, then returns to T_GenCamMax.
    t, position, yaw, speed = straight(14.0, duration_s=8.0)
    position[:, 0] = 14.0 * np.minimum(t, 3.0)
    cam_t = t[cam_generation(t, position, yaw, speed, CamSpec())]
    assert list(np.round(cam_t[cam_t > 2.95], 6)) == [3.0, 3.3, 3.6, 3.9, 4.9, 5.9, 6.9, 7.9]
    # With N_GenCam = 1 only one timed CAM keeps the short interval.
    cam_t = t[cam_generation(t, position, yaw, speed, CamSpec(n_gen_cam=1))]
    assert list(np.round(cam_t[cam_t > 2.95], 6)) == [3.0, 3.3, 4.3, 5.3, 6.3, 7.3]


def test_a_dynamic_cam_restarts_the_n_gen_cam_count() -> None:
    # Frozen after 3 s as above, but a 0.6 m/s speed step at t = 3.5 s: a condition-1 CAM at 3.5 s sets
    # T_GenCam = 0.2 s (elapsed since 3.3 s); three timed CAMs follow at that interval, then 1 Hz.
    t, position, yaw, speed = straight(14.0, duration_s=8.0)
    position[:, 0] = 14.0 * np.minimum(t, 3.0)
    speed[t >= 3.5 - 1e-9] += 0.6
    cam_t = t[cam_generation(t, position, yaw, speed, CamSpec())]
    assert list(np.round(cam_t[cam_t > 2.95], 6)) == [3.0, 3.3, 3.5, 3.7, 3.9, 4.1, 5.1, 6.1, 7.1]


@pytest.mark.parametrize("fix_rate_hz", [10.0, 20.0])
def test_generated_rate_stays_between_1_and_10_hz_on_a_noisy_city_drive(fix_rate_hz: float) -> None:
    t, position, yaw, speed = city_drive()
    t_fix = np.round(np.arange(0.0, t[-1], 1.0 / fix_rate_hz), 9)
    track = measure_gnss(
        t_fix,
        np.column_stack([np.interp(t_fix, t, position[:, k]) for k in range(3)]),
        np.interp(t_fix, t, yaw),
        np.interp(t_fix, t, speed),
        GnssSpec.rtk_float(),
        np.random.default_rng(11),
    )
    idx = cam_generation(track.t_s, track.position, track.yaw, track.speed_mps, CamSpec())
    gaps = np.diff(track.t_s[idx])
    assert gaps.min() >= 0.1 - 1e-6  # T_GenCamMin
    assert gaps.max() <= 1.0 + 0.1 + 1e-6  # T_GenCamMax + one check period
    # Both regimes occur on this drive: dynamics-triggered CAMs (< 1 s) and the 1 Hz floor.
    assert (gaps < 0.95).mean() > 0.3 and (gaps > 0.95).any()
    if fix_rate_hz == 20.0:  # checks only at fixes on the 0.1 s check grid
        assert np.allclose(np.round(track.t_s[idx] / 0.1), track.t_s[idx] / 0.1, atol=1e-6)


def test_bad_inputs_are_named() -> None:
    t, position, yaw, speed = straight(5.0, 2.0)
    with pytest.raises(SimulationError, match="position"):
        cam_generation(t, position[:, :2], yaw, speed, CamSpec())
    with pytest.raises(SimulationError, match="t_s"):
        cam_generation(t[::-1].copy(), position, yaw, speed, CamSpec())
    with pytest.raises(SimulationError, match="t_gen_cam_dcc_s"):
        CamSpec(t_gen_cam_dcc_s=0.05)
    with pytest.raises(SimulationError, match="rtk_float_sigma_m"):
        GnssSpec(rtk_float_sigma_m=(1.0, 0.3))
    with pytest.raises(SimulationError, match="speed_mps"):
        measure_gnss(t, position, yaw, speed[:-1], GnssSpec(), np.random.default_rng(0))


# ---------------------------------------------------------------- GNSS error model


def test_perfect_receiver_reports_the_truth() -> None:
    t, position, yaw, speed = city_drive(60.0)
    for track in (
        measure_gnss(t, position, yaw, speed, GnssSpec.perfect(), np.random.default_rng(3)),
        ideal_gnss(t, position, yaw, speed),
    ):
        assert np.array_equal(track.position, position) and not track.error.any()
        assert np.allclose(track.yaw, np.angle(np.exp(1j * yaw)), atol=1e-12)
        assert np.array_equal(track.speed_mps, speed) and track.is_rtk_fixed.all()


def test_deterministic_per_seed() -> None:
    t, position, yaw, speed = city_drive(120.0)
    spec = GnssSpec.rtk_float()

    def run(seed: int) -> GnssTrack:
        return measure_gnss(t, position, yaw, speed, spec, np.random.default_rng(seed))

    a, b, c = run(5), run(5), run(6)
    for name in ("position", "yaw", "speed_mps", "horizontal_std_m", "is_rtk_fixed", "error"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.error, c.error)


def test_bias_is_constant_per_run_with_the_spec_sigma() -> None:
    spec = only(bias_sigma_m=0.02, vertical_factor=2.0)
    t, position, yaw, speed = straight(10.0, 0.4)
    runs = 2000
    biases = np.empty((runs, 3))
    for seed in range(runs):
        error = measure_gnss(t, position, yaw, speed, spec, np.random.default_rng(seed)).error
        assert np.ptp(error, axis=0).max() == 0.0
        biases[seed] = error[0]
    # Sample std of n normal draws: relative standard error 1/sqrt(2n) = 1.6 %; 4 SE = 6.3 %.
    tol = 4 / math.sqrt(2 * runs)
    assert np.allclose(biases.std(axis=0) / [0.02, 0.02, 0.04], 1.0, atol=tol)
    assert np.all(np.abs(biases.mean(axis=0)) < 4 * np.array([0.02, 0.02, 0.04]) / math.sqrt(runs))


def test_gauss_markov_wander_has_the_spec_variance_and_time_constant() -> None:
    sigma, tau = 0.03, 60.0
    spec = only(wander_sigma_m=sigma, wander_tau_s=tau, vertical_factor=1.0)
    # Stationary variance: the first fix of many runs (the process starts in its stationary law).
    runs = 2000
    t2, p2, y2, s2 = straight(10.0, 0.1)
    first = np.array(
        [measure_gnss(t2, p2, y2, s2, spec, np.random.default_rng(s)).error[0, :2] for s in range(runs)]
    )
    # Pooled x and y: 2n draws, relative SE of the std 1/sqrt(4n) = 1.1 %; 4 SE = 4.5 %.
    assert abs(first.std() / sigma - 1.0) < 4 / math.sqrt(4 * runs)
    # Correlation: one 20 h run at 1 Hz; lag-1 regression x_k+1 = phi x_k + e has SE(phi) =
    # sqrt((1 - phi^2) / N) per axis (pooled: 2N pairs); 4 SE on phi is ~ +-6 % on tau here.
    t = np.arange(0.0, 72000.0, 1.0)
    n = len(t)
    error = measure_gnss(
        t, np.zeros((n, 3)), np.zeros(n), np.full(n, 10.0), spec, np.random.default_rng(1)
    ).error[:, :2]
    x0, x1 = error[:-1].ravel(), error[1:].ravel()
    phi_hat = float(x0 @ x1 / (x0 @ x0))
    phi = math.exp(-1.0 / tau)
    assert abs(phi_hat - phi) < 4 * math.sqrt((1 - phi**2) / x0.size)
    tau_hat = -1.0 / math.log(phi_hat)
    assert 0.9 * tau < tau_hat < 1.1 * tau
    # Innovations keep the process stationary: std(e) = sigma sqrt(1 - phi^2), relative SE 1/sqrt(2 * 2N).
    innovation = x1 - phi_hat * x0
    assert innovation.std() == pytest.approx(sigma * math.sqrt(1 - phi**2), rel=4 / math.sqrt(2 * x0.size))
    # The random-walk equivalent at short lags: var(x_k+1 - x_k) = 2 sigma^2 (1 - phi) ~ q^2 dt.
    assert spec.random_walk_m_per_sqrt_s == pytest.approx(sigma * math.sqrt(2 / tau))


def test_altitude_is_noisier_than_the_horizontal() -> None:
    t, position, yaw, speed = straight(10.0, 600.0)
    # White noise alone: 6000 fixes, the std ratio's relative SE ~ 1/sqrt(n) = 1.3 %; 4 SE = 5 %.
    error = measure_gnss(
        t, position, yaw, speed, only(white_sigma_m=0.015, vertical_factor=2.0), np.random.default_rng(2)
    ).error
    assert error[:, 2].std() / error[:, :2].std() == pytest.approx(2.0, rel=4 / math.sqrt(len(t)))
    # The full RTK receiver: every component scales by vertical_factor; bias and wander give few
    # independent draws per run, so 30 runs are pooled and the bound is loose (ratio in 1.5-2.5).
    errors = np.vstack(
        [measure_gnss(t, position, yaw, speed, GnssSpec(), np.random.default_rng(s)).error for s in range(30)]
    )
    ratio = float(np.sqrt((errors[:, 2] ** 2).mean() / (errors[:, :2] ** 2).mean()))
    assert 1.5 < ratio < 2.5


def test_multipath_jumps_come_at_the_spec_rate_and_decay() -> None:
    spec = only(multipath_rate_per_min=1.0, multipath_jump_m=(0.2, 0.5), multipath_decay_s=2.0)
    t, position, yaw, speed = straight(10.0, 20000.0)
    error = measure_gnss(t, position, yaw, speed, spec, np.random.default_rng(4)).error
    # A jump is a >= 0.2 m horizontal step between fixes; decay moves < 0.05 * 0.5 m per 0.1 s.
    steps = np.hypot(*np.diff(error[:, :2], axis=0).T)
    jumps = steps > 0.15
    expected = 20000.0 / 60.0
    assert abs(jumps.sum() - expected) < 4 * math.sqrt(expected)  # Poisson count, 4 SE
    assert steps[jumps].max() < 0.5 + 0.5 + 1e-9  # a step never exceeds two overlapping maxima
    # Decaying: 10 s (5 time constants) after an isolated jump less than 1 % of 0.5 m remains.
    onsets = np.flatnonzero(jumps)
    isolated = onsets[(np.diff(onsets, prepend=-(10**9)) > 200) & (onsets + 100 < len(t) - 1)]
    isolated = isolated[np.isin(isolated + 100, onsets, invert=True)]
    assert isolated.size > 50
    later = np.hypot(*error[isolated + 1 + 100, :2].T)
    assert np.median(later) < 0.005 + 0.5 * math.exp(-5.0)


def test_rtk_float_periods_have_0_3_to_1_m_errors_and_report_a_large_std() -> None:
    spec = only(
        rtk_float_periods=2, rtk_float_duration_s=(10.0, 40.0), rtk_float_sigma_m=(0.3, 1.0),
        rtk_float_ramp_s=3.0, reported_fixed_std_m=0.014, vertical_factor=2.0,
    )  # fmt: skip
    t, position, yaw, speed = straight(10.0, 600.0)
    for seed in range(20):
        track = measure_gnss(t, position, yaw, speed, spec, np.random.default_rng(seed))
        is_float = ~track.is_rtk_fixed
        edges = np.flatnonzero(np.diff(is_float.astype(int)))
        assert len(edges) == 4  # two separate periods
        durations = np.diff(t[edges + 1])[::2]
        assert np.all((durations > 10.0 - 0.2) & (durations < 40.0 + 0.2))
        assert not track.error[~is_float].any()
        assert np.all(track.horizontal_std_m[~is_float] == 0.014)
        # The core of each period (3 s ramps excluded): 0.3-1 m horizontal error, std reported >= 0.3 m.
        for start, end in zip(t[edges[::2] + 1], t[edges[1::2]], strict=True):
            core = (t > start + 3.05) & (t < end - 3.05)
            level = np.hypot(*track.error[core, :2].T)
            assert np.all((level > 0.3 - 1e-9) & (level < 1.0 + 1e-9))
            assert np.all(track.horizontal_std_m[core] >= 0.3)
        assert np.allclose(track.vertical_std_m, 2.0 * track.horizontal_std_m)
        # Grows and recedes smoothly: no fix-to-fix step above ~ level * pi / (2 * ramp) * dt + drift.
        assert np.hypot(*np.diff(track.error[:, :2], axis=0).T).max() < 0.1


def test_course_noise_grows_as_speed_drops_and_is_held_below_the_threshold() -> None:
    spec = only(
        heading_sigma_deg=0.3, velocity_sigma_mps=0.05, course_hold_speed_mps=1.0, course_noise_tau_s=1.0
    )
    t = np.round(np.arange(0.0, 6000.0, DT_S), 9)
    n = len(t)
    # 10 m/s, then 0.3 m/s (crawling, the true yaw still turning), then 2 m/s; 2000 s each.
    speed = np.where(t < 2000, 10.0, np.where(t < 4000, 0.3, 2.0))
    yaw = np.where((t >= 2000) & (t < 4000), 0.001 * (t - 2000), 0.0)
    track = measure_gnss(t, np.zeros((n, 3)), yaw, speed, spec, np.random.default_rng(8))
    slow = speed == 0.3
    last_fast = np.flatnonzero(t < 2000)[-1]
    assert np.all(track.yaw[slow] == track.yaw[last_fast])
    # sigma = hypot(0.3 deg, 0.05 / v rad): 0.41 deg at 10 m/s, 1.46 deg at 2 m/s. The noise is AR(1)
    # with phi = exp(-0.1 / 1.0): 20000 fixes hold N (1 - phi^2) / (1 + phi^2) ~ 2000 independent ones,
    # relative SE of the std 1/sqrt(2 * 2000) = 1.6 %, 4 SE = 6.3 % (v itself carries 0.5-2.5 % noise).
    for v in (10.0, 2.0):
        expected = math.hypot(math.radians(0.3), 0.05 / v)
        assert np.std(track.yaw[speed == v] - yaw[speed == v]) == pytest.approx(expected, rel=0.07)
    # Correlated over ~1 s: the lag-1 correlation at 10 Hz is exp(-0.1) = 0.905.
    noise = track.yaw[speed == 10.0] - yaw[speed == 10.0]
    assert np.corrcoef(noise[:-1], noise[1:])[0, 1] == pytest.approx(math.exp(-0.1), abs=0.02)


def test_odometry_speed_has_a_per_run_scale_error_and_reads_zero_at_rest() -> None:
    spec = only(speed_scale_error=0.007, speed_sigma_mps=0.03)
    t, position, yaw, speed = straight(10.0, 10.0)
    speed[-20:] = 0.0
    runs = 500
    scales = np.empty(runs)
    for seed in range(runs):
        track = measure_gnss(t, position, yaw, speed, spec, np.random.default_rng(seed))
        assert np.all(track.speed_mps[-20:] == 0.0) and np.all(track.speed_mps >= 0.0)
        scales[seed] = track.speed_mps[:-20].mean() / 10.0 - 1.0
    # Per-run noise on the scale estimate: 0.03 / 10 / sqrt(81) = 3e-4, small beside 0.007; the std of
    # 500 scale draws has relative SE 1/sqrt(1000) = 3.2 %; 4 SE = 12.6 %.
    assert scales.std() == pytest.approx(math.hypot(0.007, 3.3e-4), rel=4 / math.sqrt(2 * runs))
