"""V2X as vehicles send it: a GNSS/odometry error model and the ETSI CAM generation rules.

`measure_gnss` turns the true trajectory of a vehicle, sampled at its receiver's fix instants, into what
the receiver and the odometry report (a `GnssTrack`: position with a per-run bias, correlated wander,
white noise, decaying multipath jumps and RTK-float periods; course-over-ground heading held at low
speed; odometry speed with a scale error). `cam_generation` then picks the fixes at which an on-board
unit following ETSI EN 302 637-2 clause 6.1.3 generates a CAM (1-10 Hz, motion-triggered).
Units: metres, seconds, radians unless a name says otherwise; local frame x east, y north, z up; yaw is
grid yaw (0 = east, counter-clockwise). Converting to a CAM's true-north heading is the caller's job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import lfilter

from sim.errors import SimulationError
from sim.geometry import BoolArray, FloatArray, IntArray

# Comparisons of elapsed times tolerate float round-off of fix stamps (t0 + k * 0.1 is not exact).
_TIME_EPS_S = 1e-6


@dataclass(frozen=True, slots=True)
class GnssSpec:
    """Error model of a vehicle's GNSS receiver and odometry; the defaults are an RTK-fixed receiver.

    Reference figures: u-blox ZED-F9P data sheet (RTK 0.01 m + 1 ppm CEP horizontal, velocity 0.05 m/s,
    heading of motion 0.3 deg), Septentrio mosaic-X5 (RTK 0.6 cm H / 1 cm V). Data-sheet figures are
    open-sky; a junction with masts, signs and buildings is worse, hence the bias, wander and multipath.
    """

    fix_rate_hz: float = 10.0  # F9P / mosaic RTK navigation rate commonly used by OBUs
    # Per-fix white noise, each horizontal axis (receiver measurement noise, ~1 cm class RTK).
    white_sigma_m: float = 0.015
    # Constant offset per run and axis: base-station coordinate error, antenna phase-centre and
    # lever-arm residuals (~2 cm for RTK fixed).
    bias_sigma_m: float = 0.02
    # Correlated wander: a first-order Gauss-Markov process (steady-state sigma, time constant). Chosen
    # over a pure random walk because fixed RTK ambiguities anchor the solution to the base station, so
    # the error stays bounded over a run; residual multipath and troposphere change with satellite
    # geometry over tens of seconds to minutes, hence a time constant of ~60 s. Its short-term
    # diffusion is `random_walk_m_per_sqrt_s` = sigma * sqrt(2 / tau) (~5.5 mm/sqrt(s) here).
    wander_sigma_m: float = 0.03
    wander_tau_s: float = 60.0
    # Altitude is noisier than the horizontal (vertical DOP > horizontal DOP, troposphere): every
    # error component's vertical sigma is this factor times the horizontal per-axis sigma.
    vertical_factor: float = 2.0
    # Multipath near buildings and masts: Poisson events, each a step of a drawn magnitude in a random
    # horizontal direction that decays exponentially (the receiver re-weights the reflected signal).
    multipath_rate_per_min: float = 1.0
    multipath_jump_m: tuple[float, float] = (0.2, 0.5)
    multipath_decay_s: float = 2.0
    # RTK float: the ambiguities are lost (shadowing under a bridge, a cycle slip); the error grows
    # smoothly to a drawn 0.3-1 m level, drifts, and returns when the fix is regained.
    rtk_float_periods: int = 0
    rtk_float_duration_s: tuple[float, float] = (10.0, 40.0)
    rtk_float_sigma_m: tuple[float, float] = (0.3, 1.0)
    rtk_float_ramp_s: float = 3.0  # convergence time of the float filter, in and out
    # What the receiver reports as its horizontal std when fixed (optimistic, as receivers are: it does
    # not see bias or multipath).
    reported_fixed_std_m: float = 0.014
    # Course over ground from the Doppler velocity: sigma = hypot(heading_sigma_deg,
    # velocity_sigma_mps / speed), and held at its last value below course_hold_speed_mps (receivers
    # freeze the heading of motion at low speed; the F9P's default threshold is of that order).
    heading_sigma_deg: float = 0.3
    velocity_sigma_mps: float = 0.05
    course_hold_speed_mps: float = 1.0
    # The receiver's navigation filter smooths velocity, so the course error is correlated over about a
    # second (first-order Gauss-Markov); white 10 Hz course noise would flicker more than receivers do.
    course_noise_tau_s: float = 1.0
    # Odometry (wheel speed): per-run scale error std (tyre wear and pressure, ~0.5-1 %) and white noise.
    speed_scale_error: float = 0.007
    speed_sigma_mps: float = 0.03

    def __post_init__(self) -> None:
        for name in ("fix_rate_hz", "wander_tau_s", "multipath_decay_s", "vertical_factor"):
            if not getattr(self, name) > 0.0:
                raise SimulationError(name, f"{getattr(self, name)} must be > 0")
        for name in ("multipath_jump_m", "rtk_float_duration_s", "rtk_float_sigma_m"):
            low, high = getattr(self, name)
            if not 0.0 <= low <= high:
                raise SimulationError(name, f"({low}, {high}) is not a range 0 <= low <= high")
        if self.rtk_float_periods < 0:
            raise SimulationError("rtk_float_periods", f"{self.rtk_float_periods} < 0")

    @property
    def random_walk_m_per_sqrt_s(self) -> float:
        """Short-term diffusion of the Gauss-Markov wander (its random-walk equivalent at lags << tau)."""
        return self.wander_sigma_m * math.sqrt(2.0 / self.wander_tau_s)

    @classmethod
    def rtk_fixed(cls) -> GnssSpec:
        """An RTK-fixed receiver for the whole run (the default)."""
        return cls()

    @classmethod
    def rtk_float(cls, periods: int = 2) -> GnssSpec:
        """An RTK receiver that drops to float `periods` times per run (0.3-1 m errors; preset rtk-float)."""
        return cls(rtk_float_periods=periods)

    @classmethod
    def perfect(cls) -> GnssSpec:
        """No error at all (the `ideal` world): measured states equal the truth."""
        return cls(
            white_sigma_m=0.0,
            bias_sigma_m=0.0,
            wander_sigma_m=0.0,
            multipath_rate_per_min=0.0,
            rtk_float_periods=0,
            reported_fixed_std_m=0.0,
            heading_sigma_deg=0.0,
            velocity_sigma_mps=0.0,
            course_hold_speed_mps=0.0,
            speed_scale_error=0.0,
            speed_sigma_mps=0.0,
        )

    def with_float(self, periods: int) -> GnssSpec:
        """This receiver with `periods` RTK-float periods per run."""
        return replace(self, rtk_float_periods=periods)


@dataclass(frozen=True, slots=True)
class GnssTrack:
    """What the vehicle's receiver and odometry report at each fix (N fixes)."""

    t_s: FloatArray  # (N,) fix instants
    position: FloatArray  # (N, 3) measured antenna/reference position, local frame
    yaw: FloatArray  # (N,) measured course as grid yaw (rad, 0 = east, ccw), in (-pi, pi]
    speed_mps: FloatArray  # (N,) odometry speed, >= 0
    horizontal_std_m: FloatArray  # (N,) the receiver's reported horizontal std
    vertical_std_m: FloatArray  # (N,) the receiver's reported vertical std
    is_rtk_fixed: BoolArray  # (N,) the receiver's fix flag
    error: FloatArray  # (N, 3) ground truth: measured minus true position


def _check_inputs(t_s: FloatArray, position: FloatArray, yaw: FloatArray, speed_mps: FloatArray) -> int:
    n = t_s.shape[0] if t_s.ndim == 1 else -1
    if n < 1:
        raise SimulationError("t_s", f"expected shape (N,) with N >= 1, got {t_s.shape}")
    for name, arr, shape in (
        ("position", position, (n, 3)),
        ("yaw", yaw, (n,)),
        ("speed_mps", speed_mps, (n,)),
    ):
        if arr.shape != shape:
            raise SimulationError(name, f"expected shape {shape}, got {arr.shape}")
    if n > 1 and not np.all(np.diff(t_s) > 0):
        raise SimulationError("t_s", "fix instants must be strictly increasing")
    if not all(np.all(np.isfinite(a)) for a in (t_s, position, yaw, speed_mps)):
        raise SimulationError("gnss input", "non-finite values")
    return n


def gauss_markov(
    t_s: FloatArray, sigma: float, tau_s: float, dims: int, rng: np.random.Generator
) -> FloatArray:
    """First-order Gauss-Markov samples (N, dims) at irregular instants, started in its stationary law.

    Exact discretisation: x_k+1 = phi x_k + sqrt(1 - phi^2) sigma w_k with phi = exp(-dt / tau).
    """
    out = np.zeros((t_s.shape[0], dims))
    if sigma <= 0.0:
        return out
    steps_s = np.diff(t_s)
    phi = np.exp(-steps_s / tau_s)
    drive = rng.standard_normal((t_s.shape[0], dims)) * sigma
    drive[1:] *= np.sqrt(1.0 - phi**2)[:, None]
    if steps_s.size and np.allclose(steps_s, steps_s[0], rtol=1e-6, atol=0.0):
        # Regular fixes (the usual case): the recursion is one IIR filter, fast on long runs.
        return np.asarray(lfilter([1.0], [1.0, -phi[0]], drive, axis=0), dtype=np.float64)
    out[0] = drive[0]
    for k in range(1, t_s.shape[0]):
        out[k] = phi[k - 1] * out[k - 1] + drive[k]
    return out


def _multipath(t_s: FloatArray, spec: GnssSpec, rng: np.random.Generator) -> FloatArray:
    """Decaying multipath offsets (N, 3): Poisson onsets over the run, each a step that decays."""
    out = np.zeros((t_s.shape[0], 3))
    span_s = float(t_s[-1] - t_s[0])
    rate_per_s = spec.multipath_rate_per_min / 60.0
    if rate_per_s <= 0.0:
        return out
    count = int(rng.poisson(rate_per_s * span_s))
    onsets = np.sort(rng.uniform(t_s[0], t_s[-1], count))
    magnitudes = rng.uniform(*spec.multipath_jump_m, count)
    directions = rng.uniform(-math.pi, math.pi, count)
    # Reflections lengthen the path along the line of sight, so the vertical moves as well, by more.
    vertical = rng.standard_normal(count) * magnitudes * spec.vertical_factor / math.sqrt(2.0)
    # Each offset is cut after 10 decay constants (e^-10: below 0.03 mm of a 0.5 m jump).
    first = np.searchsorted(t_s, onsets)
    last = np.searchsorted(t_s, onsets + 10.0 * spec.multipath_decay_s)
    for k in range(count):
        span = slice(first[k], last[k])
        decay = np.exp(-(t_s[span] - onsets[k]) / spec.multipath_decay_s)
        jump = magnitudes[k] * np.array([math.cos(directions[k]), math.sin(directions[k]), 0.0])
        jump[2] = vertical[k]
        out[span] += decay[:, None] * jump
    return out


def _float_envelope(t_s: FloatArray, start_s: float, duration_s: float, ramp_s: float) -> FloatArray:
    """0 outside, 1 in the core, raised-cosine ramps of `ramp_s` at both ends (inside the period)."""
    ramp_s = min(ramp_s, duration_s / 2.0)
    into = np.clip((t_s - start_s) / ramp_s, 0.0, 1.0) if ramp_s > 0 else (t_s >= start_s).astype(float)
    end_s = start_s + duration_s
    out_of = np.clip((end_s - t_s) / ramp_s, 0.0, 1.0) if ramp_s > 0 else (t_s <= end_s).astype(float)
    level = np.minimum(into, out_of)
    return np.asarray(0.5 - 0.5 * np.cos(math.pi * level), dtype=np.float64)


def _rtk_float(t_s: FloatArray, spec: GnssSpec, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Float-period error (N, 3) and the envelope (N,) (0 = fixed, > 0 = float). One period per equal
    slot of the run, so periods never overlap; the horizontal error's magnitude is a drawn level in
    rtk_float_sigma_m, its direction turns slowly (the float filter wanders as it converges)."""
    n = t_s.shape[0]
    error = np.zeros((n, 3))
    envelope = np.zeros(n)
    periods = spec.rtk_float_periods
    if periods <= 0:
        return error, envelope
    slot_s = float(t_s[-1] - t_s[0]) / periods
    for slot in range(periods):
        duration_s = min(rng.uniform(*spec.rtk_float_duration_s), slot_s)
        start_s = float(t_s[0]) + slot * slot_s + rng.uniform(0.0, slot_s - duration_s)
        level_m = rng.uniform(*spec.rtk_float_sigma_m)
        shape = _float_envelope(t_s, start_s, duration_s, spec.rtk_float_ramp_s)
        # Direction: a random start turning at up to 0.02 rad/s (up to ~1 rad over a 40 s period).
        direction = rng.uniform(-math.pi, math.pi) + rng.uniform(-0.02, 0.02) * (t_s - start_s)
        dz = rng.uniform(-1.0, 1.0) * level_m * spec.vertical_factor / math.sqrt(2.0)
        error[:, 0] += shape * level_m * np.cos(direction)
        error[:, 1] += shape * level_m * np.sin(direction)
        error[:, 2] += shape * dz
        envelope = np.maximum(envelope, shape * level_m)
    return error, envelope


def _wrap(angle: FloatArray) -> FloatArray:
    return np.asarray(np.angle(np.exp(1j * angle)), dtype=np.float64)


def measure_gnss(
    t_s: FloatArray,
    true_position: FloatArray,
    true_yaw: FloatArray,
    true_speed_mps: FloatArray,
    spec: GnssSpec,
    rng: np.random.Generator,
) -> GnssTrack:
    """What the receiver and odometry report at the fix instants `t_s` (N,) of a true trajectory.

    true_position (N, 3) local frame, true_yaw (N,) grid yaw of the direction of travel, true_speed_mps
    (N,) >= 0. The caller samples the truth at spec.fix_rate_hz. Every random draw comes from `rng`.
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    true_position = np.asarray(true_position, dtype=np.float64)
    true_yaw = np.asarray(true_yaw, dtype=np.float64)
    true_speed_mps = np.asarray(true_speed_mps, dtype=np.float64)
    n = _check_inputs(t_s, true_position, true_yaw, true_speed_mps)
    per_axis = np.array([1.0, 1.0, spec.vertical_factor])

    bias = rng.standard_normal(3) * spec.bias_sigma_m * per_axis
    wander = gauss_markov(t_s, spec.wander_sigma_m, spec.wander_tau_s, 3, rng) * per_axis
    white = rng.standard_normal((n, 3)) * spec.white_sigma_m * per_axis
    multipath = _multipath(t_s, spec, rng)
    float_error, float_level = _rtk_float(t_s, spec, rng)
    error = bias + wander + white + multipath + float_error

    # The receiver flags float while the float filter runs (ramps included) and reports its error level;
    # it does not see its bias, wander or multipath, so its fixed std stays the optimistic data-sheet one.
    is_rtk_fixed = float_level <= 0.0
    horizontal_std = np.hypot(spec.reported_fixed_std_m, float_level)

    # Course over ground from Doppler velocity: its noise grows as speed drops; below the hold speed the
    # receiver repeats the last course (before the first valid one: the true parked heading, which the
    # previous drive's last course approximates).
    ground_speed = true_speed_mps + rng.standard_normal(n) * spec.velocity_sigma_mps
    with np.errstate(divide="ignore", invalid="ignore"):
        course_sigma = np.hypot(math.radians(spec.heading_sigma_deg), spec.velocity_sigma_mps / ground_speed)
    course_noise = (
        gauss_markov(t_s, 1.0, spec.course_noise_tau_s, 1, rng)[:, 0]
        if spec.course_noise_tau_s > 0.0
        else rng.standard_normal(n)
    )
    course = true_yaw + course_noise * np.where(np.isfinite(course_sigma), course_sigma, 0.0)
    is_course_valid = ground_speed >= spec.course_hold_speed_mps
    last_valid = np.maximum.accumulate(np.where(is_course_valid, np.arange(n), -1))
    yaw = np.where(last_valid >= 0, course[np.maximum(last_valid, 0)], true_yaw[0])

    # Odometry: wheel ticks scale with the rolling radius (per-run scale error); at rest they read zero.
    scale = 1.0 + rng.standard_normal() * spec.speed_scale_error
    noisy_speed = true_speed_mps * scale + rng.standard_normal(n) * spec.speed_sigma_mps
    speed = np.where(true_speed_mps > 0.0, np.maximum(noisy_speed, 0.0), 0.0)

    return GnssTrack(
        t_s=t_s.copy(),
        position=true_position + error,
        yaw=_wrap(yaw),
        speed_mps=speed,
        horizontal_std_m=horizontal_std,
        vertical_std_m=horizontal_std * spec.vertical_factor,
        is_rtk_fixed=is_rtk_fixed,
        error=error,
    )


def ideal_gnss(
    t_s: FloatArray, true_position: FloatArray, true_yaw: FloatArray, true_speed_mps: FloatArray
) -> GnssTrack:
    """The `ideal` world's receiver: the truth, reported as RTK fixed with zero std."""
    return measure_gnss(
        t_s, true_position, true_yaw, true_speed_mps, GnssSpec.perfect(), np.random.default_rng(0)
    )


@dataclass(frozen=True, slots=True)
class CamSpec:
    """CAM generation parameters of ETSI EN 302 637-2 (V1.3.2 / V1.4.1) clause 6.1.3."""

    t_check_cam_gen_s: float = 0.1  # T_CheckCamGen <= T_GenCamMin
    t_gen_cam_min_s: float = 0.1  # T_GenCamMin
    t_gen_cam_max_s: float = 1.0  # T_GenCamMax
    # T_GenCamDcc: set by decentralised congestion control within [T_GenCamMin, T_GenCamMax];
    # T_GenCamMin on an uncongested channel.
    t_gen_cam_dcc_s: float = 0.1
    heading_change_deg: float = 4.0  # condition 1 thresholds, vs the last CAM sent
    position_change_m: float = 4.0
    speed_change_mps: float = 0.5
    n_gen_cam: int = 3  # N_GenCam default

    def __post_init__(self) -> None:
        if not 0.0 < self.t_check_cam_gen_s <= self.t_gen_cam_min_s + _TIME_EPS_S:
            raise SimulationError("t_check_cam_gen_s", f"{self.t_check_cam_gen_s} not in (0, T_GenCamMin]")
        if not self.t_gen_cam_min_s <= self.t_gen_cam_dcc_s <= self.t_gen_cam_max_s:
            raise SimulationError(
                "t_gen_cam_dcc_s", f"{self.t_gen_cam_dcc_s} not in [T_GenCamMin, T_GenCamMax]"
            )
        if self.n_gen_cam < 1:
            raise SimulationError("n_gen_cam", f"{self.n_gen_cam} < 1")


def cam_generation(
    t_s: FloatArray, position: FloatArray, yaw: FloatArray, speed_mps: FloatArray, spec: CamSpec
) -> IntArray:
    """Indices (M,) into the fixes at which an on-board unit generates CAMs (EN 302 637-2 clause 6.1.3).

    Inputs are the measured states at the fix instants (N,): t_s, position (N, 3) local frame, yaw (N,)
    grid yaw, speed_mps (N,). Generation is checked at the first fix at or after each T_CheckCamGen
    tick (with 10 Hz fixes and a 0.1 s check period: every fix). The first check generates a CAM.
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    speed_mps = np.asarray(speed_mps, dtype=np.float64)
    n = _check_inputs(t_s, position, yaw, speed_mps)
    heading_limit = math.radians(spec.heading_change_deg)

    generated: list[int] = [0]
    last = 0
    t_gen_cam = spec.t_gen_cam_max_s  # clause 6.1.3: the default value of T_GenCam is T_GenCamMax
    consecutive_timed = 0
    period_s = spec.t_check_cam_gen_s
    next_tick = 1  # check ticks at t_s[0] + m * T_CheckCamGen
    for k in range(1, n):
        if t_s[k] < t_s[0] + next_tick * period_s - _TIME_EPS_S:
            continue
        # The first tick after this fix is the next check (a gap in the fixes skips ticks).
        next_tick = math.floor((t_s[k] - t_s[0]) / period_s + _TIME_EPS_S) + 1
        elapsed_s = t_s[k] - t_s[last]
        if elapsed_s < spec.t_gen_cam_dcc_s - _TIME_EPS_S:
            continue
        # Condition 1 (clause 6.1.3): elapsed >= T_GenCamDcc and heading changed > 4 deg, or position
        # > 4 m, or speed > 0.5 m/s, each vs the values in the CAM previously transmitted.
        heading_change = abs(math.remainder(float(yaw[k] - yaw[last]), math.tau))
        distance = math.hypot(*(position[k, :2] - position[last, :2]))  # reference-position distance
        speed_change = abs(float(speed_mps[k] - speed_mps[last]))
        is_dynamic = (
            heading_change > heading_limit
            or distance > spec.position_change_m
            or speed_change > spec.speed_change_mps
        )
        if is_dynamic:
            # "If a CAM is generated due to condition 1), T_GenCam shall be set to the time elapsed
            # since the last CAM generation."
            t_gen_cam = min(elapsed_s, spec.t_gen_cam_max_s)  # the cap only matters after a fix gap
            consecutive_timed = 0
        elif elapsed_s >= t_gen_cam - _TIME_EPS_S:
            # Condition 2: elapsed >= T_GenCam (and >= T_GenCamDcc, checked above). After N_GenCam
            # consecutive CAMs generated due to condition 2, T_GenCam falls back to T_GenCamMax.
            consecutive_timed += 1
            if consecutive_timed >= spec.n_gen_cam:
                t_gen_cam = spec.t_gen_cam_max_s
                consecutive_timed = 0
        else:
            continue
        generated.append(k)
        last = k
    return np.asarray(generated, dtype=np.int64)
