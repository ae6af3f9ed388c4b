"""Every bad argument of `rsucal` gets one line naming the option or field and exit 2, never a traceback.

The cases are the ones a careful first use found (issue 12): negative seeds, an --out that is a file or
whose directory is missing, a --preview that is no PNG path, a zero or negative demo rate, an unknown log
level, --workers < 1, an unusable storage.state_dir for the daemon, and evaluate against another scene's
ground truth. Each also checks that nothing was written or started on the way to the error.
"""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import free_port

from daemon import __version__, cli
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.results import CalibrationResult

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "rsu.example.yaml"


@dataclass(frozen=True)
class Run:
    code: int
    out: str
    err: str


def rsucal(argv: Sequence[str]) -> Run:
    """cli.main in-process; argparse's own errors (SystemExit) become exit codes as in a shell."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(argv))
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else 0
    return Run(code, out.getvalue(), err.getvalue())


def assert_bad_input(run: Run, *names: str) -> None:
    """Exit 2, exactly one line on stderr, naming every one of `names`, and no traceback."""
    assert run.code == 2, run
    lines = run.err.strip().splitlines()
    assert len(lines) == 1, run.err
    for name in names:
        assert name in lines[0], run.err
    assert "Traceback" not in run.err and "internal error" not in run.err


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--preset", "carla-like", "--seed", "-1", "--out", "X"],
        ["simulate", "--seed", "1.5", "--out", "X"],
        ["demo", "--seed", "-7"],
        ["calibrate", "--camera", "c", "--vehicle", "v", "--mcap", "m", "--seed", "-3", "--out", "r.json"],
        ["calibrate", "--camera", "c", "--vehicle", "v", "--mcap", "m", "--seed", str(2**128), "--out", "r"],
    ],
)
def test_a_negative_or_non_integer_seed_is_refused_by_name(argv: list[str]) -> None:
    assert_bad_input(rsucal(argv), "--seed")


@pytest.mark.parametrize("workers", ["0", "-2", "two"])
def test_workers_below_one_are_refused(workers: str) -> None:
    argv = ["calibrate", "--camera", "c", "--vehicle", "v", "--mcap", "m", "--workers", workers, "--out", "r"]
    assert_bad_input(rsucal(argv), "--workers")


@pytest.mark.parametrize("command", ["calibrate", "report"])
@pytest.mark.parametrize("limit", ["0", "-0.1", "nan", "inf", "rtk"])
def test_the_v2x_accuracy_limit_must_be_a_positive_finite_number(command: str, limit: str) -> None:
    argv = [command, "--camera", "c", "--vehicle", "v", "--mcap", "m", "--max-v2x-std", limit, "--out", "r"]
    if command == "report":
        argv = ["report", "r.json", "--vehicle", "v", "--mcap", "m", "--max-v2x-std", limit, "--out", "r"]
    assert_bad_input(rsucal(argv), "--max-v2x-std")


@pytest.mark.parametrize("rate", ["0", "-1", "nan", "inf", "fast"])
def test_demo_rate_must_be_a_positive_finite_number(rate: str) -> None:
    assert_bad_input(rsucal(["demo", "--rate", rate]), "--rate")


def test_demo_timeout_must_be_positive() -> None:
    assert_bad_input(rsucal(["demo", "--timeout", "0"]), "--timeout")


def test_demo_unknown_preset_is_named_before_anything_runs() -> None:
    run = rsucal(["demo", "--preset", "nope"])
    assert_bad_input(run, "--preset", "nope", "sil-west")
    assert run.out == ""  # not even "simulating ..."


@pytest.mark.parametrize("level", ["LOUD", "", "5"])
def test_unknown_log_level_is_refused_by_name(level: str) -> None:
    assert_bad_input(rsucal(["--log-level", level, "status"]), "--log-level", "WARNING")


def test_log_level_is_case_insensitive() -> None:
    assert cli.build_parser().parse_args(["--log-level", "debug", "status"]).log_level == "DEBUG"


def test_version_prints_the_package_version() -> None:
    run = rsucal(["--version"])
    assert run.code == 0
    assert run.out.strip() == f"rsucal {__version__}"


# ------------------------------------------------------------------------------------------ simulate


def test_simulate_out_that_is_a_file_is_refused(tmp_path: Path) -> None:
    existing = tmp_path / "empty.yaml"
    existing.write_text("")
    assert_bad_input(rsucal(["simulate", "--preset", "carla-like", "--out", str(existing)]), "--out")
    assert existing.read_text() == ""


@pytest.mark.parametrize("preview", ["preview", "adir", "picture.jpg", "missing-dir/p.png", ""])
def test_simulate_preview_that_is_no_png_file_is_refused_before_anything_is_written(
    tmp_path: Path, preview: str
) -> None:
    (tmp_path / "adir").mkdir()
    out = tmp_path / "out"
    run = rsucal(
        ["simulate", "--preset", "carla-like", "--out", str(out), "--preview", str(tmp_path / preview)]
    )
    assert_bad_input(run, "--preview")
    assert not any(out.iterdir())  # the simulation never ran: no recording, no YAML


def test_simulate_preview_inside_the_new_out_directory_is_accepted(tmp_path: Path) -> None:
    out = tmp_path / "new" / "sim"
    run = rsucal(["simulate", "--preset", "carla-like", "--out", str(out), "--preview", str(out / "p.png")])
    assert run.code == 0, run.err
    assert (out / "p.png").stat().st_size > 0 and (out / "recording.mcap").is_file()


# ----------------------------------------------------------------------------------------- calibrate


def test_calibrate_out_in_a_missing_directory_is_refused_and_nothing_created(tmp_path: Path) -> None:
    out = tmp_path / "nonexistent" / "dir" / "r.json"
    argv = ["calibrate", "--camera", "c.yaml", "--vehicle", "v.yaml", "--mcap", "m.mcap", "--out", str(out)]
    assert_bad_input(rsucal(argv), "--out", "does not exist")
    assert not (tmp_path / "nonexistent").exists()


def test_calibrate_out_that_is_a_directory_is_refused(tmp_path: Path) -> None:
    argv = [
        "calibrate",
        "--camera",
        "c.yaml",
        "--vehicle",
        "v.yaml",
        "--mcap",
        "m.mcap",
        "--out",
        str(tmp_path),
    ]
    assert_bad_input(rsucal(argv), "--out", "directory")


# -------------------------------------------------------------------------------------------- daemon


def _config_with_state_dir(tmp_path: Path, state_dir: str) -> Path:
    data = yaml.safe_load(EXAMPLE.read_text())
    data["storage"]["state_dir"] = state_dir
    data["zenoh"] = {"listen": [f"tcp/127.0.0.1:{free_port()}"]}
    path = tmp_path / "rsu.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("where", ["proc", "file", "under-file"])
def test_daemon_with_an_unusable_state_dir_exits_2_naming_the_field(tmp_path: Path, where: str) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    state_dir = {"proc": "/proc/nope", "file": str(a_file), "under-file": str(a_file / "state")}[where]
    run = rsucal(["daemon", "--config", str(_config_with_state_dir(tmp_path, state_dir))])
    assert_bad_input(run, "storage.state_dir", state_dir)


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere: no permission error to provoke")
def test_daemon_with_a_state_dir_it_may_not_write_exits_2(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        run = rsucal(["daemon", "--config", str(_config_with_state_dir(tmp_path, str(locked / "state")))])
    finally:
        locked.chmod(0o700)
    assert_bad_input(run, "storage.state_dir")


# ------------------------------------------------------------------------------------------ evaluate


def _truth(camera_position_utm: tuple[float, float, float], stamps: Sequence[int]) -> GroundTruth:
    from pipeline.camera import camera_rotation_from_view

    R = camera_rotation_from_view(yaw=0.3, pitch_down=0.25)
    centre = np.asarray(camera_position_utm)
    origin = centre.round(-3)
    t_local = -R @ (centre - origin)
    return GroundTruth(
        camera_id="cam",
        crs="EPSG:32632",
        origin=tuple(origin),
        R=R.tolist(),
        t_utm=tuple(-R @ centre),
        t_local=tuple(t_local),
        camera_position_utm=camera_position_utm,
        intrinsics={"width": 1920, "height": 1080, "fx": 1000.0, "fy": 1000.0, "cx": 960.0, "cy": 540.0},
        station_id=4242,
        traversals=3,
        frames=[GroundTruthFrame(stamp_ns=stamp) for stamp in stamps],
    )


def _result_of(truth: GroundTruth, window: tuple[int, int]) -> CalibrationResult:
    from pipeline.metrics import result_from_ground_truth

    result = result_from_ground_truth(truth, rsu_id="rsu")
    provenance = result.provenance.model_copy(
        update={"window_start_ns": window[0], "window_end_ns": window[1]}
    )
    return result.model_copy(update={"provenance": provenance})


def _evaluate(tmp_path: Path, result: CalibrationResult, truth: GroundTruth) -> Run:
    calib, truth_path = tmp_path / "result.json", tmp_path / "truth.json"
    calib.write_text(result.model_dump_json())
    truth_path.write_text(truth.model_dump_json())
    return rsucal(["evaluate", "--calib", str(calib), "--ground-truth", str(truth_path)])


STAMPS = [1_700_000_000_000_000_000 + k * 100_000_000 for k in range(5)]


def test_evaluate_against_its_own_truth_exits_0(tmp_path: Path) -> None:
    truth = _truth((500_000.0, 5_400_000.0, 8.0), STAMPS)
    run = _evaluate(tmp_path, _result_of(truth, (STAMPS[0], STAMPS[-1])), truth)
    assert run.code == 0, run.err
    assert "position error" in run.out


def test_evaluate_against_the_truth_of_a_scene_134_km_away_exits_2(tmp_path: Path) -> None:
    truth = _truth((500_000.0, 5_400_000.0, 8.0), STAMPS)
    elsewhere = _truth((600_000.0, 5_490_000.0, 8.0), STAMPS)
    run = _evaluate(tmp_path, _result_of(truth, (STAMPS[0], STAMPS[-1])), elsewhere)
    assert_bad_input(run, "--ground-truth", "134.5 km", "another scene")


def test_evaluate_against_the_truth_of_another_recording_exits_2(tmp_path: Path) -> None:
    truth = _truth((500_000.0, 5_400_000.0, 8.0), STAMPS)
    later = [stamp + 86_400 * 10**9 for stamp in STAMPS]  # same camera, a day later
    run = _evaluate(
        tmp_path, _result_of(truth, (STAMPS[0], STAMPS[-1])), _truth((500_000.0, 5_400_000.0, 8.0), later)
    )
    assert_bad_input(run, "--ground-truth", "do not overlap")
