"""The simulator's file output in the reference toolbox's layout, beside the MCAP recording.

detections.yaml (`stamp: - [cx, cy, w, h, class_id]`), poses.yaml (`stamp: [x, y, z, yaw, pitch, roll]`,
absolute UTM), camera.yaml (intrinsics), vehicle.yaml (the data-sheet dimensions and IMU offset an operator
would give) and ground_truth.json. Written by the world itself, so the pipeline's loaders are tested
against files they did not write.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from pydantic import BaseModel

from schemas.atomic import write_atomic
from schemas.messages import DetectionFrame, VehiclePose

if TYPE_CHECKING:
    from sim.simulate import SimulationResult

_YamlDumper: Any = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def _write_atomic(path: Path, text: str) -> Path:
    """A crash never leaves a half-written file under the real name (schemas.atomic)."""
    write_atomic(path, text.encode("utf-8"))
    return path


def format_toolbox_detections(frames: Iterable[DetectionFrame]) -> str:
    """detections.yaml text: one `- [cx, cy, w, h, class_id]` line per box, 0.01 px resolution."""
    lines = []
    for frame in sorted(frames, key=lambda f: f.stamp_ns):
        if not frame.boxes:
            lines.append(f"{frame.stamp_ns}: []")
            continue
        lines.append(f"{frame.stamp_ns}:")
        for box in frame.boxes:
            # Fixed-point on purpose: YAML 1.1 reads "1e-05" (no dot) as a string, and `.2f` never
            # produces an exponent. Schema objects are finite, so no nan/inf can reach this.
            cx, cy = 0.5 * (box.x1 + box.x2), 0.5 * (box.y1 + box.y2)
            lines.append(f"- [{cx:.2f}, {cy:.2f}, {box.x2 - box.x1:.2f}, {box.y2 - box.y1:.2f}, {box.cls}]")
    return "\n".join(lines) + "\n" if lines else "{}\n"


def _fixed(value: float, digits: int) -> str:
    text = f"{value:.{digits}f}"
    # "-0.000000000" (a tiny negative pitch) reads as noise to a human; the value is the same.
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text


def format_toolbox_poses(poses: Iterable[VehiclePose]) -> str:
    """poses.yaml text: `stamp: [x, y, z, yaw, pitch, roll]`, mm in UTM, 1e-9 rad."""
    lines = [
        f"{p.stamp_ns}: [{_fixed(p.x, 3)}, {_fixed(p.y, 3)}, {_fixed(p.z, 3)}, "
        f"{_fixed(p.yaw, 9)}, {_fixed(p.pitch, 9)}, {_fixed(p.roll, 9)}]"
        for p in sorted(poses, key=lambda p: p.stamp_ns)
    ]
    return "\n".join(lines) + "\n" if lines else "{}\n"


def _dump_model_yaml(model: BaseModel) -> str:
    data = model.model_dump(mode="json")
    text: str = yaml.dump(data, Dumper=_YamlDumper, sort_keys=False, default_flow_style=None)
    return text


def write_simulation_files(result: SimulationResult, out_dir: Path) -> list[Path]:
    """Write the toolbox file set of a simulation; returns the paths written.

    One camera: detections.yaml, camera.yaml, ground_truth.json. Several: detections_<cam>.yaml,
    camera_<cam>.yaml, ground_truth_<cam>.json each. Always one poses.yaml and one vehicle.yaml.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    several = len(result.cameras) > 1
    written: list[Path] = []
    for camera in result.cameras:
        cam = camera.camera_id
        suffix = f"_{cam}" if several else ""
        frames = result.detections.get(cam, [])
        written.append(_write_atomic(out_dir / f"detections{suffix}.yaml", format_toolbox_detections(frames)))
        written.append(_write_atomic(out_dir / f"camera{suffix}.yaml", _dump_model_yaml(camera.intrinsics)))
        if cam in result.ground_truth:
            truth_json = result.ground_truth[cam].model_dump_json(indent=1) + "\n"
            written.append(_write_atomic(out_dir / f"ground_truth{suffix}.json", truth_json))
    written.append(_write_atomic(out_dir / "poses.yaml", format_toolbox_poses(result.poses)))
    written.append(_write_atomic(out_dir / "vehicle.yaml", _dump_model_yaml(result.vehicle)))
    return written
