"""pipeline.final_fit on a small exact scene: the drive-passes it reports are those it could check."""

from __future__ import annotations

import numpy as np
import pytest
from test_selection import CAMERA, FRAME_NS, PATHS, VEHICLE, hypothesis, poses_along, true_pose

from pipeline.association import MatchedTrack, Trajectory
from pipeline.camera import project_points
from pipeline.final_fit import final_fit, joint_fit
from pipeline.refinement import RefinementParams
from pipeline.selection import Scene, SelectionParams, refine_group
from pipeline.validation import count_traversals
from pipeline.vehicle import body_corners
from pipeline.vehicle_model import ModelParams

START_NS = 1_700_000_000_000_000_000
TAIL = 15  # rows (1.5 s) of each drive kept beyond the view: the vehicle is out of view 3 s between them


def _visible(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, t = true_pose()
    pixels, depth = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, t, CAMERA)
    uv = pixels.reshape(len(poses), 8, 2)
    boxes = np.column_stack([uv[:, :, 0].min(1), uv[:, :, 1].min(1), uv[:, :, 0].max(1), uv[:, :, 1].max(1)])
    keep = np.all(depth.reshape(len(poses), 8) > 1.0, axis=1)
    keep &= (boxes[:, 0] > 2) & (boxes[:, 1] > 2) & (boxes[:, 2] < CAMERA.width - 2)
    keep &= boxes[:, 3] < CAMERA.height - 2
    return boxes, keep


def _scene(pause_s: float) -> tuple[Scene, list[MatchedTrack]]:
    """Two drive-pasts across the view (PATHS 0 and 2), each cut `TAIL` rows beyond the view, the second
    starting `pause_s` after the first ends; exact cuboid boxes."""
    drives = []
    for path, cut in ((PATHS[0], slice(None, 92 + TAIL)), (PATHS[2], slice(49 - TAIL, None))):
        drives.append(poses_along(path)[cut])
    first_ns = START_NS + FRAME_NS * np.arange(len(drives[0]), dtype=np.int64)
    second_start = int(first_ns[-1]) + round(pause_s * 1e9)
    second_ns = second_start + FRAME_NS * np.arange(len(drives[1]), dtype=np.int64)
    tracks = []
    for index, (poses, stamps) in enumerate(zip(drives, (first_ns, second_ns), strict=True)):
        boxes, keep = _visible(poses)
        tracks.append(MatchedTrack(index, stamps[keep], boxes[keep], poses[keep]))
    trajectory = Trajectory(np.concatenate([first_ns, second_ns]), np.concatenate(drives))
    scene = Scene(
        {m.track_id: m for m in tracks}, trajectory, CAMERA, VEHICLE, RefinementParams(), SelectionParams()
    )
    return scene, tracks


@pytest.mark.parametrize(("pause_s", "expected"), [(0.1, 1), (60.0, 2)])
def test_drive_pasts_count_only_as_far_as_the_leave_one_out_check_tells_them_apart(
    pause_s: float, expected: int
) -> None:
    scene, tracks = _scene(pause_s)
    pose = true_pose()
    gap_s = (tracks[1].stamps[0] - tracks[0].stamps[-1]) / 1e9
    # The vehicle is out of view for 3 s or more between the tracks: two drive-pasts by the view alone.
    assert gap_s >= 3.0
    spans = [(int(t.stamps[0]), int(t.stamps[-1])) for t in tracks]
    assert count_traversals(spans, scene.trajectory.stamps, scene.trajectory.poses, *pose, CAMERA) == 2
    candidate = refine_group(tracks, [hypothesis(0, pose), hypothesis(1, pose)], scene)
    model = ModelParams()
    final = final_fit(joint_fit(candidate, scene, model, 0.01), scene, model, 0.9)
    # 3 s apart the two are one cluster of the leave-one-out check (TRAVERSAL_GAP_S, 5 s): nothing held them
    # against each other, so they count once (and validation refuses); a minute apart they count twice.
    assert final.traversals == expected
    assert np.linalg.norm(final.fit.camera_centre - np.array([0.0, 0.0, 10.0])) < 1e-3
