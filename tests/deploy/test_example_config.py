"""deploy/rsu.example.yaml is a valid DaemonConfig showing and documenting every field: it cannot go stale.

A field is documented by its inline comment or the comment lines directly above it; the comment says
"required" or "default: VALUE", and VALUE must equal the model's default. Walking the pydantic models
(not a list kept here) means a field added to schemas/config.py fails this test until the example has it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, get_args

import yaml
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from schemas.common import decode_mapping
from schemas.config import DaemonConfig

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "rsu.example.yaml"
_KEY_LINE = re.compile(r"^(?P<indent>\s*)(?P<item>- )?(?P<key>[A-Za-z_][A-Za-z0-9_]*):(?P<rest>.*)$")


def _documented_keys(text: str) -> dict[str, list[str]]:
    """Dotted key path ('cameras.intrinsics.fx', no list indices) -> the comment of each occurrence."""
    docs: dict[str, list[str]] = {}
    stack: list[tuple[int, str]] = []  # (indent of the key, key)
    above: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(stripped.lstrip("#").strip())
            continue
        match = _KEY_LINE.match(line)
        if match is None:
            above = []
            continue
        indent = len(match["indent"]) + (2 if match["item"] else 0)
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, match["key"]))
        inline = match["rest"].split(" #", 1)[1].strip() if " #" in match["rest"] else ""
        docs.setdefault(".".join(key for _, key in stack), []).append(" ".join([*above, inline]).strip())
        above = []
    return docs


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model inside an annotation (Model, Model | None, list[Model]), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        model = _model_of(arg)
        if model is not None:
            return model
    return None


def _fields(model: type[BaseModel], prefix: str = "", seen: set[type] | None = None) -> list[tuple[str, Any]]:
    """(dotted path, default or PydanticUndefined) of every field of `model` and of the models inside it.

    A model used in two places (GeoPoint: camera position and polygon vertices) is documented at the first.
    """
    seen = set() if seen is None else seen
    out: list[tuple[str, Any]] = []
    for name, info in model.model_fields.items():
        path = f"{prefix}{name}"
        default = info.default_factory() if info.default_factory is not None else info.default  # type: ignore[call-arg]
        out.append((path, default))
        inner = _model_of(info.annotation)
        if inner is not None and inner not in seen:
            seen.add(inner)
            out.extend(_fields(inner, f"{path}.", seen))
    return out


def _plain(value: Any) -> Any:
    """A default as YAML would spell it: models as mappings, tuples as lists, paths as strings."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    if isinstance(value, Path):
        return str(value)
    return value


def test_example_is_a_valid_config() -> None:
    config = decode_mapping(DaemonConfig, yaml.safe_load(EXAMPLE.read_text()))
    assert [camera.camera_id for camera in config.cameras] == ["west-junction", "west-arm"]
    # One camera with the daemon's own detector on its images, so every detector field is shown.
    assert config.cameras[1].detector is not None and config.cameras[1].labels is not None
    assert [vehicle.station_id for vehicle in config.vehicles] == [4242]
    # One camera per coverage kind, so both are shown working.
    assert config.cameras[0].coverage_radius_m is not None
    assert config.cameras[1].coverage_polygon is not None


def test_example_shows_and_documents_every_field_with_its_default() -> None:
    docs = _documented_keys(EXAMPLE.read_text())
    problems = []
    for path, default in _fields(DaemonConfig):
        comments = [comment for comment in docs.get(path, []) if comment]
        if not comments:
            problems.append(f"{path}: missing or without a comment")
            continue
        if isinstance(default, BaseModel):
            continue  # a section: its fields carry the defaults
        if default is PydanticUndefined:
            if not any("required" in comment.lower() for comment in comments):
                problems.append(f"{path}: required field, but no comment says 'required'")
            continue
        stated = [m[1] for c in comments if (m := re.search(r"default: (\S+)$", c))]
        if not stated:
            problems.append(f"{path}: no comment ends with 'default: VALUE'")
        elif yaml.safe_load(stated[0]) != _plain(default):
            problems.append(f"{path}: comment says default {stated[0]}, the model's is {_plain(default)!r}")
    assert not problems, "deploy/rsu.example.yaml:\n" + "\n".join(problems)


def test_every_example_key_is_a_field() -> None:
    # decode_mapping already refuses unknown keys; this also catches a commented-out stale key path.
    fields = {path for path, _ in _fields(DaemonConfig)}
    assert set(_documented_keys(EXAMPLE.read_text())) - fields == set()
