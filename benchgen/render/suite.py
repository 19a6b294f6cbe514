"""``benchgen suite``: generate every paper-style preset and tabulate what each benchmark is.

One dataset per preset under ``OUT/<preset>`` (each resumable exactly like ``benchgen generate``),
then one table, printed and written to ``OUT/suite.json`` and ``OUT/suite.md`` after every preset
(so a killed run keeps the rows it finished). Per preset: objects, training / test frames, the
exact valid region's share of the paper's sampling box (Eq. 1, from each object's depth range in
the training video), its narrowest and widest per-object interval inside that box, verification
and the wall time spent generating (summed over resumed runs).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.lock import output_lock
from scenecore.scale_space import eq1_box
from scenecore.validity import box_share
from benchgen.render.generate import generate
from benchgen.scene.spec import SceneSpec, load_preset

#: The paper's scene suite: the Dynamic Indoor Scene protocol's four scenes, Chessboard++ with
#: objects leaving the view, two Oxford-Multimotion-style stereo scenes and an NVIDIA-style
#: multi-camera scene.
SUITE_PRESETS = ("gnome-house", "dining-table", "chessboard", "factory", "chessboard-8", "swinging-cubes", "occlusion-tower", "balloons")
#: Monte Carlo points for the region's share of the Eq. 1 box (its standard error is reported).
SHARE_SAMPLES = 200_000


@dataclass
class SuiteRow:
    """One preset's dataset, as the table shows it."""

    preset: str
    protocol: str
    objects: int
    train_frames: int
    test_frames: int
    resolution: int
    share: float
    share_stderr: float
    narrowest: str
    widest: str
    configurations: int
    verified: int
    seconds: float

    @property
    def passed(self) -> bool:
        return self.configurations > 0 and self.verified == self.configurations


def depth_ranges(root: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(K,)`` nearest and farthest planar depth of each object where it is visible in the training video.

    Raises:
        ValueError: an object is visible in no training frame (Eq. 1 has no range for it).
    """
    scene = D.load_scene(root)
    K = len(scene.objects)
    near, far = np.full(K, np.inf), np.zeros(K)
    for f in scene.train_frames:
        paths = D.frame_paths(root, f.name)
        ids, depth = D.read_ids(paths.ids), D.read_depth(paths.depth)
        for k in np.unique(ids[ids < K]):
            d = depth[ids == k]
            near[k], far[k] = min(near[k], float(d.min())), max(far[k], float(d.max()))
    missing = [scene.objects[k].name for k in range(K) if not np.isfinite(near[k])]
    if missing:
        raise ValueError(f"{root}: object(s) {missing} visible in no training frame")
    return near, far


def _interval_text(name: str, lo: float, hi: float) -> str:
    return f"{name} [{lo:.3g}, {hi:.3g}]"


def dataset_row(preset: str, root: str | Path, seconds: float, protocol: str) -> SuiteRow:
    """The table row of a generated dataset (reads its manifest, region, depths and verification)."""
    root = Path(root)
    scene, region = D.load_scene(root), D.load_valid_region(root)
    near, far = depth_ranges(root)
    box = eq1_box(near, far)
    share, err = box_share(region, box, samples=SHARE_SAMPLES)
    # Each object's valid interval inside its Eq. 1 range, ranked by log width (the anchor is fixed).
    lo, hi = np.maximum(region.intervals[:, 0], box[:, 0]), np.minimum(region.intervals[:, 1], box[:, 1])
    free = [k for k in range(len(scene.objects)) if k != region.anchor]
    width = {k: np.log(hi[k] / lo[k]) if hi[k] > lo[k] else -np.inf for k in free}
    k_min, k_max = min(free, key=width.get), max(free, key=width.get)
    cfgs = D.read_json(root / "verification.json").get("configurations", []) if (root / "verification.json").is_file() else []
    return SuiteRow(
        preset=preset,
        protocol=protocol,
        objects=len(scene.objects) - 1,
        train_frames=len(scene.train_frames),
        test_frames=len(scene.test_frames),
        resolution=scene.width,
        share=share,
        share_stderr=err,
        narrowest=_interval_text(scene.objects[k_min].name, lo[k_min], hi[k_min]),
        widest=_interval_text(scene.objects[k_max].name, lo[k_max], hi[k_max]),
        configurations=len(cfgs),
        verified=sum(bool(c["passed"]) for c in cfgs),
        seconds=seconds,
    )


def table_lines(rows: Sequence[SuiteRow]) -> list[str]:
    """A Markdown table of the rows (what ``suite.md`` holds and the command prints)."""
    out = [
        "| preset | rig | objects | train / test frames | px | valid share of Eq. 1 box | narrowest interval | widest interval | verified | time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r.preset} | {r.protocol} | {r.objects} | {r.train_frames} / {r.test_frames} | {r.resolution} | "
            f"{r.share:.3g} ± {r.share_stderr:.1g} | {r.narrowest} | {r.widest} | {r.verified}/{r.configurations} | {r.seconds:.0f} s |"
        )
    return out


def run_suite(
    out: str | Path,
    presets: Sequence[str | SceneSpec] = SUITE_PRESETS,
    resolution: int | None = None,
    configs: int | None = None,
    workers: int = 1,
    executor: str = "local",
    address: str | None = None,
    progress: bool = True,
    echo: Callable[[str], None] = print,
) -> list[SuiteRow]:
    """Generate (or finish) every preset (a name, or a spec such as a procedural scene, under its
    name) under ``out`` and write the table; returns its rows."""
    out = Path(out)
    specs = {p if isinstance(p, str) else p.name: (load_preset(p) if isinstance(p, str) else p).with_overrides(resolution=resolution, configs=configs)
             for p in presets}  # bad names fail before any render
    with output_lock(out):  # suite.json and suite.md; each dataset under it has its own lock
        return _run_suite_locked(out, specs, workers, executor, address, progress, echo)


def _run_suite_locked(out: Path, specs: dict[str, SceneSpec], workers: int, executor: str, address: str | None,
                      progress: bool, echo: Callable[[str], None]) -> list[SuiteRow]:
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "suite.json"
    previous = {r["preset"]: r for r in (D.read_json(state_path)["rows"] if state_path.is_file() else [])}
    rows: list[SuiteRow] = []
    for preset, spec in specs.items():
        t0 = time.perf_counter()
        summary = generate(spec, out / preset, workers, executor, address, progress=progress)
        for line in summary.lines():
            echo(line)
        # A resumed preset adds this run's time to what earlier runs spent on it.
        before = previous.get(preset, {})
        spent = time.perf_counter() - t0 + (before.get("seconds", 0.0) if before.get("resolution") == spec.width else 0.0)
        rows.append(dataset_row(preset, out / preset, spent, spec.rig.protocol))
        D.atomic_write_json(state_path, {"rows": [asdict(r) for r in rows] + [r for p, r in previous.items() if p not in {x.preset for x in rows}]})
        D.atomic_write_bytes(out / "suite.md", ("\n".join(table_lines(rows)) + "\n").encode())
    for line in table_lines(rows):
        echo(line)
    return rows
