"""Preview image of a simulated frame: size, the highlighted calibration vehicle, frame choice."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from schemas.common import Box
from schemas.files import GroundTruthFrame
from schemas.messages import DetectionFrame
from sim.errors import SimulationError
from sim.preview import HIGHLIGHT_BGR, busiest_calib_frame, render_preview, write_preview
from sim.simulate import SimulationResult, simulate


@pytest.fixture(scope="module")
def carla() -> SimulationResult:
    return simulate("carla-like", seed=0)


def test_write_preview_draws_the_calibration_vehicle_at_its_box(
    carla: SimulationResult, tmp_path: Path
) -> None:
    path = write_preview(carla, tmp_path / "sub" / "preview.png")
    image = cv2.imread(str(path))
    camera = carla.cameras[0]
    assert image is not None and image.dtype == np.uint8
    assert image.shape == (camera.intrinsics.height, camera.intrinsics.width, 3)

    frames = carla.detections[camera.camera_id]
    index, truth = busiest_calib_frame(
        frames, carla.ground_truth[camera.camera_id].frames, camera.intrinsics.width, camera.intrinsics.height
    )
    assert index is not None and truth is not None and truth.calib_box is not None
    box = frames[index].boxes[truth.calib_box]
    highlight = np.all(image == np.array(HIGHLIGHT_BGR, dtype=np.uint8), axis=2)
    # The 2 px outline of the calibration box (the footprint may cover a little of it).
    x1, y1, x2, y2 = (round(box.x1) - 2, round(box.y1) - 2, round(box.x2) + 3, round(box.y2) + 3)
    on_box = int(highlight[y1:y2, x1:x2].sum()) - int(highlight[y1 + 5 : y2 - 5, x1 + 5 : x2 - 5].sum())
    perimeter = 2 * ((box.x2 - box.x1) + (box.y2 - box.y1))
    assert on_box > perimeter
    # Only there and in the legend's swatch (top-left panel).
    elsewhere = highlight.copy()
    elsewhere[y1:y2, x1:x2] = False
    elsewhere[:300, :900] = False
    assert not elsewhere.any()


def test_preview_is_deterministic_and_rejects_an_unknown_camera(carla: SimulationResult) -> None:
    image = render_preview(carla, carla.cameras[0].camera_id)
    assert np.array_equal(image, render_preview(carla))
    # Not a blank canvas: sky, grass and asphalt at least.
    assert len(np.unique(image[::8, ::8].reshape(-1, 3), axis=0)) > 50
    with pytest.raises(SimulationError, match="camera_id"):
        render_preview(carla, "no-such-camera")


T0 = 1_700_000_000_000_000_000


def _frame(stamp: int, n_boxes: int, at_border: bool = False) -> DetectionFrame:
    boxes = [Box(x1=100.0 + 50 * i, y1=100.0, x2=140.0 + 50 * i, y2=130.0) for i in range(n_boxes)]
    if at_border:
        boxes[0] = Box(x1=0.0, y1=100.0, x2=400.0, y2=300.0)
    return DetectionFrame(camera_id="cam", stamp_ns=T0 + stamp, boxes=boxes)


def test_busiest_frame_with_the_vehicle_is_chosen() -> None:
    frames = [_frame(1, 9), _frame(2, 4), _frame(3, 5, at_border=True), _frame(4, 5), _frame(5, 2)]
    truth = [
        GroundTruthFrame(stamp_ns=T0 + 1),  # busiest overall, but the vehicle is not in it
        GroundTruthFrame(stamp_ns=T0 + 2, calib_box=0),
        GroundTruthFrame(stamp_ns=T0 + 3, calib_box=0),  # as busy as 4, but its box is clipped
        GroundTruthFrame(stamp_ns=T0 + 4, calib_box=0),
        GroundTruthFrame(stamp_ns=T0 + 5, calib_box=1),
    ]
    index, chosen = busiest_calib_frame(frames, truth, 1280, 720)
    assert index == 3 and chosen is not None and chosen.stamp_ns == T0 + 4
    # The vehicle never detected: the busiest frame, without truth.
    none_seen = [GroundTruthFrame(stamp_ns=t.stamp_ns) for t in truth]
    assert busiest_calib_frame(frames, none_seen, 1280, 720) == (0, None)
    assert busiest_calib_frame([], [], 1280, 720) == (None, None)
