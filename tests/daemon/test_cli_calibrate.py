"""`rsucal calibrate` end to end through daemon.cli.main on `rsucal simulate` output.

The same carla-like scene (seed 0) is calibrated from its MCAP recording and from its toolbox YAML pair;
a refusal (no-target) exits 3; broken inputs exit 2 naming the file and the field.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import ros_camera_info

from daemon import cli, offline
from daemon.recording import write_simulation_mcap
from pipeline.camera import rotation_angle_rad
from pipeline.frames import UtmFrame, v2x_from_pose
from pipeline.loaders import (
    load_calibration_result,
    load_intrinsics,
    load_toolbox_detections,
    load_toolbox_poses,
)
from schemas.results import CalibrationResult
from sim.files import write_simulation_files
from sim.simulate import PRESETS, SimulationResult, simulate

STAGES = ("association", "tracking", "hypotheses", "grouping", "refinement", "validation")


@dataclass(frozen=True)
class Run:
    code: int
    stdout: str
    stderr: str
    out: Path


def _rsucal(args: Sequence[str], out: Path | None = None) -> Run:
    """main() in-process, with its output captured (module-scoped fixtures cannot use capsys)."""
    stdout, stderr = io.StringIO(), io.StringIO()
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)  # --out's directory must exist (rsucal creates none)
    argv = [*args, "--out", str(out)] if out is not None else list(args)
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = cli.main(argv)
    return Run(code, stdout.getvalue(), stderr.getvalue(), out or Path())


@dataclass(frozen=True)
class Scene:
    sim: SimulationResult
    dir: Path

    def files(self, *names: str) -> list[str]:
        return [str(self.dir / name) for name in names]

    def common(self) -> list[str]:
        return ["calibrate", "--camera", *self.files("camera.yaml"), "--vehicle", *self.files("vehicle.yaml")]


def _write_scene(sim: SimulationResult, directory: Path) -> Scene:
    directory.mkdir(parents=True, exist_ok=True)
    write_simulation_files(sim, directory)
    write_simulation_mcap(sim, directory / "recording.mcap")
    return Scene(sim, directory)


@pytest.fixture(scope="module")
def carla(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    scene = _write_scene(simulate("carla-like", seed=0, ideal=True), tmp_path_factory.mktemp("carla"))
    # The same scene once more as an MCAP, but built from what the YAML pair holds: boxes rounded to
    # 0.01 px and poses to 1 mm / 1e-9 rad. It isolates the MCAP path's own conversions (V2X lat/lon and
    # true heading -> UTM and grid yaw) from the YAML format's rounding.
    sim = scene.sim
    camera_id = sim.cameras[0].camera_id
    frames = load_toolbox_detections(scene.dir / "detections.yaml", camera_id)
    poses = load_toolbox_poses(scene.dir / "poses.yaml")
    utm = UtmFrame(sim.origin.crs)
    assert [p.stamp_ns for p in poses] == [m.stamp_ns for m in sim.v2x]
    v2x = [v2x_from_pose(p, utm, m.station_id, m.speed) for p, m in zip(poses, sim.v2x, strict=True)]
    rounded = dataclasses.replace(sim, detections={camera_id: frames}, v2x=v2x)
    write_simulation_mcap(rounded, scene.dir / "rounded.mcap")
    return scene


@pytest.fixture(scope="module")
def mcap_run(carla: Scene) -> Run:
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--verbose"]
    return _rsucal(args, carla.dir / "results" / "mcap.json")


@pytest.fixture(scope="module")
def yaml_run(carla: Scene) -> Run:
    # --camera-id names the camera as the recording does; --crs is the simulator's zone (also the default).
    args = [
        *carla.common(),
        *("--detections", *carla.files("detections.yaml"), "--poses", *carla.files("poses.yaml")),
        *("--camera-id", "carla", "--crs", "EPSG:32632"),
    ]
    return _rsucal(args, carla.dir / "results" / "yaml.json")


@pytest.fixture(scope="module")
def rounded_run(carla: Scene) -> Run:
    return _rsucal(
        [*carla.common(), "--mcap", *carla.files("rounded.mcap")], carla.dir / "results" / "rounded.json"
    )


def _pose_difference(a: CalibrationResult, b: CalibrationResult) -> tuple[float, float, float]:
    """(rotation angle deg, |t_a - t_b| m, |camera centre_a - centre_b| m); both in the same local frame."""
    assert a.R is not None and b.R is not None and a.t is not None and b.t is not None
    assert a.frame == b.frame
    assert a.camera_position is not None and b.camera_position is not None
    angle = math.degrees(rotation_angle_rad(np.array(a.R), np.array(b.R)))
    shift_t = float(np.linalg.norm(np.subtract(a.t, b.t)))
    shift_c = float(np.linalg.norm(np.subtract(a.camera_position.utm, b.camera_position.utm)))
    return angle, shift_t, shift_c


# ---------------------------------------------------------------------------------------------- accepted


def test_mcap_run_exits_0_and_writes_a_valid_result(mcap_run: Run) -> None:
    assert mcap_run.code == cli.EXIT_OK, mcap_run.stdout + mcap_run.stderr
    result = load_calibration_result(mcap_run.out)  # strict schema validation of what was written
    assert result.verdict.status == "accepted"
    assert (result.rsu_id, result.camera_id) == ("sim-rsu", "carla")
    assert result.provenance.station_id == 4242
    assert result.frame.crs == "EPSG:32632"  # the zone of the first V2X position (Karlsruhe)
    assert sorted(p.name for p in mcap_run.out.parent.iterdir()) == ["mcap.json"]  # no temporary left
    assert "verdict      accepted" in mcap_run.stdout
    for label in ("position", "lat", "delta_p", "traversals", "std", "wrote"):
        assert label in mcap_run.stdout


def test_yaml_pair_gives_the_mcaps_result_within_its_rounding(mcap_run: Run, yaml_run: Run) -> None:
    assert yaml_run.code == cli.EXIT_OK, yaml_run.stdout + yaml_run.stderr
    mcap = load_calibration_result(mcap_run.out)
    yaml = load_calibration_result(yaml_run.out)
    # The YAML pair stores boxes at 0.01 px and poses at 1 mm: on this noise-free scene that moves the
    # estimate by at most ~0.1 mm / 5e-5 deg (measured 0.02-0.09 mm, 2-4e-5 deg). 1 mm / 0.001 deg leaves
    # room for the solver's tolerance and is still far below any real error (a wrong convention: dm, deg).
    angle, shift_t, shift_c = _pose_difference(mcap, yaml)
    assert angle < 1e-3 and shift_t < 1e-3 and shift_c < 1e-3, (angle, shift_t, shift_c)
    # Which marginal tracks join the chosen group may differ (seen: the same pose to 0.03 mm from 2 tracks
    # on 2 traversals vs 4 tracks on 3), so the pose is what is compared; both rest on >= 2 traversals.
    assert yaml.quality is not None and mcap.quality is not None
    assert min(yaml.quality.traversals, mcap.quality.traversals) >= 2


def test_mcap_of_the_rounded_data_matches_the_yaml_pair_to_float_precision(
    yaml_run: Run, rounded_run: Run
) -> None:
    # Same boxes, same poses: only the V2X round trip (UTM -> lat/lon/true heading -> UTM/grid yaw, ~1e-10
    # m, ~1e-12 rad) separates the two inputs, so every decision matches and the poses agree to within the
    # least-squares solver's tolerance (measured 1.7e-6 deg, 1.7e-10 m in t); a real difference (another
    # track, another clock, a convention) costs millimetres and hundredths of a degree.
    assert rounded_run.code == cli.EXIT_OK, rounded_run.stdout + rounded_run.stderr
    angle, shift_t, shift_c = _pose_difference(
        load_calibration_result(rounded_run.out), load_calibration_result(yaml_run.out)
    )
    assert angle < 1e-4 and shift_t < 1e-6 and shift_c < 1e-6, (angle, shift_t, shift_c)


def test_verbose_reports_every_stage_and_the_candidates(mcap_run: Run) -> None:
    for stage in STAGES:
        assert f"\n  {stage}" in mcap_run.stdout, stage
    assert "candidate groups (* chosen):" in mcap_run.stdout
    assert "  * tracks [" in mcap_run.stdout


def test_without_verbose_only_the_summary_is_printed(yaml_run: Run) -> None:
    assert "stages:" not in yaml_run.stdout
    assert "note: " not in yaml_run.stdout  # --crs was given: nothing assumed
    assert yaml_run.stdout.splitlines()[0].startswith("verdict      accepted")


# ---------------------------------------------------------------------------------------------- refused


def test_no_target_exits_3_with_the_reason(tmp_path: Path) -> None:
    # A shorter no-target scene (90 s of other traffic; the calibration vehicle drives elsewhere).
    config = dataclasses.replace(PRESETS["no-target"], duration_s=90.0)
    scene = _write_scene(simulate(config, seed=0, ideal=True), tmp_path / "scene")
    run = _rsucal([*scene.common(), "--mcap", *scene.files("recording.mcap")], tmp_path / "refused.json")
    assert run.code == cli.EXIT_REFUSED, run.stdout + run.stderr
    result = load_calibration_result(run.out)
    assert result.verdict.status == "refused" and result.verdict.reasons
    assert "verdict      refused" in run.stdout
    for reason in result.verdict.reasons:
        assert f"reason     {reason}" in run.stdout


def test_a_vehicle_less_accurate_than_the_limit_is_refused_saying_so(carla: Scene, tmp_path: Path) -> None:
    # The simulated vehicle reports 0.02 m (1 sigma); a limit of 0.01 m leaves none of its positions.
    sent = len(carla.sim.v2x)
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--max-v2x-std", "0.01"]
    run = _rsucal(args, tmp_path / "strict.json")
    assert run.code == cli.EXIT_REFUSED, run.stdout + run.stderr
    said = f"{sent} of {sent} V2X position(s) not used: the vehicle reported them less accurate than 0.01 m"
    assert f"note: {carla.dir / 'recording.mcap'}: {said}" in run.stdout
    assert (
        load_calibration_result(run.out)
        .verdict.reasons[0]
        .startswith(f"no calibration-vehicle poses in the data window ({said}")
    )


# ---------------------------------------------------------------------------------------------- bad input


def _bad_input(run: Run, *expected: str) -> None:
    assert run.code == cli.EXIT_BAD_INPUT, run.stdout + run.stderr
    assert run.stderr.startswith("error: ")
    for text in expected:
        assert text in run.stderr, (text, run.stderr)
    assert not run.out.exists()


def test_broken_camera_yaml_names_file_and_field(carla: Scene, tmp_path: Path) -> None:
    camera = tmp_path / "camera.yaml"
    text = (carla.dir / "camera.yaml").read_text()
    camera.write_text("\n".join(line for line in text.splitlines() if not line.startswith("fx:")) + "\n")
    args = ["calibrate", "--camera", str(camera), "--vehicle", *carla.files("vehicle.yaml")]
    run = _rsucal([*args, "--mcap", *carla.files("recording.mcap")], tmp_path / "out.json")
    _bad_input(run, str(camera), "fx")


def test_a_ros_camera_info_file_calibrates_as_the_camera_yaml_does(
    carla: Scene, mcap_run: Run, tmp_path: Path
) -> None:
    # The camera as ROS's camera_calibration saves it (ost.yaml): the same intrinsics, the same result.
    k = load_intrinsics(carla.dir / "camera.yaml")
    info = ros_camera_info(k)
    camera = tmp_path / "ost.yaml"
    camera.write_text(yaml.safe_dump(info))
    args = ["calibrate", "--camera", str(camera), "--vehicle", *carla.files("vehicle.yaml")]
    run = _rsucal([*args, "--mcap", *carla.files("recording.mcap"), "--verbose"], tmp_path / "ros.json")
    assert run.code == cli.EXIT_OK, run.stdout + run.stderr
    ros, native = load_calibration_result(run.out), load_calibration_result(mcap_run.out)
    assert ros.intrinsics == native.intrinsics
    assert (ros.R, ros.t, ros.verdict) == (native.R, native.t, native.verdict)
    # A fisheye calibration is refused by name: rsucal models pinhole lenses.
    info["distortion_model"] = "equidistant"
    camera.write_text(yaml.safe_dump(info))
    run = _rsucal([*args, "--mcap", *carla.files("recording.mcap")], tmp_path / "fisheye.json")
    _bad_input(run, str(camera), "distortion_model: 'equidistant' (a fisheye lens) is not supported")


def test_nan_in_detections_yaml_names_file_stamp_and_field(carla: Scene, tmp_path: Path) -> None:
    lines = (carla.dir / "detections.yaml").read_text().splitlines()
    first_box = next(i for i, line in enumerate(lines) if line.startswith("- ["))
    stamp = next(line for line in reversed(lines[:first_box]) if not line.startswith("-")).rstrip(":")
    lines[first_box] = "- [.nan, 540.0, 20.0, 20.0, 4]"
    detections = tmp_path / "detections.yaml"
    detections.write_text("\n".join(lines) + "\n")
    args = [*carla.common(), "--detections", str(detections), "--poses", *carla.files("poses.yaml")]
    _bad_input(_rsucal(args, tmp_path / "out.json"), str(detections), f"{stamp}.0.cx", "finite")


def test_truncated_mcap_names_the_file_and_the_damage(carla: Scene, tmp_path: Path) -> None:
    # Cut inside the first chunk: nothing can be proven intact. (A file cut later still calibrates from
    # what it holds, with a note; see tests/daemon/test_offline.py.)
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes((carla.dir / "recording.mcap").read_bytes()[:2000])
    run = _rsucal([*carla.common(), "--mcap", str(truncated)], tmp_path / "out.json")
    _bad_input(run, str(truncated), "truncated")


def test_unknown_camera_id_lists_the_recordings_cameras(carla: Scene, tmp_path: Path) -> None:
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--camera-id", "north"]
    _bad_input(_rsucal(args, tmp_path / "out.json"), "recording.mcap", "no camera 'north'", "carla")


def test_crs_that_is_not_utm_is_refused_before_reading(carla: Scene, tmp_path: Path) -> None:
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--crs", "EPSG:4326"]
    _bad_input(_rsucal(args, tmp_path / "out.json"), "--crs", "not a UTM zone")


def test_poses_without_detections_is_a_usage_error(carla: Scene, tmp_path: Path) -> None:
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--poses", *carla.files("poses.yaml")]
    _bad_input(_rsucal(args, tmp_path / "out.json"), "--mcap", "--detections")


def test_help_states_the_yaml_default_crs(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.DEFAULT_YAML_CRS == offline.DEFAULT_YAML_CRS  # cli keeps a copy to stay light to import
    with pytest.raises(SystemExit) as exited:
        cli.main(["calibrate", "--help"])
    assert exited.value.code == 0
    assert f"YAML default: {offline.DEFAULT_YAML_CRS}" in " ".join(capsys.readouterr().out.split())


# ------------------------------------------------------------------------------------------ local frames

# Where the local frame's origin sits in the scene's UTM zone: whole metres, as a site survey gives it.
LOCAL_ORIGIN_EN = (456_400.0, 5_428_700.0)


@pytest.fixture(scope="module")
def local_poses(carla: Scene) -> Path:
    """The scene's poses.yaml moved into a local metric frame (x, y of metres around the site), as the
    reference toolbox publishes its real track."""
    from sim.files import format_toolbox_poses

    east, north = LOCAL_ORIGIN_EN
    poses = [
        pose.model_copy(update={"x": pose.x - east, "y": pose.y - north})
        for pose in load_toolbox_poses(carla.dir / "poses.yaml")
    ]
    assert all(abs(pose.x) < 5_000.0 and abs(pose.y) < 5_000.0 for pose in poses)
    path = carla.dir / "poses_local.yaml"
    path.write_text(format_toolbox_poses(poses))
    return path


def _local_args(carla: Scene, local_poses: Path, *extra: str) -> list[str]:
    return [
        *carla.common(),
        *("--detections", *carla.files("detections.yaml"), "--poses", str(local_poses)),
        *("--camera-id", "carla"),
        *extra,
    ]


def test_local_poses_without_an_option_name_the_local_frame_option(
    carla: Scene, local_poses: Path, tmp_path: Path
) -> None:
    run = _rsucal(_local_args(carla, local_poses), tmp_path / "out.json")
    _bad_input(run, str(local_poses), "not a UTM coordinate", "--frame local", "--origin E,N --crs EPSG:N")


def test_frame_local_calibrates_in_the_poses_frame_without_lat_lon(
    carla: Scene, local_poses: Path, yaml_run: Run, tmp_path: Path
) -> None:
    run = _rsucal(_local_args(carla, local_poses, "--frame", "local"), tmp_path / "local.json")
    assert run.code == cli.EXIT_OK, run.stdout + run.stderr
    local = load_calibration_result(run.out)
    utm = load_calibration_result(yaml_run.out)
    assert local.frame.crs == "local"
    assert local.camera_position is not None and utm.camera_position is not None
    assert (local.camera_position.lat, local.camera_position.lon, local.camera_position.alt) == (None,) * 3
    assert "no lat/lon" in run.stdout
    # The same camera, in the local frame: the UTM result's position minus the frame's origin, and the
    # same rotation (the frames differ by a translation). The poses were re-rounded to 1 mm after the
    # shift, hence a tolerance of the YAML pair's rounding (see test_yaml_pair_gives_the_mcaps_result...).
    east, north = LOCAL_ORIGIN_EN
    shifted = np.subtract(utm.camera_position.utm, (east, north, 0.0))
    assert np.linalg.norm(np.subtract(local.camera_position.utm, shifted)) < 1e-3
    assert local.R is not None and utm.R is not None
    assert math.degrees(rotation_angle_rad(np.array(local.R), np.array(utm.R))) < 1e-3


def test_origin_places_the_local_frame_in_utm_with_lat_lon(
    carla: Scene, local_poses: Path, yaml_run: Run, tmp_path: Path
) -> None:
    east, north = LOCAL_ORIGIN_EN
    args = _local_args(carla, local_poses, "--origin", f"{east:.0f},{north:.0f}", "--crs", "EPSG:32632")
    run = _rsucal(args, tmp_path / "placed.json")
    assert run.code == cli.EXIT_OK, run.stdout + run.stderr
    placed = load_calibration_result(run.out)
    utm = load_calibration_result(yaml_run.out)
    assert placed.frame.crs == "EPSG:32632"
    assert placed.frame == utm.frame  # the same median origin: the frames differ by whole metres
    angle, shift_t, shift_c = _pose_difference(placed, utm)
    assert placed.camera_position is not None and utm.camera_position is not None
    assert np.linalg.norm(np.subtract(placed.camera_position.utm, utm.camera_position.utm)) < 1e-3
    assert placed.camera_position.lat is not None and utm.camera_position.lat is not None
    assert abs(placed.camera_position.lat - utm.camera_position.lat) < 1e-7
    assert angle < 1e-3 and shift_t < 1e-3 and shift_c < 1e-3


@pytest.mark.parametrize(
    ("extra", "names"),
    [
        (("--origin", "456400,5428700"), ("--origin", "--crs EPSG:N")),
        (("--origin", "456400", "--crs", "EPSG:32632"), ("--origin", "E,N")),
        (("--origin", "nan,5428700", "--crs", "EPSG:32632"), ("--origin",)),
        (("--origin", "13,14", "--crs", "EPSG:32632"), ("--origin", "not a UTM coordinate")),
        (("--frame", "local", "--crs", "EPSG:32632"), ("--crs", "--origin")),
    ],
)
def test_bad_local_frame_options_are_refused_by_name(
    carla: Scene, local_poses: Path, tmp_path: Path, extra: tuple[str, ...], names: tuple[str, ...]
) -> None:
    _bad_input(_rsucal(_local_args(carla, local_poses, *extra), tmp_path / "out.json"), *names)


def test_a_local_frame_does_not_apply_to_a_recording(carla: Scene, tmp_path: Path) -> None:
    args = [*carla.common(), "--mcap", *carla.files("recording.mcap"), "--frame", "local"]
    _bad_input(_rsucal(args, tmp_path / "out.json"), "--frame", "WGS84")


def test_report_re_runs_a_local_frame_result_in_its_frame(
    carla: Scene, local_poses: Path, tmp_path: Path
) -> None:
    run = _rsucal(_local_args(carla, local_poses, "--frame", "local"), tmp_path / "local.json")
    assert run.code == cli.EXIT_OK, run.stdout + run.stderr
    args = ["report", str(run.out), "--vehicle", *carla.files("vehicle.yaml")]
    args += ["--detections", *carla.files("detections.yaml"), "--poses", str(local_poses)]
    report = _rsucal([*args, "--out", str(tmp_path / "report")])
    assert report.code == cli.EXIT_OK, report.stdout + report.stderr
    html = (tmp_path / "report" / "report.html").read_text()
    assert "no lat/lon" in html
