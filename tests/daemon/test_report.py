"""`rsucal report` end to end through daemon.cli.main on `rsucal simulate` output, and its figures' numbers.

A simulated run (RESULT.json + the MCAP) and an offline one (+ the toolbox YAML pair) each give one
self-contained HTML file and its PNGs; a refused result is reported as refused with its reasons; bad input
exits 2 with one line naming the file. The per-box errors behind the figures come from the result's pose:
the truth's pose scores better than one 1 m off.
"""

from __future__ import annotations

import base64
import contextlib
import io
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from daemon import cli, report
from daemon.recording import write_simulation_mcap
from pipeline.calibrate import CalibrationInputs, CalibrationOutcome, PipelineParams, calibrate
from pipeline.frames import UtmFrame, poses_from_v2x
from pipeline.loaders import load_calibration_result
from pipeline.metrics import result_from_ground_truth
from schemas.results import CalibrationResult, Verdict
from sim.files import write_simulation_files
from sim.simulate import SimulationResult, simulate

CREATED_AT_NS = 1_700_000_000_000_000_000  # the result's creation time: the caller's clock

FIGURES = ("map.png", "distance.png", "residuals.png", "hypotheses.png", "uncertainty.png")


@dataclass(frozen=True)
class Run:
    code: int
    stdout: str
    stderr: str


def _rsucal(args: Sequence[str]) -> Run:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = cli.main(list(args))
    return Run(code, stdout.getvalue(), stderr.getvalue())


@dataclass(frozen=True)
class Scene:
    sim: SimulationResult
    dir: Path
    result: Path  # RESULT.json of `rsucal calibrate --mcap`

    def path(self, name: str) -> str:
        return str(self.dir / name)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    directory = tmp_path_factory.mktemp("report")
    sim = simulate("carla-like", seed=0, ideal=True)  # the report is under test, not the method: its world
    write_simulation_files(sim, directory)
    write_simulation_mcap(sim, directory / "recording.mcap")
    result = directory / "result.json"
    run = _rsucal(
        [
            "calibrate",
            *("--camera", str(directory / "camera.yaml"), "--vehicle", str(directory / "vehicle.yaml")),
            *("--mcap", str(directory / "recording.mcap"), "--workers", "1", "--out", str(result)),
        ]
    )
    assert run.code == 0, run.stderr
    return Scene(sim, directory, result)


def _figures_in(html_path: Path) -> dict[str, np.ndarray]:
    """name -> decoded image of every figure embedded in the report (one that does not decode fails)."""
    text = html_path.read_text(encoding="utf-8")
    found = {}
    for name, encoded in re.findall(
        r"<img alt='([^']+)' src='data:image/png;base64,([A-Za-z0-9+/=]+)'>", text
    ):
        image = cv2.imdecode(np.frombuffer(base64.b64decode(encoded), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None, name
        found[name] = image
    return found


def _check_report(out: Path, result: CalibrationResult, run: Run) -> str:
    assert run.code == 0, run.stderr
    html_path = out / "report.html"
    assert f"wrote {html_path}" in run.stdout
    text = html_path.read_text(encoding="utf-8")
    # Self-contained: every figure inlined, nothing to fetch.
    assert "<link" not in text and "<script" not in text and "src='http" not in text
    embedded = _figures_in(html_path)
    assert result.quality is not None
    overlays = [f"overlay-{i + 1}.png" for i in range(result.quality.traversals)]
    assert sorted(embedded) == sorted([*overlays, *FIGURES])
    for name, image in embedded.items():
        on_disk = cv2.imread(str(out / name), cv2.IMREAD_COLOR)
        assert on_disk is not None and np.array_equal(on_disk, image), name
    return text


def test_report_of_a_simulated_run_from_its_recording(scene: Scene, tmp_path: Path) -> None:
    out = tmp_path / "mcap-report"
    run = _rsucal(
        [
            "report",
            str(scene.result),
            "--vehicle",
            scene.path("vehicle.yaml"),
            "--mcap",
            scene.path("recording.mcap"),
            "--workers",
            "1",
            "--out",
            str(out),
        ]
    )
    result = load_calibration_result(scene.result)
    text = _check_report(out, result, run)
    assert "Accepted: every validation gate passed" in text
    # The re-run on the same data with the same seed reproduces the result exactly.
    assert "re-run on this data (seed 0): accepted, 0.000 m / 0.000 deg from the result" in text
    assert result.result_id in text


def test_report_of_an_offline_run_from_the_yaml_pair(scene: Scene, tmp_path: Path) -> None:
    result_path = tmp_path / "yaml-result.json"
    common = ["--vehicle", scene.path("vehicle.yaml")]
    pair = ["--detections", scene.path("detections.yaml"), "--poses", scene.path("poses.yaml")]
    calibrated = _rsucal(
        [
            "calibrate",
            "--camera",
            scene.path("camera.yaml"),
            *common,
            *pair,
            "--camera-id",
            "carla",
            "--workers",
            "1",
            "--out",
            str(result_path),
        ]
    )
    assert calibrated.code == 0, calibrated.stderr
    out = tmp_path / "yaml-report"
    run = _rsucal(["report", str(result_path), *common, *pair, "--workers", "1", "--out", str(out)])
    text = _check_report(out, load_calibration_result(result_path), run)
    assert "re-run on this data (seed 0): accepted, 0.000 m / 0.000 deg" in text


def test_a_refused_result_is_reported_as_refused_with_its_reasons(scene: Scene, tmp_path: Path) -> None:
    result = load_calibration_result(scene.result)
    refused = result.model_copy(
        update={"verdict": Verdict(status="refused", reasons=["rotation std 0.91 deg > 0.5 deg"])}
    )
    path = tmp_path / "refused.json"
    path.write_text(refused.model_dump_json())
    out = tmp_path / "refused-report"
    run = _rsucal(
        [
            "report",
            str(path),
            "--vehicle",
            scene.path("vehicle.yaml"),
            "--mcap",
            scene.path("recording.mcap"),
            "--workers",
            "1",
            "--out",
            str(out),
        ]
    )
    text = (out / "report.html").read_text(encoding="utf-8")
    assert run.code == 0, run.stderr
    assert "Refused: this calibration must not be used." in text
    assert "<li>rotation std 0.91 deg &gt; 0.5 deg</li>" in text


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        pytest.param("missing.json", None, "missing.json", id="missing-result"),
        pytest.param("not-a-result.json", '{"rsu_id": 7}', "not-a-result.json", id="not-a-result"),
        pytest.param("not-json.json", "{", "not-json.json", id="not-json"),
    ],
)
def test_bad_result_exits_2_with_one_line(
    scene: Scene, tmp_path: Path, name: str, content: str | None, expected: str
) -> None:
    if content is not None:
        (tmp_path / name).write_text(content)
    out = tmp_path / "out"
    run = _rsucal(
        [
            "report",
            str(tmp_path / name),
            "--vehicle",
            scene.path("vehicle.yaml"),
            "--mcap",
            scene.path("recording.mcap"),
            "--out",
            str(out),
        ]
    )
    assert run.code == 2
    [line] = run.stderr.strip().splitlines()
    assert line.startswith("error: ") and expected in line
    assert not out.exists()


def test_bad_data_file_exits_2_naming_it(scene: Scene, tmp_path: Path) -> None:
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap at all")
    run = _rsucal(
        [
            "report",
            str(scene.result),
            "--vehicle",
            scene.path("vehicle.yaml"),
            "--mcap",
            str(broken),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    assert run.code == 2
    [line] = run.stderr.strip().splitlines()
    assert str(broken) in line


@pytest.fixture(scope="module")
def outcome(scene: Scene) -> CalibrationOutcome:
    sim = scene.sim
    camera = sim.cameras[0]
    poses, _ = poses_from_v2x(sim.v2x, UtmFrame(sim.origin.crs))
    inputs = CalibrationInputs(
        rsu_id=sim.rsu_id,
        camera_id=camera.camera_id,
        intrinsics=camera.intrinsics,
        vehicle=sim.vehicle,
        detections=sim.detections[camera.camera_id],
        poses=poses,
        crs=sim.origin.crs,
        time_offset_ns=sim.ground_truth[camera.camera_id].clock_offset_ns,
    )
    return calibrate(inputs, PipelineParams(), np.random.default_rng(0), created_at_ns=CREATED_AT_NS)


def test_overlays_are_drawn_on_the_recorded_image_when_there_is_one(
    scene: Scene, outcome: CalibrationOutcome
) -> None:
    """The image source is asked for every frame of the vehicle's boxes; a recording with images of every
    7th frame only (as `rsucal simulate --images 7` writes) still puts every drive-past on a recorded image
    (a uniform magenta JPEG here); without images the overlays keep the rendered frame."""
    sim = scene.sim
    camera = sim.cameras[0]
    result = outcome.result
    asked: list[list[int]] = []
    magenta = np.zeros((camera.intrinsics.height, camera.intrinsics.width, 3), np.uint8)
    magenta[:] = (200, 30, 220)  # BGR
    ok, jpeg = cv2.imencode(".jpg", magenta)
    assert ok

    def every_7th(stamps: Sequence[int]) -> dict[int, bytes]:
        asked.append(list(stamps))
        return {stamp: jpeg.tobytes() for stamp in sorted(stamps)[::7]}

    def none(stamps: Sequence[int]) -> dict[int, bytes]:
        return {}

    figures = report.render_figures(result, outcome, sim.vehicle, sim.detections[camera.camera_id], every_7th)
    assert result.quality is not None and len(asked) == 1 and len(asked[0]) > 10 * result.quality.traversals
    frame_stamps = {f.stamp_ns for f in sim.detections[camera.camera_id]}
    assert set(asked[0]) <= frame_stamps  # the overlays' frames are detection frames
    rendered = report.render_figures(result, outcome, sim.vehicle, sim.detections[camera.camera_id], none)

    def share(png: bytes, bgr: tuple[int, int, int]) -> float:
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        close = np.all(np.abs(image.astype(int) - np.array(bgr)) < 40, axis=2)
        return float(close.mean())

    for index in range(1, result.quality.traversals + 1):
        name = f"overlay-{index}.png"
        assert share(figures.png[name], (200, 30, 220)) > 0.3  # mostly the recorded image
        assert share(figures.png[name], (0x3A, 0x34, 0x30)) < 0.01
        assert share(rendered.png[name], (200, 30, 220)) < 0.01
        assert share(rendered.png[name], (0x3A, 0x34, 0x30)) > 0.3  # the rendered frame (#30343a)


def test_report_errors_come_from_the_results_pose(scene: Scene, outcome: CalibrationOutcome) -> None:
    """The figures' per-box delta_p and box error are the result's: the truth scores better than 1 m off."""
    sim = scene.sim
    camera = sim.cameras[0]
    assert outcome.diagnostics is not None and outcome.chosen is not None
    truth = result_from_ground_truth(sim.ground_truth[camera.camera_id], sim.rsu_id)
    assert truth.t is not None and truth.R is not None
    shifted = truth.model_copy(
        update={"t": tuple(np.asarray(truth.t) + np.asarray(truth.R) @ [1.0, 0.0, 0.0])}
    )
    chosen = [m for m in outcome.diagnostics.tracks if m.track_id in set(outcome.chosen.track_ids)]
    medians = []
    for result in (truth, shifted):
        R, t = report._pose_in_run_frame(result, outcome.diagnostics)
        data = report._chosen_boxes(
            chosen, R, t, report.CameraModel.from_intrinsics(camera.intrinsics), sim.vehicle
        )
        assert len(data.stamps) == sum(len(m.stamps) for m in chosen)
        medians.append((float(np.nanmedian(data.delta_p_m)), float(np.nanmedian(data.box_error_pct))))
    (truth_dp, truth_box), (shifted_dp, shifted_box) = medians
    assert truth_box < shifted_box and truth_dp < shifted_dp
