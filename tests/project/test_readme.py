"""The README's first two commands are what a newcomer runs; CI must run the second one verbatim."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = text.split("```bash", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.strip().splitlines() if line.strip()]


def test_readme_opens_with_main_job_then_tests() -> None:
    main_job, tests = _readme_commands()[:2]
    assert main_job.endswith("rsucal demo")
    assert "pytest" in tests


def test_ci_runs_the_readme_test_command_verbatim() -> None:
    test_command = _readme_commands()[1]
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_command in ci, "the README's test command must appear verbatim in .ci/run"


def test_ci_runs_the_readme_main_job_verbatim() -> None:
    """The main job's `pip install .` is the Dockerfile's install step: CI running it proves the image."""
    main_job = _readme_commands()[0]
    ci = (ROOT / ".ci" / "run").read_text()
    assert main_job in ci, "the README's first command must appear verbatim in .ci/run"


def test_ci_type_checks_every_package_strictly() -> None:
    """mypy --strict (pyproject's [tool.mypy]) covers the daemon as well as the pipeline and schemas."""
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    mypy_lines = [line.split() for line in ci_lines if line.startswith("mypy ")]
    assert len(mypy_lines) == 1
    assert set(mypy_lines[0][1:]) >= {"pipeline", "schemas", "daemon"}
    assert "strict = true" in (ROOT / "pyproject.toml").read_text()
