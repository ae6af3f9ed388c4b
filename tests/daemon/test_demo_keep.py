"""`rsucal demo --keep DIR`: the run's recordings open with the mcap reader, every foxglove.* message
validates against the schema in the file and Foxglove's official classes, and the reports are there."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest
from foxglove_check import check_recording
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from mcap.reader import make_reader

from daemon import cli
from daemon.demo import run_demo

FOXGLOVE = (
    "foxglove.LocationFix",
    "foxglove.ImageAnnotations",
    "foxglove.FrameTransform",
    "foxglove.CameraCalibration",
)


def test_keep_refuses_a_directory_with_files(tmp_path: Path) -> None:
    (tmp_path / "old.txt").write_text("someone's files")
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        code = cli.main(["demo", "--keep", str(tmp_path)])
    assert code == 2
    [line] = stderr.getvalue().strip().splitlines()
    assert "--keep" in line and str(tmp_path) in line
    assert [p.name for p in tmp_path.iterdir()] == ["old.txt"]


@pytest.mark.slow
def test_demo_keeps_recordings_that_foxglove_can_open(tmp_path: Path) -> None:
    keep = tmp_path / "kept"
    lines: list[str] = []
    assert run_demo(keep_dir=keep, ideal=True, out=lines.append) == 0, "\n".join(lines)
    [recording] = sorted((keep / "recordings").glob("*.mcap"))
    counts = check_recording(recording)
    assert all(counts[name] > 0 for name in FOXGLOVE), counts
    # One overlay per detection frame, plus the calibration vehicle's boxes after each accepted job.
    with open(recording, "rb") as stream:
        vehicle_overlays = sum(
            channel.topic.endswith("/calibration/annotations")
            for _, channel, _ in make_reader(stream).iter_messages()
        )
    assert vehicle_overlays > 0
    assert counts["foxglove.ImageAnnotations"] == counts["rsucal.DetectionFrame"] + vehicle_overlays
    assert counts["foxglove.LocationFix"] == counts["rsucal.V2xPosition"]
    assert counts["foxglove.CameraCalibration"] == 2  # one accepted result per camera of sil-west
    assert counts["rsucal.CalibrationResult"] >= 2
    simulation = keep / "simulation.mcap"
    simulated = check_recording(simulation)
    assert all(simulated[name] > 0 for name in FOXGLOVE), simulated
    # The simulator's recording places both cameras in the UTM frame.
    with open(simulation, "rb") as stream:
        children = {
            FrameTransform.FromString(message.data).child_frame_id
            for schema, channel, message in make_reader(stream).iter_messages()
            if channel.topic.endswith("/calibration/transform")
        }
    assert children == {"rsu/sim-rsu/camera/west-junction", "rsu/sim-rsu/camera/west-arm"}
    reports = sorted(keep.glob("cameras/*/history/*.html"))
    assert len(reports) >= 2
    printed = "\n".join(lines)
    assert str(recording) in printed and str(simulation) in printed
    assert all(str(report) in printed for report in reports)
