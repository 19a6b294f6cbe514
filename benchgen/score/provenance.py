"""Provenance of a score (docs/predictions.md, "Provenance and re-checking a score").

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

How files are hashed is :mod:`benchgen.score.digests`'s; :mod:`benchgen.score.check` recomputes
the digests from the directories recorded (or given) and returns one line per difference.
"""

from __future__ import annotations

import functools
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

from scenecore import dataset as D
from benchgen.score.digests import DATASET_LISTING, PREDICTIONS_LISTING, file_sha256, hash_groups, listing_bytes

PROTOCOL_NAME = "benchgen-best-of-n"
#: Bumped when what a score means changes (matching, masks or a metric's definition).
PROTOCOL_VERSION = 1
VERIFICATION = "verification.json"
UNVERIFIED_HINT = "pass --unverified to score it anyway"


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
