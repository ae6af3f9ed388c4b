"""Fuzzing the YAML file decoders of pipeline.loaders: rsu.yaml, camera.yaml, vehicle.yaml and the
toolbox pair (detections.yaml, poses.yaml).

Inputs: arbitrary bytes, arbitrary documents, structural mutations of a good file (fields deleted,
duplicated, swapped for junk, NaN/inf, huge numbers, deep nesting, long and unicode strings) and byte/line
edits of its text. Clean rejection: the loader returns its value or raises InputError naming the file,
then "<field>: <problem>"; nothing else. Known crashes are pinned at the end as strict xfails.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from fuzzing import document_inputs, fuzz_settings, label, mutated_bytes, mutated_lines, scratch_dir
from hypothesis import given
from hypothesis import strategies as st

from daemon.ingest import Counters, Decoder, RejectLog
from pipeline.errors import InputError
from pipeline.loaders import (
    load_daemon_config,
    load_intrinsics,
    load_toolbox_detections,
    load_toolbox_poses,
    load_vehicle,
)
from schemas.common import Box
from schemas.messages import DetectionFrame, VehiclePose
from sim.files import format_toolbox_detections, format_toolbox_poses

T0 = 1_700_000_000_000_000_000
EXAMPLE_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "rsu.example.yaml"
CAMERA_YAML = (
    "width: 1920\nheight: 1080\nfx: 960.0\nfy: 960.0\ncx: 960.0\ncy: 540.0\n"
    + "dist: [-0.1, 0.01, 0, 0, 0]\n"
)
# The same camera as ROS's camera_calibration saves it, and as OpenCV's calibration sample writes it.
ROS_CAMERA_YAML = """image_width: 1920
image_height: 1080
camera_name: rsu_cam
camera_matrix:
  rows: 3
  cols: 3
  data: [960.0, 0.0, 960.0, 0.0, 960.0, 540.0, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1, 0.01, 0.0, 0.0, 0.0]
"""
OPENCV_CAMERA_YAML = """%YAML:1.0
---
image_width: 1920
image_height: 1080
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 960., 0., 960., 0., 960., 540., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
avg_reprojection_error: 0.31
"""
OPENCV_CAMERA_XML = """<?xml version="1.0"?>
<opencv_storage>
<image_width>1920</image_width>
<image_height>1080</image_height>
<camera_matrix type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    960. 0. 960. 0. 960. 540. 0. 0. 1.</data></camera_matrix>
<distortion_coefficients type_id="opencv-matrix">
  <rows>5</rows>
  <cols>1</cols>
  <dt>d</dt>
  <data>
    -0.1 0.01 0. 0. 0.</data></distortion_coefficients>
</opencv_storage>
"""
VEHICLE_YAML = "length: 4.8\nwidth: 1.85\nheight: 1.5\nimu_offset: [1.3, 0.925, 0.35]\n"
DETECTIONS_YAML = format_toolbox_detections(
    DetectionFrame(
        camera_id="camera",
        stamp_ns=T0 + i * 100_000_000,
        boxes=[Box(x1=100.0 + j, y1=200.0, x2=180.5 + j, y2=260.25, cls=4 + j) for j in range(i % 3)],
    )
    for i in range(6)
)
POSES_YAML = format_toolbox_poses(
    VehiclePose(stamp_ns=T0 + i * 20_000_000, x=456_424.0 - i, y=5_428_742.75, z=165.35, yaw=3.14, pitch=0.01)
    for i in range(6)
)


def _example_config_text() -> str:
    if EXAMPLE_CONFIG.exists():
        return EXAMPLE_CONFIG.read_text(encoding="utf-8")
    # Without the deploy/ example: the demo's config for a simulated site, as an installer would write it.
    from daemon.demo import demo_config
    from sim.simulate import simulate

    config = demo_config(simulate("sil-west", 0), Path("/var/lib/rsucal"), 7447)
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


CONFIG_YAML = _example_config_text()
DIR = scratch_dir("rsucal-fuzz-loaders-")


def load_or_reject(loader: Callable[[Path], Any], data: bytes, name: str) -> Any:
    """The loader's value, or None after checking that its InputError names the file and a field."""
    path = DIR / name
    path.write_bytes(data)
    try:
        value = loader(path)
    except InputError as err:
        assert err.source == str(path)
        where, sep, problem = err.detail.partition(": ")
        assert sep and problem.strip(), err.detail
        # An unknown key that is whitespace or holds ": " is named, but unreadably (a finding: xfail below).
        assert where.strip() or "Extra inputs are not permitted" in problem, err.detail
        label(f"rejected: {where if where in ('(yaml)', '(root)', '(file)') else 'a field'}")
        return None
    label("accepted")
    return value


def test_the_good_files_load() -> None:
    camera = load_or_reject(load_intrinsics, CAMERA_YAML.encode(), "camera.yaml")
    assert camera is not None
    assert load_or_reject(load_intrinsics, ROS_CAMERA_YAML.encode(), "ost.yaml") == camera
    assert load_or_reject(load_intrinsics, OPENCV_CAMERA_YAML.encode(), "out_camera_data.yml") == camera
    assert load_or_reject(load_intrinsics, OPENCV_CAMERA_XML.encode(), "out_camera_data.xml") == camera
    assert load_or_reject(load_vehicle, VEHICLE_YAML.encode(), "vehicle.yaml") is not None
    assert load_or_reject(load_daemon_config, CONFIG_YAML.encode(), "rsu.yaml") is not None
    assert len(load_or_reject(load_toolbox_detections, DETECTIONS_YAML.encode(), "detections.yaml")) == 6
    assert len(load_or_reject(load_toolbox_poses, POSES_YAML.encode(), "poses.yaml")) == 6


@fuzz_settings(slow_data=True)
@given(data=document_inputs(CAMERA_YAML, yaml.safe_load))
def test_camera_yaml(data: bytes) -> None:
    load_or_reject(load_intrinsics, data, "camera.yaml")


@fuzz_settings(slow_data=True)
@given(data=document_inputs(ROS_CAMERA_YAML, yaml.safe_load))
def test_ros_camera_info_yaml(data: bytes) -> None:
    load_or_reject(load_intrinsics, data, "ost.yaml")


def _opencv_yaml(text: str) -> Any:
    """OpenCV FileStorage YAML as data: without its directive, the matrices as plain mappings."""
    return yaml.safe_load(text.replace("%YAML:1.0\n", "").replace("!!opencv-matrix", ""))


@fuzz_settings(slow_data=True)
@given(data=document_inputs(OPENCV_CAMERA_YAML, _opencv_yaml))
def test_opencv_storage_yaml(data: bytes) -> None:
    load_or_reject(load_intrinsics, data, "out_camera_data.yml")


@fuzz_settings(slow_data=True)
@given(
    data=st.one_of(
        st.binary(max_size=300).map(lambda b: b'<?xml version="1.0"?>\n' + b),
        mutated_bytes(OPENCV_CAMERA_XML.encode()),
        mutated_lines(OPENCV_CAMERA_XML).map(lambda text: text.encode("utf-8")),
    )
)
def test_opencv_storage_xml(data: bytes) -> None:
    load_or_reject(load_intrinsics, data, "out_camera_data.xml")


@fuzz_settings(slow_data=True)
@given(data=document_inputs(VEHICLE_YAML, yaml.safe_load))
def test_vehicle_yaml(data: bytes) -> None:
    load_or_reject(load_vehicle, data, "vehicle.yaml")


class _Clock:
    def now_ns(self) -> int:
        return T0


@fuzz_settings(slow_data=True)
@given(data=document_inputs(CONFIG_YAML, yaml.safe_load))
def test_rsu_yaml(data: bytes) -> None:
    config = load_or_reject(load_daemon_config, data, "rsu.yaml")
    if config is not None:
        # An accepted config is one the daemon can start with: its ingest decoder builds from it.
        counters = Counters()
        Decoder(config, _Clock(), counters, RejectLog(counters, 10.0, _Clock()))


@fuzz_settings(slow_data=True)
@given(data=document_inputs(DETECTIONS_YAML, yaml.safe_load))
def test_detections_yaml(data: bytes) -> None:
    frames = load_or_reject(load_toolbox_detections, data, "detections.yaml")
    if frames is not None:
        assert [f.stamp_ns for f in frames] == sorted({f.stamp_ns for f in frames})


@fuzz_settings(slow_data=True)
@given(data=document_inputs(POSES_YAML, yaml.safe_load))
def test_poses_yaml(data: bytes) -> None:
    poses = load_or_reject(load_toolbox_poses, data, "poses.yaml")
    if poses is not None:
        assert [p.stamp_ns for p in poses] == sorted({p.stamp_ns for p in poses})


# ---------------------------------------------------------------------------------------------- found


LOADERS = {
    "camera.yaml": load_intrinsics,
    "vehicle.yaml": load_vehicle,
    "rsu.yaml": load_daemon_config,
    "detections.yaml": load_toolbox_detections,
    "poses.yaml": load_toolbox_poses,
}


@pytest.mark.parametrize("name", ["camera.yaml", "vehicle.yaml", "rsu.yaml"])
@pytest.mark.parametrize("style", ["flow", "block"])
def test_deep_nesting_is_rejected_cleanly(name: str, style: str) -> None:
    depth = 1_500
    if style == "flow":
        text = "width: " + "[" * depth + "]" * depth + "\n"
    else:
        text = "width:\n" + "".join(" " * level + "- \n" for level in range(1, depth))
    assert load_or_reject(LOADERS[name], text.encode(), name) is None


@pytest.mark.parametrize("name", ["camera.yaml", "detections.yaml"])
def test_very_deep_nesting_does_not_kill_the_process(name: str, tmp_path: Path) -> None:
    depth = 30_000
    key = "width" if name == "camera.yaml" else str(T0)
    path = tmp_path / name
    path.write_text(f"{key}: " + "[" * depth + "]" * depth + "\n")
    code = "from pipeline.errors import InputError\n"
    code += f"from pipeline.loaders import {LOADERS[name].__name__} as load\n"
    code += f"try:\n    load({str(path)!r})\nexcept InputError as err:\n    print(err)\n"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, f"exit {run.returncode}: {run.stderr[-300:]}"
    assert str(path) in run.stdout


@pytest.mark.parametrize("name", ["camera.yaml", "rsu.yaml"])
def test_alias_bombs_are_refused_before_expansion(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    import schemas.common

    levels = 4
    text = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"
    text += "".join(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n" for i in range(1, levels + 1))
    dumped: list[int] = []
    real_dumps = json.dumps

    def measuring_dumps(data: Any, **kwargs: Any) -> str:
        out = real_dumps(data, **kwargs)
        dumped.append(len(out))
        return out

    # Speed is not asserted (bench/ does that); the size of what reaches the JSON validator is.
    monkeypatch.setattr(schemas.common.json, "dumps", measuring_dumps)
    assert load_or_reject(LOADERS[name], text.encode(), name) is None
    assert not dumped or max(dumped) < 20_000, f"{max(dumped)} bytes of JSON from a {len(text)}-byte file"


def test_an_unknown_crs_is_rejected_by_name() -> None:
    text = CONFIG_YAML.replace("crs: EPSG:32632", "crs: EPSG:99999")
    assert "EPSG:99999" in text
    path = DIR / "rsu.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        config = load_daemon_config(path)  # today: accepted
        counters = Counters()
        Decoder(config, _Clock(), counters, RejectLog(counters, 10.0, _Clock()))
    except InputError as err:
        assert "crs" in err.detail
        return
    pytest.fail("an unknown crs was accepted")


@pytest.mark.parametrize("key", [" ", "\\r", "a\\nb", ": "])
@pytest.mark.parametrize("name", ["camera.yaml", "rsu.yaml"])
def test_an_unknown_key_is_named_visibly(name: str, key: str) -> None:
    path = DIR / name
    path.write_text(f'"{key}": 1\n')  # a YAML double-quoted key: \\r and \\n are escapes there
    with pytest.raises(InputError) as info:
        LOADERS[name](path)
    detail = info.value.detail
    assert detail.isprintable(), detail  # on one line
    # The problems come in pydantic's order (missing fields first since pydantic 2.14): find the key's.
    extra = [problem for problem in detail.split("; ") if problem.endswith("Extra inputs are not permitted")]
    assert len(extra) == 1 and extra[0][:1] in ("'", '"'), detail  # the key quoted
