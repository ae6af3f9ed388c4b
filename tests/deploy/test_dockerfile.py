"""The Dockerfile and .dockerignore, checked without a Docker engine (there is none on CI's machine).

What is checked: the two stages and their base, that the builder installs with the README's own install
step (which CI runs, so the step is proven there), that the runtime stage installs nothing itself, the
runtime contract (non-root user, state volume, config path, health check, entrypoint; the last two parse
with the real `rsucal` argument parser) and that the build context holds what COPY needs and nothing else.
What is not: that `docker build` succeeds and the container starts; deploy/README.md says how to check that.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

from daemon.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
RUNTIME_VENV = "/opt/rsucal"


@dataclass(frozen=True)
class Instruction:
    keyword: str
    args: str


def _stages() -> list[list[Instruction]]:
    """The Dockerfile's instructions (continuation lines joined, comments dropped), one list per stage."""
    text = (ROOT / "Dockerfile").read_text()
    lines: list[str] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1].strip() + " "
            continue
        lines.append(pending + line)
        pending = ""
    assert not pending, "Dockerfile ends inside a continued line"
    stages: list[list[Instruction]] = []
    for line in lines:
        keyword, _, args = line.partition(" ")
        instruction = Instruction(keyword.upper(), args.strip())
        if instruction.keyword == "FROM":
            stages.append([])
        assert stages, f"{instruction.keyword} before the first FROM"
        stages[-1].append(instruction)
    return stages


def _args(stage: list[Instruction], keyword: str) -> list[str]:
    return [instruction.args for instruction in stage if instruction.keyword == keyword]


def _readme_commands() -> list[str]:
    block = (ROOT / "README.md").read_text().split("```bash", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.strip().splitlines() if line.strip()]


def test_two_stages_on_python_slim() -> None:
    builder, runtime = _stages()
    assert builder[0].args == "python:3.11-slim AS builder"
    assert runtime[0].args == "python:3.11-slim AS runtime"


def test_builder_installs_with_the_readme_install_step() -> None:
    """The README's first command installs rsucal; the image must do exactly that (in its own venv)."""
    readme_steps = [step.strip() for step in _readme_commands()[0].split("&&")]
    install = readme_steps[: next(i for i, step in enumerate(readme_steps) if step.startswith("pip ")) + 1]
    assert install[-1] == "pip install .", readme_steps
    expected = [step.replace(".venv", RUNTIME_VENV) for step in install]
    builder = _stages()[0]
    pip_runs = [run for run in _args(builder, "RUN") if re.search(r"\bpip install\b", run)]
    assert [[step.strip() for step in run.split("&&")] for run in pip_runs] == [expected]


def test_builder_copies_every_package_of_the_project() -> None:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [name.rstrip("*") for name in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]]
    copied = {source for args in _args(_stages()[0], "COPY") for source in shlex.split(args)[:-1]}
    assert set(packages) <= copied
    assert {"pyproject.toml", "README.md"} <= copied  # the build needs both (readme = "README.md")


def test_runtime_installs_nothing_of_its_own() -> None:
    runtime = _stages()[1]
    for run in _args(runtime, "RUN"):
        assert not re.search(r"\b(pip|apt-get|apt|gcc|make)\b", run), run
    copies = _args(runtime, "COPY")
    assert f"--from=builder {RUNTIME_VENV} {RUNTIME_VENV}" in copies
    assert all("[test]" not in args for stage in _stages() for args in _args(stage, "RUN"))


def test_runtime_contract() -> None:
    runtime = _stages()[1]
    (user,) = _args(runtime, "USER")
    assert user.split(":")[0] not in {"root", "0"}
    assert json.loads(_args(runtime, "VOLUME")[0]) == ["/var/lib/rsucal"]
    (entrypoint,) = _args(runtime, "ENTRYPOINT")
    assert json.loads(entrypoint) == ["rsucal", "daemon", "--config", "/etc/rsucal/rsu.yaml"]
    (healthcheck,) = _args(runtime, "HEALTHCHECK")
    options, command = healthcheck.split(" CMD ", 1)
    assert json.loads(command) == ["rsucal", "status", "--connect", "tcp/127.0.0.1:7447", "--timeout", "3"]
    assert "--start-period=" in options
    assert _args(runtime, "STOPSIGNAL") == ["SIGTERM"]
    # The state volume belongs to the runtime user (a named volume inherits this ownership).
    (setup,) = [run for run in _args(runtime, "RUN") if "useradd" in run]
    assert re.search(r"--uid (\d+)", setup) and not re.search(r"--uid 0\b", setup)
    assert "-o rsucal -g rsucal" in setup and "/var/lib/rsucal" in setup


@pytest.mark.parametrize("which", ["ENTRYPOINT", "HEALTHCHECK"])
def test_commands_parse_with_the_real_cli(which: str) -> None:
    runtime = _stages()[1]
    (args,) = _args(runtime, which)
    argv = json.loads(args.split(" CMD ", 1)[-1])
    assert argv[0] == "rsucal"
    build_parser().parse_args(argv[1:])  # argparse exits (SystemExit) on an unknown subcommand or option


# ---------------------------------------------------------------------------------------------- context


def _dockerignore_rules() -> list[tuple[bool, re.Pattern[str]]]:
    """(is_exception, regex) per line, in order; Docker's rules: last match wins, a match on a directory
    covers everything below it, `**` spans directories, `*` and `?` stay within one."""
    rules = []
    for raw in (ROOT / ".dockerignore").read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        exception = line.startswith("!")
        pattern = line.lstrip("!").strip("/")
        regex = ""
        i = 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                regex, i = regex + "(?:.*/)?", i + 3
            elif pattern.startswith("**", i):
                regex, i = regex + ".*", i + 2
            elif pattern[i] == "*":
                regex, i = regex + "[^/]*", i + 1
            elif pattern[i] == "?":
                regex, i = regex + "[^/]", i + 1
            elif pattern[i] == "[":
                end = pattern.index("]", i)
                regex, i = regex + pattern[i : end + 1], end + 1
            else:
                regex, i = regex + re.escape(pattern[i]), i + 1
        rules.append((exception, re.compile(regex)))
    return rules


def _in_context(path: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    parts = path.split("/")
    candidates = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    included = True
    for exception, regex in rules:
        if any(regex.fullmatch(candidate) for candidate in candidates):
            included = exception
    return included


def _project_files() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    return [path for path in listed if (ROOT / path).is_file()]


def test_build_context_holds_what_copy_needs_and_nothing_else() -> None:
    rules = _dockerignore_rules()
    files = _project_files()
    context = {path for path in files if _in_context(path, rules)}
    for stage in _stages():
        for args in _args(stage, "COPY"):
            if args.startswith("--from="):
                continue
            for source in shlex.split(args)[:-1]:
                wanted = [
                    path for path in files if path == source or path.startswith(source.rstrip("/") + "/")
                ]
                assert wanted, f"COPY {source}: nothing in the project"
                missing = [path for path in wanted if path not in context and not path.endswith(".pyc")]
                assert not missing, f"COPY {source}: excluded by .dockerignore: {missing[:5]}"
    package_files = [path for path in files if path.split("/")[0] in {"schemas", "pipeline", "sim", "daemon"}]
    assert package_files and all(path in context for path in package_files if "__pycache__" not in path)
    for outside in ("tests/", "bench/", ".ci/", ".venv/", "deploy/make-test-certs.sh", "Dockerfile"):
        assert not any(path.startswith(outside) or path == outside for path in context), outside
    assert not any(path.endswith(".key") for path in context)
