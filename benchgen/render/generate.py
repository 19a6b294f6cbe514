"""``benchgen generate`` and ``benchgen verify``: orchestration, workers and executors.

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

Tasks run on a ``Worker`` holding one Blender scene: in-process, in N spawned processes
(``--workers``), or in N Ray actors (``--executor ray``; the output directory must then be on a
file system shared by the cluster). Results never depend on how frames are sharded: emission-only
materials make renders bit-identical across processes.
"""

from __future__ import annotations

import multiprocessing
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator

import numpy as np

from scenecore import dataset as D
from scenecore.cli import UserError
from scenecore.lock import output_lock
from benchgen.scene.configs import choose_configurations
from benchgen.scene.geometry import BuiltScene, build_scene
from benchgen.scene.plausibility import PlausibilityChecker, check_authored_scene, room_scale_limits
from benchgen.scene.spec import SceneSpec, dump_spec, read_spec_yaml, spec_from_dict
from scenecore.validity import EmptyRegionError, ValidRegion, accumulate_ratio_bounds
from benchgen.render.verify import compare_training, summarise, test_difference, thresholds
from scenecore.dataset.model import Frame

if TYPE_CHECKING:  # bpy is imported only by processes that render
    from benchgen.render.blender import RenderOutput, Renderer

#: Hidden directory inside a dataset for resumable bookkeeping (per-configuration verification).
STATE_DIR = ".benchgen"
#: Test views per task: small enough to balance workers and update progress often.
TEST_CHUNK = 15
#: Samples for the per-object depth renders: depth and ids come from one ray per pixel anyway.
ALONE_SAMPLES = 1


def render_with_alone_depths(renderer: Renderer, built: BuiltScene, frame: Frame) -> tuple[RenderOutput, np.ndarray]:
    """One training ``frame``: its full render and every object's planar depth rendered alone,
    ``(K, H, W)`` (``inf`` where the object does not cover the pixel): the exact region's inputs.

    Raises:
        RuntimeError: the per-object renders do not trace the full render's ray per pixel (the
            bounds are exact only if they do: checked rather than assumed).
    """
    K = len(built.objects)
    poses = built.poses(frame.time_index)
    full = renderer.render(frame.camera_to_world, poses)
    alone = np.stack([renderer.render(frame.camera_to_world, poses, ALONE_SAMPLES, only=k).depth for k in range(K)])
    hit = full.ids != D.NO_OBJECT
    seen_depth = np.take_along_axis(alone, np.minimum(full.ids, K - 1)[None].astype(np.int64), 0)[0]
    if not np.allclose(seen_depth[hit], full.depth[hit], rtol=1e-5):
        raise RuntimeError(f"frame {frame.name}: per-object depth renders disagree with the full render")
    return full, alone


@dataclass
class Task:
    """A unit of work: ``kind`` in {train, video, test, verify}; ``config`` and its ``scales``; frame names."""

    kind: str
    frames: list[str]
    config: int | None = None
    scales: list[float] | None = None
    reference: list[float] | None = None  # configuration 0's scales, for verify


@dataclass
class TaskResult:
    task: Task
    rendered: int
    render_seconds: float
    bounds: np.ndarray | None = None
    train_stats: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    test_stats: list[tuple[str, int, int]] = field(default_factory=list)


class Worker:
    """One Blender scene (created lazily) that executes tasks against a dataset directory."""

    def __init__(self, spec_data: dict[str, Any], source: str, root: str, threads: int | None = None):
        self.built = build_scene(spec_from_dict(spec_data, source))
        self.root = Path(root)
        self.threads = threads
        self._renderer = None
        self._base: dict[str, Any] = {}
        self._reference: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.frames = {f.name: f for f in self.built.scene.frames}

    @property
    def renderer(self):
        if self._renderer is None:
            from benchgen.render.blender import Renderer  # bpy is imported only by processes that render

            self._renderer = Renderer(self.built, self.threads)
        return self._renderer

    def run(self, task: Task) -> TaskResult:
        r = self.renderer
        calls, secs = r.render_calls, r.render_seconds
        result = getattr(self, f"_{task.kind}")(task)
        result.rendered, result.render_seconds = r.render_calls - calls, r.render_seconds - secs
        return result

    def _train(self, task: Task) -> TaskResult:
        K = len(self.built.objects)
        bounds = np.full((K, K), np.inf)
        for name in task.frames:
            full, alone = render_with_alone_depths(self.renderer, self.built, self.frames[name])
            if not D.frame_paths(self.root, name).exist():
                D.write_frame(self.root, name, full.rgb8(), full.depth, full.ids)
            accumulate_ratio_bounds(bounds, full.ids, alone, where=f"frame {name}")
        return TaskResult(task, 0, 0.0, bounds=bounds)

    def _video(self, task: Task) -> TaskResult:
        for name in task.frames:
            if not D.frame_paths(self.root, name).exist():
                f = self.frames[name]
                full = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index))
                D.write_frame(self.root, name, full.rgb8(), full.depth, full.ids)
        return TaskResult(task, 0, 0.0)

    def _test(self, task: Task) -> TaskResult:
        for name in task.frames:
            if D.frame_paths(self.root, name, task.config).exist():
                continue
            f = self.frames[name]
            out = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index, np.asarray(task.scales)))
            D.write_frame(self.root, name, out.rgb8(), out.depth, out.ids, config=task.config)
        return TaskResult(task, 0, 0.0)

    def _base_frame(self, name: str):
        if name not in self._base:
            f = self.frames[name]
            self._base[name] = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index))
        return self._base[name]

    def _verify(self, task: Task) -> TaskResult:
        res = TaskResult(task, 0, 0.0)
        scales = np.asarray(task.scales)
        for f in self.built.scene.train_frames:
            base = self._base_frame(f.name)
            out = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index, scales))
            res.train_stats.append((f.name, compare_training(base.rgb, base.ids, out.rgb, out.ids, base.facing, out.facing)))
        if task.config:
            scaled = np.abs(np.log(scales) - np.log(np.asarray(task.reference))) > 1e-9
            for name in task.frames:
                if name not in self._reference:
                    self._reference[name] = D.read_frame(self.root, name, 0)
                seen, differ = test_difference(self._reference[name], D.read_frame(self.root, name, task.config), scaled)
                res.test_stats.append((name, seen, differ))
        return res


# --------------------------------------------------------------------------------------------
# Executors
# --------------------------------------------------------------------------------------------

_WORKER: Worker | None = None


def _init_process(spec_data: dict[str, Any], source: str, root: str, threads: int | None) -> None:
    global _WORKER
    _WORKER = Worker(spec_data, source, root, threads)


def _run_in_process(task: Task) -> TaskResult:
    assert _WORKER is not None
    return _WORKER.run(task)


class Executor:
    """Runs tasks on ``workers`` Blender scenes and yields results as they finish."""

    def __init__(self, spec: SceneSpec, root: Path, workers: int = 1, executor: str = "local", address: str | None = None):
        if workers < 1:
            raise UserError(f"--workers must be >= 1, got {workers}")
        self.workers = workers
        threads = max(1, (os.cpu_count() or 1) // workers)
        args = (spec.to_dict(), spec.source, str(root), threads)
        self._local: Worker | None = None
        self._pool = None
        self._actors = None
        if executor == "ray":
            try:
                import ray
                from ray.util import ActorPool
            except ImportError:
                raise UserError("--executor ray needs Ray: pip install 'osn-toolkit[ray]'") from None
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
            actor = ray.remote(num_cpus=threads)(Worker)
            self._ray = ray
            self._actors = ActorPool([actor.remote(*args) for _ in range(workers)])
        elif executor != "local":
            raise UserError(f"unknown executor {executor!r} (expected local or ray)")
        elif workers == 1:
            self._local = Worker(*args)
        else:
            ctx = multiprocessing.get_context("spawn")  # bpy is not fork-safe
            self._pool = ctx.Pool(workers, initializer=_init_process, initargs=args)

    def map(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        tasks = list(tasks)
        if self._local is not None:
            return (self._local.run(t) for t in tasks)
        if self._pool is not None:
            return self._pool.imap_unordered(_run_in_process, tasks)
        return self._actors.map_unordered(lambda a, t: a.run.remote(t), tasks)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool.join()
        self._pool = None

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc: Any) -> None:
        if exc[0] is not None and self._pool is not None:
            self._pool.terminate()
        self.close()


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
