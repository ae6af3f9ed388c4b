"""Fuzzing the inputs of `rsucal calibrate`: daemon.offline.load_offline_inputs and daemon.cli.main.

load_offline_inputs gets damaged copies of the small recording (fuzz_mcap.py) and mutated toolbox YAML
pairs, and must return inputs or raise InputError/RecordingError naming the damaged file. cli.main runs the
whole command in-process, calibration included, on damaged recordings: exit 2 with a message naming the
file when nothing usable is left, else 0 or 3, never a traceback. A calibration takes ~1 s even on this
small scene, so the command gets FUZZ_EXAMPLES / 50 examples; the decoding it does gets the full count
through load_offline_inputs.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import yaml
from fuzz_mcap import simulation, small_recording
from fuzzing import document_inputs, fuzz_settings, label, scratch_dir
from hypothesis import given
from hypothesis import strategies as st

from daemon.cli import main
from daemon.offline import OfflineInputs, load_offline_inputs
from pipeline.errors import InputError, RecordingError
from pipeline.loaders import load_toolbox_poses
from sim.files import format_toolbox_detections, format_toolbox_poses

DIR = scratch_dir("rsucal-fuzz-offline-")
damage = st.tuples(
    st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 255)), max_size=3),
    st.none() | st.floats(0.0, 1.0),
)


def damaged_recording(flips: list[tuple[float, int]], cut: float | None) -> Path:
    rec = small_recording()
    data = bytearray(rec.data)
    for position, mask in flips:
        data[int(position * len(data))] ^= mask
    path = DIR / "recording.mcap"
    path.write_bytes(bytes(data[: int(cut * len(data))] if cut is not None else data))
    return path


def load_or_reject(damaged: Path, **files: Path) -> OfflineInputs | None:
    """load_offline_inputs' value, or None after checking its error names the damaged file."""
    rec = small_recording()
    try:
        loaded = load_offline_inputs(rec.camera_yaml, rec.vehicle_yaml, **files)
    except (InputError, RecordingError) as err:
        assert str(damaged) in str(err), err
        label(f"rejected: {type(err).__name__}")
        return None
    label("loaded")
    return loaded


@fuzz_settings(0.5)
@given(damage=damage)
def test_load_offline_inputs_from_a_damaged_recording(
    damage: tuple[list[tuple[float, int]], float | None],
) -> None:
    path = damaged_recording(*damage)
    loaded = load_or_reject(path, mcap_path=path)
    if loaded is not None:
        assert loaded.inputs.detections


# A toolbox pair of the same scene, thinned like the recording: what `--detections --poses` reads.
_SIM = simulation()
DETECTIONS_YAML = format_toolbox_detections(next(iter(_SIM.detections.values()))[:40:4])
POSES_YAML = format_toolbox_poses(_SIM.poses[:40:4])


@fuzz_settings(0.25, slow_data=True)
@given(data=document_inputs(DETECTIONS_YAML, yaml.safe_load))
def test_load_offline_inputs_from_damaged_detections(data: bytes) -> None:
    detections, poses = DIR / "detections.yaml", DIR / "poses.yaml"
    detections.write_bytes(data)
    poses.write_text(POSES_YAML, encoding="utf-8")
    load_or_reject(detections, detections_path=detections, poses_path=poses)


@fuzz_settings(0.25, slow_data=True)
@given(data=document_inputs(POSES_YAML, yaml.safe_load))
def test_load_offline_inputs_from_damaged_poses(data: bytes) -> None:
    detections, poses = DIR / "detections.yaml", DIR / "poses.yaml"
    detections.write_text(DETECTIONS_YAML, encoding="utf-8")
    poses.write_bytes(data)
    loaded = load_or_reject(poses, detections_path=detections, poses_path=poses)
    if loaded is not None:  # absolute UTM, as the toolbox writes it, or refused by name
        assert all(100_000.0 < pose.x < 900_000.0 for pose in load_toolbox_poses(poses))


def run_calibrate(*args: str) -> tuple[int, str]:
    """`rsucal calibrate ...` in-process: (exit code, stderr). Any exception is a failed test."""
    rec = small_recording()
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(
            [
                "calibrate",
                "--camera",
                str(rec.camera_yaml),
                "--vehicle",
                str(rec.vehicle_yaml),
                "--workers",
                "1",
                "--out",
                str(DIR / "result.json"),
                *args,
            ]
        )
    return code, stderr.getvalue()


def test_calibrate_accepts_the_intact_recording() -> None:
    assert run_calibrate("--mcap", str(small_recording().path)) == (0, "")


@fuzz_settings(0.02)
@given(damage=damage)
def test_calibrate_on_a_damaged_recording(damage: tuple[list[tuple[float, int]], float | None]) -> None:
    path = damaged_recording(*damage)
    code, stderr = run_calibrate("--mcap", str(path))
    label(f"exit {code}")
    assert code in (0, 2, 3), (code, stderr)
    if code == 2:
        assert stderr.startswith("error: ") and str(path) in stderr, stderr


def test_calibrate_on_a_recording_cut_to_nothing_usable() -> None:
    for cut in (0.0, 0.0001, 0.01):
        path = damaged_recording([], cut)
        code, stderr = run_calibrate("--mcap", str(path))
        assert code == 2 and str(path) in stderr, (cut, code, stderr)
