"""Selection (pipeline.selection) on small exact scenes: boxes projected from a known pose, a few tracks."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from pipeline.association import MatchedTrack, Trajectory
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    project_points,
    rotation_from_rvec,
)
from pipeline.hypotheses import Hypothesis
from pipeline.refinement import RefinementParams
from pipeline.selection import (
    Candidate,
    Scene,
    SelectionParams,
    box_error,
    choose,
    extend,
    fits_as_well,
    merge_agreeing,
    rank,
    refine_group,
    regroup,
    set_aside,
    trim,
)
from pipeline.vehicle import body_corners
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.7, width=1.85, height=1.5, imu_offset=(1.4, 0.92, 0.3))
OTHER_VEHICLE = VehicleProfile(length=9.0, width=2.5, height=3.2, imu_offset=(1.4, 0.92, 0.3))
CAMERA = CameraModel.from_intrinsics(
    CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)
)
PASS_NS = 10**12  # passes start this far apart: never seen at the same time
FRAME_NS = 100_000_000  # 10 fps at 1 m a frame: 10 m/s

Pose = tuple[np.ndarray, np.ndarray]


def true_pose() -> Pose:
    """10 m high at the origin, looking east, 25 deg down."""
    R = camera_rotation_from_view(0.0, math.radians(25.0))
    return R, -R @ np.array([0.0, 0.0, 10.0])


def moved(pose: Pose, shift_m: float, angle_deg: float) -> Pose:
    """The pose turned by angle_deg about the vertical and its centre moved north by shift_m."""
    R, t = pose
    R_new = R @ rotation_from_rvec(np.array([0.0, 0.0, math.radians(angle_deg)])).T
    centre = camera_centre(R, t) + np.array([0.0, shift_m, 0.0])
    return R_new, -R_new @ centre


def line(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    start, end = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    count = int(np.linalg.norm(end - start)) + 1
    return start + np.linspace(0.0, 1.0, count)[:, None] * (end - start)


# Four drive-pasts in front of the camera, each leaving the view at both ends: across it at 25 m, towards
# it, across at 35 m the other way, and diagonally.
PATHS = (
    line((25.0, -70.0), (25.0, 70.0)),
    line((120.0, -4.0), (6.0, -4.0)),
    line((35.0, 80.0), (35.0, -80.0)),
    line((12.0, -40.0), (60.0, 40.0)),
)


def poses_along(xy: np.ndarray) -> np.ndarray:
    """Level poses (n, 6) along a path, yaw along it."""
    direction = np.gradient(xy, axis=0)
    poses = np.zeros((len(xy), 6))
    poses[:, :2] = xy
    poses[:, 2] = VEHICLE.imu_offset[2]
    poses[:, 3] = np.arctan2(direction[:, 1], direction[:, 0])
    return poses


def stamps_of(index: int, count: int) -> np.ndarray:
    return PASS_NS * (index + 1) + FRAME_NS * np.arange(count, dtype=np.int64)


def track(index: int, pose: Pose, seen: VehicleProfile = VEHICLE, offset_m: float = 0.0) -> MatchedTrack:
    """Pass `index`: the exact tight boxes of `seen`'s body (offset north by offset_m from the reported
    poses), kept where wholly in the image; the reported poses are the calibration vehicle's."""
    reported = poses_along(PATHS[index])
    shown = reported + np.array([0.0, offset_m, 0.0, 0.0, 0.0, 0.0])
    pixels, depth = project_points(body_corners(shown, seen).reshape(-1, 3), pose[0], pose[1], CAMERA)
    uv = pixels.reshape(len(shown), 8, 2)
    boxes = np.column_stack([uv[:, :, 0].min(1), uv[:, :, 1].min(1), uv[:, :, 0].max(1), uv[:, :, 1].max(1)])
    keep = np.all(depth.reshape(len(shown), 8) > 1.0, axis=1)
    keep &= (boxes[:, 0] > 2) & (boxes[:, 1] > 2) & (boxes[:, 2] < CAMERA.width - 2)
    keep &= boxes[:, 3] < CAMERA.height - 2
    assert 10 <= keep.sum() < len(keep), "scene: a pass is in view for a while and leaves it"
    return MatchedTrack(index, stamps_of(index, len(reported))[keep], boxes[keep], reported[keep])


def scene_of(tracks: list[MatchedTrack], params: SelectionParams | None = None) -> Scene:
    """The scene with the vehicle's whole trajectory over every path (in and out of view)."""
    stamps = np.concatenate([stamps_of(i, len(p)) for i, p in enumerate(PATHS)])
    poses = np.concatenate([poses_along(p) for p in PATHS])
    return Scene(
        {m.track_id: m for m in tracks},
        Trajectory(stamps, poses),
        CAMERA,
        VEHICLE,
        RefinementParams(),
        params or SelectionParams(),
    )


def hypothesis(track_id: int, pose: Pose) -> Hypothesis:
    return Hypothesis(track_id, pose[0], pose[1], np.ones(1, dtype=bool), 0.0)


def pose_error(candidate: Candidate, pose: Pose) -> float:
    return float(np.linalg.norm(candidate.whole_box.camera_centre - camera_centre(*pose)))


def relocated(candidate: Candidate, pose: Pose, track_ids: tuple[int, ...]) -> Candidate:
    """The candidate with another pose and tracks, its scores kept (for ranking)."""
    whole_box = replace(
        candidate.whole_box,
        R_cam_from_local=pose[0],
        t_cam_from_local=pose[1],
        camera_centre=camera_centre(*pose),
    )
    return replace(candidate, whole_box=whole_box, track_ids=track_ids)


@pytest.fixture(scope="module")
def truth_candidate() -> Candidate:
    """Passes 0 and 1 refined from starts 0.3 m / 1 deg off the true pose."""
    pose = true_pose()
    tracks = [track(0, pose), track(1, pose)]
    start = moved(pose, 0.3, 1.0)
    return refine_group(tracks, [hypothesis(0, start), hypothesis(1, start)], scene_of(tracks))


def test_box_error_is_zero_at_the_true_pose_and_grows_away_from_it() -> None:
    pose = true_pose()
    tracks = [track(0, pose), track(1, pose)]
    scene = scene_of(tracks)
    assert box_error(*pose, tracks, scene) < 1e-9
    near, far = (
        box_error(*moved(pose, 0.2, 0.2), tracks, scene),
        box_error(*moved(pose, 1.0, 1.0), tracks, scene),
    )
    assert 1e-3 < near < far
    # Another, larger vehicle's boxes at the reported poses are far from the calibration vehicle's cuboid.
    assert box_error(*pose, [track(0, pose, OTHER_VEHICLE)], scene) > 0.2


def test_trim_drops_the_worst_boxes_and_a_track_left_with_none() -> None:
    pose = true_pose()
    good = track(0, pose)
    bad_rows = [2, 5, 9]
    boxes = good.boxes.copy()
    boxes[bad_rows] += np.array([80.0, 40.0, 80.0, 40.0])  # an occluder or another vehicle's box
    damaged = MatchedTrack(0, good.stamps, boxes, good.poses)
    whole = track(1, pose, OTHER_VEHICLE)  # every box misfits the calibration vehicle (a few of them, so
    other = MatchedTrack(1, whole.stamps[:5], whole.boxes[:5], whole.poses[:5])  # the median stays low)
    scene = scene_of([damaged, other])
    kept = trim([damaged, other], *pose, scene, floor=0.08)
    assert [m.track_id for m in kept] == [0]
    expected = np.setdiff1d(np.arange(len(good.stamps)), bad_rows)
    np.testing.assert_array_equal(kept[0].stamps, good.stamps[expected])
    # The floor keeps boxes whose misfit is below it whatever the median.
    assert len(trim([damaged], *pose, scene, floor=10.0)[0].stamps) == len(good.stamps)


def test_refining_a_group_recovers_the_pose_and_counts_its_traversals(truth_candidate: Candidate) -> None:
    assert truth_candidate.track_ids == (0, 1)
    assert pose_error(truth_candidate, true_pose()) < 1e-3
    assert truth_candidate.box_error_rel < 1e-4
    assert truth_candidate.traversals == 2
    assert len(truth_candidate.track_spans) == 2


def test_candidates_that_agree_are_merged_and_ones_that_do_not_are_kept_apart(
    truth_candidate: Candidate,
) -> None:
    pose = true_pose()
    tracks = [track(0, pose), track(1, pose), track(2, pose)]
    scene = scene_of(tracks)
    third = refine_group([tracks[2]], [hypothesis(2, moved(pose, 0.2, 0.5))], scene)
    hypotheses = {i: hypothesis(i, pose) for i in range(3)}
    merged = merge_agreeing([truth_candidate, third], hypotheses, scene)
    assert [c.track_ids for c in merged] == [(0, 1, 2)]
    assert merged[0].traversals == 3
    assert pose_error(merged[0], pose) < 1e-3
    # The same two with the third's pose 3 m away: no merge, both kept as they were.
    apart = relocated(third, moved(pose, 3.0, 0.0), (2,))
    kept = merge_agreeing([truth_candidate, apart], hypotheses, scene)
    assert sorted(c.track_ids for c in kept) == [(0, 1), (2,)]
    assert any(c is apart for c in kept) and any(c is truth_candidate for c in kept)


def test_a_pair_that_fits_as_well_with_a_different_pose_is_reported_ambiguous(
    truth_candidate: Candidate,
) -> None:
    params = SelectionParams()
    rival = relocated(truth_candidate, moved(true_pose(), 2.0, 0.0), (7, 8))
    best, reason = rank([truth_candidate, rival], params)
    assert best is truth_candidate or best is rival
    assert reason.startswith("ambiguous: tracks ")
    assert "2.00 m" in reason
    # Not ambiguous: a rival that fits clearly worse, one that agrees, one seen on a single traversal.
    worse = replace(
        rival, box_error_rel=2.0 * params.tie_ratio * max(truth_candidate.box_error_rel, params.tie_floor)
    )
    near = relocated(truth_candidate, moved(true_pose(), 0.5, 0.5), (7, 8))
    once = replace(rival, traversals=1)
    for other in (worse, near, once):
        best, reason = rank([truth_candidate, other], params)
        assert (best, reason) == (truth_candidate, "")


def test_ranking_puts_groups_seen_twice_first_then_the_lower_box_error(truth_candidate: Candidate) -> None:
    params = SelectionParams()
    once_better = replace(
        relocated(truth_candidate, moved(true_pose(), 5.0, 3.0), (4,)), traversals=1, box_error_rel=0.0
    )
    assert rank([once_better, truth_candidate], params)[0] is truth_candidate
    better = replace(relocated(truth_candidate, true_pose(), (5, 6)), box_error_rel=-1.0)
    assert rank([truth_candidate, better], params)[0] is better


def test_extension_adds_a_track_the_pose_explains_and_not_one_it_does_not(truth_candidate: Candidate) -> None:
    pose = true_pose()
    explained = track(2, pose)  # the calibration vehicle on another drive-past
    shifted = track(3, pose, offset_m=3.0)  # boxes 3 m from the reported poses: another vehicle
    tracks = [track(0, pose), track(1, pose), explained, shifted]
    scene = scene_of(tracks)
    extended = extend(truth_candidate, scene)
    assert extended.track_ids == (0, 1, 2)
    assert extended.traversals == 3
    assert pose_error(extended, pose) < 1e-3
    # Without the explained track nothing is added: the same candidate comes back.
    assert extend(truth_candidate, scene_of([tracks[0], tracks[1], shifted])) is truth_candidate
    # choose() reports the extension as a stage of its own, and none when nothing was added.
    choice = choose([truth_candidate], scene)
    assert choice.chosen.track_ids == (0, 1, 2) and choice.ambiguity == ""
    assert choice.candidates == (choice.chosen,)
    assert [(r.stage, r.kept) for r in choice.reports] == [("extension", 1)]
    assert choose([truth_candidate], scene_of(tracks[:2])).reports == ()


def test_a_candidate_whose_pose_cannot_explain_one_that_explains_it_is_set_aside(
    truth_candidate: Candidate,
) -> None:
    """Short tracks of the vehicle can fit a wrong pose more closely than long ones fit the right one (an
    unseen scene: 3.6 % against 6.9 %, the wrong pose 23 m off). The right pose reproduces their boxes; the
    wrong one cannot reproduce the right one's: it is set aside before the ranking by box error."""
    pose = true_pose()
    scene = scene_of([track(i, pose) for i in range(4)])
    wrong = replace(relocated(truth_candidate, moved(pose, 4.0, 15.0), (2, 3)), box_error_rel=0.0)
    assert rank([truth_candidate, wrong], scene.selection)[0] is wrong  # by box error alone

    kept, report = set_aside([truth_candidate, wrong], scene)
    assert kept == [truth_candidate]
    assert report is not None and (report.stage, report.kept, report.discarded) == ("set aside", 1, 1)
    assert report.lines()[0].startswith("tracks [2, 3] set aside: the pose of tracks [0, 1] explains")
    choice = choose([wrong, truth_candidate], scene)
    assert choice.chosen.track_ids == (0, 1, 2, 3) and choice.ambiguity == ""  # extended by 2 and 3
    assert pose_error(choice.chosen, pose) < 1e-3
    assert [r.stage for r in choice.reports] == ["set aside", "extension"]

    # Poses that explain each other's boxes set nothing aside (rank's ambiguity rule judges them), nor
    # does a candidate seen on one traversal.
    near = relocated(truth_candidate, moved(pose, 0.05, 0.05), (2, 3))
    assert set_aside([truth_candidate, near], scene) == ([truth_candidate, near], None)
    once = replace(wrong, traversals=1)
    assert set_aside([truth_candidate, once], scene) == ([truth_candidate, once], None)


def test_a_track_seen_at_the_same_time_as_a_member_is_never_added(truth_candidate: Candidate) -> None:
    pose = true_pose()
    explained = track(2, pose)
    # The same boxes stamped within pass 0's time span: the vehicle cannot be in two places.
    overlapping = MatchedTrack(
        9,
        truth_candidate.track_spans[0][0] + (explained.stamps - explained.stamps[0]),
        explained.boxes,
        explained.poses,
    )
    scene = scene_of([track(0, pose), track(1, pose), overlapping])
    assert extend(truth_candidate, scene) is truth_candidate


def test_regrouping_joins_single_track_poses_that_agree() -> None:
    pose = true_pose()
    tracks = [track(i, pose) for i in range(4)]
    scene = scene_of(tracks)
    # Passes 0-2 start near the truth and converge on it; pass 3's hypothesis is of another camera: refined
    # on its own boxes it stays far away (the truth is 5 m / 8 deg off).
    far = moved(pose, 5.0, 8.0)
    hypotheses = [
        hypothesis(0, moved(pose, 0.3, 1.0)),
        hypothesis(1, pose),
        hypothesis(2, moved(pose, -0.3, -1.0)),
    ]
    groups, report = regroup(
        [*hypotheses, hypothesis(3, far)], replace(scene, tracks={**scene.tracks, 3: track(3, far)})
    )
    assert groups == [(0, 1, 2)]
    assert report.stage == "regrouping" and report.kept == 1
    assert report.notes == ("refined hypotheses agree: tracks [0, 1, 2]",)
    groups, report = regroup([hypotheses[0]], scene)
    assert groups == [] and report.notes == ("no two refined hypotheses agree either",)


def test_box_errors_tie_within_the_ratio_or_both_below_the_floor() -> None:
    params = SelectionParams(tie_ratio=1.25, tie_floor=0.002)
    assert fits_as_well(0.05, 0.045, params)  # within 25 %
    assert not fits_as_well(0.06, 0.045, params)
    # Exact boxes: 1e-9 against 1e-10 is rounding, not a worse fit.
    assert fits_as_well(1e-9, 1e-10, params)
    assert fits_as_well(0.0025, 0.0, params)
    assert not fits_as_well(0.003, 0.0, params)
