"""Generated parts of README and docs: results tables from benchmark JSON, the options table, the experiments index.

    python3 scripts/docs_generate.py            # rewrite every generated part
    python3 scripts/docs_generate.py --check    # exit 1 naming each part that differs from its source

A results table lives between two comments; the first names the results JSON (relative to the
repository root) and the table in it::

    <!-- generated: benchmarks/results/demo.json#results -->
    ...written by this script: one provenance line, then the table...
    <!-- end generated -->

The training options' table lives between ``<!-- generated: options -->`` and the same end
comment: one row per option of ``TrainConfig`` (``osn/train/config.py``) and ``FieldConfig``
(``osn/model/fields.py``, prefixed ``field.``) with its default and the attribute docstring under
its declaration, read with ``ast`` (nothing is imported). Every docstring begins with its
category: ``paper (<section or equation of the OSN paper>): ``, ``addition (<experiments/FILE.md
that measured it, comma separated, or "not measured">): `` or ``infrastructure: ``; an option
without one is an error (:func:`option_problems`).

``docs/experiments/README.md`` lists every experiment file by date with its title. Standard
library only (it runs before any virtual environment exists).
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import sys
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from results_json import read_results  # noqa: E402

BLOCK = re.compile(r"(<!-- generated: (?P<src>[^#\s]+)#(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)
EXPERIMENTS = REPO / "docs" / "experiments"
INDEX = EXPERIMENTS / "README.md"
EXPERIMENT_NAME = re.compile(r"^(\d{4}-\d{2}-\d{2})-[a-z0-9-]+\.md$")

OPTIONS_BLOCK = re.compile(r"(<!-- generated: options -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)
#: The option classes the options table lists: source file, class, prefix of its options' names.
OPTION_CLASSES = (("osn/train/config.py", "TrainConfig", ""), ("osn/model/fields.py", "FieldConfig", "field."))
#: An option docstring's first words: its category, and what it cites.
CATEGORY = re.compile(r"(?:(?P<kind>paper|addition) \((?P<cite>[^()]*)\)|(?P<infra>infrastructure)):\s+(?P<text>\S.*)", re.S)
#: What a ``paper (...)`` category must name: a section, an equation or the appendix.
PAPER_CITE = re.compile(r"\b(?:Sec\.|Eq\.|appendix)")
EXPERIMENT_CITE = re.compile(r"experiments/(?P<name>\d{4}-\d{2}-\d{2}-[a-z0-9-]+\.md)")


def experiment_title(file_name: str) -> str:
    """A link text for an experiment file: its name without the date and ``.md`` (the date is the
    file's, history; the reference text cites the experiment, not when it ran)."""
    return re.sub(r"^\d{4}-\d{2}-\d{2}-", "", file_name).removesuffix(".md")
NOT_MEASURED = "not measured"


def markdown_files(root: Path = REPO) -> list[Path]:
    """README.md and every Markdown file under docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def provenance(doc: dict) -> str:
    """One line: what was run, on which commit and machine, and how long it took (the date stays in
    the results JSON: reference docs hold no history)."""
    m = doc["machine"]
    commit = doc["commit"][:10] + (" with local changes" if doc.get("dirty") else "")
    wall = (doc.get("data") or {}).get("wall_seconds")
    took = f", {wall:.0f} s from start to table" if isinstance(wall, (int, float)) else ""
    load = (doc.get("data") or {}).get("load_average_at_end")
    took += f" (load average {load:.1f} at the end)" if isinstance(load, (int, float)) else ""
    # What else ran, when the figures were not taken on a quiet machine (a results JSON's own words).
    conditions = (doc.get("data") or {}).get("conditions")
    took += f"; {conditions}" if isinstance(conditions, str) and conditions else ""
    return f"*`{doc['command']}` on commit {commit}, {m['cpu']} ({m['cores']} cores){took}.*"


def render_table(doc: dict, name: str, src: str) -> str:
    """The Markdown a block shows: provenance line, blank line, table."""
    if name not in doc["tables"]:
        raise ValueError(f"{src}: no table {name!r} (has {', '.join(doc['tables'])})")
    t = doc["tables"][name]
    esc = lambda c: str(c).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(map(esc, t["columns"])) + " |", "|" + "---|" * len(t["columns"])]
    lines += ["| " + " | ".join(map(esc, r)) + " |" for r in t["rows"]]
    return provenance(doc) + "\n\n" + "\n".join(lines) + "\n"


class Option(NamedTuple):
    """One option of a config class: its name, its default as written, its attribute docstring, its
    line, and its source's module-level numeric constants (name -> value as written) for ``:data:`NAME```."""

    name: str
    default: str
    doc: str | None
    line: int
    constants: dict[str, str]


def module_constants(source: str, tree: ast.Module | None = None) -> dict[str, str]:
    """Module-level names bound to a number (``A = 1`` or ``A, B = 1, 2``), with the number as written."""
    out = {}
    for node in (tree or ast.parse(source)).body:
        if isinstance(node, ast.Assign) or (isinstance(node, ast.AnnAssign) and node.value is not None):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                pairs = (zip(target.elts, node.value.elts) if isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple)
                         else [(target, node.value)])
                for name, value in pairs:
                    if (isinstance(name, ast.Name) and isinstance(value, ast.Constant)
                            and isinstance(value.value, (int, float)) and not isinstance(value.value, bool)):
                        out[name.id] = ast.get_source_segment(source, value)
    return out


def class_options(source: str, class_name: str) -> list[Option]:
    """The annotated fields of class ``class_name`` in ``source``, in order, each with the string
    literal right under its declaration (None when there is none)."""
    tree = ast.parse(source)
    cls = next((n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == class_name), None)
    if cls is None:
        raise ValueError(f"no class {class_name}")
    constants = module_constants(source, tree)
    out = []
    for i, node in enumerate(cls.body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        after = cls.body[i + 1] if i + 1 < len(cls.body) else None
        doc = (after.value.value if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
               and isinstance(after.value.value, str) else None)
        out.append(Option(node.target.id, _default(source, node.value), doc, node.lineno, constants))
    return out


def _default(source: str, value: ast.expr | None) -> str:
    """A field's default as the source writes it: a string without quotes, ``field(default_factory=F)`` as ``F()``."""
    if value is None:
        return ""
    if isinstance(value, ast.Constant) and isinstance(value.value, str):
        return value.value
    if isinstance(value, ast.Call) and getattr(value.func, "id", None) == "field":
        for kw in value.keywords:
            if kw.arg == "default_factory":
                return f"{ast.get_source_segment(source, kw.value)}()"
    return ast.get_source_segment(source, value) or ast.unparse(value)


def option_problems(options: list[Option], where: str, experiments: Path | None = None) -> list[str]:
    """Options whose docstring is missing or does not begin with its category; a ``paper (...)``
    that names no section, equation or appendix; an ``addition (...)`` that cites anything but
    experiment files (or ``not measured``), or, given ``experiments``, a file not there."""
    out = []
    for o in options:
        at = f"{where}:{o.line}: option {o.name}"
        m = CATEGORY.match(o.doc.strip()) if o.doc else None
        if o.doc is None:
            out.append(f"{at} has no docstring")
        elif m is None:
            out.append(f"{at}: docstring does not begin with 'paper (...): ', 'addition (...): ' or 'infrastructure: '")
        elif m["kind"] == "paper" and not PAPER_CITE.search(m["cite"]):
            out.append(f"{at}: 'paper (...)' names no section (Sec.), equation (Eq.) or appendix paragraph")
        elif m["kind"] == "addition" and m["cite"].strip() != NOT_MEASURED:
            for cite in (c.strip() for c in m["cite"].split(",")):
                e = EXPERIMENT_CITE.fullmatch(cite)
                if e is None:
                    out.append(f"{at}: 'addition (...)' cites {cite!r}, not experiments/FILE.md or '{NOT_MEASURED}'")
                elif experiments is not None and not (experiments / e["name"]).is_file():
                    out.append(f"{at}: cites missing {cite}")
    return out


def all_options(root: Path = REPO) -> list[tuple[str, Option]]:
    """Every option of :data:`OPTION_CLASSES` as ``(name as written in a config, option)``;
    a ``ValueError`` naming each option :func:`option_problems` finds."""
    rows, problems = [], []
    for rel, cls, prefix in OPTION_CLASSES:
        options = class_options((root / rel).read_text(), cls)
        problems += option_problems(options, rel, root / "docs" / "experiments")
        rows += [(prefix + o.name, o) for o in options]
    if problems:
        raise ValueError("option docstrings: " + "; ".join(problems))
    return rows


def _markdown(doc: str, constants: dict[str, str] | None = None) -> str:
    """One table cell from reST: ``x`` and :role:`x` as `x`, :data:`NAME` of a numeric constant
    of ``constants`` as its value and name, one line, ``|`` escaped."""
    constants = constants or {}

    def role(m: re.Match) -> str:
        name = m["name"].split(".")[-1]
        if m["role"] == "data" and name in constants:
            return f"{constants[name]} (`{m['name']}`)"
        return f"`{m['name']}`"
    text = re.sub(r":(?P<role>\w+):`~?(?P<name>[^`]*)`", role, " ".join(doc.split()))
    return text.replace("``", "`").replace("|", "\\|")


def render_options(root: Path = REPO, base: Path | None = None) -> str:
    """The options table; experiment files are linked relative to ``base`` (default docs/)."""
    base = base if base is not None else root / "docs"
    lines = ["*Written by `scripts/docs_generate.py` from the docstring under each option in "
             "`osn/train/config.py` and `osn/model/fields.py`.*", "",
             "| option | default | category | what it does |", "|---|---|---|---|"]
    counts = {"paper": 0, "addition": 0, "infrastructure": 0}
    for name, o in all_options(root):
        m = CATEGORY.match(o.doc.strip())
        kind = "infrastructure" if m["infra"] else m["kind"]
        counts[kind] += 1
        if kind == "infrastructure":
            category = kind
        elif kind == "paper" or m["cite"].strip() == NOT_MEASURED:
            category = f"{m['kind']} ({_markdown(m['cite'])})"
        else:
            links = [f"[{experiment_title(e['name'])}]({os.path.relpath(root / 'docs' / 'experiments' / e['name'], base)})"
                     for e in EXPERIMENT_CITE.finditer(m["cite"])]
            category = f"addition ({', '.join(links)})"
        default = f"`{_markdown(o.default)}`" if o.default else ""
        lines.append(f"| `{name}` | {default} | {category} | {_markdown(m['text'], o.constants)} |")
    lines[1:1] = ["", f"{sum(counts.values())} options: {counts['paper']} of the paper, {counts['addition']} additions, "
                  f"{counts['infrastructure']} infrastructure."]
    return "\n".join(lines) + "\n"


def regenerate(text: str, root: Path = REPO, path: Path | None = None) -> str:
    """``text`` with every generated block rendered again from its JSON, and its options block
    from the option docstrings (links relative to ``path``'s folder, default docs/)."""
    def sub(m: re.Match) -> str:
        doc = read_results(root / m["src"])
        return m.group(1) + render_table(doc, m["name"], m["src"]) + m.group(5)
    text = BLOCK.sub(sub, text)
    if OPTIONS_BLOCK.search(text):
        table = render_options(root, path.parent if path is not None else None)
        text = OPTIONS_BLOCK.sub(lambda m: m.group(1) + table + m.group(3), text)
    return text


def experiments_index(root: Path = REPO) -> str:
    """``docs/experiments/README.md``: every experiment file, newest first, with its title."""
    rows = []
    for p in sorted((root / "docs" / "experiments").glob("*.md"), reverse=True):
        m = EXPERIMENT_NAME.match(p.name)
        if not m:
            continue
        first = p.read_text().splitlines()[0] if p.read_text() else ""
        title = first.lstrip("#").strip() or p.stem
        rows.append(f"| {m.group(1)} | [{title}]({p.name}) |")
    head = ("# Experiments\n\n"
            "Dated measurements, one file each: the command, the figures, what was kept and what was not. "
            "Reference docs cite them as evidence; they are not updated after the fact. "
            "This index is written by `scripts/docs_generate.py`.\n\n"
            "| date | experiment |\n|---|---|\n")
    return head + "\n".join(rows) + "\n"


def stale(root: Path = REPO) -> list[str]:
    """Files whose generated parts differ from their sources (empty when all are current)."""
    out = [str(p.relative_to(root)) for p in markdown_files(root)
           if p.exists() and p != root / "docs" / "experiments" / "README.md" and regenerate(p.read_text(), root, p) != p.read_text()]
    index = root / "docs" / "experiments" / "README.md"
    if (root / "docs" / "experiments").is_dir() and (not index.exists() or index.read_text() != experiments_index(root)):
        out.append(str(index.relative_to(root)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 naming each stale file")
    a = ap.parse_args(argv)
    try:
        bad = stale()
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.check:
        for f in bad:
            print(f"{f}: generated part differs from its source (run python3 scripts/docs_generate.py)")
        return 1 if bad else 0
    for f in bad:
        p = REPO / f
        p.write_text(experiments_index() if p == INDEX else regenerate(p.read_text(), REPO, p))
        print(f"rewrote {f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
