"""Rendered camera images: the vehicles' bodies where the camera saw them, every EVERY-th frame, recorded as
foxglove.CompressedImage beside the detections."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from test_simulate import shrink

from daemon.recording import read_images, write_simulation_mcap
from sim.images import render_images
from sim.presets import PRESETS
from sim.simulate import SimulationResult, simulate


@pytest.fixture(scope="module")
def carla() -> SimulationResult:
    return simulate(shrink(PRESETS["carla-like"], routes=("E>W",), traffic=3), seed=2, ideal=True)


def _orange(image: np.ndarray) -> np.ndarray:
    """Pixels of the calibration vehicle's paint (BGR 20, 140, 250), however the sun shades it."""
    b, g, r = (image[:, :, k].astype(int) for k in range(3))
    return np.asarray((r > 120) & (r > 1.4 * g) & (g > 1.8 * b) & (g > 40))


def test_the_calibration_vehicle_is_drawn_inside_its_box(carla: SimulationResult) -> None:
    truth = carla.ground_truth["carla"]
    frames = [i for i, f in enumerate(truth.frames) if f.calib_box is not None and f.gross_error is None]
    assert len(frames) > 20
    wanted = set(frames[:: max(1, len(frames) // 6)])
    checked = 0
    for index, (stamp, image) in enumerate(render_images(carla, "carla")):
        assert stamp == carla.detections["carla"][index].stamp_ns
        if index not in wanted:
            continue
        assert image.shape == (truth.intrinsics.height, truth.intrinsics.width, 3) and image.dtype == np.uint8
        x1, y1, x2, y2 = truth.frames[index].box  # type: ignore[misc]
        v, u = np.nonzero(_orange(image))
        # The ideal world's box is the rectangle of the same cuboid the image shows: its paint lies inside,
        # give or take the anti-aliased edge, and fills a good part of it.
        assert len(u) > 0.2 * (x2 - x1) * (y2 - y1)
        assert u.min() >= x1 - 2 and u.max() <= x2 + 2 and v.min() >= y1 - 2 and v.max() <= y2 + 2
        checked += 1
    assert checked == len(wanted)


def test_every_nth_frame_is_rendered_and_recorded_as_a_compressed_image(
    carla: SimulationResult, tmp_path: Path
) -> None:
    stamps = [f.stamp_ns for f in carla.detections["carla"]]
    every = 50
    path = write_simulation_mcap(carla, tmp_path / "recording.mcap", image_every=every)
    images = read_images([path], carla.rsu_id, "carla", stamps)
    assert sorted(images) == stamps[::every]
    # read_images gives the JPEG data of each recorded foxglove.CompressedImage, by stamp.
    decoded = cv2.imdecode(np.frombuffer(images[stamps[every]], dtype=np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape == (1080, 1920, 3)
    with pytest.raises(ValueError, match="every"):
        next(render_images(carla, "carla", every=0))
