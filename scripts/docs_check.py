"""Checks that keep README and docs reference text (run by ``tests/test_docs.py``).

    python3 scripts/docs_check.py     # one line per problem, exit 1 if any

1. Every relative link and ``#anchor`` in README.md and docs/**.md resolves (GitHub's heading
   slugs; fenced code and inline code are not links).
2. Outside docs/experiments/ and generated blocks: no date (YYYY-MM-DD), no commit hash, and no
   results table (a table row holding ``±`` or a figure in dB): measured figures come from a
   results JSON through ``scripts/docs_generate.py``, history lives in docs/experiments/.
3. Code, configs and tests hold no date and no commit hash in any comment, docstring or string.
Standard library only.
"""

from __future__ import annotations

import re
import sys
import unicodedata
from pathlib import Path
from urllib.parse import unquote

REPO = Path(__file__).resolve().parents[1]
CODE_DIRS = ("osn", "benchgen", "scenecore", "blender_addon", "configs", "benchmarks", "scripts", "tests")
CODE_SUFFIXES = (".py", ".yaml", ".yml", ".toml", ".cff")

#: The checker's own tests hold dates and hashes on purpose: they are its cases.
EXEMPT = ("test_docs.py",)
DATE = re.compile(r"\b(?:19|20)\d\d-[01]\d-[0-3]\d\b")
HEX = re.compile(r"(?<![0-9A-Za-z_./-])[0-9a-f]{7,40}(?![0-9A-Za-z_])")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
GENERATED = re.compile(r"<!-- generated: .*?<!-- end generated -->", re.S)
#: An experiment cited by its path (code, docstrings): its file name begins with its date.
EXPERIMENT_PATH = re.compile(r"experiments/(?:19|20)\d\d-[01]\d-[0-3]\d-[a-z0-9-]+\.md")
#: A link target citing an experiment file: its file name begins with its date, which is a citation
#: there; the same date in the link text or the prose is history.
EXPERIMENT_TARGET = re.compile(r"(\]\(\s*<?[^)\s]*experiments/)(?:19|20)\d\d-[01]\d-[0-3]\d-([a-z0-9-]+\.md)")
RESULTS_ROW = re.compile(r"^\s*\|.*(±|\d\s?dB\b)")


def looks_like_hash(token: str) -> bool:
    """A hex run of 7-40 characters with both a digit and a letter (a short commit hash; a word such as ``deadbeef`` is not one)."""
    return any(c.isdigit() for c in token) and any(c.isalpha() for c in token)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links keep their text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").strip().lower()
    out = []
    for ch in text:
        cat = unicodedata.category(ch)
        if ch in " -_" or cat[0] in "LN":
            out.append("-" if ch == " " else ch)
    return "".join(out)


def strip_code(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` outside fenced code, inline code spans blanked."""
    out, fenced = [], False
    for n, ln in enumerate(text.splitlines(), 1):
        if FENCE.match(ln):
            fenced = not fenced
            continue
        if not fenced:
            out.append((n, re.sub(r"`[^`]*`", "``", ln)))
    return out


def anchors(path: Path, _cache: dict[Path, set[str]] = {}) -> set[str]:
    """The anchors a Markdown file defines: its headings' slugs (GitHub's -1, -2 for repeats;
    headings in fenced code are not headings) and explicit ``<a id|name="...">``."""
    if path not in _cache:
        seen: dict[str, int] = {}
        found: set[str] = set()
        text = path.read_text()
        fenced = False
        for ln in text.splitlines():
            if FENCE.match(ln):
                fenced = not fenced
                continue
            m = None if fenced else re.match(r"^\s{0,3}#{1,6}\s+(.*?)\s*#*\s*$", ln)
            if m:
                s = slug(m.group(1))
                k = seen.get(s, 0)
                seen[s] = k + 1
                found.add(s if k == 0 else f"{s}-{k}")
        found |= set(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", text))
        _cache[path] = found
    return _cache[path]


def markdown_files(root: Path = REPO) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def link_problems(root: Path = REPO) -> list[str]:
    out = []
    for md in markdown_files(root):
        if not md.exists():
            continue
        rel = md.relative_to(root)
        for n, ln in strip_code(md.read_text()):
            for target in LINK.findall(ln):
                if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, mailto:, ...
                    continue
                file_part, _, frag = target.partition("#")
                dest = (md.parent / unquote(file_part)).resolve() if file_part else md
                if file_part and not dest.exists():
                    out.append(f"{rel}:{n}: link to missing {file_part}")
                    continue
                try:
                    dest.relative_to(root)
                except ValueError:
                    out.append(f"{rel}:{n}: link {target} leaves the repository")
                    continue
                if frag and dest.suffix == ".md" and unquote(frag).lower() not in anchors(dest):
                    out.append(f"{rel}:{n}: no anchor #{frag} in {dest.relative_to(root)}")
    return out


def _history_problems(rel: Path, text: str, markdown: bool = False) -> list[str]:
    """Dates and commit hashes in ``text``, but in generated blocks and in citations of an
    experiment file: its path in code, a link's target in Markdown (the link text shows no date)."""
    out = []
    text = GENERATED.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    text = EXPERIMENT_TARGET.sub(r"\1\2", text) if markdown else EXPERIMENT_PATH.sub("experiments/FILE", text)
    for n, ln in enumerate(text.splitlines(), 1):
        for m in DATE.finditer(ln):
            out.append(f"{rel}:{n}: date {m.group(0)} (history goes in docs/experiments/)")
        for m in HEX.finditer(ln):
            if looks_like_hash(m.group(0)):
                out.append(f"{rel}:{n}: commit hash {m.group(0)} (history goes in docs/experiments/)")
    return out


def reference_problems(root: Path = REPO) -> list[str]:
    """Dates, hashes and hand-written results tables in README and reference docs."""
    out = []
    for md in markdown_files(root):
        if not md.exists() or (root / "docs" / "experiments") in md.parents:
            continue
        rel = md.relative_to(root)
        text = md.read_text()
        out += _history_problems(rel, text, markdown=True)
        bare = GENERATED.sub(lambda m: "\n" * m.group(0).count("\n"), text)
        fenced = False
        for n, ln in enumerate(bare.splitlines(), 1):
            if FENCE.match(ln):
                fenced = not fenced
            elif not fenced and RESULTS_ROW.match(ln):
                out.append(f"{rel}:{n}: a results table written by hand (generate it from a results JSON)")
                break
    return out


def code_problems(root: Path = REPO) -> list[str]:
    """Dates and commit hashes anywhere in code, configs and tests."""
    out = []
    for d in CODE_DIRS:
        for p in sorted((root / d).rglob("*")):
            if p.suffix in CODE_SUFFIXES and p.is_file() and "__pycache__" not in p.parts and p.name not in EXEMPT:
                out += _history_problems(p.relative_to(root), p.read_text(errors="replace"))
    for p in (root / "pyproject.toml", root / "Makefile", root / "CITATION.cff"):
        if p.exists() and p.name != "CITATION.cff":  # the citation's release date is its own field
            out += _history_problems(p.relative_to(root), p.read_text())
    return out


def problems(root: Path = REPO) -> list[str]:
    return link_problems(root) + reference_problems(root) + code_problems(root)


def main() -> int:
    found = problems()
    print("\n".join(found) if found else "docs check: no problems")
    return 1 if found else 0


if __name__ == "__main__":
    raise SystemExit(main())
