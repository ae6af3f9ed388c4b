"""`rsucal demo --images`: the simulated camera sends rendered images (foxglove.CompressedImage over Zenoh on
127.0.0.1), the daemon's ONNX detector (the simulator's colour-key model, through onnxruntime) makes every
DetectionFrame, records and publishes it, and the calibration job runs on those frames."""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import threading
from dataclasses import replace
from pathlib import Path

import pytest
from helpers import free_port, wait_until
from mcap.reader import make_reader

from daemon import cli
from daemon.demo import run_demo, simulation_messages
from daemon.demo_images import COCO_LABELS, RenderedImages, ReplayClock, image_setup
from daemon.images import decode_compressed_image
from sim.presets import PRESETS, ScenarioConfig
from sim.simulate import simulate


def _scene() -> ScenarioConfig:
    """sil-north in the real world, shorter arms, little traffic, 5 fps: ~1100 images, three drive-pasts."""
    base = PRESETS["sil-north"]
    return replace(
        base,
        road=replace(base.road, arm_length_m=260.0),
        traffic=replace(base.traffic, count=5),
        detector=replace(base.detector, fps=5.0),
    )


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    inter = max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


@pytest.mark.slow
def test_images_go_through_the_daemons_detector_into_a_calibration(tmp_path: Path) -> None:
    scene = _scene()
    keep = tmp_path / "kept"
    lines: list[str] = []
    code = run_demo(
        preset=scene,
        seed=0,
        rate=40.0,
        timeout_s=900.0,
        port=free_port(),
        out=lines.append,
        images=True,
        keep_dir=keep,
    )
    text = "\n".join(lines)
    sim = simulate(scene, 0)
    stamps = [frame.stamp_ns for frame in sim.detections["north"]]
    # Every image was answered by the detector, none dropped (the daemon's health counters, over Zenoh).
    n = len(stamps)
    assert f"north            images {n:>6}  detector frames {n:>6}  dropped    0" in text, text
    assert f"{n} images put, 0 not answered within the wait" in text
    # The daemon recorded one DetectionFrame per image, stamped with the image's stamp; the simulator's
    # boxes were never sent, so every box in the recording is the detector's.
    frames: dict[int, list[tuple[float, ...]]] = {}
    for path in sorted((keep / "recordings").glob("*.mcap")):
        with path.open("rb") as stream:
            for _, _, message in make_reader(stream).iter_messages(
                topics=["rsu/sim-rsu/camera/north/detections"]
            ):
                frame = json.loads(message.data)
                frames[frame["stamp_ns"]] = [(b["x1"], b["y1"], b["x2"], b["y2"]) for b in frame["boxes"]]
                assert {b["cls"] for b in frame["boxes"]} <= {"car"}
    assert sorted(frames) == stamps
    # The calibration vehicle is found where the truth says it is seen (its visible outline's box).
    truth = [f for f in sim.ground_truth["north"].frames if f.visible_box is not None]
    found = [max((_iou(f.visible_box, b) for b in frames[f.stamp_ns]), default=0.0) for f in truth]  # type: ignore[arg-type]
    assert len(found) > 100
    assert sum(iou > 0.8 for iou in found) > 0.6 * len(found)
    # A job ran on those frames and kept the demo's promise: right when published, else refused.
    row = next(line for line in lines if line.startswith("north "))
    assert "PASS" in row or "REFUSED (" in row, row
    assert code == 0
    assert "job north-" in text


def _cli(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(argv)
    return code, err.getvalue()


def test_a_missing_or_lonely_detector_model_is_one_line_and_exit_2(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.onnx"
    code, err = _cli(["demo", "--images", "--detector-model", str(missing)])
    assert code == 2
    [line] = err.strip().splitlines()
    assert "--detector-model" in line and str(missing) in line
    model = tmp_path / "model.onnx"
    model.write_bytes(b"not read")
    code, err = _cli(["demo", "--detector-model", str(model)])
    assert code == 2
    [line] = err.strip().splitlines()
    assert "--detector-model" in line and "--images" in line


def test_an_operators_model_gets_coco_vehicle_classes_and_ordinary_paint(tmp_path: Path) -> None:
    model = tmp_path / "model.onnx"
    model.write_bytes(b"checked when the daemon loads it")
    setup = image_setup(model, "yolox")
    assert not setup.keyed and setup.labels == COCO_LABELS
    assert setup.detector.layout == "yolox" and setup.detector.classes == ["car", "bus", "truck"]
    assert image_setup(None).keyed


def test_the_replay_clock_follows_the_messages_then_runs_on() -> None:
    clock = ReplayClock(1_000, rate=1000.0)
    assert clock.now_ns() == 1_000
    clock.advance(5_000)
    clock.advance(4_000)  # never backwards
    assert clock.now_ns() == 5_000
    clock.release()
    clock.advance(10**12)  # ignored once released: the clock runs on its own
    released_at = clock.now_ns()
    assert 5_000 <= released_at < 10**12
    wait_until(lambda: clock.now_ns() > released_at, timeout_s=5.0)


def test_the_renderer_sends_every_cameras_images_in_the_replays_order() -> None:
    # Two cameras (sil-west): the renderer process merges their frames into the order of the replay.
    base = PRESETS["sil-west"]
    scene = replace(base, traffic=replace(base.traffic, count=3), detector=replace(base.detector, fps=5.0))
    sim = simulate(scene, 0)
    slots = [(m.key, m.stamp_ns) for m in simulation_messages(sim, images=True) if m.key.endswith("/image")]
    assert len(slots) == sum(len(frames) for frames in sim.detections.values())
    assert {key.split("/")[3] for key, _ in slots[:12]} == {"west-junction", "west-arm"}
    rendered = RenderedImages(scene, 0, False, keyed=True)
    rendered.start()
    try:
        first = list(itertools.islice(rendered.images(threading.Event()), 12))
    finally:
        rendered.close()
    assert [(key, stamp_ns) for key, stamp_ns, _ in first] == slots[:12]
    sizes = {c.camera_id: (c.intrinsics.height, c.intrinsics.width, 3) for c in sim.cameras}
    for key, stamp_ns, payload in first:
        image = decode_compressed_image(payload)
        camera_id = key.split("/")[3]
        assert (image.stamp_ns, image.frame_id, image.image.shape) == (stamp_ns, camera_id, sizes[camera_id])
