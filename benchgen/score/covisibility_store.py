"""Co-visibility masks stored in the dataset: computed by ``benchgen generate``, recomputed and
compared by ``benchgen verify``, read by ``benchgen score``.

The masks depend on the dataset only (ground-truth depth and ids, poses, scales), and computing
them is most of the cost of reading the ground truth at the paper's size (10,500 masks at 128 px).
The file format is :mod:`scenecore.dataset.covisibility`'s; the rule is
:func:`covisibility.configuration_masks` under :data:`covisibility.RULE_VERSION` and
:data:`covisibility.DEPTH_RTOL`, both stored beside the masks. Masks stored under another rule are
not used (the scorer computes them and says so). Numpy only: the work runs in forked processes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.dataset.covisibility import covisibility_frames, read_covisibility, write_covisibility
from benchgen.score import covisibility as C
from benchgen.score.parallel import ordered_map


def compute(root: Path, scene: D.Scene, scales: np.ndarray, config: int, train: tuple[np.ndarray, np.ndarray],
            frames: Sequence[D.Frame] | None = None) -> np.ndarray:
    """Configuration ``config``'s masks ``(V, H, W)`` on ``frames`` (default: every test frame in
    the stored order, :func:`covisibility_frames`), from its ground-truth depth and ids and the
    training video's ``train = (depth, ids)`` in time order."""
    frames = covisibility_frames(scene) if frames is None else frames
    depth, ids = zip(*(D.read_frame(root, f.name, config, scene=scene)[1:] for f in frames))
    return C.configuration_masks(scene, scales, frames, np.stack(depth), np.stack(ids), *train)


def stored(root: Path, scene: D.Scene, config: int, frames: Sequence[D.Frame]) -> tuple[np.ndarray | None, str]:
    """Configuration ``config``'s stored masks on ``frames`` ``(V, H, W)``, or None and why not
    (no file; a file of another rule). A corrupt or wrong-size file raises ``DatasetError`` (one
    line naming it): masks that cannot be trusted are not silently replaced."""
    try:
        m = read_covisibility(root, scene, config)
    except FileNotFoundError:
        return None, "absent"
    if (m.version, m.rtol) != (C.RULE_VERSION, C.DEPTH_RTOL):
        return None, f"rule version {m.version} rtol {m.rtol:g} (the scorer's: {C.RULE_VERSION}, {C.DEPTH_RTOL:g})"
    row = {f.name: i for i, f in enumerate(covisibility_frames(scene))}
    return m.masks[[row[f.name] for f in frames]], "stored"


# Set before forking workers (:func:`parallel.ordered_map`), so that they inherit it unpickled.
_JOB: dict[str, Any] = {}


def _setup(root: Path) -> tuple[D.Scene, np.ndarray]:
    scene = D.load_scene(root)
    configs = D.load_configurations(root, scene)
    _, t_depth, t_ids = D.read_training_video(root, scene)
    scales = np.stack([c.scales for c in configs]) if configs else np.zeros((0, scene.num_objects))
    _JOB.update(root=root, scene=scene, scales=scales, train=(t_depth, t_ids))
    return scene, scales


def _compute_job(g: int) -> np.ndarray:
    return compute(_JOB["root"], _JOB["scene"], _JOB["scales"][g], g, _JOB["train"])


def _is_current(root: Path, scene: D.Scene, g: int) -> bool:
    """A readable mask file of the current rule exists for configuration ``g``."""
    try:
        m = read_covisibility(root, scene, g)
    except (FileNotFoundError, D.DatasetError):
        return False
    return (m.version, m.rtol) == (C.RULE_VERSION, C.DEPTH_RTOL)


def write_masks(root: str | Path, workers: int = 1, progress: bool = False) -> int:
    """Compute and store the masks of every configuration that has no readable file of the
    current rule (so a rerun of ``benchgen generate`` resumes, and adds them to an older dataset);
    ``workers`` processes. Returns how many configurations were written."""
    from tqdm import tqdm

    root = Path(root)
    try:
        scene, _ = _setup(root)
        todo = [g for g in range(scene.num_configurations) if not _is_current(root, scene, g)]
        with tqdm(total=len(todo), desc="co-visibility masks", unit="config", disable=not progress, leave=False,
                  dynamic_ncols=True) as bar:
            for g, masks in zip(todo, ordered_map(_compute_job, [(g,) for g in todo], workers)):
                write_covisibility(root, g, scene, masks, C.RULE_VERSION, C.DEPTH_RTOL)
                bar.update()
    finally:
        _JOB.clear()
    return len(todo)


def stored_status(root: str | Path) -> list[dict[str, Any]]:
    """Per configuration, ``match`` where a readable mask file of the current rule is stored (as
    generation writes it: computed by this code from these depths, so equal to a recomputation),
    else ``absent``; the records :func:`merge_into_verification` takes, so that generation and
    ``benchgen verify`` write the same ``verification.json``."""
    root = Path(root)
    scene = D.load_scene(root)
    return [{"index": g, "status": "match" if _is_current(root, scene, g) else "absent"}
            for g in range(scene.num_configurations)]


def _check_job(g: int) -> dict[str, Any]:
    """Configuration ``g``'s stored masks against a recomputation: ``status`` is ``match``,
    ``differs`` (with the first differing view and the count of differing pixels), ``absent``,
    ``unreadable`` (with the reader's line) or ``other rule``."""
    root, scene = _JOB["root"], _JOB["scene"]
    try:
        m = read_covisibility(root, scene, g)
    except FileNotFoundError:
        return {"index": g, "status": "absent"}
    except D.DatasetError as e:
        return {"index": g, "status": "unreadable", "detail": str(e)}
    if (m.version, m.rtol) != (C.RULE_VERSION, C.DEPTH_RTOL):
        return {"index": g, "status": "other rule", "detail": f"{m.path}: rule version {m.version} rtol {m.rtol:g}, "
                f"the current rule is {C.RULE_VERSION} rtol {C.DEPTH_RTOL:g}"}
    fresh = _compute_job(g)
    differ = (fresh != m.masks).reshape(len(fresh), -1).sum(1)
    if not differ.any():
        return {"index": g, "status": "match"}
    v = int(np.flatnonzero(differ)[0])
    name = covisibility_frames(scene)[v].name
    return {"index": g, "status": "differs", "differing_pixels": int(differ.sum()),
            "detail": f"{m.path}: view {name} differs from the recomputed mask in {int(differ[v])} pixel(s) "
                      f"({int(differ.sum())} over all views)"}


def check_masks(root: str | Path, workers: int = 1, progress: bool = False) -> list[dict[str, Any]]:
    """Per configuration, :func:`_check_job`'s verdict (recomputing every stored mask)."""
    from tqdm import tqdm

    root = Path(root)
    try:
        scene, _ = _setup(root)
        G = scene.num_configurations
        with tqdm(total=G, desc="co-visibility masks", unit="config", disable=not progress, leave=False,
                  dynamic_ncols=True) as bar:
            out = []
            for r in ordered_map(_check_job, [(g,) for g in range(G)], workers):
                out.append(r)
                bar.update()
    finally:
        _JOB.clear()
    return out


def merge_into_verification(verification: dict[str, Any], checks: list[dict[str, Any]]) -> list[str]:
    """Add each configuration's mask check to ``verification`` (``covisibility`` per configuration
    and ``covisibility_masks`` overall): stored masks that differ from the recomputation or cannot
    be read fail their configuration. Returns notes for the summary (absent or other-rule masks,
    which the scorer computes itself)."""
    by_index = {c["index"]: c for c in verification.get("configurations", [])}
    for r in checks:
        c = by_index.get(r["index"])
        if c is None:
            continue
        c["covisibility"] = r["status"]
        if r["status"] in ("differs", "unreadable"):
            c["passed"] = False
            c.setdefault("failures", []).append(f"co-visibility masks: {r['detail']}")
    statuses = sorted({r["status"] for r in checks})
    verification["covisibility_masks"] = statuses[0] if len(statuses) == 1 else "mixed" if statuses else "absent"
    if by_index:
        verification["passed"] = all(c["passed"] for c in by_index.values())
    notes = []
    absent = [r["index"] for r in checks if r["status"] == "absent"]
    if absent:
        notes.append(f"{len(absent)} of {len(checks)} configurations store no co-visibility masks (rerun 'benchgen "
                     "generate' with the same options to add them; 'benchgen score' computes them meanwhile)")
    notes += [r["detail"] + " ('benchgen score' computes them; rerun 'benchgen generate' to refresh)"
              for r in checks if r["status"] == "other rule"][:1]
    return notes
