"""Generated parts of README and docs: results tables from benchmark JSON, the experiments index.

    python3 scripts/docs_generate.py            # rewrite every generated part
    python3 scripts/docs_generate.py --check    # exit 1 naming each part that differs from its source

A results table lives between two comments; the first names the results JSON (relative to the
repository root) and the table in it::

    <!-- generated: benchmarks/results/demo.json#results -->
    ...written by this script: one provenance line, then the table...
    <!-- end generated -->

``docs/experiments/README.md`` lists every experiment file by date with its title. Standard
library only (it runs before any virtual environment exists).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from results_json import read_results  # noqa: E402

BLOCK = re.compile(r"(<!-- generated: (?P<src>[^#\s]+)#(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)
EXPERIMENTS = REPO / "docs" / "experiments"
INDEX = EXPERIMENTS / "README.md"
EXPERIMENT_NAME = re.compile(r"^(\d{4}-\d{2}-\d{2})-[a-z0-9-]+\.md$")


def markdown_files(root: Path = REPO) -> list[Path]:
    """README.md and every Markdown file under docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def provenance(doc: dict) -> str:
    """One line: what was run, on which commit and machine, when."""
    m = doc["machine"]
    commit = doc["commit"][:10] + (" with local changes" if doc.get("dirty") else "")
    wall = (doc.get("data") or {}).get("wall_seconds")
    took = f", {wall:.0f} s from start to table" if isinstance(wall, (int, float)) else ""
    return (f"*`{doc['command']}` on commit {commit}, {m['cpu']} ({m['cores']} cores), "
            f"{doc['time'][:10]}{took}.*")


def render_table(doc: dict, name: str, src: str) -> str:
    """The Markdown a block shows: provenance line, blank line, table."""
    if name not in doc["tables"]:
        raise ValueError(f"{src}: no table {name!r} (has {', '.join(doc['tables'])})")
    t = doc["tables"][name]
    esc = lambda c: str(c).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(map(esc, t["columns"])) + " |", "|" + "---|" * len(t["columns"])]
    lines += ["| " + " | ".join(map(esc, r)) + " |" for r in t["rows"]]
    return provenance(doc) + "\n\n" + "\n".join(lines) + "\n"


def regenerate(text: str, root: Path = REPO) -> str:
    """``text`` with every generated block rendered again from its JSON."""
    def sub(m: re.Match) -> str:
        doc = read_results(root / m["src"])
        return m.group(1) + render_table(doc, m["name"], m["src"]) + m.group(5)
    return BLOCK.sub(sub, text)


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
           if p.exists() and p != root / "docs" / "experiments" / "README.md" and regenerate(p.read_text(), root) != p.read_text()]
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
        p.write_text(experiments_index() if p == INDEX else regenerate(p.read_text()))
        print(f"rewrote {f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
