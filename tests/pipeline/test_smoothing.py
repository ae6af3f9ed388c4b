"""pipeline.smoothing: high-rate poses smoothed by a local quadratic before the method interpolates them."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.association import Trajectory
from pipeline.smoothing import smoothed

START_NS = 1_700_000_000_000_000_000


def _trajectory(t: np.ndarray, poses: np.ndarray) -> Trajectory:
    return Trajectory(START_NS + np.round(t * 1e9).astype(np.int64), poses)


def _turning(t: np.ndarray, radius: float = 20.0, speed: float = 12.0) -> np.ndarray:
    """A vehicle on a circle: x, y, z, yaw (wrapped), pitch, roll."""
    angle = speed / radius * t
    poses = np.zeros((len(t), 6))
    poses[:, 0], poses[:, 1] = radius * np.sin(angle), radius * (1.0 - np.cos(angle))
    poses[:, 2] = 0.4 + 0.02 * t**2
    poses[:, 3] = np.angle(np.exp(1j * angle))
    return poses


@settings(max_examples=30, deadline=None)
@given(
    coefficients=st.lists(st.floats(-5.0, 5.0), min_size=18, max_size=18),
    rate=st.sampled_from([25.0, 50.0, 100.0]),
    jitter=st.floats(0.0, 0.2),
)
def test_a_quadratic_path_at_a_high_rate_is_kept_as_it_is(
    coefficients: list[float], rate: float, jitter: float
) -> None:
    # A local quadratic reproduces a quadratic exactly, whatever the spacing of the stamps (to the stamps'
    # rounding to whole nanoseconds: up to 8 m/s x 0.5 ns here).
    rng = np.random.default_rng(0)
    count = round(3.0 * rate)
    t = (np.arange(count) + jitter * rng.uniform(-0.5, 0.5, count)) / rate
    c = np.reshape(coefficients, (3, 6))
    poses = c[0] + c[1] * t[:, None] + 0.1 * c[2] * t[:, None] ** 2
    poses[:, 3] = np.angle(np.exp(1j * poses[:, 3]))
    out = smoothed(_trajectory(t, poses))
    np.testing.assert_array_equal(out.stamps, _trajectory(t, poses).stamps)
    yaw_error = np.angle(np.exp(1j * (out.poses[:, 3] - poses[:, 3])))
    np.testing.assert_allclose(yaw_error, 0.0, atol=1e-7)
    np.testing.assert_allclose(np.delete(out.poses, 3, axis=1), np.delete(poses, 3, axis=1), atol=1e-7)


def test_a_turning_vehicle_keeps_its_path_and_its_yaw_wraps_across_pi() -> None:
    t = np.arange(0.0, 12.0, 0.02)  # 50 Hz, more than a full circle of 20 m at 12 m/s
    poses = _turning(t)
    out = smoothed(_trajectory(t, poses))
    np.testing.assert_allclose(out.poses[:, :3], poses[:, :3], atol=1e-4)  # a circle is a quadratic to 0.1 mm
    assert np.all(np.abs(out.poses[:, 3]) <= math.pi)
    np.testing.assert_allclose(np.angle(np.exp(1j * (out.poses[:, 3] - poses[:, 3]))), 0.0, atol=1e-5)


def test_noise_on_50_hz_poses_no_longer_depends_on_where_between_two_poses_a_box_falls() -> None:
    # Boxes at 10 Hz all fall at one phase between the 50 Hz poses. Interpolated between noisy poses, the
    # vehicle's position is as noisy as one pose at phase 0 and as the mean of two at phase 1/2: the cause
    # of the clock's ripple (pipeline.smoothing). Smoothed, both phases are alike and far less noisy.
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 600.0, 0.02)
    truth = _turning(t)
    noisy = truth.copy()
    noisy[:, :2] += rng.normal(0.0, 0.075, (len(t), 2))
    trajectories = {"reported": _trajectory(t, noisy), "smoothed": smoothed(_trajectory(t, noisy))}
    spread = {}
    for name, trajectory in trajectories.items():
        for phase in (0.0, 0.5):
            at = np.arange(1.0, 599.0, 0.1) + phase * 0.02
            x = np.interp(at, t, trajectory.poses[:, 0]) - np.interp(at, t, truth[:, 0])
            spread[name, phase] = float(np.std(x))
    assert spread["reported", 0.0] > 1.3 * spread["reported", 0.5]  # measured: 0.075 against 0.053 m
    assert spread["smoothed", 0.0] < 1.1 * spread["smoothed", 0.5]  # measured: within 1 %
    assert spread["smoothed", 0.0] < spread["reported", 0.5]  # measured: 0.033 m


def test_poses_at_cam_rates_and_beside_gaps_are_kept_as_reported() -> None:
    # CAMs at 1-10 Hz have at most 4 poses in the 0.3 s window: nothing to average, too few for a curve.
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.1, 1.0, 300))
    poses = _turning(t) + rng.normal(0.0, 0.05, (300, 6)) * [1, 1, 1, 0, 0, 0]
    out = smoothed(_trajectory(t, poses))
    np.testing.assert_array_equal(out.poses, poses)
    # 50 Hz with a 2 s dropout: no window reaches across it, and the poses beside it (half a window, a
    # one-sided fit) stay as close to the path as the reported ones are.
    t = np.concatenate([np.arange(0.0, 5.0, 0.02), np.arange(7.0, 12.0, 0.02)])
    truth = _turning(t)
    noisy = truth.copy()
    noisy[:, 0] += rng.normal(0.0, 0.05, len(t))
    out = smoothed(_trajectory(t, noisy))
    beside = np.abs(np.abs(t - 6.0) - 1.0) < 0.05  # within 0.05 s of the gap
    assert np.std(out.poses[beside, 0] - truth[beside, 0]) < np.std(noisy[:, 0] - truth[:, 0])
    inside = ~beside & (t > 0.2) & (t < 11.8)
    assert np.std(out.poses[inside, 0] - truth[inside, 0]) < 0.5 * np.std(noisy[:, 0] - truth[:, 0])
