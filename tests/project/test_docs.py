"""The project's documentation stands alone: every relative link resolves inside the checkout, nothing
points at files a clone does not have (../shared/), and the README's file names match what the simulator
writes."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [
    ROOT / "README.md",
    ROOT / "deploy" / "README.md",
    ROOT / "docs" / "design.md",
    ROOT / "docs" / "method.md",
]
LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve_inside_the_project(doc: Path) -> None:
    text = doc.read_text()
    assert "../shared" not in text and "paper.tex" not in text and "DESIGN.md" not in text
    for target in LINK.findall(text):
        if target.startswith(("http://", "https://", "#")):
            continue
        path = (doc.parent / target.split("#", 1)[0]).resolve()
        assert path.is_relative_to(ROOT), f"{doc.name}: {target} leaves the project"
        assert path.exists(), f"{doc.name}: {target} does not exist"


def test_readme_and_deploy_guide_link_the_design_and_method() -> None:
    for doc in DOCS[:2]:
        text = doc.read_text()
        assert "docs/design.md" in text and "docs/method.md" in text, doc


def test_the_paper_is_cited_by_title_and_link() -> None:
    for doc in (ROOT / "README.md", ROOT / "docs" / "method.md", ROOT / "docs" / "design.md"):
        text = " ".join(doc.read_text().split())
        assert "Automated Static Camera Calibration with Intelligent Vehicles" in text, doc
        assert "https://github.com/Tuxacker/infrastructure_calibration_toolbox" in text, doc


def test_no_source_file_refers_to_the_unshipped_design_file() -> None:
    offenders = [
        str(path.relative_to(ROOT))
        for folder in ("schemas", "pipeline", "sim", "daemon", "bench", "deploy", "docs", "tests")
        for path in (ROOT / folder).rglob("*")
        if path.is_file()
        and path.suffix in (".py", ".md", ".yaml", ".json5", ".json")
        and path != Path(__file__).resolve()
        and (
            "DESIGN.md" in path.read_text(errors="replace")
            or "../shared/" in path.read_text(errors="replace")
        )
    ]
    assert offenders == []


def test_readme_names_the_per_camera_files_of_multi_camera_presets(tmp_path: Path) -> None:
    """The README's list of `rsucal simulate` outputs matches what write_simulation_files writes."""
    from sim.files import write_simulation_files
    from sim.simulate import simulate

    readme = (ROOT / "README.md").read_text()
    sim = simulate("sil-west", seed=0)  # two cameras
    written = {path.name for path in write_simulation_files(sim, tmp_path)}
    camera = sim.cameras[0].camera_id
    assert f"camera_{camera}.yaml" in written and f"detections_{camera}.yaml" in written
    for pattern in ("detections_<camera>.yaml", "camera_<camera>.yaml", "ground_truth_<camera>.json"):
        assert pattern in readme
        assert pattern.replace("<camera>", camera) in written
    for single in ("poses.yaml", "vehicle.yaml"):
        assert single in readme and single in written
