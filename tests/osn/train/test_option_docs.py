"""Every training option says what it is: a docstring under its declaration that begins with its
category (the paper's, this project's addition, or infrastructure), and docs/training.md's Options
table is generated from those docstrings (scripts/docs_generate.py)."""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import re
from pathlib import Path

import pytest

from osn.model.fields import FieldConfig
from osn.train import TrainConfig

REPO = Path(__file__).resolve().parents[3]


def _load_generate():
    spec = importlib.util.spec_from_file_location("docs_generate", REPO / "scripts" / "docs_generate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


generate = _load_generate()

CLASSES = (("osn/train/config.py", TrainConfig, ""), ("osn/model/fields.py", FieldConfig, "field."))


def _options() -> dict[str, object]:
    """Every option as a config writes it (``field.`` for FieldConfig's) -> its parsed ``Option``."""
    return dict(generate.all_options(REPO))


def _category(doc: str) -> re.Match:
    m = generate.CATEGORY.match(doc.strip())
    assert m is not None, doc
    return m


def test_the_parsed_options_are_the_dataclass_fields_in_order() -> None:
    for rel, cls, _ in CLASSES:
        parsed = [o.name for o in generate.class_options((REPO / rel).read_text(), cls.__name__)]
        assert parsed == [f.name for f in dataclasses.fields(cls)], rel


def test_every_option_has_a_docstring_that_begins_with_its_category_and_names_its_neutral_value() -> None:
    for rel, cls, _ in CLASSES:
        options = generate.class_options((REPO / rel).read_text(), cls.__name__)
        assert generate.option_problems(options, rel, REPO / "docs" / "experiments") == []
        for o in options:
            m = _category(o.doc)
            assert (m["kind"] in ("paper", "addition")) != bool(m["infra"]), o.name
            assert "Neutral:" in o.doc, f"{o.name}: no neutral value"


def test_paper_options_cite_the_paper_and_additions_cite_experiments_that_exist() -> None:
    experiments = REPO / "docs" / "experiments"
    for name, o in _options().items():
        m = _category(o.doc)
        if m["kind"] == "paper":
            assert generate.PAPER_CITE.search(m["cite"]), name
        elif m["kind"] == "addition" and m["cite"].strip() != generate.NOT_MEASURED:
            cites = [c.strip() for c in m["cite"].split(",")]
            assert cites, name
            for c in cites:
                e = generate.EXPERIMENT_CITE.fullmatch(c)
                assert e is not None and (experiments / e["name"]).is_file(), (name, c)


@pytest.mark.parametrize("kind, names", [
    ("paper", ["stage1_iters", "rounds", "field_iters", "scale_iters", "rays", "samples", "depth_rays",
               "scale_lr", "scale_samples", "field.resolution"]),
    ("addition", ["final_scale_iters", "w_opacity", "w_free",
                  "w_distortion", "w_hidden_smooth", "w_edge", "w_alone", "depth_robust",
                  "final_label_trim", "pair_minority", "label_replay", "anchor_bias",
                  "anchor_guide_samples", "field.object_resolution", "field.anchor_planes"]),
    ("infrastructure", ["seed", "eval_every", "device"]),
])
def test_the_options_fall_in_their_categories(kind: str, names: list[str]) -> None:
    options = _options()
    for name in names:
        m = _category(options[name].doc)
        assert (m["kind"] or m["infra"]) == kind, name


# ---- the checker fails when an option lacks its docstring or category --------------------------

SOURCE = '''
from dataclasses import dataclass

N = 3


@dataclass
class C:
    """A config."""

    good_paper: int = 1
    """paper (Sec. 3.3, Eq. 8): fine. Neutral: none."""
    no_docstring: int = 2
    no_category: float = 0.5
    """What it does, without a category."""
    paper_without_cite: str = "auto"
    """paper (somewhere): cites no section, equation or appendix."""
    addition_cites_a_note: int = 0
    """addition (my-notes.md): not an experiment file."""
    addition_cites_a_missing_file: int = 0
    """addition (experiments/2026-01-02-not-there.md): no such file."""
    good_addition: int = 0
    """addition (experiments/2026-01-02-a-test.md): fine; :data:`N` of them."""
    good_unmeasured: int = 0
    """addition (not measured): fine."""
    good_infrastructure: int = 0
    """infrastructure: fine."""
    wrong_word: int = 0
    """infra: not one of the three forms."""

    def method(self) -> None:
        """Not an option."""
'''


def test_the_checker_names_each_option_without_docstring_or_category(tmp_path: Path) -> None:
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments/2026-01-02-a-test.md").write_text("# A test\n")
    options = generate.class_options(SOURCE, "C")
    assert [o.name for o in options][:2] == ["good_paper", "no_docstring"] and "method" not in [o.name for o in options]
    found = generate.option_problems(options, "c.py", tmp_path / "experiments")
    flagged = {re.search(r"option (\w+)", f).group(1) for f in found}
    assert flagged == {"no_docstring", "no_category", "paper_without_cite", "addition_cites_a_note",
                       "addition_cites_a_missing_file", "wrong_word"}, found
    assert all(f.startswith("c.py:") for f in found)
    # Without the experiments folder only the form of a citation is checked.
    assert "addition_cites_a_missing_file" not in " ".join(generate.option_problems(options, "c.py"))


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    """A repository with the two option classes, one experiment and an options block."""
    root = tmp_path / "repo"
    (root / "osn" / "train").mkdir(parents=True)
    (root / "osn" / "model").mkdir(parents=True)
    (root / "docs" / "experiments").mkdir(parents=True)
    (root / "osn" / "train" / "config.py").write_text(
        'K = 0.5\n\nclass TrainConfig:\n    seed: int = 0\n    """infrastructure: the seed. Neutral: none."""\n'
        '    w_x: float | str = "auto"\n    """addition (experiments/2026-01-02-a-test.md): a term; ``auto``: :data:`K`.'
        ' Neutral: 0 | off."""\n')
    (root / "osn" / "model" / "fields.py").write_text(
        'class FieldConfig:\n    resolution: int = 64\n    """paper (appendix \\"Details of Networks\\"): voxels. Neutral: none."""\n')
    (root / "docs/experiments/2026-01-02-a-test.md").write_text("# A test\n")
    (root / "docs" / "experiments" / "README.md").write_text(generate.experiments_index(root))
    (root / "docs" / "training.md").write_text("# T\n\n## Options\n\n<!-- generated: options -->\n<!-- end generated -->\n")
    return root


def test_the_options_block_is_generated_and_stale_when_a_docstring_changes(tree: Path) -> None:
    doc = tree / "docs" / "training.md"
    assert generate.stale(tree) == ["docs/training.md"]
    doc.write_text(generate.regenerate(doc.read_text(), tree, doc))
    assert generate.stale(tree) == []
    text = doc.read_text()
    assert "| `seed` | `0` | infrastructure | the seed. Neutral: none. |" in text
    assert (f"| `w_x` | `auto` | addition ([a-test](experiments/2026-01-02-a-test.md)) | a term; `auto`: "
            "0.5 (`K`). Neutral: 0 \\| off. |") in text
    assert '| `field.resolution` | `64` | paper (appendix "Details of Networks") | voxels. Neutral: none. |' in text
    config = tree / "osn" / "train" / "config.py"
    config.write_text(config.read_text().replace("the seed.", "the run's seed."))
    assert generate.stale(tree) == ["docs/training.md"]
    config.write_text(config.read_text().replace('    """infrastructure: the run\'s seed. Neutral: none."""\n', ""))
    with pytest.raises(ValueError, match="option seed has no docstring"):
        generate.stale(tree)


# ---- the table in docs/training.md ------------------------------------------------------------


def test_the_generated_table_lists_every_option_with_its_default() -> None:
    table = generate.render_options(REPO)
    rows = [ln for ln in table.splitlines() if ln.startswith("| `")]
    names = [re.match(r"\| `([\w.]+)` \|", r).group(1) for r in rows]
    expected = [prefix + f.name for _, cls, prefix in CLASSES for f in dataclasses.fields(cls)]
    assert names == expected
    defaults = {"": TrainConfig(), "field.": FieldConfig()}
    for row in rows:
        name, default = re.match(r"\| `([\w.]+)` \| `([^`]*)` \|", row).groups()
        prefix, attr = ("field.", name[6:]) if name.startswith("field.") else ("", name)
        value = getattr(defaults[prefix], attr)
        if isinstance(value, FieldConfig):
            assert default == "FieldConfig()"
        elif isinstance(value, str):
            assert default == value, name
        else:
            assert ast.literal_eval(default) == value, name


def test_training_md_options_section_holds_the_current_generated_table() -> None:
    path = REPO / "docs" / "training.md"
    text = path.read_text()
    section = text[text.index("\n## Options\n"):]
    section = section[:section.index("\n## ", 1)]
    assert "<!-- generated: options -->" in section and "<!-- end generated -->" in section
    assert generate.regenerate(text, REPO, path) == text, "run python3 scripts/docs_generate.py"
