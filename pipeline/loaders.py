"""The one file edge of the pipeline: YAML/JSON files <-> schema objects.

Reads the reference toolbox's files (camera.yaml, vehicle.yaml, detections.yaml, poses.yaml), our own
results (CalibrationResult JSON) and the simulator's ground_truth.json; writes the simulator's files in
the same formats. Every loader raises InputError(str(path), "<field>: <problem>") on bad input.
Recordings (MCAP) are read in daemon/recording.py: pipeline/ never imports mcap.
"""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import yaml
from pydantic import BaseModel, ValidationError

from pipeline.arrays import FloatArray, Stamps
from pipeline.errors import InputError
from pipeline.frames import UtmFrame
from pipeline.tables import DetectionTable, PoseTable
from schemas.common import (
    IDENTIFIER,
    MAX_CLASS_ID,
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
from schemas.messages import MAX_BOXES_PER_FRAME, DetectionFrame, VehiclePose
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
# schemas.common.PixelCoord's bound: a box corner beyond it fails the DetectionFrame's validation.
_PIXEL_LIMIT = 1e5

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


class _OpenCvYamlLoader(_StrictYamlLoader):
    """_StrictYamlLoader that also reads OpenCV FileStorage's `!!opencv-matrix` nodes, as mappings (rows,
    cols, dt, data)."""


_OpenCvYamlLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix",
    lambda loader, node: loader.construct_mapping(node, deep=True),  # type: ignore[arg-type]
)
# OpenCV writes the directive as `%YAML:1.0` (older) or `%YAML 1.2`; PyYAML reads neither.
_OPENCV_DIRECTIVE = re.compile(rb"\A%YAML[: ]1\.[0-9][^\n]*\n")


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


def _parse_yaml(path: Path, text: str | bytes, loader: type[_StrictYamlLoader] = _StrictYamlLoader) -> Any:
    try:
        _check_depth(path, text)
        return yaml.load(text, Loader=loader)
    except yaml.YAMLError as err:
        raise InputError(str(path), f"(yaml): {_describe_yaml_error(err)}") from err
    except ValueError as err:  # PyYAML's int() of a scalar beyond Python's 4300-digit limit
        raise InputError(str(path), f"(yaml): {err}") from err


# The toolbox files are large and regular. PyYAML (even with libyaml) spends ~2 s per 1000 frames of 30
# boxes resolving scalar tags in Python, and far more on the toolbox's own block style (one value per line),
# so the layouts below are parsed here, record by record with regular expressions (~20-50x faster); any
# other text (comments, anchors, quoting styles, odd indentation...) sends the whole file through PyYAML.
#   flow:   `stamp: [x, y, ...]`            or `stamp:` + `- [cx, cy, w, h, cls]` per row
#   block:  `stamp:` + `- x` per value      or `stamp:` + `- - cx` / `  - cy` ... per row (PyYAML's dump)
# The number grammar is deliberately narrower than YAML 1.1's so both parsers agree on every value:
# integers without leading zeros (YAML 1.1 reads 012 as octal), plain decimals with a dot, and exponents
# only after a dot and with a sign (YAML 1.1 reads 1e3 and 1.0e3 as strings).
_NUMBER = r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+(?:[eE][-+][0-9]+)?)?"
_FLOW_ROW = rf"\[ *(?:{_NUMBER}(?: *, *{_NUMBER})*)? *\]"
# One record: a key at column 0, an optional flow row after it, then the lines of its block sequence
# (checked by _parse_block below); blank lines may precede it.
_RECORD_RE = re.compile(
    rf"(?: *\n)*(?:([0-9]+)|\"([0-9]+)\"|'([0-9]+)'):(?: +({_FLOW_ROW}))? *\n((?: *- [^\n]*\n)*)"
)
_SPLIT_RE = re.compile(r" *, *")


def _number_token(token: str) -> int | float:
    return float(token) if "." in token else int(token)


def _parse_flow_numbers(row: str) -> list[int | float]:
    inner = row[1:-1].strip()
    if not inner:
        return []
    return list(map(_number_token, _SPLIT_RE.split(inner)))


@functools.cache
def _block_patterns(indent: int) -> tuple[re.Pattern[str], re.Pattern[str], re.Pattern[str], re.Pattern[str]]:
    """Whole-body patterns of a block sequence at `indent` spaces: values, flow rows, nested block rows,
    and one nested row (for splitting)."""
    pad = " " * indent
    values = re.compile(rf"(?:{pad}- {_NUMBER} *\n)+")
    flows = re.compile(rf"(?:{pad}- {_FLOW_ROW} *\n)+")
    row = rf"{pad}- - {_NUMBER} *\n(?:{pad}  - {_NUMBER} *\n)*"
    return values, flows, re.compile(rf"(?:{row})+"), re.compile(row)


def _parse_block(body: str) -> list[Any] | None:
    """The items of one block sequence in a toolbox layout (numbers, flow rows or nested block rows, all
    at one indentation); None for anything else."""
    indent = len(body) - len(body.lstrip(" "))
    values, flows, rows, row = _block_patterns(indent)
    if values.fullmatch(body):
        tokens = body.split()[1::2]  # "-", value, "-", value, ...
        # Every number has at most one dot, so as many dots as values means all are floats (the usual case).
        all_floats = body.count(".") == len(tokens)
        return list(map(float if all_floats else _number_token, tokens))
    if rows.fullmatch(body):
        # "-", "-", value, then "-", value per further value: the values are every other token from 2.
        return [list(map(_number_token, one.split()[2::2])) for one in row.findall(body)]
    if flows.fullmatch(body):
        return [_parse_flow_numbers(line.strip(" ")[2:].strip(" ")) for line in body.splitlines()]
    return None


def _fast_parse_stamped_rows(text: str) -> dict[int | str, Any] | None:
    """Parse the toolbox layouts (flow or block) of `{stamp: rows}`; None when the text leaves them.

    Returns what yaml.safe_load would (int keys for plain stamps, str keys for quoted ones).
    """
    # Split lines on LF only (and CRLF): YAML also breaks at a lone CR and at characters str.splitlines()
    # knows (\x1c-\x1e are not breaks in YAML), where the patterns would then accept what PyYAML rejects.
    if "\r" in text:
        text = text.replace("\r\n", "\n")
        if "\r" in text:
            return None
    if not text.endswith("\n"):
        text += "\n"
    data: dict[int | str, Any] = {}
    position = 0
    for match in _RECORD_RE.finditer(text):
        if match.start() != position:
            return None  # something between records: not a toolbox layout
        position = match.end()
        plain, double, single, flow, body = match.groups()
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
            if body:
                return None  # `stamp: [..]` followed by items is not YAML
            data[key] = _parse_flow_numbers(flow)
        elif not body:
            data[key] = None  # `stamp:` followed by no items is null in YAML, not an empty list
        else:
            items = _parse_block(body)
            if items is None:
                return None
            data[key] = items
    if text[position:].strip(" \n") or not data:
        return None
    return data


def _load_stamped_yaml(path: Path, raw: bytes | None = None) -> dict[Any, Any]:
    """The `{stamp: rows}` mapping of a toolbox file (`raw`: its bytes, if read already)."""
    raw = _read_bytes(path) if raw is None else raw
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


# The toolbox's block layout exactly as yaml.dump writes it (and the toolbox publishes its real track), read
# straight into columns: one regular expression over the whole file instead of a mapping of lists built
# record by record (the `long` preset's 45,000 poses: 0.25 -> 0.12 s). A file that is anything else, even
# slightly (trailing spaces, other indentation, quoted or unsorted stamps...), goes the general way above.
#   poses:       `stamp:` + `- x` per value, 6 values
#   detections:  `stamp:` + `- - cx` `  - cy` `  - w` `  - h` `  - class_id` per box, or `stamp: []`
_BLOCK_POSE_RE = re.compile(rf"(0|[1-9][0-9]*):\n((?:- {_NUMBER}\n){{{len(POSE_FIELDS)}}})")
_BLOCK_DETECTION_RE = re.compile(
    rf"(0|[1-9][0-9]*):(?: \[\]\n|\n((?:- - {_NUMBER}\n(?:  - {_NUMBER}\n){{{len(DETECTION_FIELDS) - 1}}})+))"
)


def _block_records(raw: bytes, record: re.Pattern[str]) -> tuple[Stamps, list[str]] | None:
    """The stamps (int64 ns) and record bodies of a file that is nothing but `record`s, its stamps strictly
    increasing and within [STAMP_NS_MIN, STAMP_NS_MAX]; None for any other file."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    found = record.findall(text)
    if not found:
        return None
    keys = [key for key, _ in found]
    bodies = [body for _, body in found]
    # Matches do not overlap, so if their lengths add up to the text's, nothing lies between them. A record
    # is its key, `:\n` and its body, or (an empty frame, body "") its key and `: []\n`, 3 characters more.
    length = sum(map(len, keys)) + 2 * len(keys) + sum(map(len, bodies)) + 3 * bodies.count("")
    if length != len(text):
        return None
    try:
        stamps = np.array(list(map(int, keys)), dtype=np.int64)
    except (ValueError, OverflowError):  # beyond Python's digit limit, or int64
        return None
    if not (stamps[0] >= STAMP_NS_MIN and stamps[-1] <= STAMP_NS_MAX and (np.diff(stamps) > 0).all()):
        return None
    return stamps, bodies


def _block_numbers(tokens: list[str], dots: int) -> FloatArray | None:
    """Number tokens of `_NUMBER`'s grammar, `dots` dots among them -> float64 (N,), read as the general
    path reads them (a token with a dot a float, else an int, then float64); None if one is beyond an int's
    digits or float range, or not finite."""
    # A number has at most one dot: as many dots as tokens means all are floats (the usual case).
    try:
        numbers = list(map(float if dots == len(tokens) else _number_token, tokens))
        values = np.array(numbers, dtype=np.float64)
    except (ValueError, OverflowError):
        return None
    return values if np.isfinite(values).all() else None


def _block_pose_table(raw: bytes) -> PoseTable | None:
    """The poses of a file in the block layout, exactly the general path's table; None for another file."""
    records = _block_records(raw, _BLOCK_POSE_RE)
    if records is None:
        return None
    stamps, bodies = records
    text = "".join(bodies)
    values = _block_numbers(text.split()[1::2], text.count("."))  # "-", value, "-", value, ...
    if values is None:
        return None
    return PoseTable(stamps, values.reshape(-1, len(POSE_FIELDS)))


def _block_detection_table(raw: bytes, camera_id: str) -> DetectionTable | None:
    """The frames of a file in the block layout, exactly the general path's table; None for another file
    or when a check might fail (the general path then names it)."""
    records = _block_records(raw, _BLOCK_DETECTION_RE)
    if records is None:
        return None
    stamps, bodies = records
    rows_per_frame = [body.count("\n") // len(DETECTION_FIELDS) for body in bodies]  # a line per value
    text = "".join(bodies)
    values = _block_numbers([token for token in text.split() if token != "-"], text.count("."))
    if values is None:
        return None
    return _detection_table(camera_id, stamps, rows_per_frame, values.reshape(-1, len(DETECTION_FIELDS)))


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
            values = list(map(float, row))
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
    return _decode_yaml_mapping(path, _parse_yaml(path, _read_bytes(path)), model)


def _decode_yaml_mapping(path: Path, data: Any, model: type[M]) -> M:
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
    """rsu.yaml of `rsucal daemon`; relative paths in it (state_dir, zenoh.config_file) stay as written,
    except a camera's `intrinsics` given as a file name (any camera file load_intrinsics reads: camera.yaml,
    a ROS camera_info file, OpenCV FileStorage), read here, relative to rsu.yaml's directory."""
    path = Path(path)
    data = _parse_yaml(path, _read_bytes(path))
    cameras = data.get("cameras") if isinstance(data, dict) else None
    for index, camera in enumerate(cameras if isinstance(cameras, list) else []):
        if isinstance(camera, dict) and isinstance(camera.get("intrinsics"), str):
            camera_file = path.parent / camera["intrinsics"]
            try:
                camera["intrinsics"] = load_intrinsics(camera_file).model_dump(mode="json")
            except InputError as err:
                raise InputError(str(path), f"cameras.{index}.intrinsics: {err}") from err
    config = _decode_yaml_mapping(path, data, DaemonConfig)
    if config.crs is not None:
        try:
            UtmFrame(config.crs)  # the schema checks the form only; the daemon needs a UTM zone
        except InputError as err:
            raise InputError(str(path), err.detail) from err
    return config


# Camera files other tools write: ROS camera_info calibration files (camera_calibration's ost.yaml,
# camera_info_manager's format) and OpenCV FileStorage (its calibration sample's out_camera_data.yml/xml).
# Both carry a 3 x 3 camera matrix and OpenCV's distortion vector; read into the same CameraIntrinsics.
_ROS_DISTORTION_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,)}
_FISHEYE_MODELS = ("equidistant", "fisheye", "kannala_brandt")
_OTHER_TOOLS_KEYS = frozenset({"camera_matrix", "image_width", "image_height", "distortion_coefficients"})


def load_intrinsics(path: Path) -> CameraIntrinsics:
    """The camera's intrinsics from camera.yaml: rsucal's own keys, exactly width, height, fx, fy, cx, cy (px)
    and optional dist (OpenCV's [k1, k2, p1, p2], [k1, k2, p1, p2, k3] or [k1, k2, p1, p2, k3, k4, k5, k6]);
    or a ROS camera_info calibration file (image_width, image_height, camera_matrix, distortion_model
    plumb_bob or rational_polynomial, distortion_coefficients; the rectification and projection matrices,
    which describe rectified images, are not used); or OpenCV FileStorage YAML or XML (image_width,
    image_height, camera_matrix, distortion_coefficients, as OpenCV's calibration sample and tutorial write
    them). The intrinsics must be those of the images the detector sees.

    OpenCV's files are read here, not by cv2.FileStorage: its parser aborted the process (a heap
    corruption) on one of 3000 randomly damaged files."""
    path = Path(path)
    raw = _read_bytes(path)
    if raw.lstrip()[:5] == b"<?xml":
        return _intrinsics_from_ros(path, _opencv_xml(path, raw))
    text = _OPENCV_DIRECTIVE.sub(b"\n", raw, count=1)  # a blank line: the lines keep their numbers
    data = _parse_yaml(path, text, _OpenCvYamlLoader)
    if isinstance(data, dict) and not data.keys().isdisjoint(_OTHER_TOOLS_KEYS):
        return _intrinsics_from_ros(path, data)
    return _decode_yaml_mapping(path, data, CameraIntrinsics)


def _opencv_xml(path: Path, raw: bytes) -> dict[str, Any]:
    """OpenCV FileStorage XML (<opencv_storage>, as OpenCV's calibration tutorial writes out_camera_data.xml)
    as the mapping its YAML form gives: image_width, image_height, and camera_matrix and
    distortion_coefficients as {rows, cols, dt, data}. Only those keys are read."""
    from xml.etree import ElementTree

    try:
        root = ElementTree.fromstring(raw)  # expat: no external entities, entity expansion bounded
    except ElementTree.ParseError as err:
        line, column = err.position
        problem = re.sub(r": line \d+, column \d+$", "", str(err))
        raise InputError(str(path), f"(xml): line {line}, column {column + 1}: {problem}") from err
    if root.tag != "opencv_storage":
        raise InputError(str(path), f"(xml): the root is <{root.tag}>, not <opencv_storage>")

    def number(text: str | None, key: str) -> int | float:
        try:
            value = float(text or "")
        except ValueError:
            raise InputError(
                str(path), f"{key}: expected a number, got {(text or '').strip()[:40]!r}"
            ) from None
        return int(value) if value.is_integer() and abs(value) < 2**53 else value

    data: dict[str, Any] = {}
    for key in ("image_width", "image_height"):
        node = root.find(key)
        if node is not None:
            data[key] = number(node.text, key)
    for key in ("camera_matrix", "distortion_coefficients"):
        node = root.find(key)
        if node is None:
            continue
        rows, cols, values = node.find("rows"), node.find("cols"), node.find("data")
        if rows is None or cols is None or values is None:
            raise InputError(str(path), f"{key}: expected an opencv-matrix with rows, cols and data")
        data[key] = {
            "rows": number(rows.text, f"{key}.rows"),
            "cols": number(cols.text, f"{key}.cols"),
            "data": [number(v, f"{key}.data") for v in (values.text or "").split()],
        }
    return data


def _intrinsics_from_ros(path: Path, data: dict[str, Any]) -> CameraIntrinsics:
    """A ROS camera_info calibration file's mapping, or OpenCV FileStorage's (the same keys but the
    distortion model, the matrices as opencv-matrix nodes) -> CameraIntrinsics; errors name the file's own
    keys."""
    _check_size(path, data)
    model = data.get("distortion_model")
    if model is not None and not isinstance(model, str):
        raise InputError(str(path), f"distortion_model: expected a name, got {type(model).__name__}")
    if model in _FISHEYE_MODELS:
        raise InputError(
            str(path),
            f"distortion_model: {model!r} (a fisheye lens) is not supported; rsucal models OpenCV's pinhole "
            "lenses: plumb_bob or rational_polynomial",
        )
    if model is not None and model not in _ROS_DISTORTION_MODELS:
        raise InputError(
            str(path), f"distortion_model: {model!r} is not one of {', '.join(_ROS_DISTORTION_MODELS)}"
        )
    K = _ros_matrix(path, data, "camera_matrix", (3, 3))
    dist: tuple[float, ...] = (0.0,) * 5
    if data.get("distortion_coefficients") is not None:
        dist = tuple(float(v) for v in _ros_matrix(path, data, "distortion_coefficients", None).ravel())
        if model is not None and len(dist) not in _ROS_DISTORTION_MODELS[model]:
            raise InputError(
                str(path),
                f"distortion_coefficients.data: {len(dist)} values for distortion_model {model} (expected "
                f"{' or '.join(str(n) for n in _ROS_DISTORTION_MODELS[model])})",
            )
    return _intrinsics_of(path, data.get("image_width"), data.get("image_height"), K, dist)


def _ros_matrix(path: Path, data: dict[str, Any], key: str, shape: tuple[int, int] | None) -> FloatArray:
    """A ROS calibration file's {rows, cols, data} matrix `key` as an array of its rows x cols."""
    node = data.get(key)
    if node is None:
        raise InputError(str(path), f"{key}: missing")
    if not isinstance(node, dict) or not isinstance(node.get("data"), list):
        raise InputError(str(path), f"{key}: expected a mapping with rows, cols and a data list")
    values = node["data"]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise InputError(str(path), f"{key}.data: expected numbers")
    if not all(abs(v) < 1e300 for v in values):  # finite (an integer of 400 digits has no float)
        raise InputError(str(path), f"{key}.data: expected finite numbers")
    rows, cols = node.get("rows"), node.get("cols")
    if not (type(rows) is int and type(cols) is int and rows > 0 and cols > 0 and rows * cols == len(values)):
        raise InputError(
            str(path), f"{key}: rows x cols = {rows!r} x {cols!r} does not match {len(values)} values"
        )
    if shape is not None and (rows, cols) != shape:
        raise InputError(str(path), f"{key}: {rows} x {cols}, expected {shape[0]} x {shape[1]}")
    return np.asarray(values, dtype=np.float64).reshape(rows, cols)


def _intrinsics_of(
    path: Path, width: object, height: object, K: FloatArray, dist: tuple[float, ...]
) -> CameraIntrinsics:
    """CameraIntrinsics from another format's image size, camera matrix and distortion vector; a problem is
    named by that format's key (image_width, image_height, camera_matrix, distortion_coefficients)."""
    size = []
    for key, value in (("image_width", width), ("image_height", height)):
        if value is None:
            raise InputError(str(path), f"{key}: missing")
        whole = isinstance(value, int) or (isinstance(value, float) and value.is_integer())
        if isinstance(value, bool) or not whole:
            raise InputError(str(path), f"{key}: expected a whole number of pixels, got {value!r}")
        size.append(int(value))  # type: ignore[call-overload]  # an int, or a float with no fraction
    if not np.all(np.isfinite(K)):
        raise InputError(str(path), "camera_matrix: not finite")
    if not (K[1, 0] == 0.0 and K[2, 0] == 0.0 and K[2, 1] == 0.0 and K[2, 2] == 1.0):
        raise InputError(str(path), "camera_matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if K[0, 1] != 0.0:
        raise InputError(str(path), f"camera_matrix: a skew of {K[0, 1]:g} px is not supported (expected 0)")
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    fields = {"width": size[0], "height": size[1], "fx": fx, "fy": fy, "cx": cx, "cy": cy, "dist": dist}
    try:
        return CameraIntrinsics.model_validate(fields)
    except ValidationError as err:
        names = {"width": "image_width", "height": "image_height", "dist": "distortion_coefficients"}
        problems = []
        for item in err.errors(include_url=False):
            field = str(item["loc"][0]) if item["loc"] else "(root)"
            where = names.get(field, f"camera_matrix ({field})")
            problems.append(f"{where}: {item['msg']}")
        raise InputError(str(path), "; ".join(problems)) from err


def load_vehicle(path: Path) -> VehicleProfile:
    """vehicle.yaml: length, width, height (m) and imu_offset [x, y, z] in the vehicle box frame (m)."""
    return _load_model_yaml(Path(path), VehicleProfile)


def load_toolbox_detections(path: Path, camera_id: str = "camera") -> list[DetectionFrame]:
    """detections.yaml `{stamp_ns: [[cx, cy, w, h, class_id], ...]}` (box centre and size, px) -> frames.

    The reference toolbox's format; class_id 4 car, 5 truck, 6 van, 7 bus. The file names no camera, so
    `camera_id` is set on every frame. Frames come back sorted by stamp, boxes as x1, y1, x2, y2 with
    score 1.0 (the toolbox has none). A frame may hold no boxes.
    """
    return list(load_toolbox_detection_table(path, camera_id))


def load_toolbox_detection_table(path: Path, camera_id: str = "camera") -> DetectionTable:
    """load_toolbox_detections' frames as columns (pipeline.tables), with the same errors."""
    path = Path(path)
    raw = _read_bytes(path)
    table = _block_detection_table(raw, camera_id)
    if table is not None:
        return table
    entries = _sorted_stamps(path, _load_stamped_yaml(path, raw))
    table = _detection_columns(entries, camera_id)
    if table is None:
        # Something is wrong (or unusual): the row-by-row checks below find it and name it.
        table = _table_of(_checked_detection_frames(path, entries, camera_id), camera_id)
    return table


def _table_of(frames: Sequence[DetectionFrame], camera_id: str) -> DetectionTable:
    """Valid frames (of integer class ids, as the toolbox's are) as a DetectionTable."""
    boxes = [(b.x1, b.y1, b.x2, b.y2) for frame in frames for b in frame.boxes]
    classes = [b.cls for frame in frames for b in frame.boxes]
    starts = np.zeros(len(frames) + 1, dtype=np.int64)
    np.cumsum([len(frame.boxes) for frame in frames], out=starts[1:])
    return DetectionTable(
        camera_id,
        np.array([frame.stamp_ns for frame in frames], dtype=np.int64),
        starts,
        np.array(boxes, dtype=np.float64).reshape(-1, 4),
        np.array(classes, dtype=np.int64),
    )


def _detection_columns(entries: Sequence[tuple[int, Any, Any]], camera_id: str) -> DetectionTable | None:
    """The frames of `entries` (stamp, key, rows) as a DetectionTable, every check of
    _checked_detection_frames done on whole columns; None when any might fail (or the rows are not plain
    lists of 5 numbers), for the row-by-row path to report."""
    frames = [[] if rows is None else rows for _, _, rows in entries]
    if not all(type(rows) is list for rows in frames):
        return None
    rows = list(itertools.chain.from_iterable(frames))
    # Exact types only (bool is an int, and numpy would read "1.5" as a number): every row a list of 5
    # floats or ints. Checked with C-level passes over the rows and values.
    if not set(map(type, rows)) <= {list} or not set(map(len, rows)) <= {len(DETECTION_FIELDS)}:
        return None
    if not set(map(type, itertools.chain.from_iterable(rows))) <= {float, int}:
        return None
    try:
        values = np.array(rows, dtype=np.float64).reshape(-1, len(DETECTION_FIELDS))
    except OverflowError:  # an integer beyond float range
        return None
    if not np.isfinite(values).all():
        return None
    stamps = np.array([stamp for stamp, _, _ in entries], dtype=np.int64)
    return _detection_table(camera_id, stamps, list(map(len, frames)), values)


def _detection_table(
    camera_id: str, stamps: Stamps, rows_per_frame: Sequence[int], values: FloatArray
) -> DetectionTable | None:
    """Frames of `rows_per_frame` boxes each at `stamps` (sorted), their rows `values` (N, 5) cx, cy, w, h,
    class_id (finite) as a DetectionTable, every check of _checked_detection_frames done on whole
    columns; None when any might fail, for the row-by-row path to report."""
    if IDENTIFIER.fullmatch(camera_id) is None or max(rows_per_frame, default=0) > MAX_BOXES_PER_FRAME:
        return None
    cx, cy, w, h, class_id = values.T
    # The same arithmetic as the row-by-row path, elementwise in float64 (a sum beyond float range is inf
    # there too, and fails the bounds below).
    with np.errstate(over="ignore"):
        half_w, half_h = 0.5 * w, 0.5 * h
        boxes = np.stack([cx - half_w, cy - half_h, cx + half_w, cy + half_h], axis=1)
    x1, y1, x2, y2 = boxes.T
    is_valid = (
        (w > 0.0).all()
        and (h > 0.0).all()
        and (np.trunc(class_id) == class_id).all()
        and ((class_id >= 0.0) & (class_id <= MAX_CLASS_ID)).all()
        and ((boxes >= -_PIXEL_LIMIT) & (boxes <= _PIXEL_LIMIT)).all()
        and (x2 > x1).all()
        and (y2 > y1).all()
    )
    if not is_valid:
        return None
    starts = np.zeros(len(rows_per_frame) + 1, dtype=np.int64)
    np.cumsum(rows_per_frame, out=starts[1:])
    return DetectionTable(camera_id, stamps, starts, boxes, class_id.astype(np.int64))


def _checked_detection_frames(
    path: Path, entries: Sequence[tuple[int, Any, Any]], camera_id: str
) -> list[DetectionFrame]:
    """The frames built and validated one by one: the first problem raises InputError naming its field."""
    frames: list[DetectionFrame] = []
    for stamp, key, rows in entries:
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
    return list(load_toolbox_pose_table(path))


def load_toolbox_pose_table(path: Path) -> PoseTable:
    """load_toolbox_poses' poses as columns (pipeline.tables), with the same errors."""
    path = Path(path)
    raw = _read_bytes(path)
    table = _block_pose_table(raw)
    if table is not None:
        return table
    entries = _sorted_stamps(path, _load_stamped_yaml(path, raw))
    stamps = np.array([stamp for stamp, _, _ in entries], dtype=np.int64)
    rows = [row for _, _, row in entries]
    values: FloatArray | None = None
    # Exact types only, as in _detection_columns; then one finiteness test for the whole file.
    if (
        set(map(type, rows)) <= {list}
        and set(map(len, rows)) <= {len(POSE_FIELDS)}
        and set(map(type, itertools.chain.from_iterable(rows))) <= {float, int}
    ):
        try:
            values = np.array(rows, dtype=np.float64).reshape(-1, len(POSE_FIELDS))
        except OverflowError:  # an integer beyond float range
            values = None
        if values is not None and not np.isfinite(values).all():
            values = None
    if values is None:
        # Row by row: the first bad row raises InputError naming its field.
        values = np.array(
            [_row(path, str(key), row, POSE_FIELDS) for _, key, row in entries], dtype=np.float64
        ).reshape(-1, len(POSE_FIELDS))
    return PoseTable(stamps, values)


def load_calibration_result(path: Path) -> CalibrationResult:
    """A CalibrationResult JSON file (what `rsucal calibrate` writes and the daemon publishes)."""
    return _load_model_json(Path(path), CalibrationResult)


def load_ground_truth(path: Path) -> GroundTruth:
    """The simulator's ground_truth.json (one camera)."""
    return _load_model_json(Path(path), GroundTruth)
