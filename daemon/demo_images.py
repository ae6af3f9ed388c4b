"""`rsucal demo --images`: the simulated cameras send images, the daemon's ONNX detector makes the boxes.

A separate process re-runs the (deterministic) simulation and renders every frame of every camera
(sim.images, JPEG in foxglove.CompressedImage), in stamp order, into a bounded queue; the demo's RSU puts
each image on `rsu/{rsu}/camera/{cam}/image` in place of the simulator's boxes. The daemon decodes it,
runs the camera's detector and puts the DetectionFrame on `.../detections`, where the demo hears it.

Rendering and detecting an image takes tens of milliseconds, so the replay cannot keep a fixed time
scale: it goes as fast as the detector answers. A camera's next image is put once the detector's frame of
its previous one came back (or IMAGE_ANSWER_TIMEOUT_S passed), and the daemon's clock is a ReplayClock
that shows the stamp of the last message put, so quiet periods, traversals and timeouts see the scene's
own time whatever the machine's speed; after the last message it runs `rate` times faster than real time.
"""

from __future__ import annotations

import heapq
import json
import multiprocessing
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import zenoh

from daemon.keys import image_key, parse_detections_key, parse_image_key
from pipeline.errors import InputError
from schemas.config import DetectorConfig

# An image the detector has not answered after this long (real seconds) is given up on: the next is put.
IMAGE_ANSWER_TIMEOUT_S = 10.0
RENDER_QUEUE_IMAGES = 8  # rendered images waiting to be put (~150 kB each)
RENDER_TIMEOUT_S = 120.0  # the first image may wait for the renderer's own simulation run
JPEG_QUALITY = 90
# The simulator's key colours are the key detector's classes 0-3: all vehicles.
KEY_LABELS = {0: "car", 1: "car", 2: "car", 3: "car"}
# An operator's model is taken to be trained on COCO (YOLOv5/v8/X exports are): its vehicle classes.
COCO_LABELS = {2: "car", 3: "motorcycle", 5: "bus", 7: "truck"}
COCO_VEHICLES: list[int | str] = ["car", "bus", "truck"]

Layout = Literal["yolov5", "yolov8", "yolox"]


@dataclass(frozen=True, slots=True)
class ImageSetup:
    """What `--images` gives every camera: a detector config, its label map, and how images are painted
    (keyed: the key colours of sim.key_detector's model; else the ordinary paints a real model expects)."""

    detector: DetectorConfig
    labels: dict[int, str]
    keyed: bool

    @property
    def description(self) -> str:
        if self.keyed:
            return (
                "the simulator's colour-key detector (sim/models/key_detector.onnx: vehicles found by their "
                "key paint, not a learned model)"
            )
        return f"{self.detector.model} ({self.detector.layout}, COCO classes car, bus, truck)"


def image_setup(model: Path | None, layout: Layout = "yolov8") -> ImageSetup:
    """The key detector without `model`; else the operator's model (InputError naming --detector-model)."""
    if model is None:
        from sim.key_detector import KEY_DETECTOR_MODEL

        return ImageSetup(DetectorConfig(model=KEY_DETECTOR_MODEL, layout="yolov8"), KEY_LABELS, keyed=True)
    model = Path(model)
    if not model.is_file():
        raise InputError("--detector-model", f"{model}: no such file (models are never downloaded)")
    config = DetectorConfig(model=model.resolve(), layout=layout, classes=COCO_VEHICLES)
    return ImageSetup(config, COCO_LABELS, keyed=False)


class ReplayClock:
    """The daemon's clock during an image replay: `now_ns` is the stamp of the last message put
    (`advance`), never earlier than `start_ns`; after `release()` it runs `rate` times faster than the
    monotonic clock from there. Readers on other threads see one consistent value (a single attribute)."""

    def __init__(self, start_ns: int, rate: float = 1.0) -> None:
        if not rate > 0.0:
            raise ValueError(f"rate = {rate} must be positive")
        self.start_ns = start_ns
        self.rate = rate
        self._now_ns = start_ns
        self._released: tuple[int, int] | None = None  # (monotonic ns, clock ns) at release

    def now_ns(self) -> int:
        released = self._released
        if released is None:
            return self._now_ns
        monotonic_ns, base_ns = released
        return base_ns + int((time.monotonic_ns() - monotonic_ns) * self.rate)

    def advance(self, stamp_ns: int) -> None:
        if self._released is None and stamp_ns > self._now_ns:
            self._now_ns = stamp_ns

    def release(self) -> None:
        if self._released is None:
            self._released = (time.monotonic_ns(), self._now_ns)

    @property
    def released(self) -> bool:
        return self._released is not None


class DetectorAnswers:
    """The stamps of the DetectionFrames the daemon's detectors put on the bus, newest per camera."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._latest: dict[str, int] = {}
        self.frames = 0
        self.boxes = 0

    def on_sample(self, sample: zenoh.Sample) -> None:
        parsed = parse_detections_key(str(sample.key_expr))
        if parsed is None:
            return
        camera_id = parsed[1]
        try:
            frame = json.loads(sample.payload.to_bytes())
            stamp_ns, boxes = int(frame["stamp_ns"]), len(frame["boxes"])
        except (ValueError, KeyError, TypeError):
            return
        with self._cond:
            self._latest[camera_id] = max(stamp_ns, self._latest.get(camera_id, stamp_ns))
            self.frames += 1
            self.boxes += boxes
            self._cond.notify_all()

    def wait(self, camera_id: str, stamp_ns: int, timeout_s: float, stop: threading.Event) -> bool:
        """Until the frame of the image stamped `stamp_ns` (or a later one) came back; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._latest.get(camera_id, -1) < stamp_ns:
                remaining = deadline - time.monotonic()
                if remaining <= 0.0 or stop.is_set():
                    return False
                self._cond.wait(min(remaining, 0.5))
            return True


def _render_process(
    preset: Any, seed: int, ideal: bool, keyed: bool, out: Any, stop: Any
) -> None:  # pragma: no cover - runs in the child process (covered through run_demo)
    """Child process: simulate (the same scene as the parent: deterministic), then put (key, stamp,
    CompressedImage payload) of every frame of every camera, stamp order, and None at the end."""
    try:
        from daemon.images import encode_compressed_image
        from sim.simulate import simulate

        sim = simulate(preset, seed, ideal=ideal)
        streams = [_frames(sim, camera.camera_id, keyed) for camera in sim.cameras]
        for stamp, key, camera_id, image in heapq.merge(*streams, key=lambda item: (item[0], item[1])):
            payload = encode_compressed_image(image, stamp, camera_id, "jpeg", jpeg_quality=JPEG_QUALITY)
            if not _put(out, (key, stamp, payload), stop):
                return
        _put(out, None, stop)
    except Exception as err:
        _put(out, ("error", f"{type(err).__name__}: {err}"), stop)


def _frames(sim: Any, camera_id: str, keyed: bool) -> Iterator[tuple[int, str, str, Any]]:
    """(stamp_ns, image key, camera id, BGR image) of every frame of one camera."""
    from sim.images import render_images

    key = image_key(sim.rsu_id, camera_id)
    for stamp_ns, image in render_images(sim, camera_id, 1, keyed=keyed):
        yield stamp_ns, key, camera_id, image


def _put(out: Any, item: Any, stop: Any) -> bool:
    while not stop.is_set():
        try:
            out.put(item, timeout=0.5)
            return True
        except queue.Full:
            continue
    return False


class RenderedImages:
    """The renderer process and its queue; iterate for (key, stamp_ns, payload) in stamp order."""

    def __init__(self, preset: Any, seed: int, ideal: bool, keyed: bool) -> None:
        # spawn: the parent runs Zenoh's and the daemon's threads, which a fork must not copy.
        context = multiprocessing.get_context("spawn")
        self._queue: Any = context.Queue(maxsize=RENDER_QUEUE_IMAGES)
        self._stop: Any = context.Event()
        self._process = context.Process(
            target=_render_process,
            args=(preset, seed, ideal, keyed, self._queue, self._stop),
            name="rsucal-demo-render",
            daemon=True,
        )
        self.rendered = 0

    def start(self) -> None:
        self._process.start()

    def images(self, stop: threading.Event) -> Iterator[tuple[str, int, bytes]]:
        """(key, stamp_ns, payload) in stamp order until the last, or until `stop` is set."""
        while not stop.is_set():
            deadline = time.monotonic() + RENDER_TIMEOUT_S
            while True:
                try:
                    item = self._queue.get(timeout=0.5)
                    break
                except queue.Empty:
                    if stop.is_set():
                        return
                    if time.monotonic() > deadline or not self._process.is_alive():
                        raise RuntimeError(
                            f"the renderer sent no image for {RENDER_TIMEOUT_S:.0f} s"
                            if self._process.is_alive()
                            else f"the renderer ended (exit code {self._process.exitcode})"
                        ) from None
            if item is None:
                return
            if item[0] == "error":
                raise RuntimeError(f"rendering the camera images failed: {item[1]}")
            self.rendered += 1
            yield item

    def close(self) -> None:
        self._stop.set()
        # Unblock a child waiting on a full queue, then end it.
        with_timeout = time.monotonic() + 5.0
        while self._process.is_alive() and time.monotonic() < with_timeout:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                self._process.join(0.1)
        if self._process.is_alive():
            self._process.terminate()
        self._process.join(5.0)
        self._queue.close()
        self._queue.join_thread()


@dataclass(slots=True)
class ImageReplay:
    """What the image replay did: images put, and those whose detector frame never came back."""

    images: int = 0
    unanswered: int = 0
    error: str | None = None


def publish_with_images(
    session: zenoh.Session,
    messages: list[Any],
    clock: ReplayClock,
    stop: threading.Event,
    rendered: RenderedImages,
    answers: DetectorAnswers,
    stats: ImageReplay,
) -> None:
    """Put each message in stamp order, the clock following; an image (a message on an image key, its
    payload empty: the renderer has it) only once the detector answered the camera's previous image."""
    publishers: dict[str, zenoh.Publisher] = {}
    last_image: dict[str, int] = {}
    stream = rendered.images(stop)
    encoding = zenoh.Encoding.APPLICATION_PROTOBUF.with_schema("foxglove.CompressedImage")
    try:
        for message in messages:
            if stop.is_set():
                return
            payload = message.payload
            image = parse_image_key(message.key)
            if image is not None:
                key, stamp_ns, payload = next(stream)
                if (key, stamp_ns) != (message.key, message.stamp_ns):
                    raise RuntimeError(f"renderer out of step: {key} {stamp_ns} for {message.key}")
                camera_id = image[1]
                previous = last_image.get(camera_id)
                if previous is not None and not answers.wait(
                    camera_id, previous, IMAGE_ANSWER_TIMEOUT_S, stop
                ):
                    stats.unanswered += 1
                last_image[camera_id] = stamp_ns
                stats.images += 1
            clock.advance(message.stamp_ns)
            publisher = publishers.get(message.key)
            if publisher is None:
                publisher = publishers[message.key] = session.declare_publisher(
                    message.key,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    encoding=encoding if image is not None else None,
                )
            publisher.put(payload)
        for camera_id, stamp_ns in last_image.items():
            if not answers.wait(camera_id, stamp_ns, IMAGE_ANSWER_TIMEOUT_S, stop):
                stats.unanswered += 1
    except (RuntimeError, StopIteration) as err:
        stats.error = str(err) or "the renderer stopped early"
    finally:
        clock.release()
        for publisher in publishers.values():
            publisher.undeclare()  # type: ignore[no-untyped-call]
