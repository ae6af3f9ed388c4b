"""pipeline.pairs: straight drive-pasts along lines that are not parallel, solved together with the clock."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from pipeline.association import MatchedTrack, Trajectory
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    project_points,
    rotation_angle_rad,
)
from pipeline.clock import ClockParams
from pipeline.ground import GroundPlaneFit
from pipeline.hypotheses import Hypothesis, HypothesisParams
from pipeline.pairs import PairParams, corroborated_pairs, straight_tracks
from pipeline.stage import Reason
from pipeline.vehicle import body_centres
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.6, width=1.9, height=1.5, imu_offset=(1.3, 0.95, 0.4))
GROUND = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
CENTRE = np.array([4.0, -14.0, 8.0])
START_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 fps
SPEED_MPS = 10.0


def camera() -> CameraModel:
    return CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0, dist=(-0.05,) + (0.0,) * 4
        )
    )


def rolled_pose() -> tuple[np.ndarray, np.ndarray]:
    """A camera rolled 8 deg off square, looking along +y: no straight-track mount fits it."""
    R = camera_rotation_from_view(math.radians(95.0), math.radians(18.0), math.radians(8.0))
    return R, -R @ CENTRE


def drive(heading_deg: float, through: tuple[float, float], start_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A straight drive at SPEED_MPS through `through` (x, y) at `heading_deg` (from east, ccw), 30 m
    each side: trajectory times (s since START_NS) and poses (N, 6) at 10 Hz."""
    heading = math.radians(heading_deg)
    along = np.arange(-30.0, 30.0, SPEED_MPS * 0.1)
    zeros = np.zeros(len(along))
    poses = np.column_stack(
        [
            through[0] + along * math.cos(heading),
            through[1] + along * math.sin(heading),
            np.full(len(along), 0.4),
            np.full(len(along), heading),
            zeros,
            zeros,
        ]
    )
    return start_s + (along + 30.0) / SPEED_MPS, poses


def seen_track(
    track_id: int,
    times_s: np.ndarray,
    poses: np.ndarray,
    latency_s: float,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
) -> MatchedTrack:
    """The drive's boxes where the camera (default `rolled_pose`) sees the vehicle: each box stamped t shows
    the vehicle where it was `latency_s` earlier (boxes centred on the body centre's projection), paired
    with the pose the assumed clock gives (at t)."""
    R, t = pose or rolled_pose()
    shown = poses.copy()
    shown[:, :2] -= latency_s * SPEED_MPS * np.column_stack([np.cos(poses[:, 3]), np.sin(poses[:, 3])])
    centres = body_centres(shown, VEHICLE)
    pixels, depth = project_points(centres, R, t, camera())
    inside = (depth > 2.0) & np.all((pixels > 40.0) & (pixels < [1880.0, 1040.0]), axis=1)
    # Only what the lens sees: a point far off axis can land inside the image where the distortion
    # polynomial folds back (k1 -0.05 turns at r = 2.6); the image's corners lie at r = 1.1.
    in_camera = centres @ R.T + t
    inside &= np.hypot(in_camera[:, 0], in_camera[:, 1]) < 1.5 * in_camera[:, 2]
    if noise_px and rng is not None:
        pixels = pixels + rng.normal(0.0, noise_px, pixels.shape)
    half = np.array([40.0, 30.0])
    boxes = np.column_stack([pixels - half, pixels + half])[inside]
    stamps = START_NS + np.round(times_s[inside] * 1e9).astype(np.int64)
    return MatchedTrack(track_id=track_id, stamps=stamps, boxes=boxes, poses=poses[inside])


def scene(
    latency_s: float,
    noise_px: float = 0.0,
    seed: int = 0,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
    heading_deg: float = 0.0,
    crossing_deg: float = 90.0,
) -> tuple[list[MatchedTrack], Trajectory]:
    """Three straight drive-pasts a minute apart, seen by `pose` (default `rolled_pose`): along
    `heading_deg` (default west to east), across it at `crossing_deg` (default south to north), and back."""
    rng = np.random.default_rng(seed)
    drives = [
        drive(heading_deg, (0.0, 12.0), 0.0),
        drive(heading_deg + crossing_deg, (2.0, 10.0), 60.0),
        drive(heading_deg + 180.0, (0.0, 16.0), 120.0),
    ]
    tracks = [seen_track(i + 1, *d, latency_s, noise_px, rng, pose) for i, d in enumerate(drives)]
    times = np.concatenate([d[0] for d in drives])
    poses = np.concatenate([d[1] for d in drives])
    stamps = START_NS + np.round(times * 1e9).astype(np.int64)
    return tracks, Trajectory(stamps=stamps, poses=poses)


def solve(
    tracks: list[MatchedTrack],
    trajectory: Trajectory,
    others: list[MatchedTrack] | None = None,
    clock: ClockParams | None = None,
) -> tuple[list, object]:
    return corroborated_pairs(
        tracks,
        tracks if others is None else others,
        camera(),
        VEHICLE,
        GROUND,
        trajectory,
        HypothesisParams(),
        PairParams(),
        clock or ClockParams(),
    )


@pytest.mark.parametrize("latency_s", [0.0, 0.15, -0.3])
def test_three_straight_drive_pasts_fix_a_rolled_camera_and_its_clock(latency_s: float) -> None:
    tracks, trajectory = scene(latency_s)
    assert all(len(t.stamps) >= 20 for t in tracks)
    unions, report = solve(tracks, trajectory)
    assert [u.track_ids for u in unions] == [(1, 2, 3)], report
    (union,) = unions
    R, _ = rolled_pose()
    assert math.degrees(rotation_angle_rad(union.R, R)) < 1e-3
    assert np.linalg.norm(camera_centre(union.R, union.t) - CENTRE) < 1e-3
    assert union.shift_s == pytest.approx(latency_s, abs=1e-3)
    hypotheses = union.hypotheses()
    assert [h.track_id for h in hypotheses] == [1, 2, 3]
    assert all(h.inliers.all() and h.median_reproj_px < 1e-3 for h in hypotheses)


@settings(max_examples=40, deadline=None)
@given(
    yaw_deg=st.floats(70.0, 110.0),
    pitch_deg=st.floats(12.0, 30.0),
    roll_deg=st.floats(-15.0, 15.0),
    heading_deg=st.floats(-20.0, 20.0),
    crossing_deg=st.floats(50.0, 130.0),
    latency_s=st.floats(-0.5, 0.5),
)
def test_any_camera_and_two_crossing_roads_give_the_pose_and_clock(
    yaw_deg: float,
    pitch_deg: float,
    roll_deg: float,
    heading_deg: float,
    crossing_deg: float,
    latency_s: float,
) -> None:
    R = camera_rotation_from_view(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
    tracks, trajectory = scene(
        latency_s, pose=(R, -R @ CENTRE), heading_deg=heading_deg, crossing_deg=crossing_deg
    )
    assume(all(len(t.stamps) >= 20 for t in tracks))
    unions, report = solve(tracks, trajectory)
    found = {u.track_ids: u for u in unions}
    assert (1, 2, 3) in found, report
    union = found[(1, 2, 3)]
    assert math.degrees(rotation_angle_rad(union.R, R)) < 1e-3
    assert np.linalg.norm(camera_centre(union.R, union.t) - CENTRE) < 1e-3
    assert union.shift_s == pytest.approx(latency_s, abs=1e-3)


def test_noisy_boxes_give_the_pose_and_clock_to_their_noise() -> None:
    tracks, trajectory = scene(0.2, noise_px=1.5, seed=3)
    (union,), _ = solve(tracks, trajectory)
    R, _ = rolled_pose()
    assert math.degrees(rotation_angle_rad(union.R, R)) < 0.3
    assert np.linalg.norm(camera_centre(union.R, union.t) - CENTRE) < 0.3
    assert union.shift_s == pytest.approx(0.2, abs=0.02)


def test_a_clock_pinned_to_the_edge_of_the_search_is_no_solution() -> None:
    tracks, trajectory = scene(0.3)
    assert solve(tracks, trajectory, clock=ClockParams(max_shift_s=0.4))[0] != []
    # Searched within +-0.2 s only, the best clock is the edge: whatever pose it gives is not the tracks'.
    unions, report = solve(tracks, trajectory, clock=ClockParams(max_shift_s=0.2))
    assert unions == [] and "0 fit as one" in report.notes[0], report
    assert "pair_clock_at_edge" in {r.example.code for r in report.reasons}, report


def test_one_pair_without_a_third_drive_past_is_no_evidence() -> None:
    tracks, trajectory = scene(0.1)
    unions, report = solve(tracks[:2], trajectory)
    assert unions == []
    assert report.kept == 0 and report.discarded == 1, report
    assert any("no pair is corroborated" in n for n in report.notes), report
    assert [r.example.code for r in report.reasons] == ["pair_uncorroborated"]


def test_parallel_drive_pasts_are_not_paired() -> None:
    tracks, trajectory = scene(0.0)
    unions, report = solve([tracks[0], tracks[2]], trajectory)  # west-east and east-west
    assert unions == [] and "0 pairs" in report.notes[0], report


def test_tracks_of_one_drive_past_are_not_paired() -> None:
    tracks, trajectory = scene(0.0)
    # The south-north track moved to 3 s after the west-east one: one drive-past (a turn), not two.
    early = tracks[1]
    moved = MatchedTrack(
        early.track_id,
        early.stamps - (early.stamps[0] - tracks[0].stamps[-1]) + 3_000_000_000,
        early.boxes,
        early.poses,
    )
    unions, report = solve([tracks[0], moved], trajectory)
    assert unions == [] and "0 pairs" in report.notes[0], report


def test_a_third_track_of_another_vehicle_does_not_corroborate() -> None:
    tracks, trajectory = scene(0.0)
    # The third drive-past's boxes replaced by another vehicle's, 6 m across the road from the calibration
    # vehicle at each stamp: the pair's pose puts the vehicle away from those boxes.
    third = tracks[2]
    shifted = third.poses.copy()
    shifted[:, 1] += 6.0
    R, t = rolled_pose()
    pixels, _ = project_points(body_centres(shifted, VEHICLE), R, t, camera())
    other = MatchedTrack(3, third.stamps, np.column_stack([pixels - 40.0, pixels + 40.0]), third.poses)
    unions, _ = solve(tracks[:2], trajectory, others=[*tracks[:2], other])
    assert unions == []


def test_straight_tracks_are_those_their_line_left_unfixed() -> None:
    tracks, _ = scene(0.0)
    R, t = rolled_pose()
    level = Hypothesis(1, R, t, np.ones(1, bool), 1.0, 0.5, "level")
    free = Hypothesis(2, R, t, np.ones(1, bool), 1.0, 0.5, "epnp+lm")
    rejected = {3: Reason("straight_line", "degenerate: straight-line track")}
    assert [t.track_id for t in straight_tracks(tracks, rejected, [level, free])] == [1, 3]
    other = {3: Reason("too_few_correspondences", "too few")}
    assert [t.track_id for t in straight_tracks(tracks, other, [free])] == []
