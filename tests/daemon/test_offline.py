"""daemon.offline: assembling CalibrationInputs from files, choosing camera and station, and the reports."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from daemon.offline import (
    DEFAULT_YAML_CRS,
    TerminalProgress,
    format_summary,
    load_offline_inputs,
    write_result,
)
from daemon.recording import RecordingWriter
from pipeline.calibrate import PipelineParams, calibrate
from pipeline.errors import InputError
from pipeline.frames import UtmFrame, pose_from_v2x
from pipeline.loaders import load_calibration_result
from schemas.common import Box, CameraIntrinsics
from schemas.messages import DetectionFrame, V2xAccuracies, V2xPosition
from schemas.results import CalibrationResult, Verdict

T0 = 1_700_000_000_000_000_000
CAMERA_YAML = "width: 1920\nheight: 1080\nfx: 1000.0\nfy: 1000.0\ncx: 960.0\ncy: 540.0\n"
VEHICLE_YAML = "length: 4.8\nwidth: 1.85\nheight: 1.5\nimu_offset: [1.3, 0.925, 0.35]\n"


@pytest.fixture
def site(tmp_path: Path) -> Path:
    (tmp_path / "cam_north.yaml").write_text(CAMERA_YAML)
    (tmp_path / "vehicle.yaml").write_text(VEHICLE_YAML)
    return tmp_path


def _v2x(station_id: int, i: int, lat: float = 48.4, lon: float = 9.9) -> V2xPosition:
    return V2xPosition(
        station_id=station_id,
        stamp_ns=T0 + i * 100_000_000,
        lat=lat + 1e-5 * i,
        lon=lon,
        alt=500.0,
        heading_deg=10.0,
        speed=10.0,
    )


def _write_mcap(
    path: Path, cameras: tuple[str, ...] = ("north",), stations: tuple[int, ...] = (7,), frames: int = 20
) -> Path:
    # Small chunks, so that a cut file still holds intact ones.
    with RecordingWriter(path, chunk_size=4096) as writer:
        for i in range(frames):
            for camera_id in cameras:
                box = Box(x1=100.0 + i, y1=500.0, x2=180.0 + i, y2=560.0, cls=4, score=0.9)
                frame = DetectionFrame(camera_id=camera_id, stamp_ns=T0 + i * 100_000_000, boxes=[box])
                writer.write_detections("rsu-7", frame, frame.stamp_ns + 1000)
            for station in stations:
                message = _v2x(station, i)
                writer.write_v2x(message, message.stamp_ns + 1000)
    return path


# ---------------------------------------------------------------------------------------------- MCAP


def test_mcap_single_camera_and_station_need_no_choice(site: Path) -> None:
    mcap = _write_mcap(site / "rec.mcap")
    loaded = load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)
    inputs = loaded.inputs
    assert (inputs.rsu_id, inputs.camera_id, inputs.station_id) == ("rsu-7", "north", 7)
    assert inputs.crs == "EPSG:32632"  # lon 9.9 E: zone 32
    assert any("EPSG:32632" in note for note in loaded.notes)
    assert len(inputs.detections) == 20 and all(f.camera_id == "north" for f in inputs.detections)
    assert inputs.recordings == (str(mcap),)


def test_mcap_with_several_cameras_lists_them(site: Path) -> None:
    mcap = _write_mcap(site / "rec.mcap", cameras=("north", "south"))
    with pytest.raises(InputError, match=r"rec\.mcap: detections: 2 cameras \(north, south\).*--camera-id"):
        load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)
    loaded = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, camera_id="south"
    )
    assert {f.camera_id for f in loaded.inputs.detections} == {"south"}


def test_mcap_with_several_stations_lists_them_with_counts(site: Path) -> None:
    mcap = _write_mcap(site / "rec.mcap", stations=(7, 4711))
    with pytest.raises(InputError, match=r"v2x: 2 stations \(7 \(20 positions\), 4711 \(20 positions\)\)"):
        load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)
    loaded = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, station_id=4711
    )
    assert loaded.inputs.station_id == 4711 and len(loaded.inputs.poses) == 20
    with pytest.raises(InputError, match="no positions of station 5"):
        load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, station_id=5)


def test_mcap_positions_reported_imprecise_are_not_calibrated_from(site: Path) -> None:
    # The receiver lost RTK fix for a while (float: 0.4 m, 1 sigma) and said so.
    mcap = site / "rec.mcap"
    with RecordingWriter(mcap) as writer:
        for i in range(20):
            accuracy = 0.4 if 5 <= i < 12 else 0.015
            message = _v2x(7, i).model_copy(
                update={"accuracies": V2xAccuracies(horizontal_m=accuracy, vertical_m=2 * accuracy)}
            )
            writer.write_v2x(message, message.stamp_ns + 1000)
        box = Box(x1=100.0, y1=500.0, x2=180.0, y2=560.0, cls=4, score=0.9)
        writer.write_detections("rsu-7", DetectionFrame(camera_id="north", stamp_ns=T0, boxes=[box]), T0)
    loaded = load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)
    stamps = [pose.stamp_ns for pose in loaded.inputs.poses]
    assert stamps == [T0 + i * 100_000_000 for i in (*range(5), *range(12, 20))]
    assert any("7 of 20 V2X position(s) not used" in note and "0.1 m" in note for note in loaded.notes)
    # A looser limit (an operator's choice for a vehicle without RTK) keeps them.
    looser = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, max_v2x_std_m=0.5
    )
    assert len(looser.inputs.poses) == 20 and not any("not used" in n for n in looser.notes)
    # None precise enough: calibrate's refusal names the reason, not just the missing poses.
    stricter = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, max_v2x_std_m=0.01
    )
    assert stricter.inputs.poses == []
    outcome = calibrate(
        stricter.inputs, PipelineParams(), np.random.default_rng(0), created_at_ns=T0, map_fn=map
    )
    assert outcome.result.verdict.reasons == [
        "no calibration-vehicle poses in the data window (20 of 20 V2X position(s) not used: the vehicle "
        "reported them less accurate than 0.01 m (1 sigma, vertically twice that; --max-v2x-std): RTK "
        "float or no RTK)"
    ]


def test_mcap_without_v2x_is_bad_input(site: Path) -> None:
    mcap = _write_mcap(site / "rec.mcap", stations=())
    with pytest.raises(InputError, match=r"rec\.mcap: v2x: .*no v2x/cam/\* positions"):
        load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)


def test_truncated_mcap_keeps_what_it_can_and_says_so(site: Path) -> None:
    raw = _write_mcap(site / "full.mcap", frames=300).read_bytes()
    cut = site / "cut.mcap"
    cut.write_bytes(raw[: len(raw) // 2])
    loaded = load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=cut)
    assert 0 < len(loaded.inputs.detections) < 300 and 0 < len(loaded.inputs.poses) < 300
    assert any("not finished by its writer" in note for note in loaded.notes)
    assert any(note.startswith(f"{cut}: ") and "truncated" in note for note in loaded.notes)


def test_explicit_crs_is_normalised_and_checked(site: Path) -> None:
    mcap = _write_mcap(site / "rec.mcap")
    loaded = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, crs="epsg:32632"
    )
    assert loaded.inputs.crs == "EPSG:32632" and loaded.notes == ()
    for crs, problem in (("EPSG:4326", "not a UTM zone"), ("EPSG:99999", "not a known CRS"), ("utm", "EPSG")):
        with pytest.raises(InputError, match=f"--crs: .*{problem}"):
            load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap, crs=crs)


def test_a_lens_model_that_turns_back_inside_the_image_is_said_first(site: Path) -> None:
    # fx 900 on 1920 x 1080 with a polynomial that turns back at 913 px (the corners lie 1101 px out).
    turning = site / "turning.yaml"
    turning.write_text(
        CAMERA_YAML.replace("1000.0", "900.0") + "dist: [-0.30, 0.09, 0.0005, -0.0004, -0.012]\n"
    )
    mcap = _write_mcap(site / "rec.mcap")
    loaded = load_offline_inputs(turning, site / "vehicle.yaml", mcap_path=mcap, crs="EPSG:32632")
    assert loaded.notes == (
        f"{turning}: dist: the distortion turns back 913 px from the principal point, inside the image (its "
        "farthest corner is 1101 px away): boxes reaching beyond are not used; refit the intrinsics to use "
        "the whole image",
    )
    detections, poses = _write_pair(site)
    pair = load_offline_inputs(turning, site / "vehicle.yaml", detections_path=detections, poses_path=poses)
    assert pair.notes[0].startswith(f"{turning}: dist: the distortion turns back 913 px")
    # A physical strong barrel lens, and no distortion at all, are said nothing about.
    physical = site / "barrel.yaml"
    physical.write_text(
        CAMERA_YAML.replace("1000.0", "900.0") + "dist: [-0.25, 0.06, 0.0005, -0.0004, 0.0]\n"
    )
    for camera in (physical, site / "cam_north.yaml"):
        plain = load_offline_inputs(camera, site / "vehicle.yaml", mcap_path=mcap, crs="EPSG:32632")
        assert plain.notes == ()


# ---------------------------------------------------------------------------------------------- YAML pair


def _write_pair(site: Path, east: float = 572_000.0) -> tuple[Path, Path]:
    detections = site / "detections.yaml"
    detections.write_text(f"{T0}:\n- [140.0, 530.0, 80.0, 60.0, 4]\n{T0 + 100_000_000}: []\n")
    poses = site / "poses.yaml"
    poses.write_text(f"{T0}: [{east:.3f}, 5361000.000, 527.000, 0.1, 0.0, 0.0]\n")
    return detections, poses


def test_yaml_pair_defaults_crs_and_camera_id_from_the_camera_file(site: Path) -> None:
    detections, poses = _write_pair(site)
    loaded = load_offline_inputs(
        site / "cam_north.yaml", site / "vehicle.yaml", detections_path=detections, poses_path=poses
    )
    inputs = loaded.inputs
    assert inputs.crs == DEFAULT_YAML_CRS and any(DEFAULT_YAML_CRS in note for note in loaded.notes)
    assert (inputs.rsu_id, inputs.camera_id, inputs.station_id) == ("offline", "cam_north", None)
    assert [len(f.boxes) for f in inputs.detections] == [1, 0]
    assert inputs.poses[0].x == 572_000.0


def test_yaml_poses_in_a_local_frame_are_refused(site: Path) -> None:
    detections, poses = _write_pair(site, east=12.5)
    with pytest.raises(InputError, match=rf"poses\.yaml: {T0}\.x: 12\.5 is not a UTM coordinate"):
        load_offline_inputs(
            site / "cam_north.yaml", site / "vehicle.yaml", detections_path=detections, poses_path=poses
        )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({}, "give either --mcap"),
        ({"detections_path": Path("d.yaml")}, "--poses: the YAML pair needs both"),
        ({"poses_path": Path("p.yaml")}, "--detections: the YAML pair needs both"),
        ({"mcap_path": Path("r.mcap"), "poses_path": Path("p.yaml")}, "give either --mcap"),
        ({"mcap_path": Path("r.mcap"), "camera_id": "no spaces"}, "--camera-id: 'no spaces'"),
    ],
)
def test_argument_combinations_are_checked_before_any_file_is_read(
    kwargs: dict[str, object], message: str
) -> None:
    with pytest.raises(InputError, match=message):
        load_offline_inputs(Path("missing/camera.yaml"), Path("missing/vehicle.yaml"), **kwargs)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------- output


def _refused() -> CalibrationResult:
    return CalibrationResult(
        rsu_id="offline",
        camera_id="cam",
        result_id="r1",
        created_at_ns=T0,
        frame={"crs": "EPSG:32632", "origin": (0.0, 0.0, 0.0)},  # type: ignore[arg-type]
        intrinsics=CameraIntrinsics(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0),
        verdict=Verdict(status="refused", reasons=["no track overlaps", "second reason"]),
    )


def test_write_result_is_atomic_and_round_trips(tmp_path: Path) -> None:
    target = tmp_path / "nested" / "result.json"
    write_result(_refused(), target)
    assert load_calibration_result(target) == _refused()
    assert sorted(p.name for p in target.parent.iterdir()) == ["result.json"]
    # A directory in the way: the error names the target, and nothing else is left behind.
    blocked = tmp_path / "blocked.json"
    blocked.mkdir()
    with pytest.raises(InputError, match=r"blocked\.json: \(file\): cannot write"):
        write_result(_refused(), blocked)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocked.json", "nested"]
    assert json.loads(target.read_text())["verdict"]["status"] == "refused"


def test_summary_of_a_refusal_lists_every_reason_and_no_pose() -> None:
    text = format_summary(_refused(), Path("out.json"))
    assert text.splitlines()[0] == "verdict      refused (camera cam, rsu offline)"
    assert "  reason     no track overlaps" in text and "  reason     second reason" in text
    assert "position" not in text and text.endswith("wrote        out.json")


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_draws_only_on_a_terminal() -> None:
    for stream, draws in ((io.StringIO(), False), (_Terminal(), True)):
        with TerminalProgress(stream) as progress:
            for stage, fraction in (("tracking", 0.1), ("grouping", 0.45), ("grouping", 0.4), ("done", 1.0)):
                progress(stage, fraction)
        assert bool(stream.getvalue()) is draws
        if draws:
            for text in ("tracking", "grouping", "100%"):
                assert text in stream.getvalue()


def test_poses_are_pose_from_v2x_of_the_stations_messages(site: Path) -> None:
    # Grid yaw includes the meridian convergence: pose_from_v2x is the one conversion, used unchanged.
    mcap = _write_mcap(site / "rec.mcap")
    loaded = load_offline_inputs(site / "cam_north.yaml", site / "vehicle.yaml", mcap_path=mcap)
    frame = UtmFrame(loaded.inputs.crs)
    expected = [pose_from_v2x(_v2x(7, i), frame) for i in range(20)]
    assert list(loaded.inputs.poses) == expected
    assert np.all(np.diff([p.stamp_ns for p in loaded.inputs.poses]) > 0)
