"""README and docs are reference: links resolve, figures come from results JSON, history lives in
docs/experiments/ (scripts/docs_check.py, scripts/docs_generate.py), and the checkers catch what
they are meant to catch."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


check = _load("docs_check")
generate = _load("docs_generate")


def test_every_relative_link_and_anchor_resolves() -> None:
    assert check.link_problems() == []


def test_no_dates_hashes_or_hand_written_results_outside_experiments() -> None:
    assert check.reference_problems() == []
    assert check.code_problems() == []


def test_generated_tables_and_the_experiments_index_match_their_sources() -> None:
    assert generate.stale() == []


def test_every_results_json_names_its_command_commit_machine_and_time() -> None:
    sys_path = str(REPO / "benchmarks")
    import sys

    sys.path.insert(0, sys_path)
    try:
        from results_json import read_results
    finally:
        sys.path.remove(sys_path)
    files = sorted((REPO / "benchmarks" / "results").glob("*.json"))
    assert files, "README's tables need benchmarks/results/*.json"
    for f in files:
        doc = read_results(f)
        assert doc["command"] and re.fullmatch(r"[0-9a-f]{40}", doc["commit"]), f
        assert doc["machine"]["cpu"] and doc["machine"]["cores"] >= 1 and doc["time"][:2] == "20", f


def test_experiment_files_are_named_by_date_and_topic_and_indexed() -> None:
    files = [p for p in (REPO / "docs" / "experiments").glob("*.md") if p.name != "README.md"]
    assert files
    index = (REPO / "docs" / "experiments" / "README.md").read_text()
    for p in files:
        assert generate.EXPERIMENT_NAME.match(p.name), p.name
        assert f"]({p.name})" in index, p.name
        assert p.read_text().startswith("# "), p.name


def test_readme_is_short_and_puts_the_commands_and_results_first() -> None:
    text = (REPO / "README.md").read_text()
    assert len(text.encode()) < 12_000
    lines = text.splitlines()
    first_screen = "\n".join(lines[:50])
    assert "make demo" in first_screen and "make test" in first_screen
    first_three = "\n".join(lines[:150])
    assert "<!-- generated: benchmarks/results/demo.json#results -->" in first_three
    assert "benchgen score" in first_three
    for ref in ("LICENSE", "CITATION.cff"):
        assert ref in text


def test_licence_and_citation() -> None:
    licence = (REPO / "LICENSE").read_text()
    assert "MIT License" in licence and "pyproject.toml" not in licence
    assert 'license = "MIT"' in (REPO / "pyproject.toml").read_text() or "MIT" in (REPO / "pyproject.toml").read_text()
    cff = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert cff["cff-version"].startswith("1.2") and cff["title"] and cff["authors"] and cff["message"]
    paper = cff["preferred-citation"]
    assert paper["type"] == "conference-paper" and paper["title"].startswith("OSN: Infinite Representations")


# ---- the checkers fail when the rule is broken -------------------------------------------------


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    """A small repository: README, a reference doc, an experiment, a results JSON, the scripts."""
    root = tmp_path / "repo"
    (root / "docs" / "experiments").mkdir(parents=True)
    (root / "benchmarks" / "results").mkdir(parents=True)
    shutil.copy(REPO / "benchmarks" / "results_json.py", root / "benchmarks")
    doc = {"benchmark": "t", "command": "make demo", "commit": "0" * 40, "dirty": False,
           "machine": {"cpu": "CPU", "cores": 2, "platform": "p", "python": "3.11"}, "time": "2026-01-02T00:00:00+00:00",
           "tables": {"results": {"columns": ["method", "PSNR"], "rows": [["best of 10", "23.00 ± 0.50"]]}}, "data": {}}
    (root / "benchmarks" / "results" / "t.json").write_text(json.dumps(doc))
    (root / "docs" / "ref.md").write_text("# Reference\n\n## The part\n\ntext\n")
    (root / "docs" / "experiments" / "2026-01-02-a-test.md").write_text(
        "# A test\n\nDate: 2026-01-02. Commit 1a2b3c4d.\n\n| run | PSNR |\n|---|---|\n| a | 23.0 ± 0.1 |\n")
    block = "<!-- generated: benchmarks/results/t.json#results -->\n<!-- end generated -->"
    (root / "README.md").write_text(f"# T\n\n[ref](docs/ref.md#the-part)\n\n{block}\n")
    (root / "docs" / "experiments" / "README.md").write_text(generate.experiments_index(root))
    text = generate.regenerate((root / "README.md").read_text(), root)
    (root / "README.md").write_text(text)
    return root


def test_a_clean_tree_passes(tree: Path) -> None:
    assert check.link_problems(tree) == [] and check.reference_problems(tree) == [] and generate.stale(tree) == []
    assert "23.00 ± 0.50" in (tree / "README.md").read_text()  # the figure came from the JSON


def test_broken_links_and_anchors_are_found(tree: Path) -> None:
    ref = tree / "docs" / "ref.md"
    ref.write_text(ref.read_text() + "\n[a](missing.md) [b](#nowhere) [c](experiments/2026-01-02-a-test.md#a-test)\n"
                   "`[not a link](nowhere.md)`\n")
    found = check.link_problems(tree)
    assert len(found) == 2 and "missing.md" in found[0] and "#nowhere" in found[1]
    assert check.slug("The `w_edge` option: on/off (auto)") == "the-w_edge-option-onoff-auto"


def test_history_in_reference_docs_is_found(tree: Path) -> None:
    ref = tree / "docs" / "ref.md"
    cite = "Measured in [a-test](experiments/2026-01-02-a-test.md)."
    ref.write_text(ref.read_text() + f"\n{cite}\n")
    assert check.reference_problems(tree) == []  # citing an experiment by its file name is not history
    dated = tree / "docs" / "dated.md"  # the same file name shown as the link's text is a date in the prose
    dated.write_text("# D\n\n[experiments/2026-01-02-a-test.md](experiments/2026-01-02-a-test.md)\n")
    assert [f for f in check.reference_problems(tree) if "dated.md" in f] == [
        "docs/dated.md:3: date 2026-01-02 (history goes in docs/experiments/)"]
    dated.unlink()
    ref.write_text(ref.read_text() + "\nMeasured on 2026-11-27 at 6c94564.\n\n| a | 23.1 ± 0.2 |\n")
    found = check.reference_problems(tree)
    assert any("date 2026-11-27" in f for f in found) and any("hash 6c94564" in f for f in found)
    assert any("results table" in f for f in found)
    assert not any(f.startswith("docs/experiments") for f in found)  # history is at home there


def test_dates_and_hashes_in_code_are_found(tree: Path) -> None:
    (tree / "osn").mkdir()
    (tree / "osn" / "m.py").write_text('"""Default since 2026-11-25 (commit abc1234)."""\nX = 0xdeadbeef\n')
    found = check.code_problems(tree)
    assert len(found) == 2, found


def test_a_figure_edited_by_hand_or_a_new_json_makes_the_table_stale(tree: Path) -> None:
    readme = tree / "README.md"
    readme.write_text(readme.read_text().replace("23.00", "24.00"))
    assert generate.stale(tree) == ["README.md"]
    readme.write_text(generate.regenerate(readme.read_text(), tree))
    assert generate.stale(tree) == []
    (tree / "docs" / "experiments" / "2026-02-03-another.md").write_text("# Another\n")
    assert generate.stale(tree) == ["docs/experiments/README.md"]
