"""The committed JSON Schemas (schemas/json/) are exactly what the models produce now."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.export import DEFAULT_OUT_DIR, EXPORTED_MODELS, export_json_schemas, json_schema_text, main

REGENERATE = "run `python -m schemas.export` and commit schemas/json/"
PUBLIC_MODELS = {
    "Box",
    "CalibrationResult",
    "CalibrationStatus",
    "CameraIntrinsics",
    "DaemonConfig",
    "DetectionFrame",
    "GroundTruth",
    "Health",
    "LocalOrigin",
    "V2xPosition",
    "VehiclePose",
    "VehicleProfile",
}


def test_every_public_model_is_exported() -> None:
    assert {model.__name__ for model in EXPORTED_MODELS} == PUBLIC_MODELS


@pytest.mark.parametrize("model", EXPORTED_MODELS, ids=lambda m: m.__name__)
def test_committed_schema_is_current(model: type) -> None:
    path = DEFAULT_OUT_DIR / f"{model.__name__}.json"
    assert path.is_file(), f"{path} is missing: {REGENERATE}"
    committed = path.read_bytes().decode("utf-8")
    assert committed == json_schema_text(model), f"{path} is stale (the model changed): {REGENERATE}"


def test_no_schema_files_without_a_model() -> None:
    stray = {p.stem for p in DEFAULT_OUT_DIR.glob("*.json")} - PUBLIC_MODELS
    assert not stray, f"schemas/json/ holds files of no exported model: {sorted(stray)}; delete them"


def test_export_is_deterministic_and_well_formed(tmp_path: Path) -> None:
    first = export_json_schemas(tmp_path / "a")
    second = export_json_schemas(tmp_path / "b")
    assert [p.name for p in first] == [f"{m.__name__}.json" for m in EXPORTED_MODELS]
    for a, b in zip(first, second, strict=True):
        text = a.read_bytes()
        assert text == b.read_bytes()
        assert text.endswith(b"}\n") and not text.endswith(b"\n\n")
        assert b"\r" not in text
        schema = json.loads(text)
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert schema["title"] == a.stem
        assert schema["additionalProperties"] is False  # strict models forbid unknown fields
        # Keys are sorted at every level, so a diff shows only real changes.
        assert text.decode() == json.dumps(schema, sort_keys=True, indent=2, ensure_ascii=False) + "\n"


def test_main_writes_into_the_given_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path)]) == 0
    assert sorted(p.stem for p in tmp_path.glob("*.json")) == sorted(PUBLIC_MODELS)
    assert capsys.readouterr().out.count("wrote ") == len(PUBLIC_MODELS)


def test_schema_carries_the_field_constraints() -> None:
    frame = json.loads((DEFAULT_OUT_DIR / "DetectionFrame.json").read_text())
    assert frame["required"] == ["camera_id", "stamp_ns"]
    assert frame["properties"]["camera_id"]["pattern"] == r"^[A-Za-z0-9_.\-]+$"
    assert frame["properties"]["boxes"]["maxItems"] == 2000
    v2x = json.loads((DEFAULT_OUT_DIR / "V2xPosition.json").read_text())
    assert v2x["properties"]["heading_deg"]["exclusiveMaximum"] == 360.0
    assert v2x["properties"]["lat"]["minimum"] == -90.0


def test_good_messages_validate_against_the_exported_schemas() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    frame = json.loads((DEFAULT_OUT_DIR / "DetectionFrame.json").read_text())
    good = {
        "camera_id": "cam-1",
        "stamp_ns": 1_700_000_000_000_000_000,
        "boxes": [{"x1": 1.0, "y1": 2.0, "x2": 30.0, "y2": 40.0, "cls": 4, "score": 0.9}],
    }
    jsonschema.validate(good, frame)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**good, "camera_id": "cam/1"}, frame)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**good, "extra": 1}, frame)
