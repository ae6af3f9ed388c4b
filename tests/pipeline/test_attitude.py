"""Pitch from the driven path's height profile (pipeline/attitude.py), for CAMs that carry none."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.association import Trajectory
from pipeline.attitude import path_pitch, reports_attitude, with_path_pitch

START_NS = 1_700_000_000_000_000_000


def _path(grade: float, heading: float = 0.3, speed: float = 8.0, seconds: float = 12.0) -> Trajectory:
    """Poses at 5 Hz along a straight road on a constant grade, without pitch or roll (CAM-like)."""
    t = np.arange(0.0, seconds, 0.2)
    s = speed * t
    x, y, z = s * math.cos(heading), s * math.sin(heading), 40.0 + grade * s
    poses = np.column_stack([x, y, z, np.full_like(t, heading), 0 * t, 0 * t])
    return Trajectory(stamps=START_NS + np.round(t * 1e9).astype(np.int64), poses=poses)


@settings(max_examples=40, deadline=None)
@given(
    st.one_of(st.just(0.0), st.floats(0.005, 0.12), st.floats(-0.12, -0.005)), st.floats(-math.pi, math.pi)
)
def test_constant_grade_gives_its_pitch_nose_up_negative(grade, heading):
    trajectory = with_path_pitch(_path(grade, heading))
    # Exact heights: the shrinkage towards level (standard error ~0) leaves the grade as it is.
    assert np.allclose(trajectory.poses[:, 4], -math.atan(grade), atol=1e-9)
    assert np.array_equal(trajectory.poses[:, :4], _path(grade, heading).poses[:, :4])


def test_height_noise_averages_out_over_the_window():
    trajectory = _path(0.06)
    noisy = trajectory.poses.copy()
    noisy[:, 2] += np.random.default_rng(0).normal(0.0, 0.03, len(noisy))
    pitch = with_path_pitch(Trajectory(trajectory.stamps, noisy)).poses[:, 4]
    assert np.max(np.abs(pitch + math.atan(0.06))) < math.radians(1.0)


def test_height_noise_on_a_level_road_stays_level():
    """7.5 cm of height noise (the first simulator's pose noise) on a level road: no invented grade."""
    trajectory = _path(0.0)
    noisy = trajectory.poses.copy()
    noisy[:, 2] += np.random.default_rng(1).normal(0.0, 0.075, len(noisy))
    pitch = with_path_pitch(Trajectory(trajectory.stamps, noisy)).poses[:, 4]
    assert np.sqrt(np.mean(pitch**2)) < math.radians(0.15)


def test_a_crest_is_followed():
    """A vertical curve: grade +6 % then -6 %; pitch changes sign across the crest."""
    t = np.arange(0.0, 20.0, 0.2)
    s = 8.0 * t
    z = np.where(s < 80.0, 0.06 * s, 4.8 - 0.06 * (s - 80.0))
    poses = np.column_stack([s, 0 * s, z, 0 * s, 0 * s, 0 * s])
    pitch = path_pitch(START_NS + np.round(t * 1e9).astype(np.int64), poses[:, :3], 8.0, 1_500_000_000)
    assert np.allclose(pitch[s < 70.0], -math.atan(0.06), atol=1e-9)
    assert np.allclose(pitch[s > 90.0], math.atan(0.06), atol=1e-9)


def test_reported_attitude_is_kept():
    trajectory = _path(0.05)
    poses = trajectory.poses.copy()
    poses[:, 4] = 0.01
    imu = Trajectory(trajectory.stamps, poses)
    assert reports_attitude(imu)
    assert with_path_pitch(imu) is imu


def test_dropouts_split_the_path_and_short_runs_stay_level():
    trajectory = _path(0.05)
    stamps = trajectory.stamps.copy()
    stamps[-2:] += 10_000_000_000  # the last two poses after a 10 s dropout
    pitch = path_pitch(stamps, trajectory.poses[:, :3], 8.0, 1_500_000_000)
    assert np.allclose(pitch[:-2], -math.atan(0.05), atol=1e-9)
    assert np.array_equal(pitch[-2:], [0.0, 0.0])
