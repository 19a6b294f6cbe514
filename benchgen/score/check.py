"""``benchgen score --check``: recompute the digests a ``metrics.json`` records and name what differs
(docs/predictions.md, "Provenance and re-checking a score")."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from scenecore import dataset as D
from benchgen.score.digests import FileSet, hash_groups, parse_listing, set_digest
from benchgen.score.provenance import (PROTOCOL_NAME, PROTOCOL_VERSION, ground_truth_groups, lpips_weights_sha256,
                                       prediction_groups, scorer)

#: Most bytes of a ``metrics.json`` that ``--check`` reads.
MAX_METRICS_BYTES = 1 << 30
#: Per-file lines ``--check`` prints for one file set before it counts the rest.
MAX_FILE_LINES = 100


def load_record(metrics: str | Path) -> dict[str, Any]:
    """The ``provenance`` of a ``metrics.json`` of ``benchgen score`` or ``osn evaluate``."""
    path = Path(metrics)
    try:
        m = json.loads(D.read_regular(path, MAX_METRICS_BYTES))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise D.DatasetError(f"{path}: not valid JSON ({e})") from None
    prov = m.get("provenance") or (m.get("extra") or {}).get("provenance") if isinstance(m, dict) else None
    if not isinstance(prov, dict) or "ground_truth" not in prov:
        raise D.DatasetError(f"{path}: records no provenance (not a metrics.json of 'benchgen score' or "
                             "'osn evaluate', or written before provenance was recorded)")
    return prov


def _recorded_files(rec: dict[str, Any], report_dir: Path) -> tuple[dict[str, str] | None, str | None]:
    """The per-file listing beside ``metrics.json``, if it is there and matches the record."""
    path = report_dir / rec["listing"]
    if not path.is_file():
        return None, f"{path}: missing: the files that differ cannot be named, only their groups"
    files = parse_listing(D.read_regular(path, MAX_METRICS_BYTES), path)
    if set_digest(files) != rec["sha256"]:
        return None, f"{path}: does not match metrics.json's digest (the listing was changed)"
    return files, None


def _compare(rec: dict[str, Any], now: FileSet, recorded: dict[str, str] | None, label: str) -> list[str]:
    """One line per group or file of ``now`` that differs from ``rec`` (and the listing)."""
    lines: list[str] = []
    root = now.root
    old, new = rec["groups"], {g: now.group_digest(g) for g in now.groups}
    for g in old:
        if g not in new:
            lines.append(f"{root / g}: missing ({label} scored, not there now)")
    for g in new:
        if g not in old:
            lines.append(f"{root / g}: not in the scored {label} (added since)")
    file_lines: list[str] = []
    for g in (g for g in old if g in new and old[g] != new[g]):
        if recorded is None:
            lines.append(f"{root / g}: contents differ from the scored {label}")
            continue
        was = {r: h for r, h in recorded.items() if r == g or r.startswith(g + "/")}
        cur = now.groups[g]
        for r in sorted(set(was) | set(cur)):
            if r not in cur:
                file_lines.append(f"{root / r}: missing (scored, sha256 {was[r][:12]}...)")
            elif r not in was:
                file_lines.append(f"{root / r}: new file, not in the scored {label}")
            elif was[r] != cur[r]:
                file_lines.append(f"{root / r}: contents differ (sha256 {cur[r][:12]}..., scored {was[r][:12]}...)")
        if was == cur:  # the listing agrees with the files: the record's group digest does not
            lines.append(f"{root / g}: digest differs from metrics.json's, files match {rec['listing']}")
    if len(file_lines) > MAX_FILE_LINES:
        file_lines = file_lines[:MAX_FILE_LINES] + [f"{root}: and {len(file_lines) - MAX_FILE_LINES} more files differ"]
    lines += file_lines
    if not lines and set_digest(now.files) != rec["sha256"]:
        lines.append(f"{root}: digest over all files differs from metrics.json's")
    return lines


def _grouped(files: dict[str, str], groups: Iterable[str]) -> dict[str, list[str]]:
    """The files of a listing by the recorded groups (a file, or a directory and what lies under it)."""
    out: dict[str, list[str]] = {g: [] for g in groups}
    for rel in files:
        g = next((g for g in out if rel == g or rel.startswith(g + "/")), None)
        if g is not None:
            out[g].append(rel)
    return out


def _set_lines(rec: dict[str, Any], root: Path, report_dir: Path, label: str, workers: int,
               groups_now: dict[str, Sequence[str] | None] | Callable[[], dict[str, Sequence[str] | None]],
               ) -> tuple[list[str], list[str]]:
    """Differences and notes of one file set. ``groups_now``: its groups as the directory holds
    them now, or a function giving them, called only when the listing cannot say which files were
    scored. A listing that is gone is a note (the groups' digests are still checked); one that no
    longer matches ``metrics.json`` is a difference."""
    recorded, problem = _recorded_files(rec, report_dir)
    lines: list[str] = []
    notes: list[str] = []
    if problem:
        (lines if (report_dir / rec["listing"]).is_file() else notes).append(problem)
    if callable(groups_now):
        groups_now = _grouped(recorded, rec["groups"]) if recorded is not None else groups_now()
    # A file scored but gone is named by the listing; hashing it here would refuse it instead.
    present = {g: f if f is None else [r for r in f if os.path.lexists(root / r)] for g, f in groups_now.items()}
    now = hash_groups(root, present, rec["listing"], workers)
    return lines + _compare(rec, now, recorded, label), [f"note: {n}" for n in notes]


def check(metrics: str | Path, predictions: str | Path | None = None, dataset: str | Path | None = None,
          workers: int = 1) -> tuple[list[str], list[str]]:
    """Recompute the digests a ``metrics.json`` records, from its directories or those given.

    Returns ``(differences, notes)``: one line per file, group or setting that differs (an empty
    list: everything matches), and lines that inform without failing the check (another scorer
    version). ``DatasetError`` for a ``metrics.json`` without provenance.
    """
    metrics = Path(metrics)
    prov = load_record(metrics)
    report_dir = metrics.parent
    lines: list[str] = []
    notes: list[str] = []
    proto = prov["protocol"]
    if proto.get("name") != PROTOCOL_NAME or proto.get("version") != PROTOCOL_VERSION:
        lines.append(f"{metrics}: protocol {proto.get('name')} v{proto.get('version')}, this scorer's is "
                     f"{PROTOCOL_NAME} v{PROTOCOL_VERSION}")
    lp = proto.get("metrics", {}).get("lpips")
    if lp and lp.get("weights_sha256") != (now := lpips_weights_sha256()):
        lines.append(f"LPIPS weights: sha256 {str(now)[:12]}... here, {str(lp.get('weights_sha256'))[:12]}... when scored")
    sc, here = prov.get("scorer", {}), scorer()
    if (sc.get("version"), sc.get("git_commit")) != (here["version"], here["git_commit"]):
        notes.append(f"note: scored by {sc.get('package')} {sc.get('version')} (commit {sc.get('git_commit')}), "
                     f"this is {here['version']} (commit {here['git_commit']}); digests do not depend on it")

    gt = prov["ground_truth"]
    droot = Path(dataset).resolve() if dataset is not None else Path(gt["root"])
    if not droot.is_dir():
        lines.append(f"{droot}: missing (the scored dataset); give it with --data DATASET")
    else:
        # The scored files as the listing names them; without it, those the dataset's scene implies.
        region = "valid_region.json" in gt["groups"]
        diff, note = _set_lines(gt, droot, report_dir, "ground truth", workers,
                                lambda: ground_truth_groups(droot, D.load_scene(droot), proto["views"], region))
        lines, notes = lines + diff, notes + note

    pr = prov.get("predictions")
    if pr:
        proot = Path(predictions).resolve() if predictions is not None else Path(pr["root"])
        if not proot.is_dir():
            lines.append(f"{proot}: missing (the scored predictions); give them as PRED")
        else:
            groups = prediction_groups(proot, [s for s in pr.get("sets", [""]) if (proot / s).is_dir()])
            diff, note = _set_lines(pr, proot, report_dir, "predictions", workers, groups)
            lines, notes = lines + diff, notes + note
    elif predictions is not None:
        notes.append(f"note: {metrics} records no prediction files (candidates rendered in memory); {predictions} not checked")
    return lines, notes
