"""``benchgen generate`` and ``benchgen verify``: the phases of a dataset and their bookkeeping.

Phases (each resumable; every file is written atomically through ``scenecore.dataset``):

1. checks without rendering: the spec, the authored scene's plausibility, the output directory;
2. ``train`` tasks: the training video and each object rendered alone (depth) on every training
   frame -> exact ratio bounds -> ``valid_region.json`` (an empty region stops here);
3. G configurations chosen inside the region (``benchgen.configs``) -> ``configs/GGG/config.json``;
4. ``test`` tasks: every configuration's missing test views;
5. ``verify`` tasks: each configuration's training frames re-rendered and compared with the base
   video, its test views compared with configuration 0's -> ``verification.json``.

``video_only`` stops after the training video (``video`` tasks: frames, depth and ids, no
per-object renders): SfM's input at another resolution, read for its frames and masks, its ground
truth only measuring SfM's accuracy. Such a directory has no region, configurations or
verification; running ``generate`` without ``video_only`` on it later renders the rest.
``ground_truth=False`` stops after phase 3: what a method trains on (the video) and what training
is measured against (the region) exist, the configurations' test views and verification do not;
a later full call renders them, so a pipeline can train while they render (``osn demo``).

Tasks run on a ``Worker`` holding one Blender scene (:mod:`benchgen.render.workers`):
in-process, in N spawned processes (``--workers``), or in N Ray actors (``--executor ray``; the
output directory must then be on a file system shared by the cluster). Results never depend on
how frames are sharded: emission-only materials make renders bit-identical across processes.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scenecore import dataset as D
from scenecore.cli import UserError
from scenecore.lock import output_lock
from benchgen.scene.configs import choose_configurations
from benchgen.scene.geometry import BuiltScene, build_scene
from benchgen.scene.plausibility import PlausibilityChecker, check_authored_scene, room_scale_limits
from benchgen.scene.spec import SceneSpec, dump_spec, read_spec_yaml, spec_from_dict
from scenecore.validity import EmptyRegionError, ValidRegion
from benchgen.render.verify import summarise, thresholds
from benchgen.render.workers import Executor, Task, TaskResult

#: Hidden directory inside a dataset for resumable bookkeeping (per-configuration verification).
STATE_DIR = ".benchgen"
#: Test views per task: small enough to balance workers and update progress often.
TEST_CHUNK = 15


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled, leave=False, dynamic_ncols=True)


def _chunks(items: list[str], n: int) -> list[list[str]]:
    return [items[i : i + n] for i in range(0, len(items), n)]


@dataclass
class Summary:
    """What a generate or verify run did, for the final report."""

    root: str
    frames_rendered: int = 0
    render_seconds: float = 0.0
    wall_seconds: float = 0.0
    workers: int = 1
    intervals: list[list[float]] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    verification: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    video_only: bool = False
    ground_truth: bool = True

    @property
    def passed(self) -> bool:
        """Every configuration verified; for a training video alone, or a dataset stopped before
        its ground truths (``ground_truth=False``), that what was asked for was written."""
        return self.video_only or not self.ground_truth or bool(self.verification.get("passed"))

    def add(self, r: TaskResult) -> None:
        self.frames_rendered += r.rendered
        self.render_seconds += r.render_seconds

    def lines(self) -> list[str]:
        ratio = self.wall_seconds * self.workers / self.render_seconds if self.render_seconds else float("nan")
        out = [
            f"{self.root}: rendered {self.frames_rendered} frames in {self.wall_seconds:.1f} s wall "
            f"({self.render_seconds:.1f} s inside Cycles on {self.workers} worker(s); wall x workers / render = {ratio:.2f})"
        ]
        for name, (lo, hi) in zip(self.names, self.intervals):
            out.append(f"  scale interval of {name!r}: ({lo:.4g}, {hi:.4g})")
        cfgs = self.verification.get("configurations", [])
        bad = [c for c in cfgs if not c["passed"]]
        if cfgs:
            worst = max(c["max_interior_diff"] for c in cfgs)
            out.append(
                f"  verification: {len(cfgs) - len(bad)}/{len(cfgs)} configurations pass "
                f"(largest interior difference {worst:.2g})"
            )
        for c in bad:
            out.append(f"  FAILED configuration {c['index']:03d}: {'; '.join(c['failures'])}")
        out.extend(f"  note: {n}" for n in self.notes)
        return out


# --------------------------------------------------------------------------------------------
# generate / verify
# --------------------------------------------------------------------------------------------


def _check_output(root: Path, spec_text: str) -> None:
    if root.exists() and not root.is_dir():
        raise UserError(f"{root}: exists and is not a directory; choose another --out")
    existing = root / "spec.yaml"
    if existing.exists() and existing.read_text() != spec_text:
        raise UserError(f"{root} holds a dataset generated from a different spec or options; choose another --out")
    # A run killed while writing spec.yaml, its first file, leaves only that write's temporary.
    if not existing.exists() and root.exists() and any(not _TEMP_FILE.match(p.name) for p in root.iterdir()):
        raise UserError(f"{root} is not empty and holds no benchgen dataset; choose another --out")


#: Temporary files of ``scenecore.atomic``'s atomic writes (``.NAME.RANDOM.tmp`` / ``.exr``).
_TEMP_FILE = re.compile(r"^\..+\.[^.]+\.(tmp|exr)$")


def _remove_stale_temp_files(root: Path) -> int:
    """A killed run can leave the temporary half of an atomic write behind; remove them."""
    stale = [p for p in root.rglob(".*") if p.is_file() and _TEMP_FILE.match(p.name)]
    for p in stale:
        p.unlink()
    return len(stale)


def prepare(spec: SceneSpec) -> tuple[BuiltScene, np.ndarray]:
    """Build the scene and run every check that needs no rendering; returns room scale limits."""
    try:
        built = build_scene(spec)
    except ValueError as e:  # bad geometry; object_geometry turns every mesh-loading failure into one
        raise UserError(f"{spec.source}: {e}") from None
    check_authored_scene(built)
    return built, room_scale_limits(built)


def _verify_all(
    ex: Executor, built: BuiltScene, root: Path, configs: np.ndarray, summary: Summary, progress: bool, use_cache: bool
) -> dict[str, Any]:
    state = root / STATE_DIR / "verify"
    results: dict[int, dict[str, Any]] = {}
    tasks = []
    test_names = [f.name for f in built.scene.test_frames]
    for g, s in enumerate(configs):
        cached = state / f"{D.config_dirname(g)}.json"
        if use_cache and cached.exists():
            # A verdict is reused only under the thresholds it was reached with.
            entry = D.read_json(cached)
            if entry.get("thresholds") == thresholds() and "result" in entry:
                results[g] = entry["result"]
                continue
        tasks.append(Task("verify", test_names, g, s.tolist(), configs[0].tolist()))
    T = len(built.scene.train_frames)
    with _progress(len(tasks) * T, "verify", progress) as bar:
        for r in ex.map(tasks):
            summary.add(r)
            g = r.task.config
            results[g] = summarise(g, configs[g], r.train_stats, r.test_stats)
            if use_cache:
                D.atomic_write_json(state / f"{D.config_dirname(g)}.json", {"thresholds": thresholds(), "result": results[g]})
            bar.update(T)
    cfgs = [results[g] for g in range(len(configs))]
    return {"passed": all(c["passed"] for c in cfgs), "thresholds": thresholds(), "configurations": cfgs}


def _store_covisibility(root: Path, workers: int, progress: bool, summary: Summary) -> None:
    """Compute and store every configuration's co-visibility masks that are not stored yet
    (``configs/GGG/covisibility.npz``): they depend on the dataset only, so ``benchgen score``
    reads them instead of recomputing them. Local processes (numpy), whatever the executor."""
    from benchgen.score.covisibility_store import merge_into_verification, stored_status, write_masks

    t0 = time.perf_counter()
    n = write_masks(root, workers, progress)
    if n:
        summary.notes.append(f"co-visibility masks stored for {n} configuration(s) in {time.perf_counter() - t0:.1f} s")
    if summary.verification:  # the same record `benchgen verify` writes after recomputing them
        summary.notes += merge_into_verification(summary.verification, stored_status(root))


def _check_covisibility(root: Path, workers: int, progress: bool, summary: Summary) -> None:
    """Recompute every stored co-visibility mask and compare (a difference fails its configuration)."""
    from benchgen.score.covisibility_store import check_masks, merge_into_verification

    summary.notes += merge_into_verification(summary.verification, check_masks(root, workers, progress))


def generate(
    spec: SceneSpec, root: str | Path, workers: int = 1, executor: str = "local", address: str | None = None,
    progress: bool = True, video_only: bool = False, ground_truth: bool = True,
) -> Summary:
    """Generate (or finish) a dataset; see the module docstring for the phases (``video_only``:
    the training video alone; ``ground_truth=False``: stop once the region and the configurations
    are written, before their test views and verification)."""
    t0 = time.perf_counter()
    root = Path(root)
    built, room_limits = prepare(spec)
    with output_lock(root):  # before the clean-up: another run's temporary files are live
        return _generate_locked(spec, root, built, room_limits, t0, workers, executor, address, progress, video_only, ground_truth)


def _generate_locked(
    spec: SceneSpec, root: Path, built: BuiltScene, room_limits: np.ndarray, t0: float, workers: int, executor: str,
    address: str | None, progress: bool, video_only: bool, ground_truth: bool,
) -> Summary:
    """:func:`generate` once it holds ``root``'s lock."""
    spec_text = dump_spec(spec)
    _check_output(root, spec_text)
    if root.exists():
        _remove_stale_temp_files(root)
    D.atomic_write_bytes(root / "spec.yaml", spec_text.encode())
    scene = built.scene
    D.write_scene(root, scene)
    names = [g.name for g in built.objects]
    summary = Summary(str(root), workers=workers, names=names, video_only=video_only, ground_truth=ground_truth)
    with Executor(spec, root, workers, executor, address) as ex:
        train = [f.name for f in scene.train_frames]
        if video_only:
            todo = [n for n in train if not D.frame_paths(root, n).exist()]
            with _progress(len(todo), "training video", progress) as bar:
                for r in ex.map(Task("video", s) for s in _chunks(todo, max(1, -(-len(todo) // workers)))):
                    summary.add(r)
                    bar.update(len(r.task.frames))
            summary.wall_seconds = time.perf_counter() - t0
            return summary
        have_region = (root / "valid_region.json").exists() and all(D.frame_paths(root, n).exist() for n in train)
        if have_region:
            region = D.load_valid_region(root, scene.num_objects)
        else:
            bounds = np.full((len(names), len(names)), np.inf)
            shards = _chunks(train, max(1, -(-len(train) // workers)))
            with _progress(len(train), "training video + per-object depth", progress) as bar:
                for r in ex.map(Task("train", s) for s in shards):
                    summary.add(r)
                    bounds = np.minimum(bounds, r.bounds)
                    bar.update(len(r.task.frames))
            try:
                region = ValidRegion.from_bounds(bounds, anchor=scene.anchor_id)
            except EmptyRegionError as e:
                raise UserError(f"{spec.source}: {e}; nothing was rendered beyond the training video") from None
            D.write_valid_region(root, region)
        summary.intervals = region.intervals.tolist()
        try:
            configs = choose_configurations(
                region, room_limits, PlausibilityChecker(built).problem, spec.configs, spec.margin,
                tuple(spec.scale_range), spec.candidates, spec.seed, names,
            )
        except ValueError as e:
            raise UserError(f"{spec.source}: {e}") from None
        for g, s in enumerate(configs):
            D.write_configuration(root, D.Configuration(g, s))
        if not ground_truth:
            summary.wall_seconds = time.perf_counter() - t0
            return summary
        tests = [f.name for f in scene.test_frames]
        todo = [
            Task("test", chunk, g, s.tolist())
            for g, s in enumerate(configs)
            for chunk in _chunks([n for n in tests if not D.frame_paths(root, n, g).exist()], TEST_CHUNK)
        ]
        with _progress(sum(len(t.frames) for t in todo), "test views", progress) as bar:
            for r in ex.map(todo):
                summary.add(r)
                bar.update(len(r.task.frames))
        summary.verification = _verify_all(ex, built, root, configs, summary, progress, use_cache=True)
    _store_covisibility(root, workers, progress, summary)
    D.write_verification(root, summary.verification)
    scene = D.with_depth_range(root, scene)  # near / far enclosing every ground-truth depth
    D.write_scene(root, scene)
    try:
        D.write_transforms_json(root, scene)
    except D.DatasetError as e:  # e.g. one timestamp: the dataset is complete, only the interop files are impossible
        summary.notes.append(f"no transforms_*.json (D-NeRF / nerfstudio): {e}")
    summary.wall_seconds = time.perf_counter() - t0
    return summary


def verify_dataset(root: str | Path, workers: int = 1, executor: str = "local", address: str | None = None, progress: bool = True) -> Summary:
    """Re-render every configuration's training frames from ``spec.yaml`` and compare (no cache)."""
    t0 = time.perf_counter()
    root = Path(root)
    spec_path = root / "spec.yaml"
    if not spec_path.exists():
        raise UserError(f"{spec_path}: missing; verify needs the spec the dataset was generated from")
    with output_lock(root):  # it rewrites verification.json, which a generate of root also writes
        return _verify_locked(root, spec_path, workers, executor, address, progress, t0)


def _verify_locked(root: Path, spec_path: Path, workers: int, executor: str, address: str | None, progress: bool,
                   t0: float) -> Summary:
    spec = spec_from_dict(read_spec_yaml(spec_path), str(spec_path))
    built, _ = prepare(spec)
    scene = D.load_scene(root)
    configs = np.stack([c.scales for c in D.load_configurations(root, scene)])
    summary = Summary(str(root), workers=workers, names=[g.name for g in built.objects])
    summary.intervals = D.load_valid_region(root, scene.num_objects).intervals.tolist()
    with Executor(spec, root, workers, executor, address) as ex:
        summary.verification = _verify_all(ex, built, root, configs, summary, progress, use_cache=False)
    _check_covisibility(root, workers, progress, summary)
    D.write_verification(root, summary.verification)
    summary.wall_seconds = time.perf_counter() - t0
    return summary
