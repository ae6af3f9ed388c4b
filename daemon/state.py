"""The daemon's persistent state per camera: published result, every job's result, and its bookkeeping.

Layout under `state_dir`: cameras/{camera_id}/current.json (latest ACCEPTED result that was published),
cameras/{camera_id}/history/{created_at_ns:019d}-{result_id}.json (every finished job's result, accepted or
refused) and cameras/{camera_id}/camera_state.json (CameraState). Every write is atomic and durable: a
temporary file beside the target, fsync, os.replace, fsync of the directory. Reading is forgiving: a
damaged current.json is reported and replaced by the best history entry, never fatal.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from pydantic import Field, ValidationError

from pipeline.errors import InputError
from schemas.atomic import fsync_dir, remove_stale_tmp, write_atomic
from schemas.common import (
    IDENTIFIER,
    UNSAFE_IN_IDENTIFIER,
    StampNs,
    StrictModel,
    decode_json,
    describe_validation_error,
)
from schemas.results import CalibrationResult, JobSummary

log = logging.getLogger(__name__)

CURRENT_FILE = "current.json"
CAMERA_STATE_FILE = "camera_state.json"
HISTORY_DIR = "history"
_STAMP_DIGITS = 19  # history names start with created_at_ns:019d, so name order is time order


class CameraState(StrictModel):
    """What the daemon remembers about a camera across restarts, besides its results."""

    last_job: JobSummary | None = None
    verified_at_ns: StampNs | None = Field(default=None, description="last time a result was confirmed")
    used_until_ns: StampNs | None = Field(
        default=None, description="traversals up to this producer stamp were used by a job"
    )
    current_result_id: str | None = None
    last_reasons: list[str] = Field(default_factory=list)
    time_offset_ns: int | None = Field(
        default=None,
        description="the last accepted result's estimated time offset (CalibrationResult.time_offset_ns), "
        "the prior of the camera's next job",
    )
    time_offset_std_ns: float | None = Field(default=None, ge=0.0, allow_inf_nan=False)
    # Set when a re-verification showed the camera moved but its own fit was refused, so the current result
    # was withdrawn: drive-pasts that began before this producer stamp (those of the old pose) are never
    # pooled into the camera's next jobs (daemon.publication, "withdrawn").
    not_before_ns: StampNs | None = Field(
        default=None, description="no traversal that began before this stamp is used (the camera moved)"
    )
    withdrawn_result_id: str | None = Field(
        default=None,
        description="the result last withdrawn (the camera moved); a current.json still naming it, as a "
        "crash between saving this state and removing that file leaves it, is never current again",
    )


class StateStore:
    """Atomic persistence of results and camera state under one state directory (one daemon per directory).

    Thread-safe: writes are serialised by a lock (results arrive on the supervisor thread, state may be
    saved elsewhere).
    """

    def __init__(self, state_dir: Path) -> None:
        self.state_dir = Path(state_dir)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------------------------ paths

    def camera_dir(self, camera_id: str) -> Path:
        """cameras/{camera_id}; the id must be an Identifier, so it can never escape the state directory."""
        if not IDENTIFIER.match(camera_id) or camera_id in (".", ".."):
            raise ValueError(f"camera_id {camera_id!r} is not an identifier ([A-Za-z0-9_.-], 1-64 chars)")
        return self.state_dir / "cameras" / camera_id

    def current_path(self, camera_id: str) -> Path:
        return self.camera_dir(camera_id) / CURRENT_FILE

    def history_dir(self, camera_id: str) -> Path:
        return self.camera_dir(camera_id) / HISTORY_DIR

    def history_path(self, result: CalibrationResult) -> Path:
        """history/{created_at_ns:019d}-{result_id}.json (characters unsafe in a file name become '_')."""
        return self.history_dir(result.camera_id) / history_name(result, ".json")

    def history(self, camera_id: str) -> list[Path]:
        """History entries of a camera, oldest first."""
        directory = self.history_dir(camera_id)
        if not directory.is_dir():
            return []
        return sorted(p for p in directory.glob("*.json") if not p.name.startswith("."))

    # ------------------------------------------------------------------------------------------ results

    def save_result(self, result: CalibrationResult, current: bool) -> Path:
        """Add `result` to the history and, if `current`, make it current.json; returns the history file.

        Only accepted results may become current (ValueError otherwise). The history entry is written
        first: a crash in between leaves the previous current.json, never a current result missing from
        the history.
        """
        if current and not result.verdict.is_accepted:
            raise ValueError(
                f"result {result.result_id}: only accepted results become current "
                f"(verdict {result.verdict.status})"
            )
        data = (result.model_dump_json(indent=2) + "\n").encode("utf-8")
        path = self.history_path(result)
        with self._lock:
            write_atomic(path, data, self.state_dir)
            if current:
                write_atomic(self.current_path(result.camera_id), data, self.state_dir)
        return path

    def withdraw_current(self, camera_id: str) -> None:
        """Remove current.json (the camera moved and no new result replaces it); its history entry stays.
        Durable: the directory is synced, so a restart never finds the withdrawn result current again."""
        path = self.current_path(camera_id)
        with self._lock:
            try:
                path.unlink()
            except FileNotFoundError:
                return
            fsync_dir(path.parent)

    def load_current(self, camera_id: str) -> CalibrationResult | None:
        """The camera's current (published, accepted) result, or None when it has none.

        A truncated or otherwise invalid current.json is logged (naming the file) and replaced by the history
        entry that camera_state.json names as current, else by the newest accepted history entry.
        """
        path = self.current_path(camera_id)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as err:
            log.warning("%s: cannot read (%s); falling back to the history", path, err.strerror or err)
            return self._current_from_history(camera_id)
        checked = _decode_result(raw, camera_id)
        if isinstance(checked, CalibrationResult) and not checked.verdict.is_accepted:
            checked = f"verdict: {checked.verdict.status}; only accepted results are current"
        if isinstance(checked, CalibrationResult):
            return checked
        log.warning("%s: unusable (%s); falling back to the history", path, checked)
        return self._current_from_history(camera_id)

    def _current_from_history(self, camera_id: str) -> CalibrationResult | None:
        state = self.load_camera_state(camera_id)
        wanted = state.current_result_id if state is not None else None
        newest_accepted: CalibrationResult | None = None
        for entry in reversed(self.history(camera_id)):
            try:
                checked = _decode_result(entry.read_bytes(), camera_id)
            except OSError as err:
                log.warning("%s: cannot read (%s); skipped", entry, err.strerror or err)
                continue
            if not isinstance(checked, CalibrationResult):
                log.warning("%s: unusable (%s); skipped", entry, checked)
                continue
            if not checked.verdict.is_accepted:
                continue
            if wanted is None or checked.result_id == wanted:
                log.warning("camera %s: using %s as the current result", camera_id, entry)
                return checked
            if newest_accepted is None:
                newest_accepted = checked
        if newest_accepted is not None:
            log.warning(
                "camera %s: history holds no result %s; using the newest accepted, %s",
                camera_id,
                wanted,
                newest_accepted.result_id,
            )
        else:
            log.warning(
                "camera %s: no accepted result in the history; the camera has no current result", camera_id
            )
        return newest_accepted

    def prune_history(
        self, camera_id: str, keep: int = 1000, created_before_ns: int | None = None
    ) -> list[Path]:
        """Delete all but the newest `keep` history entries, and those created before `created_before_ns`,
        never the current result's; a job's report goes with its result. Returns the deleted paths.

        Also removes temporary files a crash left in the history directory.
        """
        if keep < 0:
            raise ValueError(f"keep = {keep} must not be negative")
        directory = self.history_dir(camera_id)
        if not directory.is_dir():
            return []
        state = self.load_camera_state(camera_id)
        protected = state.current_result_id if state is not None else None
        removed: list[Path] = []
        with self._lock:
            entries = self.history(camera_id)
            beyond = set(entries[: max(0, len(entries) - keep)])
            if created_before_ns is not None:
                beyond.update(e for e in entries if _created_ns_of(e) < created_before_ns)
            for entry in sorted(beyond):
                if protected is not None and _result_id_of(entry) == UNSAFE_IN_IDENTIFIER.sub("_", protected):
                    continue
                entry.unlink(missing_ok=True)
                removed.append(entry)
                report = entry.with_suffix(".html")  # the job's report goes with its result
                if report.exists():
                    report.unlink(missing_ok=True)
                    removed.append(report)
            removed.extend(remove_stale_tmp(directory))
            if removed:
                fsync_dir(directory)
        return removed

    # ------------------------------------------------------------------------------------------ camera state

    def save_camera_state(self, camera_id: str, state: CameraState) -> None:
        """camera_state.json, atomically."""
        data = (state.model_dump_json(indent=2) + "\n").encode("utf-8")
        with self._lock:
            write_atomic(self.camera_dir(camera_id) / CAMERA_STATE_FILE, data, self.state_dir)

    def load_camera_state(self, camera_id: str) -> CameraState | None:
        """The saved CameraState; None when never saved, or unreadable (logged, naming the file)."""
        path = self.camera_dir(camera_id) / CAMERA_STATE_FILE
        try:
            return decode_json(CameraState, path.read_bytes())
        except FileNotFoundError:
            return None
        except OSError as err:
            log.warning("%s: cannot read (%s); starting without it", path, err.strerror or err)
        except ValidationError as err:
            log.warning("%s: unusable (%s); starting without it", path, describe_validation_error(err))
        return None


# ---------------------------------------------------------------------------------------------- helpers


def _created_ns_of(entry: Path) -> int:
    """created_at_ns from a history entry's name (see history_name); an unparsable name counts as new."""
    stamp = entry.name[:_STAMP_DIGITS]
    return int(stamp) if stamp.isdigit() else 2**63


def history_name(result: CalibrationResult, suffix: str) -> str:
    """{created_at_ns:019d}-{result_id}{suffix}: a history entry (.json) or its job's report (.html)."""
    safe_id = UNSAFE_IN_IDENTIFIER.sub("_", result.result_id)
    return f"{result.created_at_ns:0{_STAMP_DIGITS}d}-{safe_id}{suffix}"


def _decode_result(raw: bytes, camera_id: str) -> CalibrationResult | str:
    """This camera's result in `raw`, or why it is not one (a string naming the field)."""
    try:
        result = decode_json(CalibrationResult, raw)
    except ValidationError as err:
        return describe_validation_error(err)
    if result.camera_id != camera_id:
        return f"camera_id: {result.camera_id!r} is not {camera_id!r}"
    return result


def _result_id_of(entry: Path) -> str:
    """The (file-name safe) result id of a history entry {created_at_ns:019d}-{result_id}.json."""
    return entry.name[_STAMP_DIGITS + 1 : -len(".json")]


def prepare_state_dir(state_dir: Path) -> Path:
    """Create `state_dir` (and its recordings/) if needed and prove it writable; InputError naming the field.

    Run before anything else at start-up: an unusable state directory is a configuration error (exit 2, so
    systemd's RestartPreventExitStatus=2 stops instead of restarting every few seconds).
    """
    state_dir = Path(state_dir)
    try:
        if state_dir.exists() and not state_dir.is_dir():
            raise InputError("storage.state_dir", f"{state_dir} exists and is not a directory")
        (state_dir / "recordings").mkdir(parents=True, exist_ok=True)
        probe = state_dir / f".write-probe-{os.getpid()}.tmp"
        with open(probe, "wb") as stream:
            stream.write(b"rsucal")
        probe.unlink()
    except OSError as err:
        raise InputError("storage.state_dir", f"{state_dir} is not usable: {err.strerror or err}") from err
    return state_dir
