"""`rsucal daemon` refuses what it cannot run with exit 2 and a message naming the field or endpoint."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import yaml
from helpers import free_port, ros_camera_info

from daemon.cli import main
from schemas.common import CameraIntrinsics

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "rsu.example.yaml"


def _example(tmp_path: Path) -> dict[str, object]:
    data = yaml.safe_load(EXAMPLE.read_text())
    data["storage"]["state_dir"] = str(tmp_path / "state")
    data["zenoh"] = {"listen": [f"tcp/127.0.0.1:{free_port()}"]}
    # The example's detector needs the site's own model file: off here.
    for camera in data["cameras"]:
        camera["detector"] = None
    return data


def _run(tmp_path: Path, data: object, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    path = tmp_path / "rsu.yaml"
    path.write_text(yaml.safe_dump(data))
    code = main(["daemon", "--config", str(path)])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["cameras"][0]["intrinsics"].update(fx=-1.0), "cameras.0.intrinsics.fx"),
        (lambda d: d["trigger"].update(min_traversals=1), "trigger.min_traversals"),
        (lambda d: d["vehicles"][0].update(station_id="4242"), "vehicles.0.station_id"),
        (lambda d: d.update(rsu_id="bad/id"), "rsu_id"),
        (lambda d: d["storage"].update(retention_byte=5), "storage.retention_byte"),
        (lambda d: d["zenoh"].update(listen=["not-an-endpoint"]), "zenoh"),
    ],
)
def test_bad_config_exits_2_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], edit: object, field: str
) -> None:
    data = _example(tmp_path)
    edit(data)  # type: ignore[operator]
    code, err = _run(tmp_path, data, capsys)
    assert code == 2
    assert field in err, err
    assert not (tmp_path / "state").exists()  # nothing started


def test_missing_or_unparsable_config_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["daemon", "--config", str(tmp_path / "absent.yaml")]) == 2
    assert "absent.yaml" in capsys.readouterr().err
    bad = tmp_path / "rsu.yaml"
    bad.write_text("rsu_id: [unclosed\n")
    assert main(["daemon", "--config", str(bad)]) == 2
    assert "line" in capsys.readouterr().err


def test_endpoint_in_use_exits_2_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _example(tmp_path)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        data["zenoh"] = {"listen": [endpoint]}
        code, err = _run(tmp_path, data, capsys)
    assert code == 2
    assert endpoint in err, err


def test_relative_paths_are_relative_to_the_config_file(tmp_path: Path) -> None:
    from daemon.cli import _resolve_relative_paths
    from pipeline.loaders import load_daemon_config

    data = yaml.safe_load(EXAMPLE.read_text())
    path = tmp_path / "etc" / "rsu.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump(data))
    config = _resolve_relative_paths(load_daemon_config(path), path.parent)
    detector = config.camera("west-arm").detector
    assert detector is not None and detector.model == tmp_path / "etc" / "models" / "vehicles.onnx"
    assert config.camera("west-junction").detector is None


def test_a_cameras_intrinsics_may_be_its_calibration_file(tmp_path: Path) -> None:
    # An operator's ROS camera_info file beside rsu.yaml, named instead of the values written out.
    from pipeline.loaders import load_daemon_config

    data = yaml.safe_load(EXAMPLE.read_text())
    k = data["cameras"][0]["intrinsics"]
    info = ros_camera_info(CameraIntrinsics.model_validate(k))
    path = tmp_path / "etc" / "rsu.yaml"
    (tmp_path / "etc" / "cameras").mkdir(parents=True)
    (tmp_path / "etc" / "cameras" / "ost.yaml").write_text(yaml.safe_dump(info))
    inline = yaml.safe_dump(data)
    data["cameras"][0]["intrinsics"] = "cameras/ost.yaml"  # relative to rsu.yaml
    path.write_text(yaml.safe_dump(data))
    (tmp_path / "inline.yaml").write_text(inline)
    assert load_daemon_config(path) == load_daemon_config(tmp_path / "inline.yaml")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (None, "cameras.0.intrinsics: "),  # no such file
        ("image_width: 1920\n", "cameras.0.intrinsics: "),
    ],
)
def test_a_bad_intrinsics_file_exits_2_naming_the_camera_and_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str | None, expected: str
) -> None:
    camera_file = tmp_path / "ost.yaml"
    if text is not None:
        camera_file.write_text(text)
    data = _example(tmp_path)
    data["cameras"][0]["intrinsics"] = "ost.yaml"  # type: ignore[index]
    code, err = _run(tmp_path, data, capsys)
    assert code == 2
    assert expected + str(camera_file) in err, err
    assert not (tmp_path / "state").exists()
