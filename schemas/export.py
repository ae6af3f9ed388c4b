"""JSON Schemas of the public models, one file per model in schemas/json/<Name>.json.

The files are generated, deterministic (sorted keys, indent 2, trailing newline) and committed, so other
languages and MCAP readers can validate rsucal messages without Python. Regenerate with
`python -m schemas.export` after changing a model; tests/schemas/test_export.py fails while they are stale.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

from pydantic import BaseModel

from schemas.common import Box, CameraIntrinsics, LocalOrigin, VehicleProfile
from schemas.config import DaemonConfig
from schemas.files import GroundTruth
from schemas.messages import DetectionFrame, V2xPosition, VehiclePose
from schemas.results import CalibrationResult, CalibrationStatus, Health

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
DEFAULT_OUT_DIR = Path(__file__).resolve().parent / "json"

EXPORTED_MODELS: tuple[type[BaseModel], ...] = (
    Box,
    CalibrationResult,
    CalibrationStatus,
    CameraIntrinsics,
    DaemonConfig,
    DetectionFrame,
    GroundTruth,
    Health,
    LocalOrigin,
    V2xPosition,
    VehiclePose,
    VehicleProfile,
)


def json_schema_text(model: type[BaseModel]) -> str:
    """The exact text of `model`'s schema file: what we accept (validation mode), pydantic's draft 2020-12."""
    schema = {"$schema": JSON_SCHEMA_DIALECT, **model.model_json_schema(mode="validation")}
    return json.dumps(schema, sort_keys=True, indent=2, ensure_ascii=False) + "\n"


def schema_path(model: type[BaseModel], out_dir: Path) -> Path:
    """Where `model`'s schema lives: out_dir/<ClassName>.json."""
    return out_dir / f"{model.__name__}.json"


def export_json_schemas(out_dir: Path = DEFAULT_OUT_DIR) -> list[Path]:
    """Write one JSON Schema file per public model into `out_dir` (created if missing); returns the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for model in EXPORTED_MODELS:
        path = schema_path(model, out_dir)
        # newline="\n" keeps the bytes identical on every platform, so the committed files never churn.
        path.write_text(json_schema_text(model), encoding="utf-8", newline="\n")
        written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m schemas.export [OUT_DIR]`: regenerate the committed JSON Schemas."""
    parser = argparse.ArgumentParser(prog="python -m schemas.export", description=__doc__)
    parser.add_argument("out_dir", nargs="?", type=Path, default=DEFAULT_OUT_DIR, help="default schemas/json")
    args = parser.parse_args(argv)
    for path in export_json_schemas(args.out_dir):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
