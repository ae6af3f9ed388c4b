"""`rsucal demo` on a run that cannot calibrate: it says why (traversals counted vs needed) and stops as
soon as nothing more can happen, instead of waiting for its time-out."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import free_port

from daemon.demo import run_demo


@pytest.mark.slow
def test_single_traversal_is_explained_and_ends_before_the_timeout(tmp_path: Path) -> None:
    lines: list[str] = []
    # A time-out far beyond the replay (67 s of data at 40x is under 2 s): reaching it would mean the
    # demo waited for a job that can never start.
    code = run_demo(
        preset="single-traversal",
        rate=40.0,
        timeout_s=600.0,
        state_dir=tmp_path / "state",
        port=free_port(),
        out=lines.append,
    )
    text = "\n".join(lines)
    assert code == 1
    assert "nothing more can happen" in text
    assert "north: 1 of 3 traversals counted (trigger.min_traversals)" in text
    assert "gave up" not in text
    assert "FAIL (no job finished; 1 of 3 traversals)" in text


@pytest.mark.slow
def test_a_finished_job_ends_the_demo_whatever_its_verdict(tmp_path: Path) -> None:
    # In the real world a job may refuse; the camera's state is then `collecting` again (its window still
    # holds the drive-pasts). The demo must end once every camera's job finished, not wait for --timeout.
    lines: list[str] = []
    code = run_demo(
        preset="sil-north",
        seed=0,
        rate=40.0,
        timeout_s=180.0,
        state_dir=tmp_path / "state",
        port=free_port(),
        out=lines.append,
    )
    text = "\n".join(lines)
    assert "gave up" not in text
    row = next(line for line in lines if line.startswith("north "))
    assert "REFUSED (" in row or "PASS" in row or "FAIL (wrong calibration published)" in row
    # Right or refused keeps the promise (exit 0); a wrong calibration published does not (exit 1).
    assert code == (1 if "FAIL" in row else 0)
