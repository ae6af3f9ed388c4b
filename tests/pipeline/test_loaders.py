"""pipeline.loaders: toolbox YAML and JSON files round-trip, and every bad input names its file and field."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline import loaders
from pipeline.errors import InputError
from pipeline.loaders import (
    _block_detection_table,
    _block_pose_table,
    _checked_detection_frames,
    _fast_parse_stamped_rows,
    _load_stamped_yaml,
    _row,
    _sorted_stamps,
    load_calibration_result,
    load_ground_truth,
    load_intrinsics,
    load_toolbox_detection_table,
    load_toolbox_detections,
    load_toolbox_pose_table,
    load_toolbox_poses,
    load_vehicle,
)
from pipeline.tables import DetectionTable, PoseTable
from schemas.common import Box, CameraIntrinsics, VehicleProfile
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.messages import DetectionFrame, VehiclePose
from schemas.results import CalibrationResult, ReferenceFrame, Verdict
from sim.files import format_toolbox_detections, format_toolbox_poses, write_simulation_files

T0 = 1_700_000_000_000_000_000
INTRINSICS = CameraIntrinsics(
    width=1920,
    height=1080,
    fx=1400.5,
    fy=1399.25,
    cx=961.3,
    cy=540.7,
    dist=(-0.21, 0.05, 0.001, -0.0005, 0.0),
)
VEHICLE = VehicleProfile(length=4.8, width=1.85, height=1.45, imu_offset=(1.35, 0.925, 0.4))
# Written at 0.01 px: a corner is centre - size/2, so its error is at most 0.005 + 0.0025 px.
BOX_TOL_PX = 0.0075 + 1e-9


def _frames(camera_id: str = "camera", n: int = 5) -> list[DetectionFrame]:
    frames = []
    for i in range(n):
        boxes = [
            Box(
                x1=100.0 + 13.37 * j + i,
                y1=200.123 + j,
                x2=180.456 + 13.37 * j + i,
                y2=260.0 + 2 * j,
                cls=4 + j % 4,
            )
            for j in range(i % 3 + 1)
        ]
        frames.append(DetectionFrame(camera_id=camera_id, stamp_ns=T0 + i * 66_666_667, boxes=boxes))
    frames.append(DetectionFrame(camera_id=camera_id, stamp_ns=T0 + n * 66_666_667, boxes=[]))  # empty frame
    return frames


def _poses(n: int = 4) -> list[VehiclePose]:
    return [
        VehiclePose(
            stamp_ns=T0 + i * 100_000_000,
            x=691_234.5678 + i,
            y=5_334_567.8912 - 0.5 * i,
            z=512.3456,
            yaw=-3.0 + 1.234567891 * i,
            pitch=0.0123456789,
            roll=-0.00987654321,
        )
        for i in range(n)
    ]


def _ground_truth(camera_id: str) -> GroundTruth:
    return GroundTruth(
        camera_id=camera_id,
        crs="EPSG:32632",
        origin=(691_000.0, 5_334_000.0, 500.0),
        R=((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
        t_utm=(-691_000.0, 510.0, -5_334_000.0),
        t_local=(0.0, 10.0, 0.0),
        camera_position_utm=(691_000.0, 5_334_000.0, 510.0),
        intrinsics=INTRINSICS,
        station_id=4711,
        traversals=1,
        frames=[
            GroundTruthFrame(stamp_ns=T0, calib_box=0, traversal=0),
            GroundTruthFrame(stamp_ns=T0 + 66_666_667),
        ],
    )


@dataclass(frozen=True)
class _Camera:
    camera_id: str
    intrinsics: CameraIntrinsics


@dataclass(frozen=True)
class _FakeSimulation:
    """The SimulationResult fields write_simulation_files reads (the simulator is another module)."""

    cameras: tuple[_Camera, ...]
    detections: dict[str, list[DetectionFrame]]
    poses: list[VehiclePose]
    vehicle: VehicleProfile = VEHICLE
    ground_truth: dict[str, GroundTruth] = field(default_factory=dict)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _assert_same_detections(got: list[DetectionFrame], want: list[DetectionFrame], camera_id: str) -> None:
    assert [f.stamp_ns for f in got] == sorted(f.stamp_ns for f in want)
    for frame_got, frame_want in zip(got, sorted(want, key=lambda f: f.stamp_ns), strict=True):
        assert frame_got.camera_id == camera_id
        assert len(frame_got.boxes) == len(frame_want.boxes)
        for a, b in zip(frame_got.boxes, frame_want.boxes, strict=True):
            assert a.cls == b.cls
            for name in ("x1", "y1", "x2", "y2"):
                assert abs(getattr(a, name) - getattr(b, name)) <= BOX_TOL_PX, name


def _assert_same_poses(got: list[VehiclePose], want: list[VehiclePose]) -> None:
    assert [p.stamp_ns for p in got] == [p.stamp_ns for p in want]
    for a, b in zip(got, want, strict=True):
        for name in ("x", "y", "z"):
            assert abs(getattr(a, name) - getattr(b, name)) <= 0.0005 + 1e-6, name  # written in mm
        for name in ("yaw", "pitch", "roll"):
            assert abs(getattr(a, name) - getattr(b, name)) <= 5e-10 + 1e-12, name  # written in 1e-9 rad


# ---------------------------------------------------------------------------------------------- round trips


def test_detections_round_trip_within_written_precision(tmp_path: Path) -> None:
    frames = _frames()
    path = _write(tmp_path, "detections.yaml", format_toolbox_detections(reversed(frames)))
    loaded = load_toolbox_detections(path, camera_id="cam-7")
    _assert_same_detections(loaded, frames, "cam-7")
    assert loaded[-1].boxes == []  # a frame without boxes is kept: the camera ran, nothing was seen
    # The file is plain YAML any toolbox reader understands: centre, size, class.
    raw = yaml.safe_load(path.read_text())
    first = frames[0].boxes[0]
    cx, cy, w, h, cls = raw[T0][0]
    assert (cx, cy) == pytest.approx((0.5 * (first.x1 + first.x2), 0.5 * (first.y1 + first.y2)), abs=0.005)
    assert (w, h, cls) == (
        pytest.approx(first.x2 - first.x1, abs=0.005),
        pytest.approx(first.y2 - first.y1, abs=0.005),
        4,
    )


def test_poses_round_trip_within_written_precision(tmp_path: Path) -> None:
    poses = _poses()
    path = _write(tmp_path, "poses.yaml", format_toolbox_poses(reversed(poses)))
    _assert_same_poses(load_toolbox_poses(path), poses)


def test_block_style_toolbox_file_with_quoted_stamps(tmp_path: Path) -> None:
    # Written by another tool: comments, quoted keys, nested block lists, ints for floats, class as 5.0.
    text = f"""# detections from the reference toolbox
'{T0 + 10}':
  - - 110
    - 220.5
    - 20
    - 10
    - 5.0
"{T0}": []
{T0 + 5}:
"""
    frames = load_toolbox_detections(_write(tmp_path, "d.yaml", text))
    assert [f.stamp_ns for f in frames] == [T0, T0 + 5, T0 + 10]
    assert frames[0].boxes == [] and frames[1].boxes == []
    assert frames[2].boxes == [Box(x1=100.0, y1=215.5, x2=120.0, y2=225.5, cls=5)]


def test_tables_hold_exactly_what_the_row_by_row_checks_build(tmp_path: Path) -> None:
    # The tables validate whole columns; their frames and poses are the objects the per-row path builds,
    # bit for bit (ints for floats, a class as 5.0, an empty frame, centre +- half size in float64).
    text = f"""{T0 + 10}: [[110, 220.5, 20, 10, 5.0], [961.3, 540.7, 0.1, 0.001, 4]]
{T0}: []
{T0 + 5}:
{T0 + 7}: [[0.30000000000000004, 1.0000000000000002, 2.5, 1.25, 7]]
"""
    path = _write(tmp_path, "d.yaml", text)
    table = load_toolbox_detection_table(path, "cam-7")
    expected = _checked_detection_frames(path, _sorted_stamps(path, _load_stamped_yaml(path)), "cam-7")
    assert list(table) == expected and len(table) == 4
    assert [frame.boxes for frame in table] == [frame.boxes for frame in expected]
    poses_text = f"""{T0 + 1}: [715674.0534, 5337055.972, 572, -3.141592653589793, 0.001, 0]
{T0}: [1.0000000000000002, 2, 3, 4, 5, 6]
"""
    poses_path = _write(tmp_path, "p.yaml", poses_text)
    poses = load_toolbox_pose_table(poses_path)
    rows = [_row(poses_path, str(k), r, ("x", "y", "z", "yaw", "pitch", "roll"))
            for _, k, r in _sorted_stamps(poses_path, _load_stamped_yaml(poses_path))]  # fmt: skip
    assert [[p.x, p.y, p.z, p.yaw, p.pitch, p.roll] for p in poses] == rows
    assert poses.stamps.tolist() == [T0, T0 + 1]


def test_empty_mapping_is_no_frames(tmp_path: Path) -> None:
    assert load_toolbox_detections(_write(tmp_path, "d.yaml", format_toolbox_detections([]))) == []
    assert load_toolbox_poses(_write(tmp_path, "p.yaml", format_toolbox_poses([]))) == []


_int_text = st.integers(-(10**6), 10**6).map(str)
_decimal_text = st.integers(-(10**9), 10**9).map(lambda i: f"{i / 1000:.3f}")
# Tokens where YAML 1.1 and a naive parser disagree (octal, exponent without dot, sign...); one branch in
# seventeen, so many generated files stay on the fast path.
_odd_number_text = st.sampled_from(["0", "-0.0", "007", "1e3", "1.5e+3", ".5", "+1", "nan", "0x1F", "1_0"])
_number_text = st.one_of(*[_int_text, _decimal_text] * 8, _odd_number_text)
_row_text = st.tuples(st.lists(_number_text, max_size=6), st.sampled_from([", ", ",", " , "])).map(
    lambda row: "[" + row[1].join(row[0]) + "]"
)
_key_text = st.tuples(st.integers(0, 10**19), st.sampled_from(["{}", "{}", "{}", "'{}'", '"{}"', "0{}"])).map(
    lambda key: key[1].format(key[0])  # 0{}: octal in YAML 1.1
)
_indent_text = st.sampled_from(["", "  ", "    ", " "])
_entry_text = st.one_of(
    st.tuples(_key_text, _row_text).map(lambda e: f"{e[0]}: {e[1]}"),
    st.tuples(_key_text, _indent_text, st.lists(_row_text, max_size=3)).map(
        lambda e: "\n".join([f"{e[0]}:", *(f"{e[1]}- {row}" for row in e[2])])
    ),
    # The toolbox's block style: one value per line (poses), or nested block rows (detections, as
    # PyYAML dumps a list of lists), sometimes with a continuation line at another indentation.
    st.tuples(_key_text, _indent_text, st.lists(_number_text, max_size=7)).map(
        lambda e: "\n".join([f"{e[0]}:", *(f"{e[1]}- {value}" for value in e[2])])
    ),
    st.tuples(
        _key_text,
        _indent_text,
        st.lists(st.lists(_number_text, min_size=1, max_size=5), max_size=3),
        st.sampled_from(["  ", "  ", "  ", " ", "   "]),
    ).map(
        lambda e: "\n".join(
            [
                f"{e[0]}:",
                *(
                    "\n".join([f"{e[1]}- - {row[0]}", *(f"{e[1]}{e[3]}- {value}" for value in row[1:])])
                    for row in e[2]
                ),
            ]
        )
    ),
)


@settings(max_examples=300, deadline=None)
@given(entries=st.lists(_entry_text, max_size=6), blank=st.sampled_from(["", "\n", "  \n"]))
def test_fast_parser_agrees_with_pyyaml(entries: list[str], blank: str) -> None:
    # The fast path must give exactly what PyYAML gives, or decline (None) and let PyYAML decide.
    text = ("\n" + blank).join(entries) + "\n"
    fast = _fast_parse_stamped_rows(text)
    if fast is None:
        return
    expected = yaml.safe_load(text)
    assert fast == expected
    assert [
        type(v) for row in fast.values() if isinstance(row, list) for v in row if not isinstance(v, list)
    ] == [
        type(v) for row in expected.values() if isinstance(row, list) for v in row if not isinstance(v, list)
    ]


def test_fast_parser_declines_other_layouts() -> None:
    assert _fast_parse_stamped_rows("# comment\n1: [1, 2]\n") is None
    assert _fast_parse_stamped_rows("1: [1e3]\n") is None  # YAML 1.1 reads 1e3 as a string
    assert _fast_parse_stamped_rows("1: [1, 2]\n1: [3, 4]\n") is None  # duplicate: PyYAML reports the line
    assert _fast_parse_stamped_rows("1:\n  - [1]\n    - [2]\n") is None  # inconsistent indentation
    assert _fast_parse_stamped_rows("- [1, 2]\n") is None
    assert _fast_parse_stamped_rows("1:\n- 1.0\n  - 2.0\n") is None  # block values at two indentations
    assert _fast_parse_stamped_rows("1:\n- 1.0\n- [2.0]\n") is None  # values and rows mixed
    assert _fast_parse_stamped_rows("1: [1]\n- 2.0\n") is None  # a flow row followed by items
    assert _fast_parse_stamped_rows("1:\n- 1.0e5\n") is None  # exponent without sign: a string in YAML 1.1


def test_fast_parser_reads_the_toolbox_block_style() -> None:
    """The reference toolbox's real poses.yaml layout (one value per line) and PyYAML's block dump of the
    detections (a nested block sequence per box) take the fast path and give PyYAML's values."""
    poses = "1659612577050000000:\n- 1.2865700321272016\n- 14.698403273709118\n- 5.100000000000023\n"
    poses += "- 3.2664690329706874\n- -0.0\n- 1.0e-05\n"
    detections = yaml.safe_dump(
        {1659612577050000000: [[87.7, 333.03, 56.68, 34.18, 4], [1.5, 2.5, 3.0, 4.0, 5]]}
    )
    assert detections.startswith("1659612577050000000:\n- - 87.7\n  - 333.03\n")
    for text in (poses, detections):
        fast = _fast_parse_stamped_rows(text)
        assert fast is not None and fast == yaml.safe_load(text)
    assert fast[1659612577050000000][1] == [1.5, 2.5, 3.0, 4.0, 5]


@contextmanager
def _general_path() -> Iterator[None]:
    """The toolbox loaders with the block layout's column reader switched off: the general path alone."""
    original = loaders._block_pose_table, loaders._block_detection_table
    loaders._block_pose_table = lambda raw: None  # type: ignore[assignment]
    loaders._block_detection_table = lambda raw, camera_id: None  # type: ignore[assignment]
    try:
        yield
    finally:
        loaders._block_pose_table, loaders._block_detection_table = original


def _load_table(path: Path, poses: bool, camera_id: str) -> PoseTable | DetectionTable | str:
    """The file's pose or detection table, or the message of the InputError it raises."""
    try:
        return load_toolbox_pose_table(path) if poses else load_toolbox_detection_table(path, camera_id)
    except InputError as err:
        return str(err)


def _same_table(a: PoseTable | DetectionTable | str, b: PoseTable | DetectionTable | str) -> bool:
    """Equal messages, or tables with the same columns bit for bit (dtype and bytes)."""
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    names = ("stamps", "values") if isinstance(a, PoseTable) else ("stamps", "starts", "boxes", "classes")
    return type(a) is type(b) and all(
        getattr(a, n).dtype == getattr(b, n).dtype and getattr(a, n).tobytes() == getattr(b, n).tobytes()
        for n in names
    )


def _block_text(stamps: list[str], records: list[list[list[str]]], poses: bool) -> str:
    """A toolbox file in yaml.dump's block style: per stamp its values one per line (poses, the first row
    only), or its rows as nested block sequences (detections; `stamp: []` for none)."""
    pairs = zip(stamps, records, strict=False)
    if poses:
        return "".join(k + ":\n" + "".join(f"- {v}\n" for v in rows[0]) for k, rows in pairs)
    return "".join(
        k + (":\n" if rows else ": []\n")
        + "".join(f"- - {row[0]}\n" + "".join(f"  - {v}\n" for v in row[1:]) for row in rows)
        for k, rows in pairs
    )  # fmt: skip


# Numbers as yaml.dump writes floats (repr, with `1.0e-05` style exponents) and ints; rarely a token outside
# the block reader's grammar or range (the general path reads or refuses it).
_dumped_float = st.floats(allow_nan=False, allow_infinity=False).map(
    lambda v: yaml.safe_dump(v).split("\n")[0]
)
_odd_token = st.sampled_from(["-0", "007", "1e3", "1.5e3", ".5", "+1", ".nan", "9" * 400, "1" * 5000, "1.0 "])
_int_token = st.integers(-(10**6), 10**6).map(str)
# Hypothesis favours the low end of a range: 0 draws the usual token, only the top one an odd one.
_block_token = st.integers(0, 40).flatmap(
    lambda k: _odd_token if k == 40 else (_dumped_float if k % 2 == 0 else _int_token)
)
_odd_stamp = st.sampled_from(["0", "5", "1" + "0" * 19, f"'{T0}'", "01", f"{T0}"])


@settings(max_examples=300, deadline=None)
@given(data=st.data(), poses=st.booleans(), camera_id=st.sampled_from(["camera", "camera", "cam 7"]))
def test_block_reader_gives_the_general_paths_tables(
    tmp_path_factory: pytest.TempPathFactory, data: st.DataObject, poses: bool, camera_id: str
) -> None:
    # The toolbox's block layout is read straight into columns; wherever the reader does not decline a file
    # (None), its table is the general path's, bit for bit, and so is the loader's outcome on every file.
    # Mostly files of the layout (sorted stamps, 6 values a pose, 5 a box), some a little off.
    count = data.draw(st.integers(1, 5))
    stamps = [
        str(s)
        for s in sorted(data.draw(st.sets(st.integers(T0, T0 + 10**9), min_size=count, max_size=count)))
    ]
    if data.draw(st.integers(0, 3)) == 3:
        stamps[data.draw(st.integers(0, count - 1))] = data.draw(_odd_stamp)  # unsorted, quoted, out of range
    width = 6 if poses else 5
    if data.draw(st.integers(0, 5)) == 5:
        width = data.draw(st.sampled_from([4, 7]))
    rows = st.lists(_block_token, min_size=width, max_size=width)
    if not poses and width == 5 and data.draw(st.integers(0, 3)) < 3:  # mostly boxes that pass every check
        size = st.floats(0.5, 500.0).map(lambda v: yaml.safe_dump(v).split("\n")[0])
        corner = st.floats(0.0, 1900.0).map(lambda v: yaml.safe_dump(v).split("\n")[0])
        rows = st.tuples(corner, corner, size, size, st.integers(0, 7).map(str)).map(list)
    records = [data.draw(st.lists(rows, min_size=1 if poses else 0, max_size=3)) for _ in stamps]
    text = _block_text(stamps, records, poses)
    path = _write(tmp_path_factory.mktemp("block"), "p.yaml" if poses else "d.yaml", text)
    with _general_path():
        general = _load_table(path, poses, camera_id)
    block = _block_pose_table(text.encode()) if poses else _block_detection_table(text.encode(), camera_id)
    if block is not None:
        assert _same_table(block, general)
    assert _same_table(_load_table(path, poses, camera_id), general)


def test_block_reader_takes_the_toolbox_files(tmp_path: Path) -> None:
    """The files `bench.speed --cli` writes (yaml.dump's block style, as the toolbox publishes its real
    track) take the block reader and give the general path's tables."""
    poses = {
        T0 + 20_000_000 * i: [715674.05 + i, 5337055.9, 572.0, -3.14159, -2.4e-17, 0.02] for i in range(50)
    }
    detections = {
        T0 + 10**8 * i: [[87.7 + j, 333.03, 56.68, 34.18, 4 + i % 4] for j in range(i % 3)] for i in range(20)
    }
    for name, data in (("p.yaml", poses), ("d.yaml", detections)):
        text = yaml.dump(data, Dumper=yaml.SafeDumper, default_flow_style=False)
        path = _write(tmp_path, name, text)
        block = (
            _block_pose_table(text.encode()) if data is poses else _block_detection_table(text.encode(), "c")
        )
        with _general_path():
            general = _load_table(path, data is poses, "c")
        assert block is not None and not isinstance(general, str)
        assert _same_table(block, general)


def test_intrinsics_and_vehicle_round_trip(tmp_path: Path) -> None:
    sim = _FakeSimulation(cameras=(_Camera("camera", INTRINSICS),), detections={}, poses=[])
    write_simulation_files(sim, tmp_path)  # type: ignore[arg-type]
    assert load_intrinsics(tmp_path / "camera.yaml") == INTRINSICS
    assert load_vehicle(tmp_path / "vehicle.yaml") == VEHICLE
    # Keys exactly as docs/design.md names them, in a file a human can edit.
    assert set(yaml.safe_load((tmp_path / "camera.yaml").read_text())) == {
        "width",
        "height",
        "fx",
        "fy",
        "cx",
        "cy",
        "dist",
    }


@pytest.mark.parametrize(
    "dist",
    [
        [-0.21, 0.05, 0.001, -0.0005],  # Kalibr's radtan, OpenCV with k3 fixed
        [-0.21, 0.05, 0.001, -0.0005, 0.01],  # OpenCV's default, ROS's plumb_bob
        [2.1, 0.6, 0.0004, -0.0003, 0.01, 2.45, 1.3, 0.08],  # the rational model, ROS's rational_polynomial
    ],
)
def test_intrinsics_take_opencvs_distortion_vectors_as_given(tmp_path: Path, dist: list[float]) -> None:
    path = _write(tmp_path, "camera.yaml", _CAMERA + f"dist: {dist}\n")
    assert load_intrinsics(path).dist == tuple(dist)


def ros_camera_info(intrinsics: CameraIntrinsics, model: str | None = None) -> dict[str, object]:
    """The ROS camera_info calibration file (camera_calibration's ost.yaml) of `intrinsics`."""
    k = intrinsics
    rational = len(k.dist) == 8
    return {
        "image_width": k.width,
        "image_height": k.height,
        "camera_name": "rsu_cam",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]},
        "distortion_model": model or ("rational_polynomial" if rational else "plumb_bob"),
        "distortion_coefficients": {"rows": 1, "cols": len(k.dist), "data": list(k.dist)},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [k.fx * 0.98, 0.0, k.cx, 0.0, 0.0, k.fy * 0.98,
                                                             k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]},
    }  # fmt: skip


RATIONAL = INTRINSICS.model_copy(update={"dist": (2.1, 0.6, 0.0004, -0.0003, 0.01, 2.45, 1.3, 0.08)})


@pytest.mark.parametrize("intrinsics", [INTRINSICS, RATIONAL])
def test_ros_camera_info_files_give_the_same_intrinsics(tmp_path: Path, intrinsics: CameraIntrinsics) -> None:
    path = _write(tmp_path, "ost.yaml", yaml.safe_dump(ros_camera_info(intrinsics)))
    assert load_intrinsics(path) == intrinsics  # the projection matrix (rectified images) is not used


@pytest.mark.parametrize("suffix", ["yml", "xml"])
@pytest.mark.parametrize("intrinsics", [INTRINSICS, RATIONAL])
def test_opencv_storage_files_give_the_same_intrinsics(
    tmp_path: Path, intrinsics: CameraIntrinsics, suffix: str
) -> None:
    # Written by OpenCV itself, as its calibration sample and tutorial write them (read by rsucal, not by
    # OpenCV's parser).
    path = tmp_path / f"out_camera_data.{suffix}"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("calibration_time", "Fri Nov 27 2026")
    storage.write("image_width", intrinsics.width)
    storage.write("image_height", intrinsics.height)
    K = np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]])
    storage.write("camera_matrix", K)
    storage.write("distortion_coefficients", np.array(intrinsics.dist).reshape(-1, 1))
    storage.write("avg_reprojection_error", 0.31)
    storage.release()
    assert load_intrinsics(path) == intrinsics


def _ros_with(change: dict[str, object]) -> str:
    info = ros_camera_info(INTRINSICS)
    for key, value in change.items():
        if value is None:
            del info[key]
        else:
            info[key] = value
    return yaml.safe_dump(info)


_OPENCV_HEAD = "%YAML:1.0\n---\nimage_width: 1280\nimage_height: 720\n"
_XML = """<?xml version="1.0"?>
<opencv_storage>
<image_width>1280</image_width>
<image_height>720</image_height>
<camera_matrix type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    1000. 0. 640. 0. 1000. 360. 0. 0. 1.</data></camera_matrix>
</opencv_storage>
"""
_OPENCV_K = (
    "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
    "   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0., 1. ]\n"
)


def _matrix(data: list[object], rows: int = 3, cols: int = 3) -> dict[str, object]:
    return {"rows": rows, "cols": cols, "data": data}


_K = [1000.0, 0.0, 640.0, 0.0, 1000.0, 360.0, 0.0, 0.0, 1.0]
BAD_OTHER_CAMERAS = [
    (_ros_with({"distortion_model": "equidistant"}), "distortion_model: 'equidistant' (a fisheye lens)"),
    (_ros_with({"distortion_model": "unified"}), "distortion_model: 'unified' is not one of plumb_bob"),
    (_ros_with({"distortion_model": "rational_polynomial"}), "distortion_coefficients.data: 5 values"),
    (_ros_with({"distortion_coefficients": _matrix([0.1] * 5, 1, 4)}), "rows x cols = 1 x 4"),
    (_ros_with({"camera_matrix": _matrix([1.0] * 8)}), "camera_matrix: rows x cols"),
    (_ros_with({"camera_matrix": _matrix(["a"] * 9)}), "camera_matrix.data: expected numbers"),
    (_ros_with({"camera_matrix": [1.0] * 9}), "camera_matrix: expected a mapping with rows, cols and"),
    (_ros_with({"camera_matrix": _matrix([*_K[:1], 3.0, *_K[2:]])}), "camera_matrix: a skew of 3 px"),
    (_ros_with({"camera_matrix": _matrix([-1000.0, *_K[1:]])}), "camera_matrix (fx): Input should be"),
    (_ros_with({"image_width": None}), "image_width: missing"),
    (_ros_with({"image_height": 720.5}), "image_height: expected a whole number of pixels, got 720.5"),
    (
        _ros_with({"distortion_coefficients": _matrix([0.0] * 6, 1, 6)}),
        "distortion_coefficients.data: 6 values for distortion_model plumb_bob (expected 4 or 5)",
    ),
    (_OPENCV_HEAD, "camera_matrix: missing"),
    (_OPENCV_HEAD + _OPENCV_K.replace("rows: 3", "rows: 1").replace("cols: 3", "cols: 9"), "1 x 9, expected"),
    (_OPENCV_HEAD + "camera_matrix: [1\n", "(yaml): line 6, column 1: did not find expected ',' or ']'"),
    ('<?xml version="1.0"?>\n<opencv_storage>\n', "(xml): line 3, column 1: no element found"),
    ('<?xml version="1.0"?>\n<calibration/>\n', "(xml): the root is <calibration>, not <opencv_storage>"),
    (
        _XML.replace("<rows>3</rows>", "<rows>three</rows>"),
        "camera_matrix.rows: expected a number, got 'three'",
    ),
    (_XML.replace("<cols>3</cols>", ""), "camera_matrix: expected an opencv-matrix with rows, cols and data"),
    (_XML.replace(" 0. 0. 1.</data>", " 0. 0. x</data>"), "camera_matrix.data: expected a number, got 'x'"),
    (_XML.replace("1280", "1280.5"), "image_width: expected a whole number of pixels, got 1280.5"),
    (_XML.replace("<image_height>720</image_height>", ""), "image_height: missing"),
    ("%YAML:1.0\n" + _OPENCV_K, "image_width: missing"),
]


@pytest.mark.parametrize(("text", "expected"), BAD_OTHER_CAMERAS)
def test_bad_camera_files_of_other_tools_name_their_own_keys(
    tmp_path: Path, text: str, expected: str
) -> None:
    path = _write(tmp_path, "camera.yaml", text)
    with pytest.raises(InputError) as info:
        load_intrinsics(path)
    assert info.value.source == str(path)
    assert expected in info.value.detail, info.value.detail


def test_hand_written_intrinsics_default_distortion(tmp_path: Path) -> None:
    path = _write(
        tmp_path, "camera.yaml", "width: 1280\nheight: 720\nfx: 1000\nfy: 1000.5\ncx: 640\ncy: 360\n"
    )
    assert load_intrinsics(path) == CameraIntrinsics(
        width=1280, height=720, fx=1000.0, fy=1000.5, cx=640.0, cy=360.0
    )


def test_write_simulation_files_single_camera(tmp_path: Path) -> None:
    frames, poses = _frames(), _poses()
    sim = _FakeSimulation(
        cameras=(_Camera("north", INTRINSICS),),
        detections={"north": frames},
        poses=poses,
        ground_truth={"north": _ground_truth("north")},
    )
    written = write_simulation_files(sim, tmp_path / "out")  # type: ignore[arg-type]
    names = sorted(p.name for p in written)
    assert names == ["camera.yaml", "detections.yaml", "ground_truth.json", "poses.yaml", "vehicle.yaml"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == names  # no temporary files left behind
    _assert_same_detections(
        load_toolbox_detections(tmp_path / "out" / "detections.yaml", "north"), frames, "north"
    )
    _assert_same_poses(load_toolbox_poses(tmp_path / "out" / "poses.yaml"), poses)
    assert load_ground_truth(tmp_path / "out" / "ground_truth.json") == _ground_truth("north")


def test_write_simulation_files_several_cameras(tmp_path: Path) -> None:
    other = INTRINSICS.model_copy(update={"fx": 900.0, "fy": 900.0})
    sim = _FakeSimulation(
        cameras=(_Camera("north", INTRINSICS), _Camera("south", other)),
        detections={"north": _frames("north"), "south": _frames("south", n=2)},
        poses=_poses(),
        ground_truth={"north": _ground_truth("north"), "south": _ground_truth("south")},
    )
    written = write_simulation_files(sim, tmp_path)  # type: ignore[arg-type]
    assert sorted(p.name for p in written) == [
        "camera_north.yaml",
        "camera_south.yaml",
        "detections_north.yaml",
        "detections_south.yaml",
        "ground_truth_north.json",
        "ground_truth_south.json",
        "poses.yaml",
        "vehicle.yaml",
    ]
    assert load_intrinsics(tmp_path / "camera_south.yaml") == other
    _assert_same_detections(
        load_toolbox_detections(tmp_path / "detections_south.yaml", "south"), _frames("south", n=2), "south"
    )
    assert load_ground_truth(tmp_path / "ground_truth_south.json").camera_id == "south"


def test_calibration_result_round_trip(tmp_path: Path) -> None:
    result = CalibrationResult(
        rsu_id="rsu-1",
        camera_id="north",
        result_id="r-1",
        created_at_ns=T0,
        frame=ReferenceFrame(crs="EPSG:32632", origin=(691_000.0, 5_334_000.0, 500.0)),
        R=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        t=(0.1, 0.2, 0.3),
        intrinsics=INTRINSICS,
        verdict=Verdict(status="accepted"),
    )
    path = _write(tmp_path, "calib.json", result.model_dump_json(indent=2))
    assert load_calibration_result(path) == result


# ---------------------------------------------------------------------------------------------- bad input

_GOOD_ROW = "[100.0, 200.0, 20.0, 10.0, 4]"
BAD_DETECTIONS = [
    ("not: [valid\n", "(yaml): line"),
    ("- [1, 2, 3, 4, 5]\n", "(root): expected a mapping"),
    ("", "(root): the file is empty"),
    (f"{T0}: [[100.0, 200.0, 20.0, 10.0]]\n", f"{T0}.0: expected 5 values"),
    (f"{T0}: [[100.0, 200.0, 20.0, 10.0, 4, 1]]\n", f"{T0}.0: expected 5 values"),
    (f"{T0}: [{_GOOD_ROW}, [.nan, 200.0, 20.0, 10.0, 4]]\n", f"{T0}.1.cx: must be finite"),
    (f"{T0}: [[100.0, .inf, 20.0, 10.0, 4]]\n", f"{T0}.0.cy: must be finite"),
    (f"{T0}: [[100.0, 200.0, 0.0, 10.0, 4]]\n", f"{T0}.0.w: box width must be > 0"),
    (f"{T0}: [[100.0, 200.0, 20.0, -3.5, 4]]\n", f"{T0}.0.h: box height must be > 0"),
    (f"{T0}: [[100.0, '200', 20.0, 10.0, 4]]\n", f"{T0}.0.cy: expected a number, got str"),
    (f"{T0}: [[100.0, 200.0, 20.0, 10.0, true]]\n", f"{T0}.0.class_id: expected a number, got bool"),
    (f"{T0}: [[100.0, 200.0, 20.0, 10.0, 4.5]]\n", f"{T0}.0.class_id: expected an integer class id"),
    (f"{T0}: [[100.0, 200.0, 20.0, 10.0, 4000]]\n", f"{T0}: boxes.0.cls:"),
    (f"{T0}: {{a: 1}}\n", f"{T0}: expected a list of boxes"),
    (f"{T0}: [7]\n", f"{T0}.0: expected a list [cx, cy, w, h, class_id]"),
    (f"1.7e+18: [{_GOOD_ROW}]\n", "stamp must be an integer (ns), got float"),
    (f"'17000000000000000x': [{_GOOD_ROW}]\n", "stamp must be an integer (ns)"),
    (f"1700000000: [{_GOOD_ROW}]\n", "1700000000: stamp 1700000000 is outside"),  # seconds, not ns
    (f"{T0}: [{_GOOD_ROW}]\n'{T0}': []\n", "duplicate stamp"),
    (f"{T0}: []\n{T0}: []\n", "duplicate key"),
    (f"{T0}: [[1.0e+5, 200.0, 20.0, 10.0, 4]]\n", f"{T0}: boxes.0.x2:"),  # beyond any image
    (f"{T0}: [[1{'0' * 5000}, 200.0, 20.0, 10.0, 4]]\n", "(yaml): Exceeds the limit"),  # int() refuses
]


@pytest.mark.parametrize(("text", "expected"), BAD_DETECTIONS)
def test_bad_detections_name_file_and_field(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path, "detections.yaml", text)
    with pytest.raises(InputError) as info:
        load_toolbox_detections(path)
    assert info.value.source == str(path)
    assert expected in info.value.detail
    assert str(path) in str(info.value)


BAD_POSES = [
    (f"{T0}: [1.0, 2.0, 3.0, 0.1, 0.0]\n", f"{T0}: expected 6 values [x, y, z, yaw, pitch, roll], got 5"),
    (f"{T0}: [1.0, 2.0, .nan, 0.1, 0.0, 0.0]\n", f"{T0}.z: must be finite"),
    (f"{T0}: [1.0, 2.0, 3.0, -.inf, 0.0, 0.0]\n", f"{T0}.yaw: must be finite"),
    (f"{T0}: [1.0, 2.0, 3.0, east, 0.0, 0.0]\n", f"{T0}.yaw: expected a number, got str"),
    (f"{T0}: [1{'0' * 400}, 2.0, 3.0, 0.0, 0.0, 0.0]\n", f"{T0}.x: 1000"),  # an int beyond float range
    (f"{T0}:\n", f"{T0}: expected a list [x, y, z, yaw, pitch, roll], got NoneType"),
    ("[1, 2]\n", "(root): expected a mapping"),
    (f"{T0}: [1.0, 2.0, 3.0, 0.1, 0.0, 0.0\n", "(yaml): line"),
]


@pytest.mark.parametrize(("text", "expected"), BAD_POSES)
def test_bad_poses_name_file_and_field(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path, "poses.yaml", text)
    with pytest.raises(InputError) as info:
        load_toolbox_poses(path)
    assert info.value.source == str(path)
    assert expected in info.value.detail


_CAMERA = "width: 1280\nheight: 720\nfx: 1000.0\nfy: 1000.0\ncx: 640.0\ncy: 360.0\n"
BAD_CAMERAS = [
    (_CAMERA + "skew: 0.0\n", "skew: Extra inputs are not permitted"),
    (_CAMERA.replace("fx: 1000.0\n", ""), "fx: Field required"),
    (_CAMERA.replace("fx: 1000.0", "fx: '1000.0'"), "fx: Input should be a valid number"),
    (_CAMERA.replace("fx: 1000.0", "fx: .nan"), "fx:"),
    (_CAMERA.replace("width: 1280", "width: 1280.5"), "width:"),
    (_CAMERA.replace("fy: 1000.0", "fy: -5.0"), "fy: Input should be greater than 0"),
    (_CAMERA + "dist: [0.1, 0.2]\n", "dist: Value error, 2 coefficients; OpenCV's pinhole model takes 4"),
    (_CAMERA + "dist: [0.1, 0.2, 0.0, 0.0, 0.0, 0.3]\n", "dist: Value error, 6 coefficients"),
    (_CAMERA + f"dist: {[0.0] * 14}\n", "the thin-prism and tilted models (12, 14) are not supported"),
    ("- width\n", "(root): expected a mapping of CameraIntrinsics fields, got list"),
    ("width: [\n", "(yaml): line"),
]


@pytest.mark.parametrize(("text", "expected"), BAD_CAMERAS)
def test_bad_intrinsics_name_file_and_field(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path, "camera.yaml", text)
    with pytest.raises(InputError) as info:
        load_intrinsics(path)
    assert info.value.source == str(path)
    assert expected in info.value.detail


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "length: 4.5\nwidth: 1.8\nheight: 1.5\nimu_offset: [1.0, 0.9, 0.3]\nmass: 1500\n",
            "mass: Extra inputs",
        ),
        ("length: 4.5\nwidth: 1.8\nheight: 1.5\nimu_offset: [1.0, 0.9]\n", "imu_offset"),
        (
            "length: -4.5\nwidth: 1.8\nheight: 1.5\nimu_offset: [1.0, 0.9, 0.3]\n",
            "length: Input should be greater",
        ),
        (
            "length: 2024-01-01\nwidth: 1.8\nheight: 1.5\nimu_offset: [1.0, 0.9, 0.3]\n",
            "not JSON-representable",
        ),
    ],
)
def test_bad_vehicle_names_file_and_field(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path, "vehicle.yaml", text)
    with pytest.raises(InputError) as info:
        load_vehicle(path)
    assert info.value.source == str(path)
    assert expected in info.value.detail


@pytest.mark.parametrize(
    "loader", [load_intrinsics, load_vehicle, load_toolbox_detections, load_toolbox_poses, load_ground_truth]
)
def test_missing_file_is_input_error(tmp_path: Path, loader: object) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(InputError) as info:
        loader(path)  # type: ignore[operator]
    assert info.value.source == str(path)
    assert info.value.detail.startswith("(file): cannot read")


def test_bad_json_files_name_field(tmp_path: Path) -> None:
    truth = json.loads(_ground_truth("north").model_dump_json())
    truth["frames"][1]["calib_box"] = -1
    path = _write(tmp_path, "ground_truth.json", json.dumps(truth))
    with pytest.raises(InputError, match=r"frames\.1\.calib_box"):
        load_ground_truth(path)
    path = _write(tmp_path, "calib.json", '{"rsu_id": "a",')
    with pytest.raises(InputError, match="Invalid JSON") as info:
        load_calibration_result(path)
    assert info.value.source == str(path)
    path = _write(tmp_path, "calib2.json", json.dumps({"rsu_id": "a", "camera_id": "b"}))
    with pytest.raises(InputError, match="result_id: Field required"):
        load_calibration_result(path)


def test_non_utf8_file_is_input_error(tmp_path: Path) -> None:
    path = tmp_path / "detections.yaml"
    path.write_bytes(b"\xff\xfe\x00garbage: [")
    with pytest.raises(InputError, match=r"\(yaml\)"):
        load_toolbox_detections(path)


def test_huge_float_row_overflowing_the_fast_check_still_loads(tmp_path: Path) -> None:
    # Finite values whose sum overflows must take the per-value path, not be reported as non-finite.
    path = _write(tmp_path, "poses.yaml", f"{T0}: [1.0e+308, 1.0e+308, 0.0, 0.0, 0.0, 0.0]\n")
    (pose,) = load_toolbox_poses(path)
    assert pose.x == 1e308 and math.isfinite(pose.y)


_yaml_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.integers() | st.text(max_size=20), inner, max_size=4)
    ),
    max_leaves=30,
)


@settings(max_examples=150, deadline=None)
@given(document=_yaml_values | st.text(max_size=200))
def test_any_document_loads_or_raises_input_error(
    tmp_path_factory: pytest.TempPathFactory, document: object
) -> None:
    # Whatever a file holds, the loaders answer with data or an InputError naming the file: never a crash.
    path = tmp_path_factory.mktemp("fuzz") / "file.yaml"
    path.write_text(document if isinstance(document, str) else yaml.safe_dump(document), encoding="utf-8")
    for loader in (load_toolbox_detections, load_toolbox_poses, load_intrinsics, load_vehicle):
        try:
            loader(path)
        except InputError as err:
            assert err.source == str(path)
