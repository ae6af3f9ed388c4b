"""pipeline.clock: a detector latency the assumed clock does not know splits the hypotheses of opposite
drive-pasts; the scan finds the clock on which grouping joins them."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.association import AssociationParams, MatchedTrack, Trajectory, match_tracks
from pipeline.camera import CameraModel, camera_rotation_from_view, project_points
from pipeline.clock import (
    ClockParams,
    ClockScan,
    _anchor_index,
    rematcher,
    scan_clock,
    shifted,
    track_velocity,
)
from pipeline.ground import GroundPlaneFit
from pipeline.grouping import GroupingParams, GroupingResult, group_hypotheses
from pipeline.hypotheses import Hypothesis, HypothesisParams, create_hypotheses
from pipeline.tracking import FrameBoxes, ImageTrack
from pipeline.vehicle import body_corners
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.6, width=1.9, height=1.5, imu_offset=(1.3, 0.95, 0.4))
CAMERA = CameraModel.from_intrinsics(
    CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)
)
CAMERA_CENTRE = np.array([4.0, -14.0, 8.0])
R_TRUE = camera_rotation_from_view(math.radians(95.0), math.radians(18.0))
T_TRUE = -R_TRUE @ CAMERA_CENTRE
GROUND = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
START_NS = 1_700_000_000_000_000_000
FRAME_NS = 50_000_000  # 20 fps
SPEED = 12.0  # m/s


def curve() -> np.ndarray:
    """150 m east along y = 0 to a left curve of radius 40 m through the camera's view, then 150 m away."""
    theta = np.linspace(-math.pi / 2, math.radians(20.0), 200)[1:]
    arc = np.column_stack([40.0 * np.cos(theta), 40.0 + 40.0 * np.sin(theta)])
    approach = np.column_stack([np.linspace(-150.0, 0.0, 60), np.zeros(60)])
    yaw = math.radians(110.0)
    leave = arc[-1] + np.linspace(1.0, 150.0, 60)[:, None] * np.array([math.cos(yaw), math.sin(yaw)])
    return np.concatenate([approach, arc, leave])


LENGTH = float(np.sum(np.linalg.norm(np.diff(curve(), axis=0), axis=1)))


def poses_at(s: np.ndarray, reverse: bool) -> np.ndarray:
    path = curve()[::-1] if reverse else curve()
    step = np.diff(path, axis=0)
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(step, axis=1))])
    s = np.clip(s, 0.0, cumulative[-1] - 1e-9)
    k = np.clip(np.searchsorted(cumulative, s, side="right") - 1, 0, len(step) - 1)
    xy = path[k] + ((s - cumulative[k]) / np.linalg.norm(step[k], axis=1))[:, None] * step[k]
    zeros = np.zeros(len(s))
    return np.column_stack([xy, np.full(len(s), 0.4), np.arctan2(step[k, 1], step[k, 0]), zeros, zeros])


def bounding_boxes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = body_corners(poses, VEHICLE).reshape(-1, 3)
    pixels, depth = project_points(corners, R_TRUE, T_TRUE, CAMERA)
    pixels, depth = pixels.reshape(-1, 8, 2), depth.reshape(-1, 8)
    boxes = np.concatenate([pixels.min(axis=1), pixels.max(axis=1)], axis=1)
    with np.errstate(invalid="ignore"):
        seen = np.all(depth > 1.0, axis=1) & (boxes[:, 0] > 1) & (boxes[:, 1] > 1)
        seen &= (boxes[:, 2] < CAMERA.width - 1) & (boxes[:, 3] < CAMERA.height - 1)
    return boxes, seen


def scene(latency_s: float) -> tuple[list[ImageTrack], list[FrameBoxes], Trajectory]:
    """Two drive-pasts in opposite directions; each box, stamped t, shows the vehicle at t - latency."""
    duration = LENGTH / SPEED
    stamps_out = START_NS + FRAME_NS * np.arange(int(duration * 20), dtype=np.int64)
    stamps_back = stamps_out + np.int64(60e9)
    poses, stamps, tracks, frames = [], [], [], []
    padding = np.int64(2_000_000_000)  # poses 2 s beyond each lap's boxes
    for number, (lap_stamps, reverse) in enumerate([(stamps_out, False), (stamps_back, True)]):
        pose_stamps = np.arange(lap_stamps[0] - padding, lap_stamps[-1] + padding, FRAME_NS, dtype=np.int64)
        poses.append(poses_at(SPEED * (pose_stamps - lap_stamps[0]) / 1e9, reverse))
        stamps.append(pose_stamps)
        t = (lap_stamps - lap_stamps[0]) / 1e9
        boxes, seen = bounding_boxes(poses_at(SPEED * (t - latency_s), reverse))
        rows = np.flatnonzero(seen)
        tracks.append(ImageTrack(number, lap_stamps[rows], boxes[rows], np.full(len(rows), 4)))
        frames += [FrameBoxes(int(lap_stamps[r]), boxes[r][None, :], np.array([4])) for r in rows]
    trajectory = Trajectory(np.concatenate(stamps), np.concatenate(poses))
    return tracks, frames, trajectory


def scan(latency_s: float, laps: int = 2, anchors: bool = True) -> tuple[GroupingResult, ClockScan]:
    """Hypotheses on the assumed (zero) clock, their grouping there, and the clock scan (with `anchors`, its
    anchor clocks' hypotheses fitted afresh as calibrate() does; else every trial moves the assumed
    clock's)."""
    tracks, frames, trajectory = scene(latency_s)
    tracks = tracks[:laps]
    matched = match_tracks(tracks, trajectory, AssociationParams())
    by_id = {m.track_id: m for m in matched}
    found = create_hypotheses(
        matched, CAMERA, VEHICLE, GROUND, HypothesisParams(), np.random.default_rng(3), trajectory=trajectory
    )

    rematch = rematcher(tracks, trajectory, AssociationParams())

    def solve(_shift_s: float, tracks: Mapping[int, MatchedTrack]) -> tuple[Hypothesis, ...]:
        found = create_hypotheses(
            list(tracks.values()),
            CAMERA,
            VEHICLE,
            GROUND,
            HypothesisParams(),
            np.random.default_rng(3),
            trajectory=trajectory,
        )
        return found.hypotheses

    grouped = group_hypotheses(found, by_id, frames, CAMERA, VEHICLE, GroupingParams())
    clock = scan_clock(
        found.hypotheses,
        by_id,
        rematch,
        frames,
        CAMERA,
        VEHICLE,
        GroupingParams(),
        ClockParams(),
        solve if anchors else None,
    )
    return grouped, clock


@pytest.mark.parametrize("latency_s", [-0.5, -0.45, -0.3, -0.2, 0.15, 0.25, 0.35, 0.5])
def test_an_unknown_latency_splits_opposite_drive_pasts_and_the_scan_joins_them(latency_s: float) -> None:
    grouped, clock = scan(latency_s)
    assert grouped.groups == ()  # the problem: on the assumed clock no two drive-pasts agree
    assert clock.found and clock.track_ids == (0, 1)
    # The box at t shows the vehicle at t - latency: the poses must be moved by the latency.
    assert clock.shift_s == pytest.approx(latency_s, abs=0.05)
    assert "tracks [0, 1] agree" in clock.describe()


@pytest.mark.parametrize("latency_s", [-0.45, -0.3, 0.35, 0.45])
def test_hypotheses_moved_from_the_assumed_clock_alone_miss_a_latency_of_a_few_tenths(
    latency_s: float,
) -> None:
    # Why the scan fits anchors afresh: from 0.3 s on, one drive-past's fit on the assumed clock lands under
    # the road or leaves the rotation unfixed, so there is only one hypothesis to move.
    _, clock = scan(latency_s, anchors=False)
    assert not clock.found


@pytest.mark.parametrize("latency_s", [0.0, 0.1])
def test_the_scan_centres_on_the_true_clock(latency_s: float) -> None:
    _, clock = scan(latency_s)  # measured: -1 ms and +101 ms
    assert clock.found
    assert clock.shift_s == pytest.approx(latency_s, abs=0.01)


def test_one_drive_past_gives_no_clock() -> None:
    _, clock = scan(0.2, laps=1)
    assert not clock.found and math.isnan(clock.shift_s)
    assert "no trial clock within +-600 ms" in clock.describe()


@settings(max_examples=50, deadline=None)
@given(
    velocity=st.tuples(*[st.floats(-30.0, 30.0)] * 3),
    start=st.floats(-50.0, 50.0),
    rate=st.sampled_from([10, 20, 50]),
)
def test_track_velocity_of_uniform_motion_is_exact(
    velocity: tuple[float, float, float], start: float, rate: int
) -> None:
    stamps = START_NS + np.int64(1e9 // rate) * np.arange(40, dtype=np.int64)
    t = (stamps - stamps[0]) / 1e9
    poses = np.zeros((40, 6))
    poses[:, :3] = start + t[:, None] * np.array(velocity)
    track = MatchedTrack(0, stamps, np.zeros((40, 4)), poses)
    np.testing.assert_allclose(track_velocity(track), velocity, atol=1e-9)
    np.testing.assert_allclose(track_velocity(track, np.arange(5, 30)), velocity, atol=1e-9)


def test_track_velocity_of_one_row_is_zero() -> None:
    track = MatchedTrack(0, np.array([START_NS]), np.zeros((1, 4)), np.ones((1, 6)))
    np.testing.assert_array_equal(track_velocity(track), np.zeros(3))


def test_shifted_moves_the_camera_back_along_the_velocity() -> None:
    hypothesis = Hypothesis(7, R_TRUE, T_TRUE, np.ones(3, dtype=bool), 0.5)
    moved = shifted(hypothesis, np.array([10.0, -4.0, 0.0]), 0.2)
    np.testing.assert_allclose(moved.camera_centre, CAMERA_CENTRE - np.array([2.0, -0.8, 0.0]), atol=1e-12)
    np.testing.assert_array_equal(moved.R_cam_from_local, R_TRUE)


@pytest.mark.parametrize(
    ("shift_s", "index"),
    [
        (0.0, 0),
        (0.1, 0),
        (0.125, 0),
        (0.13, 1),
        (0.25, 1),
        (0.375, 1),
        (0.38, 2),
        (0.6, 2),
        (-0.125, 0),
        (-0.13, -1),
        (-0.375, -1),
        (-0.6, -2),
    ],
)
def test_a_trial_clock_takes_the_nearest_anchor_a_tie_the_one_nearer_the_assumed_clock(
    shift_s: float, index: int
) -> None:
    assert _anchor_index(shift_s, 0.25) == index
    # The trial clocks of the scan's grid: ties at +-0.125 and +-0.375 s despite 0.025 * 5 != 0.125 exactly.
    assert _anchor_index(0.025 * 5, 0.25) == 0 and _anchor_index(0.025 * 15, 0.25) == 1
