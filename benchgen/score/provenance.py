"""Provenance of a score, and ``benchgen score --check`` (docs/predictions.md, "Provenance and
re-checking a score").

``metrics.json`` of ``benchgen score`` (and of ``osn evaluate``) holds a ``provenance`` object:

* ``predictions``: the SHA-256 of every file under each candidate directory (names starting with
  ``.`` skipped at every level, whether or not the score read the file), one digest per candidate
  directory over its files' paths relative to it and their contents, and one over all; the
  per-file digests go to ``predictions.sha256`` beside ``metrics.json`` (``sha256sum`` format,
  paths relative to PRED, so ``cd PRED && sha256sum -c .../predictions.sha256`` works too).
* ``ground_truth``: the same over the dataset files the score read (``scene.json``,
  ``verification.json``, ``valid_region.json`` where used, the training video, each
  configuration's ``config.json`` and evaluated test views), grouped by configuration;
  per-file digests in ``dataset.sha256``.
* ``verification``: whether the dataset's ``verification.json`` passed (a score of an unverified
  dataset needs ``--unverified`` and says so), ``protocol`` (name, version, evaluated views, the
  mask rule, each metric's settings and LPIPS's weights digest) and ``scorer`` (package version;
  the git commit of the scorer's checkout only when that checkout is clean).

Files are hashed in chunks as they are read (:data:`CHUNK`), regular files only
(:func:`scenecore.dataset.images.open_regular`: a FIFO or a device is refused, one line naming it),
and only the size a file had when opened is read. :func:`check` recomputes the digests from the
directories recorded (or given) and returns one line per difference.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from scenecore import dataset as D
from scenecore.dataset.images import open_regular, read_pieces

PROTOCOL_NAME = "benchgen-best-of-n"
#: Bumped when what a score means changes (matching, masks or a metric's definition).
PROTOCOL_VERSION = 1
#: Bytes hashed per read.
CHUNK = 1 << 20
PREDICTIONS_LISTING = "predictions.sha256"
DATASET_LISTING = "dataset.sha256"
VERIFICATION = "verification.json"
#: Most bytes of a ``metrics.json`` that ``--check`` reads.
MAX_METRICS_BYTES = 1 << 30
#: Per-file lines ``--check`` prints for one file set before it counts the rest.
MAX_FILE_LINES = 100
UNVERIFIED_HINT = "pass --unverified to score it anyway"


# --------------------------------------------------------------------------------------------
# Digests
# --------------------------------------------------------------------------------------------


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a regular file, read in :data:`CHUNK` pieces up to the size it had when
    opened (:func:`scenecore.dataset.images.read_pieces`); ``DatasetError`` naming it when it is
    missing, not a regular file or changed size."""
    fh, size = open_regular(path)
    h = hashlib.sha256()
    with fh:
        for chunk in read_pieces(fh, size, path, CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _escape(rel: str) -> tuple[str, str]:
    """``sha256sum``'s escaping of a name holding a backslash or a newline: ``("\\", escaped)``."""
    if "\\" in rel or "\n" in rel:
        return "\\", rel.replace("\\", "\\\\").replace("\n", "\\n")
    return "", rel


def listing_bytes(files: dict[str, str]) -> bytes:
    """``files`` (relative path -> SHA-256) as ``sha256sum`` lines in sorted path order."""
    lines = []
    for rel in sorted(files):
        prefix, name = _escape(rel)
        lines.append(f"{prefix}{files[rel]}  {name}\n")
    return "".join(lines).encode()


def parse_listing(data: bytes, where: Path) -> dict[str, str]:
    """The inverse of :func:`listing_bytes`; ``DatasetError`` naming ``where`` on a bad line."""
    out = {}
    for k, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        escaped = line.startswith("\\")
        body = line[1:] if escaped else line
        digest, sep, rel = body.partition("  ")
        if not sep or len(digest) != 64:
            raise D.DatasetError(f"{where}: line {k} is not '<sha256>  <path>'")
        if escaped:
            rel = rel.replace("\\\\", "\0").replace("\\n", "\n").replace("\0", "\\")
        out[rel] = digest
    return out


def set_digest(files: dict[str, str]) -> str:
    """One digest of a file set: the SHA-256 of its :func:`listing_bytes`."""
    return hashlib.sha256(listing_bytes(files)).hexdigest()


def tree_files(root: Path, group: str) -> list[str]:
    """Paths relative to ``root`` of every file under ``root/group``, in sorted order; names
    starting with ``.`` are skipped at every level, directory links are followed (a link back to
    a directory it lies in is not entered again). Anything that is not a directory is listed:
    hashing it refuses what is not a regular file."""
    out: list[str] = []

    def walk(d: Path, rel: str, above: frozenset) -> None:
        st = os.stat(d)
        key = (st.st_dev, st.st_ino)
        if key in above:
            return
        with os.scandir(d) as it:
            entries = sorted(it, key=lambda e: e.name)
        for e in entries:
            if e.name.startswith("."):
                continue
            r = f"{rel}/{e.name}" if rel else e.name
            if e.is_dir():  # follows links
                walk(Path(e.path), r, above | {key})
            else:
                out.append(r)

    walk(root / group, group, frozenset())
    return out


# Set before forking workers (:func:`benchgen.score.parallel.ordered_map`), inherited unpickled.
_JOB: dict[str, Any] = {}


def _hash_group(group: str, files: tuple[str, ...] | None) -> dict[str, str]:
    """``rel -> sha256`` of a group's files (``None``: every file under the directory ``group``)."""
    root: Path = _JOB["root"]
    rels = tree_files(root, group) if files is None else list(files)
    base = str(root)  # plain strings: a Path per file costs more than hashing a small one
    return {rel: file_sha256(os.path.join(base, rel)) for rel in rels}


@dataclass
class FileSet:
    """Digests of files under ``root``, by group (a candidate directory, a configuration, a file)."""

    root: Path
    groups: dict[str, dict[str, str]]
    listing: str

    @property
    def files(self) -> dict[str, str]:
        return {rel: h for g in self.groups.values() for rel, h in g.items()}

    def group_digest(self, group: str) -> str:
        """A directory's digest over its files' paths relative to it (identical directories have
        equal digests); a single file's is its own SHA-256."""
        files = self.groups[group]
        if list(files) == [group]:
            return files[group]
        return set_digest({rel[len(group) + 1:]: h for rel, h in files.items()})

    def record(self) -> dict[str, Any]:
        files = self.files
        return {"root": str(self.root), "sha256": set_digest(files), "files": len(files), "listing": self.listing,
                "groups": {g: self.group_digest(g) for g in self.groups}}


def hash_groups(root: str | Path, groups: dict[str, Sequence[str] | None], listing: str, workers: int = 1) -> FileSet:
    """Hash every group of ``root`` (``None``: walk the directory ``group``), in ``workers``
    processes (same result for any number)."""
    from benchgen.score.parallel import ordered_map

    root = Path(root).resolve()
    names = list(groups)
    tasks = [(g, None if groups[g] is None else tuple(groups[g])) for g in names]
    _JOB.update(root=root)
    try:
        hashed = list(ordered_map(_hash_group, tasks, workers))
    finally:
        _JOB.clear()
    return FileSet(root, dict(zip(names, hashed)), listing)


def candidate_dirs(root: Path, parent: str = "") -> list[str]:
    """Candidate directories of a prediction directory ``root/parent`` as the scorer takes them
    (sub-directories not starting with ``.``), relative to ``root``."""
    base = root / parent
    names = sorted(e.name for e in os.scandir(base) if e.is_dir() and not e.name.startswith("."))
    return [f"{parent}/{n}" if parent else n for n in names]


def prediction_groups(root: Path, sets: Sequence[str] = ("",)) -> dict[str, None | list[str]]:
    """Groups of one or more prediction directories ``root/SET``: each candidate directory, walked,
    and each ``method.json``."""
    from benchgen.score.predictions import METHOD_FILE

    groups: dict[str, None | list[str]] = {}
    for s in sets:
        method = f"{s}/{METHOD_FILE}" if s else METHOD_FILE
        if (root / method).exists():
            groups[method] = [method]
        groups.update({c: None for c in candidate_dirs(root, s)})
    return groups


def ground_truth_groups(root: Path, scene: D.Scene, views: Sequence[str], region: bool) -> dict[str, list[str]]:
    """The dataset files a score reads, by group, relative to ``root``: ``scene.json``,
    ``verification.json`` (when present), ``valid_region.json`` (when ``region``), the training
    video (``train``) and per configuration ``configs/GGG`` its ``config.json``, its stored
    co-visibility masks (when present) and the three files of each evaluated view."""
    from scenecore.dataset.covisibility import covisibility_path

    def rel(p: Path) -> str:
        return p.relative_to(root).as_posix()

    groups: dict[str, list[str]] = {"scene.json": ["scene.json"]}
    if (root / VERIFICATION).exists():
        groups[VERIFICATION] = [VERIFICATION]
    if region:
        groups["valid_region.json"] = ["valid_region.json"]
    groups["train"] = [rel(p) for f in sorted(scene.train_frames, key=lambda f: f.time_index)
                       for p in D.frame_paths(root, f.name).all()]
    for g in range(scene.num_configurations):
        c = f"configs/{D.config_dirname(g)}"
        masks = [rel(covisibility_path(root, g))] if covisibility_path(root, g).exists() else []
        groups[c] = [f"{c}/config.json", *masks] + [rel(p) for v in views for p in D.frame_paths(root, v, g).all()]
    return groups


# --------------------------------------------------------------------------------------------
# Verification, protocol, scorer
# --------------------------------------------------------------------------------------------


def verification_problem(root: str | Path, scene: D.Scene) -> str | None:
    """One line naming ``verification.json`` when the dataset is not verified: the file is
    missing (``benchgen generate`` stopped before verifying, ``--video-only``), unreadable, a
    configuration failed, or it verified other configurations than the dataset holds; else None."""
    root = Path(root)
    path = root / VERIFICATION
    if not path.exists():
        return f"{path}: missing: the dataset was never verified (run 'benchgen verify {root}')"
    try:
        v = D.read_json(path)
    except D.DatasetError as e:
        return str(e)
    cfgs = v.get("configurations") if isinstance(v, dict) else None
    if not isinstance(cfgs, list) or not all(isinstance(c, dict) for c in cfgs):
        return f"{path}: holds no per-configuration verdicts (run 'benchgen verify {root}')"
    failed = [c for c in cfgs if not c.get("passed")]
    if failed:
        c = failed[0]
        why = "; ".join(map(str, c.get("failures") or [])) or "failed"
        return (f"{path}: verification failed for {len(failed)} of {len(cfgs)} configurations "
                f"(configuration {D.config_dirname(int(c.get('index', 0)))}: {why})")
    if v.get("passed") is not True:
        return f"{path}: the verification did not pass ('passed' is {v.get('passed')!r})"
    if len(cfgs) != scene.num_configurations:
        return (f"{path}: verifies {len(cfgs)} configurations, the dataset has {scene.num_configurations} "
                f"(run 'benchgen verify {root}')")
    for g, c in enumerate(cfgs):
        try:
            same = list(map(float, c.get("scales", []))) == D.load_configuration(root, g, scene.num_objects).scales.tolist()
        except (TypeError, ValueError):
            same = False
        if not same:
            return (f"{path}: configuration {D.config_dirname(g)}'s verified scales differ from "
                    f"configs/{D.config_dirname(g)}/config.json (run 'benchgen verify {root}')")
    return None


def verification(root: str | Path, scene: D.Scene, unverified: bool = False) -> dict[str, Any]:
    """The ``verification`` record of a score of ``root``; refuses (``DatasetError``, one line
    naming ``verification.json``) an unverified dataset unless ``unverified``."""
    problem = verification_problem(root, scene)
    if problem and not unverified:
        raise D.DatasetError(f"{problem}; {UNVERIFIED_HINT}")
    return {"verified": problem is None, "problem": problem, "scored_unverified": problem is not None}


def lpips_weights_sha256() -> str | None:
    """SHA-256 of the LPIPS weights file in use (None when it is not installed)."""
    from benchgen.score.lpips import default_weights_path

    path = default_weights_path()
    return file_sha256(path) if path.is_file() else None


def metric_settings(metrics: Iterable[str]) -> dict[str, dict[str, Any]]:
    """What each reported metric is computed with (docs/metrics.md has the definitions)."""
    from benchgen.score import lpips as L
    from benchgen.score import metrics as M

    settings: dict[str, dict[str, Any]] = {
        "psnr": {"version": 1, "data_range": 1.0, "mse": "mean over channels and evaluated pixels",
                 "mse_floor": M.MSE_FLOOR, "errors": "exact (integer colours in float64)"},
        "ssim": {"version": 1, "window": "gaussian", "sigma": M.SSIM_SIGMA, "radius": M.SSIM_RADIUS, "k1": M.SSIM_K1,
                 "k2": M.SSIM_K2, "covariance": "population", "data_range": 1.0,
                 "mask": "SSIM map averaged over evaluated pixels of the window interior", "precision": "float32"},
        "lpips": {"version": 1, "net": "alex", "lpips": "0.1", "checkpoint_sha256": L.CKPT_SHA256,
                  "weights_sha256": lpips_weights_sha256(), "mask": "spatial map averaged over evaluated pixels"},
        "ssimae": {"version": 1, "normalisation": "per image: zero median, unit mean absolute deviation over valid pixels"},
        "pq": {"version": 1, "match": "IoU > 0.5, one segment per object id", "ignore_id": D.NO_OBJECT},
        "miou": {"version": 1, "classes": "object ids present in either map", "ignore_id": D.NO_OBJECT},
    }
    return {k: settings[k] for k in metrics if k in settings}


def protocol(views: Sequence[str], max_views: int, metrics: Iterable[str]) -> dict[str, Any]:
    """The ``protocol`` record: what was compared, on which views, with what."""
    from benchgen.score import covisibility as C

    return {
        "name": PROTOCOL_NAME, "version": PROTOCOL_VERSION, "views": list(views), "max_views": max_views,
        "match": "per ground truth, the candidate with the best mean PSNR over its evaluated views "
                 "(exact over all candidates; ties: the first in sorted name order)",
        "mask": {"rule": "co-visibility: a test pixel is evaluated when a training frame of the same configuration saw "
                         "its surface point (moved with its object; depth agreeing within depth_rtol)",
                 "version": C.RULE_VERSION, "depth_rtol": C.DEPTH_RTOL},
        "metrics": metric_settings(metrics),
    }


@functools.lru_cache(maxsize=1)
def scorer() -> dict[str, Any]:
    """The ``scorer`` record: the package and its version, and the git commit of the checkout
    the scorer runs from, only when that checkout is clean (no change, no untracked file)."""
    import benchgen

    try:
        from importlib.metadata import version

        pkg_version = version("osn-toolkit")
    except Exception:  # not installed as a distribution
        pkg_version = benchgen.__version__
    out: dict[str, Any] = {"package": "osn-toolkit", "version": pkg_version, "git_commit": None}
    repo = Path(benchgen.__file__).resolve().parents[1]
    if not (repo / ".git").exists():
        return {**out, "git": "not a git checkout"}
    try:
        def git(*a: str) -> str:
            return subprocess.run(["git", "-C", str(repo), *a], capture_output=True, text=True, timeout=30,
                                  check=True).stdout
        dirty = git("status", "--porcelain").strip()
        commit = git("rev-parse", "HEAD").strip()
    except (OSError, subprocess.SubprocessError) as e:
        return {**out, "git": f"git did not answer ({type(e).__name__})"}
    if dirty:
        return {**out, "git": f"checkout at {commit} has uncommitted changes: no commit recorded"}
    return {**out, "git_commit": commit, "git": "clean checkout"}


# --------------------------------------------------------------------------------------------
# The record of a score
# --------------------------------------------------------------------------------------------


@dataclass
class Provenance:
    """``record`` goes into ``metrics.json``; ``files`` (listings) beside it."""

    record: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)


def collect(
    dataset: str | Path, scene: D.Scene, views: Sequence[str], max_views: int, metrics: Iterable[str],
    verified: dict[str, Any], predictions: str | Path | None = None, sets: Sequence[str] = ("",),
    region: bool = False, workers: int = 1,
) -> Provenance:
    """Digests of the ground truth (and of the prediction directories ``predictions/SET`` when
    given), with the verification record ``verified`` (:func:`verification`), the protocol and the
    scorer. ``region``: the score read ``valid_region.json``."""
    root = Path(dataset).resolve()
    gt = hash_groups(root, ground_truth_groups(root, scene, views, region), DATASET_LISTING, workers)
    record: dict[str, Any] = {"ground_truth": gt.record(), "predictions": None, "verification": verified,
                              "protocol": protocol(views, max_views, metrics), "scorer": scorer()}
    files = {DATASET_LISTING: listing_bytes(gt.files)}
    if predictions is not None:
        proot = Path(predictions).resolve()
        pred = hash_groups(proot, prediction_groups(proot, sets), PREDICTIONS_LISTING, workers)
        record["predictions"] = {**pred.record(), "sets": list(sets)}
        files[PREDICTIONS_LISTING] = listing_bytes(pred.files)
    return Provenance(record, files)


# --------------------------------------------------------------------------------------------
# Report lines
# --------------------------------------------------------------------------------------------


def banner_lines(record: dict[str, Any] | None) -> list[str]:
    """A warning at the top of a report whose dataset was scored unverified (else nothing)."""
    v = (record or {}).get("verification") or {}
    if not v.get("scored_unverified"):
        return []
    return [f"**Unverified dataset, scored with `--unverified`:** {v.get('problem')}. Its ground truths are not known to "
            "reproduce the training video, so this score may not measure what the benchmark measures.", ""]


def report_lines(record: dict[str, Any] | None, metrics_name: str = "metrics.json") -> list[str]:
    """The report's provenance section (what ``metrics.json``'s ``provenance`` holds)."""
    if not record:
        return []
    gt, pr, proto, sc = record["ground_truth"], record.get("predictions"), record["protocol"], record["scorer"]
    v = record.get("verification") or {}
    lines = ["## Provenance", "", "| what | sha256 | files |", "|---|---|---|",
             f"| ground truth `{gt['root']}` | `{gt['sha256']}` | {gt['files']} (`{gt['listing']}`) |"]
    if pr:
        lines.append(f"| predictions `{pr['root']}` | `{pr['sha256']}` | {pr['files']} (`{pr['listing']}`) |")
    lines += ["", f"Dataset verification: {'passed' if v.get('verified') else 'NOT verified: ' + str(v.get('problem'))}. "
              f"Protocol {proto['name']} v{proto['version']} on {len(proto['views'])} views; scorer {sc['package']} "
              f"{sc['version']}" + (f" at commit {sc['git_commit']}" if sc.get("git_commit") else f" ({sc.get('git')})") + ". "
              f"`benchgen score --check {metrics_name}` recomputes every digest and names what changed.", ""]
    return lines


# --------------------------------------------------------------------------------------------
# --check
# --------------------------------------------------------------------------------------------


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
