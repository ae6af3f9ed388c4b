"""The ONNX detector path: letterbox, the three output layouts, NMS, labels, the worker's queue, the daemon.

Models are the cell detectors of onnx_models.py (built here, nothing downloaded): a cell's class scores are
its mean red, green, blue, so a solid colour rectangle aligned with the network's 32 px cells is detected as
exactly those cells. The images are 640 x 400 px into a 320 x 256 network: scale 0.5, and YOLOv5/v8 centre
the image (28 px grey above and below) while YOLOX puts it at the top left.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_until
from onnx_models import write_model

from daemon.bus import client_config, query
from daemon.clock import SystemClock
from daemon.detector import (
    DetectorError,
    DetectorWorker,
    OnnxDetector,
    decode_output,
    letterbox,
    nms,
)
from daemon.images import encode_compressed_image
from daemon.ingest import Counters
from daemon.keys import image_key
from daemon.main import Daemon
from daemon.recording import list_recordings, read_window
from schemas.common import CameraIntrinsics, VehicleProfile, decode_json
from schemas.config import CalibrationVehicle, CameraConfig, DaemonConfig, DetectorConfig, ZenohConfig
from schemas.results import Health

T0 = 1_700_000_000_000_000_000
RED, GREEN, BLUE = (0, 0, 255), (0, 255, 0), (255, 0, 0)  # BGR
COCO_LIKE = {0: "car", 1: "truck", 2: "bus"}  # the cell model's red, green, blue


def _image(rectangles: list[tuple[int, int, int, int, tuple[int, int, int]]]) -> np.ndarray:
    image = np.zeros((400, 640, 3), dtype=np.uint8)
    for x1, y1, x2, y2, colour in rectangles:
        image[y1:y2, x1:x2] = colour
    return image


# Network cells (32 px) in image pixels: x = 64 * column; y = 2 * (32 * row - 28) centred, 64 * row top-left.
CENTRED_SCENE = [(128, 72, 256, 136, RED), (448, 200, 512, 264, BLUE)]  # cells (2..3, 2) and (7, 4)
CENTRED_BOXES = [
    ((128.0, 72.0, 192.0, 136.0), 0),
    ((192.0, 72.0, 256.0, 136.0), 0),
    ((448.0, 200.0, 512.0, 264.0), 2),
]
TOP_LEFT_SCENE = [(128, 64, 256, 128, RED), (448, 256, 512, 320, BLUE)]  # cells (2..3, 1) and (7, 4)
TOP_LEFT_BOXES = [
    ((128.0, 64.0, 192.0, 128.0), 0),
    ((192.0, 64.0, 256.0, 128.0), 0),
    ((448.0, 256.0, 512.0, 320.0), 2),
]
SCENES = {
    "yolov5": (CENTRED_SCENE, CENTRED_BOXES),
    "yolov8": (CENTRED_SCENE, CENTRED_BOXES),
    "yolox": (TOP_LEFT_SCENE, TOP_LEFT_BOXES),
}


def _detector_config(model: Path, layout: str, **changes: object) -> DetectorConfig:
    # 0.5: the letterbox's grey (114/255 = 0.45 in every class) fills at most 28 of a border cell's 32 rows.
    fields = {"model": model, "layout": layout, "score_threshold": 0.5, **changes}
    return DetectorConfig.model_validate(fields)


def _sorted(boxes: np.ndarray, classes: np.ndarray) -> list[tuple[tuple[float, ...], int]]:
    return sorted((tuple(float(v) for v in box), int(c)) for box, c in zip(boxes, classes, strict=True))


@pytest.mark.parametrize("layout", ["yolov5", "yolov8", "yolox"])
def test_each_layout_finds_the_coloured_cells_in_image_pixels(tmp_path: Path, layout: str) -> None:
    scene, expected = SCENES[layout]
    detector = OnnxDetector(_detector_config(write_model(tmp_path / "m.onnx", layout), layout), None, "d")
    assert (detector.input_width, detector.input_height) == (320, 256)
    found = detector.detect(_image(scene))
    assert _sorted(found.boxes, found.class_ids) == sorted(expected)
    assert np.allclose(found.scores, 1.0)


@pytest.mark.parametrize("layout", ["yolov5", "yolov8"])
def test_nms_removes_the_larger_duplicates_and_keeps_neighbours(tmp_path: Path, layout: str) -> None:
    model = write_model(tmp_path / "m.onnx", layout)
    kept = OnnxDetector(_detector_config(model, layout), None, "d").detect(_image(CENTRED_SCENE))
    # With NMS off (IoU threshold 1.0) each cell's 1.25x box (score 0.9) comes back too.
    loose_detector = OnnxDetector(_detector_config(model, layout, nms_iou=1.0), None, "d")
    loose = loose_detector.detect(_image(CENTRED_SCENE))
    assert len(kept.boxes) == 3 and len(loose.boxes) == 6
    assert sorted(loose.scores.round(6).tolist()) == [0.9] * 3 + [1.0] * 3
    # The duplicates are 1.25x the cell about the same centre: 80 x 80 image px.
    duplicates = loose.boxes[np.isclose(loose.scores, 0.9)]
    assert np.allclose(duplicates[:, 2] - duplicates[:, 0], 80.0)


def test_labels_name_the_classes_and_classes_filters_them(tmp_path: Path) -> None:
    model = write_model(tmp_path / "m.onnx", "yolov8")
    detector = OnnxDetector(_detector_config(model, "yolov8", classes=["car"]), COCO_LIKE, "d")
    payload = json.loads(detector.frame_payload("cam", T0, detector.detect(_image(CENTRED_SCENE))))
    assert payload["camera_id"] == "cam" and payload["stamp_ns"] == T0
    assert sorted((b["x1"], b["y1"], b["x2"], b["y2"], b["cls"]) for b in payload["boxes"]) == [
        (128.0, 72.0, 192.0, 136.0, "car"),
        (192.0, 72.0, 256.0, 136.0, "car"),
    ]
    # Without labels the model's ids are sent; an id filter works without labels.
    plain = OnnxDetector(_detector_config(model, "yolov8", classes=[2]), None, "d")
    payload = json.loads(plain.frame_payload("cam", T0, plain.detect(_image(CENTRED_SCENE))))
    assert [(b["x1"], b["cls"]) for b in payload["boxes"]] == [(448.0, 2)]


def test_letterbox_places_and_scales_the_image() -> None:
    image = np.full((400, 640, 3), 7, dtype=np.uint8)
    canvas, placement = letterbox(image, 320, 256, centred=True)
    assert (placement.scale_x, placement.scale_y, placement.pad_x, placement.pad_y) == (0.5, 0.5, 0, 28)
    assert (canvas[:28] == 114).all() and (canvas[28:228] == 7).all() and (canvas[228:] == 114).all()
    canvas, placement = letterbox(image, 320, 256, centred=False)
    assert (placement.pad_x, placement.pad_y) == (0, 0)
    assert (canvas[:200] == 7).all() and (canvas[200:] == 114).all()
    # Portrait: pillarboxed.
    canvas, placement = letterbox(np.zeros((640, 400, 3), np.uint8), 256, 320, centred=True)
    assert (placement.scale_x, placement.pad_x, placement.pad_y) == (0.5, 28, 0)


def test_nms_per_class() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [20, 20, 30, 30]], dtype=np.float64)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    # Box 1 overlaps box 0 (IoU 0.68, same class): gone. Box 2 is box 0 but another class: kept.
    assert nms(boxes, scores, np.array([0, 0, 1, 0]), 0.5).tolist() == [0, 2, 3]
    assert nms(boxes, scores, np.array([0, 0, 1, 0]), 0.7).tolist() == [0, 1, 2, 3]
    assert nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), 0.5).tolist() == []


def test_bad_outputs_and_models_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(DetectorError, match=r"detector.layout: yolov8: expected \(1, 4\+C, N\)"):
        decode_output(np.zeros((1, 3, 10)), "yolov8", 320, 256)
    with pytest.raises(DetectorError, match="yolox: 7 output rows match no grid"):
        decode_output(np.zeros((1, 7, 8)), "yolox", 320, 256)
    with pytest.raises(DetectorError, match=r"cameras.0.detector.model: .*absent.onnx: no such file"):
        OnnxDetector(_detector_config(tmp_path / "absent.onnx", "yolov5"), None, "cameras.0.detector")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(DetectorError, match=r"garbage\.onnx: not a usable ONNX model"):
        OnnxDetector(_detector_config(garbage, "yolov5"), None, "cameras.0.detector")
    model = write_model(tmp_path / "m.onnx", "yolov5")
    with pytest.raises(DetectorError, match=r"cameras.0.detector.classes.1: 'van' is not a name"):
        config = _detector_config(model, "yolov5", classes=["car", "van"])
        OnnxDetector(config, COCO_LIKE, "cameras.0.detector")


class _Gate:
    """A deliver() that holds the worker on its first frame until released, recording what arrives."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.frames: list[dict[str, object]] = []

    def __call__(self, key: str, payload: bytes, received_ns: int) -> None:
        self.entered.set()
        self.release.wait(10)
        self.frames.append(json.loads(payload))


def test_worker_drops_the_oldest_images_under_load_and_counts_bad_ones(tmp_path: Path) -> None:
    config = _detector_config(write_model(tmp_path / "m.onnx", "yolov5"), "yolov5", queue_images=2)
    counters, gate = Counters(), _Gate()
    key = "rsu/r1/camera/cam/detections"
    detector = OnnxDetector(config, None, "d")
    worker = DetectorWorker("cam", key, detector, gate, counters, SystemClock(), 10.0, image_size=(640, 400))
    image = _image(CENTRED_SCENE)
    worker.start()
    try:
        worker.offer(encode_compressed_image(image, T0, "cam"), 1)
        assert gate.entered.wait(10)  # the worker is busy with image 0
        for i in range(1, 11):  # 10 more while it is busy: only the newest 2 can wait
            worker.offer(encode_compressed_image(image, T0 + i, "cam"), 1)
        assert counters.get("images.cam.dropped") == 8
        gate.release.set()
        wait_until(lambda: counters.get("images.cam.detected") == 3)
        # One at a time (the queue holds 2): each bad image is counted under its reason, then a good one.
        bad = [
            (b"\x00garbage", "decode"),
            (encode_compressed_image(image[:200], T0 + 15, "cam"), "size"),  # not the intrinsics' size
            (encode_compressed_image(image, T0 + 5, "cam"), "stamp"),  # older than the last delivered
        ]
        for payload, reason in bad:
            worker.offer(payload, 1)
            wait_until(lambda reason=reason: counters.get(f"images.rejected.{reason}") == 1)
        worker.offer(encode_compressed_image(image, T0 + 20, "cam", image_format="png"), 1)
        wait_until(lambda: counters.get("images.cam.detected") == 4)
    finally:
        worker.stop(timeout_s=5)
    assert [frame["stamp_ns"] for frame in gate.frames] == [T0, T0 + 9, T0 + 10, T0 + 20]
    assert all(len(frame["boxes"]) == 3 for frame in gate.frames)  # type: ignore[arg-type]
    assert counters.get("images.rejected.decode") == 1 and counters.get("images.rejected.stamp") == 1
    assert counters.get("images.rejected.size") == 1
    assert counters.get("images.cam.received") == 15


def _daemon_config(tmp_path: Path, port: int, model: Path) -> DaemonConfig:
    intrinsics = CameraIntrinsics(width=640, height=400, fx=500.0, fy=500.0, cx=320.0, cy=200.0)
    return DaemonConfig(
        rsu_id="r1",
        crs="EPSG:32632",
        zenoh=ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]),
        cameras=[
            CameraConfig(
                camera_id="cam",
                intrinsics=intrinsics,
                labels=COCO_LIKE,
                detector=_detector_config(model, "yolov8", classes=["car", "bus"], max_image_bytes=64 * 1024),
            ),
            CameraConfig(camera_id="plain", intrinsics=intrinsics),
        ],
        vehicles=[
            CalibrationVehicle(
                station_id=4242,
                profile=VehicleProfile(length=4.8, width=1.85, height=1.5, imu_offset=(1.5, 0.9, 0.3)),
            )
        ],
        storage={"state_dir": tmp_path / "state"},  # type: ignore[arg-type]
    )


def test_daemon_detects_images_from_the_bus_and_records_the_frames(tmp_path: Path) -> None:
    port = free_port()
    config = _daemon_config(tmp_path, port, write_model(tmp_path / "m.onnx", "yolov8"))
    daemon = Daemon(config)
    client: zenoh.Session | None = None
    stamps = [T0 + i * 100_000_000 for i in range(5)]

    def health() -> Health | None:
        assert client is not None
        replies = query(client, "rsu/r1/health", 2.0)
        return decode_json(Health, replies[0][1]) if replies else None

    try:
        daemon.start()
        client = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
        remote: list[bytes] = []  # what another session sees of the daemon's detections
        watcher = client.declare_subscriber(
            "rsu/r1/camera/cam/detections", lambda sample: remote.append(sample.payload.to_bytes())
        )
        publisher = client.declare_publisher(
            image_key("r1", "cam"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        wait_until(lambda: _matched(publisher))
        for stamp_ns in stamps:
            publisher.put(encode_compressed_image(_image(CENTRED_SCENE), stamp_ns, "cam"))
            # One at a time: the test is about what arrives, not about dropping (tested above).
            wait_until(lambda s=stamp_ns: daemon.counters.get("detections.accepted") == stamps.index(s) + 1)
        client.put(image_key("r1", "cam"), b'{"timestamp": 5}')  # bad: counted, named
        client.put(image_key("r1", "cam"), b"\0" * (64 * 1024 + 1))  # beyond max_image_bytes
        client.put(image_key("r1", "plain"), encode_compressed_image(_image([]), T0, "plain"))  # no detector
        wait_until(lambda: (h := health()) is not None and h.counters.get("images.rejected.no_detector") == 1)
        wait_until(lambda: (h := health()) is not None and h.counters.get("images.rejected.decode") == 1)
        wait_until(lambda: (h := health()) is not None and h.counters.get("images.rejected.oversized") == 1)
        wait_until(lambda: len(remote) == 5)
        counters = health().counters  # type: ignore[union-attr]
        assert counters["images.cam.received"] == 6 and counters["images.cam.detected"] == 5
        # Published for others, ingested once: the daemon's own subscriber did not take them in again.
        assert counters["detections.accepted"] == 5 and counters["detections.received"] == 5
        assert [json.loads(p)["stamp_ns"] for p in remote] == stamps
        publisher.undeclare()
        watcher.undeclare()
    finally:
        if client is not None:
            client.close()  # type: ignore[no-untyped-call]
        daemon.stop()
    files = [f.path for f in list_recordings(tmp_path / "state" / "recordings", "r1")]
    window = read_window(files, "r1", "cam", set(), 0, 2**62)
    assert [frame.stamp_ns for frame in window.detections] == stamps
    for frame in window.detections:
        assert sorted((b.x1, b.y1, b.x2, b.y2, b.cls) for b in frame.boxes) == [
            (128.0, 72.0, 192.0, 136.0, "car"),
            (192.0, 72.0, 256.0, 136.0, "car"),
            (448.0, 200.0, 512.0, 264.0, "bus"),
        ]


def _matched(publisher: zenoh.Publisher) -> bool:
    status = publisher.matching_status
    return bool(status.matching)


def test_daemon_refuses_a_missing_model_before_starting(tmp_path: Path) -> None:
    config = _daemon_config(tmp_path, free_port(), tmp_path / "absent.onnx")
    daemon = Daemon(config)
    with pytest.raises(DetectorError, match=r"cameras.0.detector.model: .*absent.onnx"):
        daemon.start()
    daemon.stop()
    assert list_recordings(tmp_path / "state" / "recordings", "r1") == []


def test_the_benchmark_backbone_leaves_the_detections_unchanged(tmp_path: Path) -> None:
    # bench.daemon's detector part times this model; its detections must still be the cell detector's.
    model = write_model(tmp_path / "m.onnx", "yolov8", backbone=True)
    found = OnnxDetector(_detector_config(model, "yolov8"), None, "d").detect(_image(CENTRED_SCENE))
    assert _sorted(found.boxes, found.class_ids) == sorted(CENTRED_BOXES)
