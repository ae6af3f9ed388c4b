"""The colour-key ONNX detector (sim/key_detector.py) through the daemon's own detector code (onnxruntime,
letterbox, YOLOv8 decoding, NMS): the shipped file is what the code builds, every key paint is found as
its class however it is shaded, nothing of the scene's background is, areas become one box each, and the
calibration vehicle of a keyed rendered frame is found where the truth says."""

from __future__ import annotations

import numpy as np
import pytest
from test_simulate import shrink

from daemon.detector import OnnxDetector
from daemon.images import decode_compressed_image, encode_compressed_image
from schemas.config import DetectorConfig
from sim import preview
from sim.images import KEY_PAINTS, KEY_WHEEL_SHADE, render_images
from sim.key_detector import KEY_CLASSES, KEY_DETECTOR_MODEL, build_model, model_bytes
from sim.presets import PRESETS
from sim.simulate import simulate

W, H = 1920, 1200  # the sil presets' cameras: network 960 x 608 at scale 0.5


@pytest.fixture(scope="module")
def detector() -> OnnxDetector:
    return OnnxDetector(DetectorConfig(model=KEY_DETECTOR_MODEL, layout="yolov8"), None, "test")


def _scene() -> np.ndarray:
    """Sky, grass, road, markings and occluders in sim.preview's colours: what surrounds the vehicles."""
    image = np.empty((H, W, 3), dtype=np.uint8)
    image[: H // 3] = preview.SKY_ZENITH_BGR
    image[H // 3 : H // 2] = preview.SKY_HORIZON_BGR
    image[H // 2 :] = preview.GRASS_BGR
    image[H // 2 + 100 :, 200:1700] = preview.ASPHALT_BGR
    image[H // 2 + 300 : H // 2 + 310, 200:1700] = preview.LANE_CENTRE_BGR
    image[H // 2 + 400 : H // 2 + 410, 200:1700] = preview.ROAD_EDGE_BGR
    image[H // 2 + 200 : H // 2 + 240, 100:1800] = preview.HAZE_BGR
    image[300:900, 1820:1850] = preview.OCCLUDER_BGR["pole"]
    image[200:500, 40:140] = preview.OCCLUDER_BGR["crown"]
    image[500:900, 80:100] = preview.OCCLUDER_BGR["trunk"]
    image[100:200, 1500:1600] = preview.JUNCTION_CENTRE_BGR
    image[150:250, 1650:1750] = preview.OTHER_OCCLUDER_BGR
    return image


def _jpeg_round_trip(image: np.ndarray) -> np.ndarray:
    return decode_compressed_image(encode_compressed_image(image, 10**18, "c", "jpeg")).image


def test_the_shipped_model_is_what_the_code_builds() -> None:
    assert KEY_DETECTOR_MODEL.read_bytes() == model_bytes()
    output = build_model().graph.output[0].type.tensor_type.shape.dim
    assert [d.dim_value for d in output] == [1, 4 + len(KEY_CLASSES), len(KEY_CLASSES) * 76 * 120]


def test_the_background_alone_is_no_vehicle(detector: OnnxDetector) -> None:
    found = detector.detect(_jpeg_round_trip(_scene()))
    assert len(found.boxes) == 0


@pytest.mark.parametrize("shade", [1.0, 0.6, 0.35, 0.35 * KEY_WHEEL_SHADE])
def test_every_key_paint_is_found_as_its_class_however_shaded(detector: OnnxDetector, shade: float) -> None:
    image = _scene()
    # One rectangle per key, on sky, road and grass; edges on even pixels (the network sees every 2nd).
    places = [(100, 40, 300, 160), (600, 700, 860, 860), (1000, 1000, 1180, 1100), (1300, 640, 1500, 760)]
    for (x1, y1, x2, y2), paint in zip(places, KEY_PAINTS, strict=True):
        image[y1:y2, x1:x2] = tuple(round(c * shade) for c in paint)
    found = detector.detect(_jpeg_round_trip(image))
    order = np.argsort(found.class_ids)
    assert found.class_ids[order].tolist() == list(range(len(KEY_PAINTS)))
    assert np.abs(found.boxes[order] - np.array(places, dtype=float)).max() <= 2.0
    assert np.all(found.scores > 0.9)


def test_a_connected_area_is_one_box_and_separate_areas_are_two(detector: OnnxDetector) -> None:
    image = _scene()
    red = KEY_PAINTS[0]
    # An L-shaped area over 60 cells long: the boxes must reach from one end to the other (the Loop).
    image[100:140, 100:1100] = red
    image[100:700, 1060:1100] = red
    image[900:1000, 300:400] = red  # a second area of the same key, far away
    found = detector.detect(_jpeg_round_trip(image))
    boxes = sorted(found.boxes.round().tolist())
    assert boxes == [[100.0, 100.0, 1100.0, 700.0], [300.0, 900.0, 400.0, 1000.0]]


def test_the_calibration_vehicle_of_a_keyed_frame_is_found_at_its_true_box(detector: OnnxDetector) -> None:
    # Little traffic, no occluders: the ideal world's true box is the rectangle of the rendered cuboid.
    config = shrink(PRESETS["carla-like"], routes=("E>W",), traffic=0)
    sim = simulate(config, seed=2, ideal=True)
    truth = sim.ground_truth["carla"]
    # Away from the border: a cuboid cut by the image edge is drawn only where the lens model holds.
    frames = [
        i
        for i, f in enumerate(truth.frames)
        if f.box is not None
        and f.gross_error is None
        and min(f.box[0], f.box[1], truth.intrinsics.width - f.box[2], truth.intrinsics.height - f.box[3])
        > 20
    ]
    wanted = set(frames[:: max(1, len(frames) // 5)])
    ious = []
    for index, (_, image) in enumerate(render_images(sim, "carla", keyed=True)):
        if index not in wanted:
            continue
        x1, y1, x2, y2 = truth.frames[index].box  # type: ignore[misc]
        best = 0.0
        for bx1, by1, bx2, by2 in detector.detect(_jpeg_round_trip(image)).boxes:
            inter = max(0.0, min(x2, bx2) - max(x1, bx1)) * max(0.0, min(y2, by2) - max(y1, by1))
            best = max(best, inter / ((x2 - x1) * (y2 - y1) + (bx2 - bx1) * (by2 - by1) - inter))
        ious.append(best)
    assert len(ious) == len(wanted) >= 4
    assert min(ious) > 0.9, ious
