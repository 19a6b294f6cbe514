"""Where a pair bound's error comes from: the exact bound's pixels against the final label pool's.

    python benchmarks/bench_bound_pixels.py RUN [RUN ...] [--data DATASET] [--show PAIR ...] [--rows N]
        [--pairs PAIR ...] [--out JSON]

Each ``RUN`` is an ``osn train`` run on ``DATASET`` (default: the one its ``run.json`` names; a
benchgen dataset: its ``spec.yaml`` is rendered again with Blender, so bpy must be installed). Every training frame's per-object depths
are rendered alone (the renders ``benchgen generate`` takes the exact region's bounds from,
``B_ij = min d_j / d_i`` over the pixels showing i, :mod:`scenecore.validity`); each run's final
fields give the label pool the final scale phase labels (:func:`osn.train.labels.build_label_pool`).

Prints per run and pair ``i < j`` (i visible in front of j): the exact bound and over how many
pixels; the pool's rays for the pair, the exact bound over those rays alone and the learned one
(before any trim), the median of learned over exact ratio per ray; how many of the pixels within 1%
of the exact bound are pool rays, and why the others are not (labelled otherwise, an object without
a pose in that frame, the front or the hidden object not covered, dropped by the pool); in the
``--out`` table also how many of the bound's pixels hide a point of the back object that another
frame sees (from the ground truth's poses: whether the video shows what sets the bound). A learned
bound off the exact one is then either the pool lacking the bound's pixels or the fields' depths
at them, and
``--show "ring-toy<gnome"`` lists those pixels with the learned and exact depth of both objects.
Per object, the median relative error of its learned depth (``depth / acc``) on its own visible
pixels (``acc`` above its coverage threshold) against the dataset's depth (docs/experiments/).
Reads the ground truth: a measurement, not part of the method.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import torch

from benchutil import command_line, print_command
from results_json import table, write_results

from osn.preprocess.inputs import ObjectInputs, load_inputs
from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, Trainer
from osn.train.labels import build_label_pool, label_pixels, render_alone_depths
from scenecore.cameras import pixel_rays, project_pixels
from scenecore.dataset.images import read_depth


def exact_depths(data: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per training frame of ``data`` (transforms order): ``alone (T, K, H, W)`` planar depth of
    every object rendered alone (``inf`` where it does not cover the pixel), ``ids (T, H, W)``,
    and the objects' names (index = dataset id)."""
    from benchgen.render.blender import Renderer
    from benchgen.render.workers import render_with_alone_depths
    from benchgen.scene.geometry import build_scene
    from benchgen.scene.spec import read_spec_yaml, spec_from_dict

    spec_path = data / "spec.yaml"
    built = build_scene(spec_from_dict(read_spec_yaml(spec_path), str(spec_path)))
    frames = {f.name: f for f in built.scene.frames}
    renderer = Renderer(built, None)
    alone, ids = [], []
    for entry in json.loads((data / "transforms_train.json").read_text())["frames"]:
        name = Path(entry["file_path"]).name
        full, depths = render_with_alone_depths(renderer, built, frames.get(name) or frames[f"train/{name}"])
        ids.append(full.ids)
        alone.append(depths)
    a = np.stack(alone).astype(np.float64)
    return np.where(np.isfinite(a) & (a > 0), a, np.inf), np.stack(ids), [o.name for o in built.objects]


def seen_elsewhere(pixels: np.ndarray, alone: np.ndarray, ids: np.ndarray, exact: ObjectInputs, j: int,
                   K: np.ndarray, tol: float = 0.02) -> int:
    """How many of ``pixels`` (flat frame * HW + pixel, where object ``j`` is hidden) show a point
    of ``j``'s surface that another training frame sees: the point at ``j``'s exact depth there,
    carried by ``exact``'s poses (the ground truth's, ``cam_to_obj`` in its unit) into each of its
    other frames, lands inside the image on a pixel labelled ``j`` whose exact depth of ``j`` is
    within ``tol`` of the point's. A bound whose hidden pixels no frame sees cannot be learned from
    the video; one whose pixels are seen elsewhere can."""
    T, _, H, W = alone.shape
    t, p = np.asarray(pixels) // (H * W), np.asarray(pixels) % (H * W)
    posed = np.array([exact.frame_slot(int(f)) is not None for f in t], dtype=bool)
    t, p = t[posed], p[posed]
    unit = exact.unit_to_world
    points = np.empty((len(t), 3))  # in the object's frame and unit
    for f in np.unique(t):
        m = t == f
        origin, direction = pixel_rays(K, exact.cam_to_obj[exact.frame_slot(int(f))], W, H, np.stack([p[m] % W, p[m] // W], 1))
        points[m] = origin + (alone[f, j].reshape(-1)[p[m]] / unit)[:, None] * direction
    seen = np.zeros(len(t), dtype=bool)
    for f2 in exact.frames.tolist():
        _, z, pix, inside = project_pixels(points, K, exact.cam_to_obj[exact.frame_slot(f2)], W, H)
        ok = inside & (t != f2)
        x, y, z = pix[ok, 0], pix[ok, 1], z[ok] * unit
        seen[ok] |= (ids[f2, y, x] == j) & (np.abs(alone[f2, j, y, x] - z) < tol * z)
    return int(seen.sum())


def why_not(pixels: np.ndarray, pool: set[int], row_of: np.ndarray, lab: np.ndarray, covered: np.ndarray,
            present: np.ndarray, hw: int, i: int, j: int) -> str:
    """Why the exact bound ``i < j``'s ``pixels`` (flat frame * HW + pixel) are not pool rays,
    counted by the first reason: not a label pixel of i in the inputs (another label, or ignored),
    i or j without a pose in that frame (``present (K, T)``: SfM did not register it there), i's
    field not covering it, j's not covering it, or dropped by the pool (no scale in the box
    explains it, or a minority pair)."""
    reasons = ("labelled otherwise", "front unposed there", "back unposed there", "front not covered",
               "back not covered", "dropped by the pool")
    counts = dict.fromkeys(reasons, 0)
    for q in pixels.tolist():
        if q in pool:
            continue
        row, frame = row_of[q], q // hw
        key = ("labelled otherwise" if row < 0 or lab[row] != i else "front unposed there" if not present[i, frame]
               else "back unposed there" if not present[j, frame] else "front not covered" if not covered[row, i]
               else "back not covered" if not covered[row, j] else "dropped by the pool")
        counts[key] += 1
    return ", ".join(f"{k} {n}" for k, n in counts.items() if n) or "none"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="osn train run directories trained on DATASET")
    ap.add_argument("--data", default=None, help="the benchgen dataset the runs were trained on (default: each run.json's)")
    ap.add_argument("--show", nargs="*", default=[], help='pairs "front<back" whose tightest pixels to list')
    ap.add_argument("--rows", type=int, default=3, help="pixels listed per shown pair (the exact bound's tightest)")
    ap.add_argument("--pairs", nargs="*", default=None, help='pairs "front<back" of the --out table (default: all)')
    ap.add_argument("--out", type=Path, default=None, help="results JSON: per run and pair, the exact bound's pixels "
                    "and why those that are not pool rays are not")
    a = ap.parse_args()
    print_command()
    logging.basicConfig(level=logging.ERROR)
    rows: list[list[str]] = []
    datasets: dict[Path, tuple] = {}
    for run_dir in map(Path, a.runs):
        data = Path(a.data or json.loads((run_dir / "run.json").read_text())["dataset"]).resolve()
        if data not in datasets:  # rendered once per dataset
            alone, ids, names_gt = exact_depths(data)
            frames = json.loads((data / "transforms_train.json").read_text())["frames"]
            truth = np.stack([read_depth(data / "train" / "depth" / (Path(f["file_path"]).name + ".exr")).reshape(-1)
                              for f in frames])
            datasets[data] = (alone, ids, names_gt, truth, oracle_inputs(data))
        alone, ids, names_gt, truth, exact_inputs = datasets[data]
        T, K_gt, H, W = alone.shape
        A = alone.reshape(T, K_gt, H * W)
        vis = ids.reshape(T, H * W)
        cfg = TrainConfig.from_yaml(run_dir / "config.yaml", run_config=True)
        tr = Trainer(load_inputs(run_dir / "inputs"), cfg, torch.device("cpu"))
        tr.load_state_dict(torch.load(run_dir / "checkpoint.pt", weights_only=True))
        st = tr.st
        if (st.H, st.W, st.T) != (H, W, T):
            raise SystemExit(f"{run_dir}: trained on {st.T} frames of {st.W}x{st.H}, {data} has {T} of {W}x{H}")
        names = [o.name for o in st.inputs.objects]
        gt_of = [names_gt.index(n) for n in names]
        units = np.array([o.unit_to_world for o in st.inputs.objects], dtype=np.float64)
        pool = build_label_pool(st, tr.fields, cfg, 0)
        flat = pool["flat"].numpy()
        lp = label_pixels(st, cfg)
        c = render_alone_depths(st, tr.fields, lp, cfg)
        lab, lpn = st.labels.reshape(-1)[lp].numpy(), lp.numpy()
        row_of = np.full(T * H * W, -1)
        row_of[lpn] = np.arange(len(lpn))
        cov_all = c["covered"].numpy()
        fr, px = flat // (H * W), flat % (H * W)
        gt, cov = pool["gt"].numpy(), pool["covered"].numpy()
        d = pool["depth"].numpy().astype(np.float64) * units
        print(f"\n{run_dir}: {len(flat)} pool rays")
        for i in range(st.K):
            for j in range(st.K):
                I, J = gt_of[i], gt_of[j]
                if i == j:
                    continue
                with np.errstate(invalid="ignore"):  # inf / inf where neither covers: masked below
                    r = np.where(vis == I, A[:, J] / A[:, I], np.inf)  # (T, HW) exact ratio where i is visible
                if not np.isfinite(r).any():
                    continue
                B = float(r.min())
                m = (gt == i) & cov[:, j]
                exact_pool, learned = r[fr[m], px[m]], d[m, j] / d[m, i]
                tight = np.argwhere(r < B * 1.01)
                in_pool = {(f, p): n for n, (f, p) in enumerate(zip(fr[m].tolist(), px[m].tolist()))}
                line = f"  {names[i]} < {names[j]}: exact {B:.4f} ({int(np.isfinite(r).sum())} px)"
                if m.any():
                    line += (f" | pool {int(m.sum())} rays: exact {exact_pool.min():.4f}, learned {learned.min():.4f}, "
                             f"learned / exact median {np.median(learned / exact_pool):.4f}")
                print(line + f" | pixels within 1% of the bound {len(tight)}, in the pool "
                      f"{sum((int(f), int(p)) in in_pool for f, p in tight)}")
                why = why_not(np.flatnonzero(np.isfinite(r)), set((f * H * W + p) for f, p in in_pool), row_of, lab,
                              cov_all, st.present.numpy(), H * W, i, j)
                if why != "none":
                    print("    the exact bound's pixels that are not pool rays: " + why)
                if a.out is not None and (a.pairs is None or f"{names[i]}<{names[j]}" in a.pairs):
                    seen = seen_elsewhere(np.flatnonzero(np.isfinite(r)), alone, ids,
                                          next(o for o in exact_inputs.objects if o.id == J), J, exact_inputs.K)
                    rows.append([str(run_dir), f"{names[i]} < {names[j]}", f"{B:.4f}", str(int(np.isfinite(r).sum())),
                                 str(int(m.sum())), why, str(seen)])
                if f"{names[i]}<{names[j]}" not in a.show:
                    continue
                for f, p in sorted(map(tuple, tight.tolist()), key=lambda fp: r[fp])[: a.rows]:
                    n = in_pool.get((f, p))
                    where = (f"learned {learned[n]:.4f}: {names[i]} {d[m][n, i]:.3f}, {names[j]} {d[m][n, j]:.3f}"
                             if n is not None else "not a pool ray (the hidden object not covered, or the ray dropped)")
                    print(f"    frame {f} x {p % W} y {p // W}: exact {r[f, p]:.4f} ({names[i]} {A[f, I, p]:.3f}, "
                          f"{names[j]} {A[f, J, p]:.3f}); {where}")
        errs = []
        for k in range(st.K):
            own = (lab == k) & c["covered"][:, k].numpy()
            e = c["depth"][:, k].numpy()[own] * units[k] / truth[lpn[own] // (H * W), lpn[own] % (H * W)] - 1
            errs.append(f"{names[k]} {np.median(e):+.4f}" if len(e) else f"{names[k]} -")
        print("  learned depth on own visible pixels, median relative error: " + ", ".join(errs))
    if a.out is not None:
        columns = ["run", "bound", "exact B_ij", "its pixels", "pool rays", "pixels not in the pool, by reason",
                   "of its pixels, the hidden object's point seen in another frame"]
        write_results(a.out, "bound_pixels", command_line(), {"bound_pixels": table(columns, rows)},
                      {"datasets": [str(d) for d in datasets]}, Path(__file__).resolve().parents[1])
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
