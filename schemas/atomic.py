"""Durable atomic file writes: the one helper every rsucal file write goes through (results, camera state,
reports, the site config, the simulator's files).

A temporary file beside the target (one fixed name per target), its data fsynced, os.replace onto the
target, then a fsync of the directory: a crash or power loss at any point leaves either the old or the new
file whole, never a half-written one, and a completed write survives.

It lives in schemas/ (standard library only) because schemas is the one package that the pipeline, the
daemon and the simulator all import and that imports none of them: the simulator may import nothing of the
daemon or the pipeline (tests/project/test_architecture.py).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


def write_atomic(path: Path, data: bytes, root: Path | None = None) -> None:
    """Replace `path` by `data` so that a crash at any point leaves either the old or the new file whole.

    Missing directories up to `root` (or the first existing one) are made, each new one made durable by a
    fsync of its parent.
    """
    _make_dirs(path.parent, root)
    # One fixed temporary name per target: a crash leaves at most one stale file, overwritten next time.
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)  # the data is on disk before the name points at it
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # cleanup must not hide the error that brought us here
            tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)  # ... and the new name itself survives a power loss


def _make_dirs(directory: Path, root: Path | None) -> None:
    """mkdir -p, fsyncing each new directory's parent so the new entries are durable too."""
    missing: list[Path] = []
    current = directory
    while not current.exists():
        missing.append(current)
        if current == root or current.parent == current:
            break
        current = current.parent
    for new in reversed(missing):
        new.mkdir(parents=root is not None and new == root, exist_ok=True)
        fsync_dir(new.parent)


def fsync_dir(directory: Path) -> None:
    """Make the directory's entries (a new or renamed file) durable: a power cut could otherwise lose them."""
    fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_stale_tmp(directory: Path) -> list[Path]:
    stale = [p for p in directory.glob(".*.tmp") if p.is_file()]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale
