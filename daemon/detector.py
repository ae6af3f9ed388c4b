"""Vehicle boxes from camera images with an ONNX detector (onnxruntime, CPU), for cameras without their own.

Pre-processing (letterbox to the network's fixed input), the three output layouts of the common exports
(YOLOv5 (1, N, 5+C) and YOLOv8 (1, 4+C, N) in network pixels, YOLOX (1, N, 5+C) undecoded, as its
export_onnx.py writes it), per-class non-maximum suppression and the camera's label map; the result is a
DetectionFrame payload in the original image's pixels. `DetectorWorker` runs one camera's detector on its
own thread behind a small queue, so images never block ingest: under load the oldest waiting image is
dropped and counted.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from daemon.clock import Clock
from daemon.images import ImageBgr, ImageError, decode_compressed_image
from daemon.ingest import Counters, RejectLog
from daemon.keys import detections_key, parse_image_key
from pipeline.errors import InputError
from schemas.common import MAX_CLASS_ID
from schemas.config import DaemonConfig, DetectorConfig

log = logging.getLogger(__name__)

Layout = Literal["yolov5", "yolov8", "yolox"]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

PAD_VALUE = 114  # grey of the letterbox borders, as all three families train with
YOLOX_STRIDES = (8, 16, 32)
YOLOX_P6_STRIDES = (8, 16, 32, 64)

# Candidates handed to NMS at most (best scores first): bounds its O(n^2) on an image full of noise.
MAX_NMS_CANDIDATES = 4096


class DetectorError(InputError):
    """The detector model or its configuration cannot be used; names the config field and the file."""


@dataclass(frozen=True, slots=True)
class Letterbox:
    """How an image was placed in the network input: network px = image px * scale + pad."""

    scale_x: float
    scale_y: float
    pad_x: int
    pad_y: int


@dataclass(frozen=True, slots=True)
class Detections:
    """Boxes (N, 4) px x1, y1, x2, y2 in the original image, scores (N,), class ids (N,) of the model."""

    boxes: FloatArray
    scores: FloatArray
    class_ids: IntArray


def letterbox(image: ImageBgr, width: int, height: int, centred: bool) -> tuple[ImageBgr, Letterbox]:
    """Resize keeping the aspect ratio and pad with grey to width x height (network px). YOLOv5/v8 centre
    the image, YOLOX puts it at the top left (`centred` False)."""
    h, w = image.shape[:2]
    scale = min(width / w, height / h)
    new_w, new_h = max(1, min(width, round(w * scale))), max(1, min(height, round(h * scale)))
    resized = image
    if (new_w, new_h) != (w, h):
        resized = np.asarray(
            cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR), dtype=np.uint8
        )
    pad_x, pad_y = ((width - new_w) // 2, (height - new_h) // 2) if centred else (0, 0)
    canvas = np.full((height, width, 3), PAD_VALUE, dtype=np.uint8)
    canvas[pad_y : pad_y + new_h, pad_x : pad_x + new_w] = resized
    # The exact per-axis scale of the rounded size, so boxes map back to the pixel they came from.
    return canvas, Letterbox(new_w / w, new_h / h, pad_x, pad_y)


def network_input(canvas: ImageBgr, layout: Layout) -> npt.NDArray[np.float32]:
    """(H, W, 3) BGR uint8 -> (1, 3, H, W) float32: YOLOv5/v8 RGB in [0, 1], YOLOX BGR in [0, 255]."""
    if layout == "yolox":
        planes = canvas.astype(np.float32)
    else:
        planes = canvas[:, :, ::-1].astype(np.float32) * np.float32(1.0 / 255.0)
    return np.ascontiguousarray(planes.transpose(2, 0, 1)[None])


def decode_output(
    output: npt.NDArray[np.floating], layout: Layout, input_width: int, input_height: int
) -> tuple[FloatArray, FloatArray, IntArray]:
    """A model's first output -> (boxes (N, 4) network px x1, y1, x2, y2, best class score (N,), class (N,)).

    yolov5: (1, N, 5+C) cx, cy, w, h, objectness, C class scores; score = objectness * class score.
    yolov8: (1, 4+C, N) cx, cy, w, h, C class scores.
    yolox: (1, N, 5+C) like yolov5 but undecoded: cx, cy are offsets in grid cells and w, h logs, per
    stride 8, 16, 32 (64 for P6 models), row-major per level, as YOLOX's demo_postprocess decodes them.
    """
    rows = np.asarray(output, dtype=np.float64)
    if rows.ndim == 3 and rows.shape[0] == 1:
        rows = rows[0]
    if rows.ndim != 2:
        raise DetectorError("detector.layout", f"{layout}: expected a (1, N, K) output, got {output.shape}")
    if layout == "yolov8":
        rows = rows.T
        if rows.shape[1] < 5:
            raise DetectorError("detector.layout", f"yolov8: expected (1, 4+C, N), got {output.shape}")
        class_scores = rows[:, 4:]
    else:
        if rows.shape[1] < 6:
            raise DetectorError("detector.layout", f"{layout}: expected (1, N, 5+C), got {output.shape}")
        class_scores = rows[:, 5:] * rows[:, 4:5]
    centre, size = rows[:, 0:2], rows[:, 2:4]
    if layout == "yolox":
        grid, strides = _yolox_grid(rows.shape[0], input_width, input_height)
        centre = (centre + grid) * strides
        with np.errstate(over="ignore"):
            size = np.exp(size) * strides
    class_ids = np.argmax(class_scores, axis=1).astype(np.int64)
    scores = class_scores[np.arange(len(class_ids)), class_ids]
    boxes = np.concatenate([centre - 0.5 * size, centre + 0.5 * size], axis=1)
    return boxes, scores, class_ids


def _yolox_grid(rows: int, input_width: int, input_height: int) -> tuple[FloatArray, FloatArray]:
    """Cell (x, y) and stride of every output row of an undecoded YOLOX head."""
    for strides in (YOLOX_STRIDES, YOLOX_P6_STRIDES):
        shapes = [(input_height // s, input_width // s) for s in strides]
        if sum(h * w for h, w in shapes) != rows:
            continue
        grids, stride_rows = [], []
        for (h, w), stride in zip(shapes, strides, strict=True):
            ys, xs = np.mgrid[0:h, 0:w]
            grids.append(np.stack([xs.ravel(), ys.ravel()], axis=1))
            stride_rows.append(np.full((h * w, 1), float(stride)))
        return np.concatenate(grids).astype(np.float64), np.concatenate(stride_rows)
    raise DetectorError(
        "detector.layout",
        f"yolox: {rows} output rows match no grid of strides {YOLOX_STRIDES} (or P6) at "
        f"{input_width} x {input_height}; is the model a decoded export (then it is not layout yolox)?",
    )


def nms(boxes: FloatArray, scores: FloatArray, class_ids: IntArray, iou_threshold: float) -> IntArray:
    """Greedy non-maximum suppression within each class: indices kept, best score first.

    boxes (N, 4) px x1, y1, x2, y2; a box is dropped when its IoU with a better box of its class exceeds
    `iou_threshold`."""
    order = np.argsort(-scores, kind="stable")
    # Shifting each class by more than any coordinate span makes boxes of different classes disjoint, so
    # one pass over all boxes suppresses within classes only.
    span = float(np.max(boxes) - np.min(boxes)) + 1.0 if len(boxes) else 0.0
    shifted = boxes + (class_ids * span)[:, None]
    x1, y1, x2, y2 = shifted.T
    areas = np.maximum(x2 - x1, 0.0) * np.maximum(y2 - y1, 0.0)
    keep: list[int] = []
    while order.size:
        best = int(order[0])
        keep.append(best)
        rest = order[1:]
        inter_w = np.maximum(np.minimum(x2[best], x2[rest]) - np.maximum(x1[best], x1[rest]), 0.0)
        inter_h = np.maximum(np.minimum(y2[best], y2[rest]) - np.maximum(y1[best], y1[rest]), 0.0)
        inter = inter_w * inter_h
        union = areas[best] + areas[rest] - inter
        iou = np.where(union > 0.0, inter / np.maximum(union, 1e-12), 0.0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def postprocess(
    boxes: FloatArray,
    scores: FloatArray,
    class_ids: IntArray,
    placement: Letterbox,
    image_width: int,
    image_height: int,
    config: DetectorConfig,
    keep_ids: frozenset[int] | None,
) -> Detections:
    """Threshold, class filter, NMS, then network px -> image px, clipped to the image."""
    mask = np.isfinite(scores) & (scores >= config.score_threshold) & np.all(np.isfinite(boxes), axis=1)
    if keep_ids is not None:
        mask &= np.isin(class_ids, list(keep_ids))
    index = np.flatnonzero(mask)
    if len(index) > MAX_NMS_CANDIDATES:
        index = index[np.argsort(-scores[index], kind="stable")[:MAX_NMS_CANDIDATES]]
    boxes, scores, class_ids = boxes[index], scores[index], class_ids[index]
    kept = nms(boxes, scores, class_ids, config.nms_iou)[: config.max_boxes]
    boxes, scores, class_ids = boxes[kept], scores[kept], class_ids[kept]
    image_boxes = np.empty_like(boxes)
    image_boxes[:, 0::2] = (boxes[:, 0::2] - placement.pad_x) / placement.scale_x
    image_boxes[:, 1::2] = (boxes[:, 1::2] - placement.pad_y) / placement.scale_y
    image_boxes[:, 0::2] = np.clip(image_boxes[:, 0::2], 0.0, float(image_width))
    image_boxes[:, 1::2] = np.clip(image_boxes[:, 1::2], 0.0, float(image_height))
    # A box entirely in the letterbox border clips to nothing: not a detection of this image.
    visible = (image_boxes[:, 2] > image_boxes[:, 0]) & (image_boxes[:, 3] > image_boxes[:, 1])
    return Detections(image_boxes[visible], np.clip(scores[visible], 0.0, 1.0), class_ids[visible])


class OnnxDetector:
    """One camera's ONNX model, loaded once (DetectorError naming `where` if it cannot be used)."""

    def __init__(self, config: DetectorConfig, labels: Mapping[int, str] | None, where: str) -> None:
        import onnxruntime as ort  # 78 MB of native code: loaded only when a camera has a detector

        self.config = config
        self.labels = dict(labels or {})
        self.where = where
        model_path = Path(config.model)
        if not model_path.is_file():
            raise DetectorError(f"{where}.model", f"{model_path}: no such file (models are never downloaded)")
        options = ort.SessionOptions()
        options.intra_op_num_threads = config.threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(
                str(model_path), sess_options=options, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises its own (non-exported) exception types
            raise DetectorError(f"{where}.model", f"{model_path}: not a usable ONNX model: {err}") from err
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise DetectorError(f"{where}.model", f"{model_path}: expected 1 input, found {len(inputs)}")
        shape = inputs[0].shape
        if len(shape) != 4 or not all(isinstance(d, int) for d in shape[1:]) or shape[1] != 3:
            raise DetectorError(
                f"{where}.model",
                f"{model_path}: input {inputs[0].name} has shape {shape}; expected a fixed (1, 3, H, W) "
                "(export the model with a fixed image size)",
            )
        self._input_name = inputs[0].name
        self.input_height, self.input_width = int(shape[2]), int(shape[3])
        self._output_name = self._session.get_outputs()[0].name
        self.keep_ids = self._class_filter(config.classes)

    def _class_filter(self, classes: Sequence[int | str] | None) -> frozenset[int] | None:
        if classes is None:
            return None
        ids: set[int] = set()
        by_name = {name.lower(): class_id for class_id, name in self.labels.items()}
        for index, label in enumerate(classes):
            if isinstance(label, int):
                ids.add(label)
            elif label.lower() in by_name:
                ids.add(by_name[label.lower()])
            else:
                raise DetectorError(
                    f"{self.where}.classes.{index}",
                    f"{label!r} is not a name in the camera's labels (the model outputs ids; labels "
                    "names them)",
                )
        return frozenset(ids)

    def detect(self, image: ImageBgr) -> Detections:
        """Boxes in `image`'s pixels (BGR (H, W, 3) uint8)."""
        layout: Layout = self.config.layout
        canvas, placement = letterbox(image, self.input_width, self.input_height, centred=layout != "yolox")
        (output,) = self._session.run([self._output_name], {self._input_name: network_input(canvas, layout)})
        boxes, scores, class_ids = decode_output(output, layout, self.input_width, self.input_height)
        height, width = image.shape[:2]
        return postprocess(boxes, scores, class_ids, placement, width, height, self.config, self.keep_ids)

    def frame_payload(self, camera_id: str, stamp_ns: int, detections: Detections) -> bytes:
        """A DetectionFrame JSON payload: the label map's name where it has one, else the model's id."""
        boxes = []
        for (x1, y1, x2, y2), score, class_id in zip(
            detections.boxes.tolist(), detections.scores.tolist(), detections.class_ids.tolist(), strict=True
        ):
            name = self.labels.get(class_id)
            # Ids beyond Box.cls's range with no name cannot be sent; they are not a vehicle class anyway.
            if name is None and class_id > MAX_CLASS_ID:
                continue
            boxes.append(
                {
                    "x1": round(x1, 2),
                    "y1": round(y1, 2),
                    "x2": round(x2, 2),
                    "y2": round(y2, 2),
                    "cls": name if name is not None else class_id,
                    "score": round(score, 4),
                }
            )
        # Rounding can close a box thinner than 0.01 px: the frame must stay valid.
        boxes = [b for b in boxes if b["x2"] > b["x1"] and b["y2"] > b["y1"]]
        return json.dumps({"camera_id": camera_id, "stamp_ns": stamp_ns, "boxes": boxes}).encode("utf-8")


Deliver = Callable[[str, bytes, int], None]
"""(detections key, DetectionFrame payload, received_ns): the daemon's ingest entry (its inbox)."""


class DetectorWorker:
    """Runs one camera's detector on its own thread. `offer` (Zenoh's callback thread) never blocks: the
    queue holds `queue_images`; a newer image drops the oldest waiting one (`images.<cam>.dropped`).

    Counters: images.<cam>.received, .detected (frames delivered), .dropped; rejections
    images.rejected.<reason> (decode, size, stamp) with a rate-limited warning naming the field."""

    def __init__(
        self,
        camera_id: str,
        detections_key: str,
        detector: OnnxDetector,
        deliver: Deliver,
        counters: Counters,
        clock: Clock,
        warn_interval_s: float,
        image_size: tuple[int, int] | None = None,
    ) -> None:
        self.camera_id = camera_id
        self._image_size = image_size  # (width, height) of the intrinsics: boxes are in those pixels
        self._key = detections_key
        self._detector = detector
        self._deliver = deliver
        self._counters = counters
        self._rejects = RejectLog(counters, warn_interval_s, clock)  # this thread's own: not shared
        self._queue: deque[tuple[bytes, int]] = deque()
        self._capacity = detector.config.queue_images
        self.max_image_bytes = detector.config.max_image_bytes
        self._cond = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"rsucal-detector-{camera_id}", daemon=True)
        self._received = f"images.{camera_id}.received"
        self._detected = f"images.{camera_id}.detected"
        self._dropped = f"images.{camera_id}.dropped"
        for name in (self._received, self._detected, self._dropped):
            counters.add(name, 0)
        self._last_stamp_ns: int | None = None
        self.failure: str | None = None

    def start(self) -> None:
        self._thread.start()

    def offer(self, payload: bytes, received_ns: int) -> None:
        """Queue an image payload; drops the oldest waiting one when full. Never blocks on the detector."""
        self._counters.add(self._received)
        with self._cond:
            if self._stopping:
                self._counters.add(self._dropped)  # received = detected + dropped + rejected, always
                return
            if len(self._queue) >= self._capacity:
                self._queue.popleft()
                self._counters.add(self._dropped)
            self._queue.append((payload, received_ns))
            self._cond.notify()

    def stop(self, timeout_s: float) -> None:
        """Finish the image in progress, drop the waiting ones (counted), join the thread."""
        with self._cond:
            self._stopping = True
            if self._queue:
                self._counters.add(self._dropped, len(self._queue))
                self._queue.clear()
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("detector of camera %s still busy after %.1f s", self.camera_id, timeout_s)

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._queue and not self._stopping:
                        self._cond.wait()
                    if self._stopping:
                        return
                    payload, received_ns = self._queue.popleft()
                self._process(payload, received_ns)
        except Exception as err:  # a detector bug must be seen, not end the camera's images silently
            self.failure = f"{type(err).__name__}: {err}"
            log.critical("detector of camera %s died", self.camera_id, exc_info=True)

    def _process(self, payload: bytes, received_ns: int) -> None:
        where = f"{self._key.rsplit('/', 1)[0]}/image"
        try:
            decoded = decode_compressed_image(payload)
        except ImageError as err:
            field = err.detail.split(":", 1)[0]
            self._rejects.reject("images", "decode", f"{where}: {err.detail}", field)
            return
        height, width = decoded.image.shape[:2]
        if self._image_size is not None and (width, height) != self._image_size:
            expected = f"{self._image_size[0]} x {self._image_size[1]}"
            self._rejects.reject(
                "images",
                "size",
                f"{where}: data: {width} x {height} px, but the camera's intrinsics are {expected}",
                "data",
            )
            return
        if self._last_stamp_ns is not None and decoded.stamp_ns <= self._last_stamp_ns:
            self._rejects.reject(
                "images",
                "stamp",
                f"{where}: timestamp = {decoded.stamp_ns} is not after the last image's "
                f"{self._last_stamp_ns}",
                "timestamp",
            )
            return
        self._last_stamp_ns = decoded.stamp_ns
        detections = self._detector.detect(decoded.image)
        self._deliver(
            self._key, self._detector.frame_payload(self.camera_id, decoded.stamp_ns, detections), received_ns
        )
        self._counters.add(self._detected)


class ImageRouter:
    """Hands each `rsu/{rsu}/camera/{cam}/image` sample to its camera's DetectorWorker (Zenoh's thread);
    images of cameras without a detector (images.rejected.no_detector) and payloads beyond the camera's
    max_image_bytes (images.rejected.oversized) are counted and warned about."""

    def __init__(
        self, rsu_id: str, workers: Mapping[str, DetectorWorker], counters: Counters, rejects: RejectLog
    ) -> None:
        self._rsu_id = rsu_id
        self._workers = dict(workers)
        self._counters = counters
        self._rejects = rejects
        self._lock = threading.Lock()  # RejectLog is single-threaded; Zenoh may call from several threads

    @property
    def workers(self) -> Mapping[str, DetectorWorker]:
        return self._workers

    def __call__(self, key: str, payload: bytes, received_ns: int) -> None:
        parsed = parse_image_key(key)
        camera_id = parsed[1] if parsed is not None and parsed[0] == self._rsu_id else ""
        worker = self._workers.get(camera_id)
        if worker is not None:
            limit = worker.max_image_bytes
            if len(payload) <= limit:
                worker.offer(payload, received_ns)
                return
            with self._lock:
                self._rejects.reject(
                    "images",
                    "oversized",
                    f"{key}: payload: {len(payload)} bytes exceeds "
                    f"cameras.{camera_id}.detector.max_image_bytes = {limit}",
                    "payload",
                )
            return
        with self._lock:
            self._rejects.reject(
                "images",
                "no_detector",
                f"{key[:160]}: no camera with a detector (cameras with one: "
                f"{', '.join(sorted(self._workers)) or 'none'})",
                "camera_id",
            )


def build_workers(
    config: DaemonConfig, deliver: Deliver, counters: Counters, clock: Clock
) -> dict[str, DetectorWorker]:
    """A DetectorWorker (not started) for every camera with a `detector`; loads every model now, so a bad
    one stops the daemon at start with a DetectorError naming `cameras.<i>.detector.<field>`."""
    workers: dict[str, DetectorWorker] = {}
    for index, camera in enumerate(config.cameras):
        if camera.detector is None:
            continue
        detector = OnnxDetector(camera.detector, camera.labels, where=f"cameras.{index}.detector")
        log.info(
            "camera %s: ONNX detector %s (%s, input %d x %d, %d thread(s))",
            camera.camera_id,
            camera.detector.model,
            camera.detector.layout,
            detector.input_width,
            detector.input_height,
            camera.detector.threads,
        )
        workers[camera.camera_id] = DetectorWorker(
            camera.camera_id,
            detections_key(config.rsu_id, camera.camera_id),
            detector,
            deliver,
            counters,
            clock,
            config.ingest.warn_interval_s,
            image_size=(camera.intrinsics.width, camera.intrinsics.height),
        )
    return workers
