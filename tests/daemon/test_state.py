"""daemon.state: results and camera state survive restarts, crashes mid-write and damaged files."""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from daemon.state import CameraState, StateStore
from schemas.common import CameraIntrinsics
from schemas.results import CalibrationResult, CameraPosition, JobSummary, ReferenceFrame, Verdict

T0 = 1_717_200_000_000_000_000
CAMERA = "west-junction"
REPO = Path(__file__).resolve().parents[2]


def _result(n: int, accepted: bool = True, camera_id: str = CAMERA) -> CalibrationResult:
    """A small valid result; n orders them in time and tells them apart."""
    return CalibrationResult(
        rsu_id="rsu-1",
        camera_id=camera_id,
        result_id=f"rsu-1-{camera_id}-{n}",
        created_at_ns=T0 + n * 1_000_000_000,
        frame=ReferenceFrame(crs="EPSG:32632", origin=(572000.0, 5361000.0, 527.0)),
        R=((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)) if accepted else None,
        t=(0.0, 9.0, float(n)) if accepted else None,
        camera_position=CameraPosition(utm=(572000.0 + n, 5361000.0, 536.0), lat=48.4, lon=9.97, alt=536.0)
        if accepted
        else None,
        intrinsics=CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0),
        verdict=Verdict(status="accepted")
        if accepted
        else Verdict(status="refused", reasons=[f"reason {n}"]),
    )


def test_results_and_camera_state_round_trip(tmp_path: Path) -> None:
    store = StateStore(tmp_path / "state")  # created on first write
    assert store.load_current(CAMERA) is None
    assert store.load_camera_state(CAMERA) is None

    first = _result(1)
    history_file = store.save_result(first, current=True)
    assert (
        history_file
        == tmp_path / "state/cameras" / CAMERA / "history" / f"{T0 + 10**9:019d}-{first.result_id}.json"
    )
    assert store.load_current(CAMERA) == first

    refused = _result(2, accepted=False)
    store.save_result(refused, current=False)
    assert store.load_current(CAMERA) == first  # a refusal never becomes current
    assert [p.name for p in store.history(CAMERA)] == [
        f"{T0 + 10**9:019d}-{first.result_id}.json",
        f"{T0 + 2 * 10**9:019d}-{refused.result_id}.json",
    ]
    assert CalibrationResult.model_validate_json(store.history(CAMERA)[1].read_bytes()) == refused

    state = CameraState(
        last_job=JobSummary(
            job_id="j1", started_ns=T0, finished_ns=T0 + 5, duration_s=3.5, verdict=refused.verdict
        ),
        verified_at_ns=T0 + 7,
        used_until_ns=T0 + 9,
        current_result_id=first.result_id,
        last_reasons=["reason 2"],
    )
    store.save_camera_state(CAMERA, state)
    assert StateStore(tmp_path / "state").load_camera_state(CAMERA) == state  # a fresh store: a restart


def test_only_accepted_results_become_current(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    with pytest.raises(ValueError, match="only accepted results become current"):
        store.save_result(_result(1, accepted=False), current=True)
    assert store.load_current(CAMERA) is None and store.history(CAMERA) == []


@pytest.mark.parametrize("camera_id", ["../escape", "a/b", "..", ""])
def test_camera_ids_cannot_leave_the_state_dir(tmp_path: Path, camera_id: str) -> None:
    with pytest.raises(ValueError, match="camera_id"):
        StateStore(tmp_path).load_current(camera_id)


def test_writes_fsync_the_file_and_the_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[str] = []
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    store = StateStore(tmp_path)
    store.save_result(_result(1), current=False)  # creates the directories
    monkeypatch.setattr(os, "fsync", recording_fsync)
    store.save_result(_result(2), current=False)
    assert synced == ["file", "dir"]  # data first, then the rename


def test_crash_between_tmp_write_and_rename_keeps_the_old_file(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    old = _result(1)
    store.save_result(old, current=True)
    current = store.current_path(CAMERA)
    before = current.read_bytes()
    # A real crash: a process that dies (no cleanup, no exception handling) right where os.replace would run.
    new = _result(2)
    script = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from daemon.state import StateStore\n"
        "from schemas.results import CalibrationResult\n"
        "result = CalibrationResult.model_validate_json(sys.stdin.read())\n"
        "store = StateStore(Path(sys.argv[1]))\n"
        "real_replace = os.replace\n"
        # The history entry is renamed first and goes through; the process dies at current.json's rename.
        "def crash_at_current(src, dst):\n"
        "    if str(dst).endswith('current.json'):\n"
        "        os._exit(9)\n"
        "    real_replace(src, dst)\n"
        "os.replace = crash_at_current\n"
        "store.save_result(result, current=True)\n"
    )
    crashed = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path)],
        input=new.model_dump_json(),
        text=True,
        cwd=REPO,
        capture_output=True,
        check=False,
        timeout=60,
    )
    assert crashed.returncode == 9, crashed.stderr
    # The old current.json is untouched; the new one was fully written (and fsynced) beside it.
    assert current.read_bytes() == before
    tmp = current.with_name(".current.json.tmp")
    assert CalibrationResult.model_validate_json(tmp.read_bytes()) == new
    assert StateStore(tmp_path).load_current(CAMERA) == old
    # The history entry made before the crash is whole, and the stale tmp does not hinder the next write.
    assert [CalibrationResult.model_validate_json(p.read_bytes()) for p in store.history(CAMERA)] == [
        old,
        new,
    ]
    store.save_result(new, current=True)
    assert store.load_current(CAMERA) == new and not tmp.exists()


def test_failed_replace_raises_and_leaves_no_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = StateStore(tmp_path)
    store.save_result(_result(1), current=True)

    def full_disk(src: object, dst: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OSError, match="No space"):
        store.save_result(_result(2), current=True)
    monkeypatch.undo()
    assert store.load_current(CAMERA) == _result(1)
    assert list(store.camera_dir(CAMERA).rglob(".*.tmp")) == []


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda raw: raw[: len(raw) // 2], id="truncated"),
        pytest.param(lambda raw: b"", id="empty"),
        pytest.param(lambda raw: raw.replace(b'"accepted"', b'"maybe"'), id="invalid-field"),
        pytest.param(lambda raw: _result(9, camera_id="other").model_dump_json().encode(), id="other-camera"),
    ],
)
def test_damaged_current_falls_back_to_the_newest_accepted_history_entry(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: object
) -> None:
    store = StateStore(tmp_path)
    store.save_result(_result(1), current=True)
    store.save_result(_result(2), current=True)
    store.save_result(_result(3, accepted=False), current=False)  # newest, but refused
    current = store.current_path(CAMERA)
    assert callable(damage)
    current.write_bytes(damage(current.read_bytes()))
    with caplog.at_level(logging.WARNING, logger="daemon.state"):
        assert store.load_current(CAMERA) == _result(2)
    assert str(current) in caplog.text


def test_fallback_prefers_the_result_camera_state_names_current(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Re-verifications are accepted but not made current: the history's newest accepted entry is not always
    # the published one, camera_state.json knows which is.
    store = StateStore(tmp_path)
    store.save_result(_result(1), current=True)
    store.save_result(_result(2), current=False)
    store.save_camera_state(CAMERA, CameraState(current_result_id=_result(1).result_id))
    store.current_path(CAMERA).write_bytes(b'{"schema_version": "1.0", "rsu_')
    assert store.load_current(CAMERA) == _result(1)
    # Without a readable camera state: the newest accepted entry; a damaged entry is skipped and named.
    (store.camera_dir(CAMERA) / "camera_state.json").write_text("{")
    newest = store.history(CAMERA)[-1]
    newest.write_text("not json")
    with caplog.at_level(logging.WARNING, logger="daemon.state"):
        assert store.load_current(CAMERA) == _result(1)
    assert str(newest) in caplog.text and "camera_state.json" in caplog.text


def test_no_accepted_result_anywhere_gives_none(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save_result(_result(1, accepted=False), current=False)
    store.current_path(CAMERA).write_text("garbage")
    assert store.load_current(CAMERA) is None


def test_prune_history_keeps_the_newest_and_the_current(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    for n in range(1, 8):
        store.save_result(_result(n, accepted=n == 2), current=n == 2)
    store.save_camera_state(CAMERA, CameraState(current_result_id=_result(2).result_id))
    stale = store.history_dir(CAMERA) / ".leftover.json.tmp"
    stale.write_text("half")
    removed = store.prune_history(CAMERA, keep=3)
    kept = [CalibrationResult.model_validate_json(p.read_bytes()).result_id for p in store.history(CAMERA)]
    assert kept == [_result(n).result_id for n in (2, 5, 6, 7)]
    assert len(removed) == 4 and stale in removed and not stale.exists()
    assert store.prune_history(CAMERA, keep=3) == []


def test_prune_history_by_age_keeps_the_current_and_takes_reports_along(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    for n in range(1, 6):
        path = store.save_result(_result(n, accepted=n == 1), current=n == 1)
        path.with_suffix(".html").write_text("report")
    store.save_camera_state(CAMERA, CameraState(current_result_id=_result(1).result_id))
    # Entries created before result 4 are old; 1 is current and stays.
    removed = store.prune_history(CAMERA, keep=100, created_before_ns=_result(4).created_at_ns)
    kept = [CalibrationResult.model_validate_json(p.read_bytes()).result_id for p in store.history(CAMERA)]
    assert kept == [_result(n).result_id for n in (1, 4, 5)]
    assert sorted(p.suffix for p in removed) == [".html", ".html", ".json", ".json"]
    assert sorted(p.name for p in store.history_dir(CAMERA).glob("*.html")) == sorted(
        p.with_suffix(".html").name for p in store.history(CAMERA)
    )
