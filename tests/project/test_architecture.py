"""Imports point one way, daemon -> pipeline -> schemas and sim -> schemas (docs/design.md): checked on the
real import graph."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUR_PACKAGES = {"schemas", "pipeline", "sim", "daemon", "tests", "bench"}
BUS_AND_RECORDING = ("zenoh", "mcap")


def _module_names(package: str) -> list[str]:
    return sorted(f"{package}.{p.stem}" for p in (ROOT / package).glob("*.py") if p.stem != "__init__")


def _imported_top_levels(path: Path) -> set[str]:
    """Top-level names of every absolute import in a file, including imports inside functions."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def _modules_loaded_by_importing(modules: list[str]) -> set[str]:
    """sys.modules of a fresh interpreter after importing `modules` (our tree first on its path)."""
    script = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    loaded = set(json.loads(done.stdout.strip().splitlines()[-1]))
    assert set(modules) <= loaded
    return loaded


def test_pipeline_never_loads_zenoh_or_mcap() -> None:
    loaded = _modules_loaded_by_importing(["pipeline", *_module_names("pipeline")])
    for forbidden in BUS_AND_RECORDING:
        offenders = sorted(m for m in loaded if m == forbidden or m.startswith(forbidden + "."))
        assert not offenders, f"importing pipeline loaded {offenders}; only daemon/ may use {forbidden}"
    assert not [m for m in loaded if m == "daemon" or m.startswith("daemon.")], "pipeline imports daemon"
    assert not [m for m in loaded if m == "sim" or m.startswith("sim.")], "pipeline imports the simulator"


def test_the_simulated_world_loads_no_pipeline_module() -> None:
    """The world must share no model with the method judged in it: importing every sim module loads
    neither pipeline/ nor daemon/ (nor the bus)."""
    loaded = _modules_loaded_by_importing(["sim", *_module_names("sim")])
    ours = sorted(m for m in loaded if m.split(".")[0] in {"pipeline", "daemon", "zenoh", "mcap"})
    assert not ours, f"importing sim loaded {ours}"


def test_sim_imports_only_schemas_of_ours() -> None:
    for path in sorted((ROOT / "sim").glob("*.py")):
        bad = _imported_top_levels(path) & (OUR_PACKAGES - {"schemas", "sim"})
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}; sim/ may import only schemas/"


def test_schemas_import_nothing_of_ours() -> None:
    for path in sorted((ROOT / "schemas").glob("*.py")):
        ours = _imported_top_levels(path) & (OUR_PACKAGES - {"schemas"})
        assert not ours, f"{path.relative_to(ROOT)} imports {sorted(ours)}; schemas/ must stand alone"


def test_pipeline_imports_neither_daemon_nor_the_bus() -> None:
    for path in sorted((ROOT / "pipeline").glob("*.py")):
        bad = _imported_top_levels(path) & {"daemon", "sim", "tests", "bench", *BUS_AND_RECORDING}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_no_test_directory_shadows_a_package_in_spawned_processes() -> None:
    """Job workers are spawned: a fresh interpreter imports `daemon` from sys.path. pytest (prepend mode)
    puts each test file's directory on sys.path; were `tests/` itself among them, tests/daemon (no
    __init__.py) would be found as a namespace package `daemon` before the installed one. So no test file
    lives directly in tests/."""
    assert not sorted((ROOT / "tests").glob("test_*.py"))


def test_test_modules_have_unique_names() -> None:
    """pytest imports test files by their base name (rootdir mode, no __init__.py): two test_x.py (or
    helper modules) in different folders collide and stop the whole run at collection. conftest.py files are
    pytest's own business."""
    names = [path.name for path in (ROOT / "tests").rglob("*.py") if path.name != "conftest.py"]
    assert sorted({n for n in names if names.count(n) > 1}) == []
