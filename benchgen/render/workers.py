"""What renders a dataset: tasks, the ``Worker`` that runs them on one Blender scene, and the
``Executor`` that shares them among workers (in-process, N spawned processes, or N Ray actors).

Results never depend on how frames are sharded: emission-only materials make renders
bit-identical across processes. bpy is imported only by processes that render.
"""

from __future__ import annotations

import multiprocessing
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator

import numpy as np

from scenecore import dataset as D
from scenecore.cli import UserError
from scenecore.dataset.model import Frame
from scenecore.validity import accumulate_ratio_bounds
from benchgen.scene.geometry import BuiltScene, build_scene
from benchgen.scene.spec import SceneSpec, spec_from_dict
from benchgen.render.verify import compare_training, test_difference

if TYPE_CHECKING:  # bpy is imported only by processes that render
    from benchgen.render.blender import RenderOutput, Renderer

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
