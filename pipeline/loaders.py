"""The one file edge of the pipeline: YAML/JSON files <-> schema objects.

Reads the reference toolbox's files (camera.yaml, vehicle.yaml, detections.yaml, poses.yaml), our own
results (CalibrationResult JSON) and the simulator's ground_truth.json; writes the simulator's files in
the same formats. Every loader raises InputError(str(path), "<field>: <problem>") on bad input.
Recordings (MCAP) are read in daemon/recording.py: pipeline/ never imports mcap.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from pipeline.errors import InputError
from pipeline.frames import UtmFrame
from schemas.common import (
    STAMP_NS_MAX,
    STAMP_NS_MIN,
    CameraIntrinsics,
    VehicleProfile,
    decode_json,
    decode_mapping,
    describe_validation_error,
)
from schemas.config import DaemonConfig
from schemas.files import GroundTruth
from schemas.messages import DetectionFrame, VehiclePose
from schemas.results import CalibrationResult

if TYPE_CHECKING:
    _YamlLoaderBase = yaml.SafeLoader
else:
    # libyaml's parser is ~5x faster than the pure-Python one; fall back when PyYAML was built without it.
    _YamlLoaderBase = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

# A 15-minute toolbox recording is ~10 MB (9000 frames x 30 boxes); 256 MiB leaves ample room for long
# recordings while refusing a file that would exhaust memory once parsed.
MAX_FILE_BYTES = 256 * 1024 * 1024

# No camera, vehicle, config or toolbox file nests deeper, and deeper is dangerous: libyaml's composer
# recurses in C (a segfault at ~25,000 levels) and json.dumps in decode_mapping at ~1,000.
MAX_YAML_DEPTH = 64
# Aliases can make a few hundred bytes expand into 10^8 values once decode_mapping serialises them
# ("billion laughs"); real camera.yaml / vehicle.yaml / rsu.yaml documents have under 2,000.
MAX_MODEL_VALUES = 100_000

DETECTION_FIELDS = ("cx", "cy", "w", "h", "class_id")
POSE_FIELDS = ("x", "y", "z", "yaw", "pitch", "roll")

M = TypeVar("M", bound=BaseModel)


# ---------------------------------------------------------------------------------------------- reading


class _StrictYamlLoader(_YamlLoaderBase):
    """Safe loader that refuses duplicate mapping keys (PyYAML silently keeps the last one)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        mapping: dict[Any, Any] = super().construct_mapping(node, deep=deep)
        if len(mapping) != len(node.value):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r}", key_node.start_mark
                    )
                seen.add(key)
        return mapping


def _read_bytes(path: Path) -> bytes:
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise InputError(str(path), f"(file): {size} bytes is more than the limit of {MAX_FILE_BYTES}")
        return path.read_bytes()
    except OSError as err:
        raise InputError(str(path), f"(file): cannot read: {err.strerror or err}") from err


def _describe_yaml_error(err: yaml.YAMLError) -> str:
    if isinstance(err, yaml.MarkedYAMLError) and err.problem_mark is not None:
        mark = err.problem_mark
        problem = err.problem or str(err)
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    return " ".join(str(err).split())


def _check_depth(path: Path, text: str | bytes) -> None:
    """Refuse nesting beyond MAX_YAML_DEPTH, on the event stream (no recursion) before anything is built."""
    depth = 0
    for event in yaml.parse(text, Loader=_YamlLoaderBase):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                mark = event.start_mark
                where = "" if mark is None else f"line {mark.line + 1}, column {mark.column + 1}: "
                raise InputError(str(path), f"(yaml): {where}nested deeper than {MAX_YAML_DEPTH} levels")
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def _parse_yaml(path: Path, text: str | bytes) -> Any:
    try:
        _check_depth(path, text)
        return yaml.load(text, Loader=_StrictYamlLoader)
    except yaml.YAMLError as err:
        raise InputError(str(path), f"(yaml): {_describe_yaml_error(err)}") from err
    except ValueError as err:  # PyYAML's int() of a scalar beyond Python's 4300-digit limit
        raise InputError(str(path), f"(yaml): {err}") from err


# The toolbox files are large and regular. PyYAML (even with libyaml) spends ~2 s per 1000 frames of 30
# boxes resolving scalar tags in Python, so lines in the exact layout written below are parsed here
# (~10x faster); any other line (comments, block rows, quoting styles, exponents...) sends the whole file
# through PyYAML.
# The number grammar is deliberately narrower than YAML 1.1's so both parsers agree on every value:
# integers without leading zeros (YAML 1.1 reads 012 as octal) and plain decimals with a dot.
_NUMBER = r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?"
_FLOW_ROW = rf"\[ *(?:{_NUMBER}(?: *, *{_NUMBER})*)? *\]"
_KEY_RE = re.compile(rf"^(?:([0-9]+)|\"([0-9]+)\"|'([0-9]+)'):(?: +({_FLOW_ROW}))? *$")
_ITEM_RE = re.compile(rf"^( *)- +({_FLOW_ROW}) *$")
_SPLIT_RE = re.compile(r" *, *")


def _parse_flow_numbers(row: str) -> list[int | float]:
    inner = row[1:-1].strip()
    if not inner:
        return []
    return [float(tok) if "." in tok else int(tok) for tok in _SPLIT_RE.split(inner)]


def _fast_parse_stamped_rows(text: str) -> dict[int | str, Any] | None:
    """Parse `stamp: [numbers]` / `stamp:` + `- [numbers]` lines; None when the file leaves that layout.

    Returns what yaml.safe_load would (int keys for plain stamps, str keys for quoted ones).
    """
    data: dict[int | str, Any] = {}
    open_key: int | str | None = None  # key whose block sequence is being filled
    rows: list[Any] = []
    indent: str | None = None  # block sequence entries must share one indentation
    # Split on LF only: str.splitlines() also breaks at characters YAML does not (\x1c-\x1e), where
    # the regexes below would then accept what PyYAML rejects.
    for raw_line in text.split("\n"):
        line = raw_line.removesuffix("\r")
        if not line.strip(" "):
            continue
        item = _ITEM_RE.match(line)
        if item is not None:
            if open_key is None or (indent is not None and item.group(1) != indent):
                return None
            indent = item.group(1)
            rows.append(_parse_flow_numbers(item.group(2)))
            continue
        key_match = _KEY_RE.match(line)
        if key_match is None:
            return None
        if open_key is not None:
            # `stamp:` followed by no items is null in YAML, not an empty list.
            data[open_key] = rows or None
            open_key = None
        plain, double, single, flow = key_match.groups()
        key: int | str
        if plain is not None:
            if len(plain) > 1 and plain.startswith("0"):
                return None  # octal in YAML 1.1: let PyYAML decide
            key = int(plain)
        else:
            key = double if double is not None else single
        if key in data:
            return None  # PyYAML reports the duplicate with its line number
        if flow is not None:
            data[key] = _parse_flow_numbers(flow)
        else:
            open_key, rows, indent = key, [], None
            data[key] = None  # placeholder keeps file order and catches a repeat of this key
    if open_key is not None:
        data[open_key] = rows or None
    return data or None


def _load_stamped_yaml(path: Path) -> dict[Any, Any]:
    raw = _read_bytes(path)
    data: Any = None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None:
        try:
            data = _fast_parse_stamped_rows(text)
        except ValueError:  # an integer beyond Python's digit limit: PyYAML reports it with its line
            data = None
    if data is None:
        data = _parse_yaml(path, raw)
    if data is None:
        raise InputError(str(path), "(root): the file is empty; expected a mapping stamp_ns -> rows")
    if not isinstance(data, dict):
        raise InputError(str(path), f"(root): expected a mapping stamp_ns -> rows, got {type(data).__name__}")
    return data


def _parse_stamp(path: Path, key: Any) -> int:
    """Stamp keys are int ns; toolbox files may quote them, but floats would have lost precision."""
    if isinstance(key, bool) or not isinstance(key, int | str):
        raise InputError(str(path), f"{key!r}: stamp must be an integer (ns), got {type(key).__name__}")
    if isinstance(key, str):
        if not re.fullmatch(r"[0-9]{1,20}", key.strip()):
            raise InputError(str(path), f"{key!r}: stamp must be an integer (ns)")
        stamp = int(key)
    else:
        stamp = key
    if not STAMP_NS_MIN <= stamp <= STAMP_NS_MAX:
        raise InputError(
            str(path), f"{key}: stamp {stamp} is outside [{STAMP_NS_MIN}, {STAMP_NS_MAX}] ns since the epoch"
        )
    return stamp


def _number(path: Path, where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(str(path), f"{where}: expected a number, got {type(value).__name__} {value!r}")
    try:
        number = float(value)
    except OverflowError:  # a YAML integer beyond float range
        raise InputError(str(path), f"{where}: {value} is out of range") from None
    if not math.isfinite(number):
        raise InputError(str(path), f"{where}: must be finite, got {value}")
    return number


def _row(path: Path, where: str, row: Any, names: Sequence[str]) -> list[float]:
    if type(row) is list and len(row) == len(names) and all(type(v) is float or type(v) is int for v in row):
        # Hot path (hundreds of thousands of rows): one finiteness test per row. A nan/inf makes the sum
        # non-finite; a sum that merely overflows, or a huge int, falls through to the per-value checks.
        try:
            values = [float(v) for v in row]
        except OverflowError:
            values = [math.inf]
        if math.isfinite(sum(values)):
            return values
    if not isinstance(row, list):
        raise InputError(
            str(path), f"{where}: expected a list [{', '.join(names)}], got {type(row).__name__}"
        )
    if len(row) != len(names):
        raise InputError(
            str(path), f"{where}: expected {len(names)} values [{', '.join(names)}], got {len(row)}"
        )
    return [_number(path, f"{where}.{name}", value) for name, value in zip(names, row, strict=True)]


def _sorted_stamps(path: Path, data: dict[Any, Any]) -> list[tuple[int, Any, Any]]:
    """(stamp, original key, value) sorted by stamp; "123" and 123 in one file are the same stamp."""
    entries = [(_parse_stamp(path, key), key, value) for key, value in data.items()]
    entries.sort(key=lambda entry: entry[0])
    for (stamp_a, key_a, _), (stamp_b, key_b, _) in itertools.pairwise(entries):
        if stamp_a == stamp_b:
            raise InputError(str(path), f"{key_b}: duplicate stamp (also given as {key_a!r})")
    return entries


def _check_size(path: Path, data: Any) -> None:
    """Refuse documents of more than MAX_MODEL_VALUES values with aliases expanded (and cyclic ones)."""
    pending, seen = [data], 0
    while pending:
        node = pending.pop()
        seen += 1
        if seen > MAX_MODEL_VALUES:
            raise InputError(
                str(path), f"(yaml): more than {MAX_MODEL_VALUES} values once aliases (*name) are expanded"
            )
        if isinstance(node, dict):
            pending.extend(node.keys())
            pending.extend(node.values())
        elif isinstance(node, list):
            pending.extend(node)


def _load_model_yaml(path: Path, model: type[M]) -> M:
    data = _parse_yaml(path, _read_bytes(path))
    if not isinstance(data, dict):
        raise InputError(
            str(path), f"(root): expected a mapping of {model.__name__} fields, got {type(data).__name__}"
        )
    _check_size(path, data)
    try:
        return decode_mapping(model, data)
    except ValidationError as err:
        raise InputError(str(path), describe_validation_error(err)) from err
    except ValueError as err:  # YAML-only values (dates, sets...) that have no JSON form
        raise InputError(str(path), f"(root): {err}") from err


def _load_model_json(path: Path, model: type[M]) -> M:
    try:
        return decode_json(model, _read_bytes(path))
    except ValidationError as err:
        raise InputError(str(path), describe_validation_error(err)) from err


def load_daemon_config(path: Path) -> DaemonConfig:
    """rsu.yaml of `rsucal daemon`; relative paths in it (state_dir, zenoh.config_file) stay as written."""
    config = _load_model_yaml(Path(path), DaemonConfig)
    if config.crs is not None:
        try:
            UtmFrame(config.crs)  # the schema checks the form only; the daemon needs a UTM zone
        except InputError as err:
            raise InputError(str(path), err.detail) from err
    return config


def load_intrinsics(path: Path) -> CameraIntrinsics:
    """camera.yaml: exactly width, height, fx, fy, cx, cy (px) and optional dist [k1, k2, p1, p2, k3]."""
    return _load_model_yaml(Path(path), CameraIntrinsics)


def load_vehicle(path: Path) -> VehicleProfile:
    """vehicle.yaml: length, width, height (m) and imu_offset [x, y, z] in the vehicle box frame (m)."""
    return _load_model_yaml(Path(path), VehicleProfile)


def load_toolbox_detections(path: Path, camera_id: str = "camera") -> list[DetectionFrame]:
    """detections.yaml `{stamp_ns: [[cx, cy, w, h, class_id], ...]}` (box centre and size, px) -> frames.

    The reference toolbox's format; class_id 4 car, 5 truck, 6 van, 7 bus. The file names no camera, so
    `camera_id` is set on every frame. Frames come back sorted by stamp, boxes as x1, y1, x2, y2 with
    score 1.0 (the toolbox has none). A frame may hold no boxes.
    """
    path = Path(path)
    frames: list[DetectionFrame] = []
    for stamp, key, rows in _sorted_stamps(path, _load_stamped_yaml(path)):
        if rows is None:
            rows = []  # `stamp:` with nothing under it: an empty frame
        if not isinstance(rows, list):
            raise InputError(str(path), f"{key}: expected a list of boxes, got {type(rows).__name__}")
        boxes = []
        for index, row in enumerate(rows):
            where = f"{key}.{index}"
            cx, cy, w, h, class_id = _row(path, where, row, DETECTION_FIELDS)
            if w <= 0.0:
                raise InputError(str(path), f"{where}.w: box width must be > 0, got {w}")
            if h <= 0.0:
                raise InputError(str(path), f"{where}.h: box height must be > 0, got {h}")
            if not class_id.is_integer():
                raise InputError(str(path), f"{where}.class_id: expected an integer class id, got {class_id}")
            half_w, half_h = 0.5 * w, 0.5 * h
            boxes.append(
                {
                    "x1": cx - half_w,
                    "y1": cy - half_h,
                    "x2": cx + half_w,
                    "y2": cy + half_h,
                    "cls": int(class_id),
                }
            )
        try:
            frames.append(
                DetectionFrame.model_validate(
                    {"camera_id": camera_id, "stamp_ns": stamp, "boxes": boxes}, strict=True
                )
            )
        except ValidationError as err:
            raise InputError(str(path), f"{key}: {describe_validation_error(err)}") from err
    return frames


def load_toolbox_poses(path: Path) -> list[VehiclePose]:
    """poses.yaml `{stamp_ns: [x, y, z, yaw, pitch, roll]}` (absolute UTM m, rad) -> poses sorted by stamp."""
    path = Path(path)
    poses = []
    for stamp, key, row in _sorted_stamps(path, _load_stamped_yaml(path)):
        x, y, z, yaw, pitch, roll = _row(path, str(key), row, POSE_FIELDS)
        poses.append(VehiclePose(stamp_ns=stamp, x=x, y=y, z=z, yaw=yaw, pitch=pitch, roll=roll))
    return poses


def load_calibration_result(path: Path) -> CalibrationResult:
    """A CalibrationResult JSON file (what `rsucal calibrate` writes and the daemon publishes)."""
    return _load_model_json(Path(path), CalibrationResult)


def load_ground_truth(path: Path) -> GroundTruth:
    """The simulator's ground_truth.json (one camera)."""
    return _load_model_json(Path(path), GroundTruth)
