"""Strict validation of every public model: bad input is rejected with an error naming the field.

The systematic tests walk a complete good example of each model and break one leaf at a time (NaN/inf in
every float, a wrong type in every leaf, an unknown key in every object), so a field added later without
the strict rules fails here. Fuzz tests check that decoding junk never raises anything but ValidationError;
RSUCAL_FUZZ_EXAMPLES raises their example count (e.g. 10000 for a long run).
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

from schemas import (
    Box,
    CalibrationResult,
    CalibrationStatus,
    CameraIntrinsics,
    DetectionFrame,
    GroundTruth,
    LocalOrigin,
    V2xPosition,
    VehiclePose,
    VehicleProfile,
)
from schemas.common import (
    OTHER_CLASS_ID,
    STAMP_NS_MAX,
    STAMP_NS_MIN,
    class_name,
    decode_json,
    decode_mapping,
    describe_validation_error,
    toolbox_class_id,
)
from schemas.messages import MAX_BOXES_PER_FRAME, apply_labels

FUZZ_EXAMPLES = int(os.environ.get("RSUCAL_FUZZ_EXAMPLES", "200"))
STAMP = 1_700_000_000_123_456_789  # 2023-11-14, ns
Path = tuple[str | int, ...]

INTRINSICS = {
    "width": 1920,
    "height": 1080,
    "fx": 1000.0,
    "fy": 1001.5,
    "cx": 960.5,
    "cy": 540.25,
    "dist": [-0.05, 0.01, 0.001, -0.001, 0.002],
}
BOX = {"x1": 10.0, "y1": 20.0, "x2": 110.5, "y2": 80.25, "cls": 4, "score": 0.9}
VERDICT = {"status": "accepted", "reasons": ["all gates passed"]}
MATRIX = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]

# A complete good example of every public model: every optional field filled, floats written as floats.
GOOD: dict[type[BaseModel], dict[str, Any]] = {
    Box: BOX,
    CameraIntrinsics: INTRINSICS,
    VehicleProfile: {"length": 4.8, "width": 1.9, "height": 1.5, "imu_offset": [1.2, 0.95, 0.4]},
    LocalOrigin: {"crs": "EPSG:32632", "x": 500_000.0, "y": 5_400_000.0, "z": 120.0},
    DetectionFrame: {
        "camera_id": "cam-1",
        "stamp_ns": STAMP,
        "boxes": [BOX, {"x1": 300.0, "y1": 400.0, "x2": 420.0, "y2": 500.0, "cls": 5, "score": 0.5}],
    },
    V2xPosition: {
        "station_id": 4242,
        "stamp_ns": STAMP,
        "lat": 48.4,
        "lon": 14.2,
        "alt": 300.5,
        "heading_deg": 359.5,
        "speed": 13.9,
        "length": 4.8,
        "width": 1.9,
        "roll": 0.01,
        "pitch": -0.02,
        "accuracies": {"horizontal_m": 0.02, "vertical_m": 0.04, "heading_deg": 0.3, "speed_mps": 0.1},
    },
    VehiclePose: {
        "stamp_ns": STAMP,
        "x": 512_345.5,
        "y": 5_401_234.25,
        "z": 120.5,
        "yaw": 1.5,
        "pitch": 0.01,
        "roll": -0.02,
    },
    CalibrationResult: {
        "schema_version": "1.0",
        "rsu_id": "rsu-7",
        "camera_id": "cam-1",
        "result_id": "r-0001",
        "created_at_ns": STAMP,
        "frame": {"crs": "EPSG:32632", "origin": [500_000.0, 5_400_000.0, 120.0]},
        "R": MATRIX,
        "t": [1.5, -2.0, 30.25],
        "camera_position": {"utm": [500_010.0, 5_400_020.0, 128.0], "lat": 48.4, "lon": 14.2, "alt": 128.0},
        "orientation_wxyz": [0.7071, 0.7071, 0.0, 0.0],
        "intrinsics": INTRINSICS,
        "ground_plane": {"normal": [0.0, 0.0, 1.0], "offset": -0.5},
        "uncertainty": {
            "covariance": [[1e-4 if i == j else 1e-6 for j in range(6)] for i in range(6)],
            "position_std_m": 0.05,
            "rotation_std_deg": 0.1,
        },
        "quality": {
            "delta_p_mean_m": 0.12,
            "delta_p_max_m": 0.4,
            "e_mean_pct": 1.5,
            "e_max_pct": 4.0,
            "reprojection_rmse_px": 1.2,
            "correspondences": 420,
            "tracks": 3,
            "traversals": 2,
        },
        "verdict": VERDICT,
        "change": {"previous_result_id": "r-0000", "shift_m": 0.02, "shift_deg": 0.05, "moved": False},
        "provenance": {
            "window_start_ns": STAMP,
            "window_end_ns": STAMP + 600_000_000_000,
            "recordings": ["rec-0001.mcap"],
            "station_id": 4242,
            "software_version": "0.1.0",
            "config_hash": "abc123",
        },
    },
    CalibrationStatus: {
        "rsu_id": "rsu-7",
        "camera_id": "cam-1",
        "state": "calibrated",
        "traversals": 3,
        "traversals_needed": 2,
        "last_job": {
            "job_id": "job-1",
            "started_ns": STAMP,
            "finished_ns": STAMP + 5_000_000_000,
            "duration_s": 5.0,
            "verdict": VERDICT,
        },
        "current_result_id": "r-0001",
        "verified_at_ns": STAMP,
        "counters": {"detections_rejected": 2},
        "updated_at_ns": STAMP,
    },
    GroundTruth: {
        "camera_id": "cam-1",
        "crs": "EPSG:32632",
        "origin": [500_000.0, 5_400_000.0, 120.0],
        "R": MATRIX,
        "t_utm": [1.0, 2.0, 3.0],
        "t_local": [4.0, 5.0, 6.0],
        "camera_position_utm": [500_010.0, 5_400_020.0, 128.0],
        "intrinsics": INTRINSICS,
        "station_id": 4242,
        "clock_offset_ns": -5_000_000,
        "traversals": 2,
        "frames": [{"stamp_ns": STAMP, "calib_box": 0, "traversal": 1}],
    },
}
MODELS = list(GOOD)
FREE_FORM_MAPS = {(CalibrationStatus, ("counters",))}  # name -> count; any key is fine


def _ids(model: type[BaseModel]) -> str:
    return model.__name__


def leaves(data: Any, path: Path = ()) -> Iterator[tuple[Path, Any]]:
    """Every (path, value) of a JSON-like tree whose value is not a dict or list."""
    if isinstance(data, dict):
        for key, value in data.items():
            yield from leaves(value, (*path, key))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            yield from leaves(value, (*path, index))
    else:
        yield path, data


def objects(data: Any, path: Path = ()) -> Iterator[Path]:
    """The path of every dict (JSON object) in the tree, the root included."""
    if isinstance(data, dict):
        yield path
        for key, value in data.items():
            yield from objects(value, (*path, key))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            yield from objects(value, (*path, index))


def replaced(data: Any, path: Path, value: Any) -> Any:
    """A deep copy of `data` with the node at `path` set to `value`."""
    out = copy.deepcopy(data)
    node = out
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    return out


def dotted(path: Path) -> str:
    return ".".join(str(part) for part in path)


def rejection(model: type[BaseModel], data: Any, *, via: str = "json") -> str:
    """Decode `data` via `via` (json, mapping or python) and return the described error; fail if accepted."""
    with pytest.raises(ValidationError) as info:
        if via == "json":
            decode_json(model, json.dumps(data, allow_nan=True))
        elif via == "mapping":
            decode_mapping(model, data)
        else:
            model.model_validate(data)
    return describe_validation_error(info.value)


def assert_names(message: str, path: Path) -> None:
    assert f"{dotted(path)}:" in message, f"error does not name {dotted(path)!r}: {message}"


# --- good input -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", MODELS, ids=_ids)
def test_good_example_is_accepted_by_both_decoders(model: type[BaseModel]) -> None:
    from_json = decode_json(model, json.dumps(GOOD[model]))
    from_mapping = decode_mapping(model, GOOD[model])
    assert from_json == from_mapping
    assert decode_json(model, from_json.model_dump_json()) == from_json
    # Every optional field of the example is filled: the systematic tests below reach every field.
    assert from_json.model_fields_set == set(GOOD[model])


def test_minimal_messages_use_the_documented_defaults() -> None:
    frame = decode_json(DetectionFrame, f'{{"camera_id": "c", "stamp_ns": {STAMP}}}')
    assert frame.boxes == []
    box = decode_json(Box, '{"x1": 0, "y1": 0, "x2": 1, "y2": 1}')  # integers are fine for floats
    assert (box.cls, box.score, box.x2) == (4, 1.0, 1.0)
    pose = decode_mapping(VehiclePose, {"stamp_ns": STAMP, "x": 1.0, "y": 2.0, "z": 3.0, "yaw": 0.5})
    assert (pose.pitch, pose.roll) == (0.0, 0.0)


def test_models_are_frozen() -> None:
    frame = decode_mapping(DetectionFrame, GOOD[DetectionFrame])
    with pytest.raises(ValidationError):
        frame.stamp_ns = 1  # type: ignore[misc]


# --- systematic single-leaf breakage ----------------------------------------------------------------------


@pytest.mark.parametrize("model", MODELS, ids=_ids)
def test_non_finite_float_is_rejected_in_every_float_field(model: type[BaseModel]) -> None:
    good = GOOD[model]
    float_paths = [path for path, value in leaves(good) if type(value) is float]
    assert float_paths
    for path in float_paths:
        for bad in (math.nan, math.inf, -math.inf):
            broken = replaced(good, path, bad)
            raw = json.dumps(broken, allow_nan=True)
            assert ("NaN" if math.isnan(bad) else "Infinity") in raw  # the JSON literal, not a string
            assert_names(rejection(model, broken, via="json"), path)
            assert_names(rejection(model, broken, via="mapping"), path)
            assert_names(rejection(model, broken, via="python"), path)  # Python floats, lax mode


@pytest.mark.parametrize("model", MODELS, ids=_ids)
def test_unknown_field_is_rejected_at_every_level(model: type[BaseModel]) -> None:
    good = GOOD[model]
    for path in objects(good):
        if (model, path) in FREE_FORM_MAPS:
            continue
        broken = replaced(good, (*path, "foo"), 1)
        message = rejection(model, broken)
        assert_names(message, (*path, "foo"))
        assert "Extra inputs are not permitted" in message


def _wrong_types(value: Any) -> list[Any]:
    """Values of the wrong JSON type for a leaf holding `value` (strict: no coercion of any kind)."""
    if type(value) is bool:
        return [1, "true", None]
    if type(value) is int:
        return [str(value), True, float(value), float(value) + 0.5, [value]]
    if type(value) is float:
        return [str(value), True, [value], {"value": value}]
    if type(value) is str:
        return [12, True, [value]]
    raise AssertionError(f"unexpected leaf {value!r}")


@pytest.mark.parametrize("model", MODELS, ids=_ids)
def test_wrong_type_is_rejected_in_every_field(model: type[BaseModel]) -> None:
    good = GOOD[model]
    for path, value in leaves(good):
        for bad in _wrong_types(value):
            assert_names(rejection(model, replaced(good, path, bad)), path)


# --- specific rules -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("lat", 90.0001),
        ("lat", -90.5),
        ("lon", 180.5),
        ("lon", -181.0),
        ("heading_deg", 360.0),
        ("heading_deg", -0.1),
        ("speed", -1.0),
        ("alt", 20_000.0),
        ("station_id", -1),
        ("station_id", 2**32),
        ("length", 0.0),
        ("pitch", 3.2),
    ],
)
def test_v2x_out_of_range_is_rejected(field: str, value: float) -> None:
    message = rejection(V2xPosition, {**GOOD[V2xPosition], field: value})
    assert_names(message, (field,))


@pytest.mark.parametrize(("field", "value"), [("lat", 90.0), ("lon", -180.0), ("heading_deg", 0.0)])
def test_v2x_range_edges_are_accepted(field: str, value: float) -> None:
    assert getattr(decode_mapping(V2xPosition, {**GOOD[V2xPosition], field: value}), field) == value


@pytest.mark.parametrize("field", ["length", "width", "height"])
@pytest.mark.parametrize("value", [-1.0, 0.0])
def test_vehicle_sizes_must_be_positive(field: str, value: float) -> None:
    assert_names(rejection(VehicleProfile, {**GOOD[VehicleProfile], field: value}), (field,))


@pytest.mark.parametrize(
    ("changes", "named"),
    [({"x2": 10.0}, "x2"), ({"x2": 5.0}, "x2"), ({"y2": 20.0}, "y2"), ({"y2": -3.0}, "y2")],
)
def test_box_needs_positive_width_and_height(changes: dict[str, float], named: str) -> None:
    frame = replaced(GOOD[DetectionFrame], ("boxes", 1), {**BOX, **changes})
    message = rejection(DetectionFrame, frame)
    assert_names(message, ("boxes", 1))
    assert named in message


@pytest.mark.parametrize("field", ["x1", "y1", "x2", "y2"])
def test_box_coordinates_beyond_any_image_are_rejected(field: str) -> None:
    box = {"x1": -2e5, "y1": -2e5, "x2": 2e5, "y2": 2e5}
    message = rejection(Box, {"x1": 0.0, "y1": 0.0, "x2": 1.0, "y2": 1.0, field: box[field]})
    assert_names(message, (field,))


def test_box_score_and_class_ranges() -> None:
    assert_names(rejection(Box, {**BOX, "score": 1.5}), ("score",))
    assert_names(rejection(Box, {**BOX, "score": -0.1}), ("score",))
    assert_names(rejection(Box, {**BOX, "cls": -1}), ("cls",))


def test_box_class_is_an_id_or_a_name() -> None:
    assert decode_json(Box, json.dumps({**BOX, "cls": "car"})).cls == "car"
    assert decode_json(Box, json.dumps({**BOX, "cls": "traffic light"})).cls == "traffic light"
    assert decode_json(Box, json.dumps({**BOX, "cls": 1000})).cls == 1000
    # Each error names the field and says what would be right.
    assert describe_validation_error(_error(Box, {**BOX, "cls": -1})) == (
        "cls: Value error, class id -1 is outside [0, 1000]"
    )
    for name in ("4", "x" * 33, "", "car!"):
        message = describe_validation_error(_error(Box, {**BOX, "cls": name}))
        assert message.startswith("cls: Value error, class name ") and "starting with a letter" in message
    for value, kind in ((4.0, "float"), (True, "bool"), (None, "NoneType"), ([4], "list")):
        message = describe_validation_error(_error(Box, {**BOX, "cls": value}))
        assert message == (
            f"cls: Value error, expected an integer class id or a class name like 'car', got {kind}"
        )


def _error(model: type[Box], data: dict[str, Any]) -> ValidationError:
    with pytest.raises(ValidationError) as info:
        decode_json(model, json.dumps(data))
    return info.value


def test_class_names_and_toolbox_ids() -> None:
    coco = {2: "car", 5: "bus", 7: "Truck"}
    assert [class_name(label, coco) for label in (2, 7, 0, "Van")] == ["car", "truck", 0, "van"]
    assert [class_name(label) for label in (2, "car")] == [2, "car"]
    assert [toolbox_class_id(label) for label in ("car", "TRUCK", "van", "bus", "motorcycle", 9)] == [
        4,
        5,
        6,
        7,
        OTHER_CLASS_ID,
        9,
    ]


@pytest.mark.parametrize(
    "stamp",
    [
        -1,
        0,
        1_700_000_000,  # seconds
        1_700_000_000_000,  # milliseconds
        1_700_000_000_000_000,  # microseconds
        STAMP_NS_MIN - 1,
        STAMP_NS_MAX + 1,  # beyond 2200
        2**63,
        2**64,
    ],
)
def test_stamp_outside_2000_to_2200_in_ns_is_rejected(stamp: int) -> None:
    assert_names(rejection(DetectionFrame, {**GOOD[DetectionFrame], "stamp_ns": stamp}), ("stamp_ns",))
    assert_names(rejection(VehiclePose, {**GOOD[VehiclePose], "stamp_ns": stamp}), ("stamp_ns",))


@pytest.mark.parametrize(
    "raw_stamp", ["1700000000.5", "1.7e18", "1700000000000000000.0", '"12"', "true", "null"]
)
def test_stamp_must_be_a_json_integer(raw_stamp: str) -> None:
    with pytest.raises(ValidationError) as info:
        decode_json(DetectionFrame, f'{{"camera_id": "c", "stamp_ns": {raw_stamp}}}')
    assert_names(describe_validation_error(info.value), ("stamp_ns",))


@pytest.mark.parametrize("stamp", [STAMP_NS_MIN, STAMP, STAMP_NS_MAX])
def test_stamp_range_edges_are_accepted(stamp: int) -> None:
    assert decode_mapping(DetectionFrame, {**GOOD[DetectionFrame], "stamp_ns": stamp}).stamp_ns == stamp


@pytest.mark.parametrize(
    "camera_id",
    ["", "cam/1", "cam*", "cam/**", "cam$1", "cam?", "cam#", "a b", "cam\n", "kämera", "x" * 65, "c:1"],
)
def test_unsafe_or_empty_identifier_is_rejected(camera_id: str) -> None:
    # '/' and '*' would change the meaning of rsu/{rsu}/camera/{cam}/... Zenoh keys.
    assert_names(rejection(DetectionFrame, {**GOOD[DetectionFrame], "camera_id": camera_id}), ("camera_id",))
    assert_names(rejection(CalibrationStatus, {**GOOD[CalibrationStatus], "rsu_id": camera_id}), ("rsu_id",))


@pytest.mark.parametrize("camera_id", ["c", "cam-1", "north_2.a", "X" * 64])
def test_safe_identifier_is_accepted(camera_id: str) -> None:
    assert (
        decode_mapping(DetectionFrame, {**GOOD[DetectionFrame], "camera_id": camera_id}).camera_id
        == camera_id
    )


def test_oversized_box_list_is_rejected() -> None:
    boxes = [BOX] * MAX_BOXES_PER_FRAME
    assert len(decode_mapping(DetectionFrame, {**GOOD[DetectionFrame], "boxes": boxes}).boxes) == len(boxes)
    message = rejection(DetectionFrame, {**GOOD[DetectionFrame], "boxes": [*boxes, BOX]})
    assert_names(message, ("boxes",))
    assert "at most 2000" in message


@pytest.mark.parametrize("missing", ["R", "t"])
def test_accepted_calibration_needs_r_and_t(missing: str) -> None:
    message = rejection(CalibrationResult, {**GOOD[CalibrationResult], missing: None})
    assert "accepted result needs R and t" in message
    without = {k: v for k, v in GOOD[CalibrationResult].items() if k != missing}
    assert "accepted result needs R and t" in rejection(CalibrationResult, without)


def test_refused_calibration_without_pose_is_accepted() -> None:
    refused = {
        **GOOD[CalibrationResult],
        "R": None,
        "t": None,
        "verdict": {"status": "refused", "reasons": ["x"]},
    }
    result = decode_mapping(CalibrationResult, refused)
    assert result.R is None and not result.verdict.is_accepted


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("R", 1), [1.0, 0.0]),  # a 3x3 matrix with a short row
        (("t",), [1.0, 2.0, 3.0, 4.0]),
        (("verdict", "status"), "maybe"),
        (("frame", "crs"), "WGS84"),
        (("uncertainty", "position_std_m"), -0.1),
        (("quality", "tracks"), -1),
    ],
)
def test_calibration_result_structure_is_enforced(path: Path, value: Any) -> None:
    message = rejection(CalibrationResult, replaced(GOOD[CalibrationResult], path, value))
    assert dotted(path) in message


def test_missing_required_field_is_named() -> None:
    frame = {k: v for k, v in GOOD[DetectionFrame].items() if k != "stamp_ns"}
    assert "stamp_ns: Field required" in rejection(DetectionFrame, frame)
    box = {k: v for k, v in BOX.items() if k != "y2"}
    assert "boxes.0.y2: Field required" in rejection(
        DetectionFrame, {**frame, "stamp_ns": STAMP, "boxes": [box]}
    )


def test_describe_lists_every_problem_with_its_dotted_path() -> None:
    bad = {"camera_id": "", "stamp_ns": -1, "boxes": [BOX, {**BOX, "x1": math.nan, "foo": 2}]}
    parts = rejection(DetectionFrame, bad).split("; ")
    assert sorted(part.split(":")[0] for part in parts) == [
        "boxes.1.foo",
        "boxes.1.x1",
        "camera_id",
        "stamp_ns",
    ]


def test_decode_mapping_rejects_non_json_data() -> None:
    with pytest.raises(ValueError, match="not JSON-representable"):
        decode_mapping(DetectionFrame, {"camera_id": "c", "stamp_ns": STAMP, "boxes": {object()}})


def test_broken_json_is_a_validation_error() -> None:
    for raw in [b"", b"{", b"\xff\xfe", b"[" * 100_000, b'{"camera_id": "c", "stamp_ns": 1e999}', b"null"]:
        with pytest.raises(ValidationError):
            decode_json(DetectionFrame, raw)


# --- property tests ----------------------------------------------------------------------------------------

identifiers = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True)
stamps = st.integers(STAMP_NS_MIN, STAMP_NS_MAX)


@st.composite
def boxes(draw: st.DrawFn) -> Box:
    x1 = draw(st.floats(-1e4, 1e4))
    y1 = draw(st.floats(-1e4, 1e4))
    # Width/height >= 1e-2 px stay representable next to |x1| <= 1e4, so x2 > x1 exactly.
    return Box(
        x1=x1,
        y1=y1,
        x2=x1 + draw(st.floats(1e-2, 1e4)),
        y2=y1 + draw(st.floats(1e-2, 1e4)),
        cls=draw(st.integers(0, 1000)),
        score=draw(st.floats(0.0, 1.0)),
    )


detection_frames = st.builds(
    DetectionFrame, camera_id=identifiers, stamp_ns=stamps, boxes=st.lists(boxes(), max_size=20)
)
v2x_positions = st.builds(
    V2xPosition,
    station_id=st.integers(0, 2**32 - 1),
    stamp_ns=stamps,
    lat=st.floats(-90.0, 90.0),
    lon=st.floats(-180.0, 180.0),
    alt=st.floats(-1000.0, 10_000.0),
    heading_deg=st.floats(0.0, 360.0, exclude_max=True),
    speed=st.floats(0.0, 100.0),
    length=st.none() | st.floats(0.1, 30.0),
    roll=st.none() | st.floats(-1.6, 1.6),
)


@settings(max_examples=100, deadline=None)
@given(frame=detection_frames)
def test_valid_detection_frames_round_trip_through_json(frame: DetectionFrame) -> None:
    raw = frame.model_dump_json()
    assert decode_json(DetectionFrame, raw) == frame
    assert decode_mapping(DetectionFrame, json.loads(raw)) == frame


@settings(max_examples=100, deadline=None)
@given(position=v2x_positions)
def test_valid_v2x_positions_round_trip_through_json(position: V2xPosition) -> None:
    assert decode_json(V2xPosition, position.model_dump_json()) == position


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=30,
)
models = st.sampled_from(MODELS)
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _decode_or_validation_error(model: type[BaseModel], raw: bytes | str) -> None:
    try:
        decoded = decode_json(model, raw)
    except ValidationError:
        return
    assert decode_json(model, decoded.model_dump_json()) == decoded


@FUZZ
@given(model=models, raw=st.binary(max_size=200) | st.text(max_size=200))
def test_junk_bytes_only_raise_validation_error(model: type[BaseModel], raw: bytes | str) -> None:
    _decode_or_validation_error(model, raw)


@FUZZ
@given(model=models, data=json_values)
def test_junk_json_only_raises_validation_error(model: type[BaseModel], data: Any) -> None:
    _decode_or_validation_error(model, json.dumps(data, allow_nan=True))
    with contextlib.suppress(ValidationError):
        decode_mapping(model, data)


@FUZZ
@given(model=models, data=st.data())
def test_one_broken_field_is_rejected_by_name_or_accepted(
    model: type[BaseModel], data: st.DataObject
) -> None:
    """A good message with one node replaced (or one key added) by junk: accepted, or rejected there."""
    good = GOOD[model]
    targets = [path for path, _ in leaves(good)] + [(*p, "extra") for p in objects(good)]
    path = data.draw(st.sampled_from(targets), label="path")
    junk = data.draw(json_values, label="junk")
    broken = replaced(good, path, junk)
    try:
        decode_mapping(model, broken)
    except ValidationError as err:
        for item in err.errors():
            loc = tuple(item["loc"])
            # The error sits at the broken node, inside it, or (model-level rules) above it.
            assert loc[: len(path)] == path or path[: len(loc)] == loc, (loc, path, item["msg"])


# ---------------------------------------------------------------------------------------------- fast path

_NUMBERS = st.one_of(
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, 1000, 1001, -1e5, 1e5, 1e5 + 1, 0.5, 1.0, 1.0000001]),
)
# Class names on both sides of the limits: valid names, digits-first, too long, empty, odd characters.
_CLASS_NAMES = st.one_of(
    st.sampled_from(["car", "Truck", "traffic light", "e-scooter", "4", "4car", "", "x" * 32, "x" * 33, "!"]),
    st.text(max_size=6),
)
_VALUES = st.one_of(
    _NUMBERS, st.booleans(), st.none(), st.text(max_size=5), st.sampled_from(["1", "4"]), _CLASS_NAMES
)
_COORDS = st.floats(-1e5, 1e5, allow_nan=False)
_SIZES = st.one_of(st.floats(0.0, 500.0, allow_nan=False), st.sampled_from([0.0, 1e-9, 2e5]))


@st.composite
def _valid_box(draw: st.DrawFn) -> dict[str, Any]:
    x1, y1 = draw(_COORDS), draw(_COORDS)
    box: dict[str, Any] = {"x1": x1, "y1": y1, "x2": x1 + draw(_SIZES), "y2": y1 + draw(_SIZES)}
    if draw(st.booleans()):
        box["cls"] = draw(st.one_of(st.integers(0, 1000), _CLASS_NAMES))
    if draw(st.booleans()):
        box["score"] = draw(st.floats(0.0, 1.0))
    return box


@st.composite
def _FRAMES(draw: st.DrawFn) -> dict[str, Any]:
    """Mostly valid frames, some with one field replaced, removed or added: both sides of every limit."""
    frame: dict[str, Any] = {
        "camera_id": draw(st.sampled_from(["c1", "cam-2.a", "X" * 64])),
        "stamp_ns": draw(st.integers(STAMP_NS_MIN, STAMP_NS_MAX)),
        "boxes": draw(st.lists(_valid_box(), max_size=4)),
    }
    target = frame
    if frame["boxes"] and draw(st.booleans()):
        target = draw(st.sampled_from(frame["boxes"]))
    action = draw(st.sampled_from(["none", "replace", "delete", "add"]))
    key = draw(st.sampled_from([*target, "extra"]))
    if action == "replace":
        target[key] = draw(_VALUES)
    elif action == "delete":
        target.pop(key, None)
    elif action == "add":
        target["extra" if key in target else key] = draw(_VALUES)
    return frame


@settings(max_examples=max(500, FUZZ_EXAMPLES), deadline=None, derandomize=True)
@given(frame=_FRAMES())
def test_fast_detection_check_accepts_exactly_what_the_model_accepts(frame: dict[str, Any]) -> None:
    """check_detection_frame's mirror of DetectionFrame must never let through what the model rejects (it
    would be logged and counted as valid) and should pass what the model passes (else it is only slower)."""
    from schemas.messages import _DETECTION_FRAME_FIELDS, check_detection_frame

    raw = json.dumps(frame, allow_nan=True)
    try:
        model = DetectionFrame.model_validate_json(raw, strict=True)
    except ValidationError:
        model = None
    try:
        fields = _DETECTION_FRAME_FIELDS.validate_json(raw, strict=True)
        ordered = all(b["x2"] > b["x1"] and b["y2"] > b["y1"] for b in fields.get("boxes", ()))
    except ValidationError:
        ordered = False
    assert ordered == (model is not None), raw
    if model is None:
        with pytest.raises(ValidationError):
            check_detection_frame(raw)
    else:
        assert check_detection_frame(raw) == (model.camera_id, model.stamp_ns, len(model.boxes))


def test_apply_labels_names_the_mapped_ids_only() -> None:
    frame = DetectionFrame(
        camera_id="c",
        stamp_ns=STAMP_NS_MIN,
        boxes=[
            Box(x1=0, y1=0, x2=1, y2=1, cls=2),
            Box(x1=0, y1=0, x2=1, y2=1, cls=9),
            Box(x1=0, y1=0, x2=1, y2=1, cls="Van"),
        ],
    )
    untouched = DetectionFrame(
        camera_id="c", stamp_ns=STAMP_NS_MIN + 1, boxes=[Box(x1=0, y1=0, x2=1, y2=1, cls=9)]
    )
    named = apply_labels([frame, untouched], {2: "Car", 7: "truck"})
    assert [box.cls for box in named[0].boxes] == ["car", 9, "Van"]
    assert named[1] is untouched
    assert apply_labels([frame], None)[0] is frame
