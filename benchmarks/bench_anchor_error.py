"""Where a run's error on the anchor's (the room's) test pixels comes from, at the exact scales.

On the co-visible anchor pixels of the first ground truths (the run rendered at each one's exact
scales, as `osn evaluate`'s "true scales" row) it prints:

* the composite against the anchor rendered alone, by distance (px) to the nearest pixel of
  another object in the ground truth: what the objects' fields cost the anchor's pixels, and
  where (their silhouettes, or floaters far from them);
* the anchor's rendered depth against the true depth (signed relative error: a field whose
  surfaces sit in front of the true ones reads negative), in the test views and, with
  ``--training-views``, in the training frames, there also by distance to the nearest object;
* with ``--grid R[,R...]``, a colour grid's own ceiling: an R^3 trilinear RGB grid over the anchor
  pixels' true surface points fitted to the training frames' colours there (exact geometry, no
  density), scored on the same test pixels. What a grid of that resolution can give the anchor
  at best, whatever the training does;
* with ``--planes P[,P...]``, the same for the colour planes of ``field.anchor_planes`` (three
  P^2 planes, :func:`osn.model.fields.triplane`), and both fits again in the run's anchor frame
  (``world_to_anchor``: where its fields live; SfM's frame is not aligned with the walls).

It reads the ground truth (a measurement, not a method).

    python benchmarks/bench_anchor_error.py RUN DATASET [--configs 3] [--views 30] [--grid 64,128] [--planes 128,256,512]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from benchutil import print_command

from benchgen.score import metrics as M
from benchgen.score.truth import load_truth
from osn.evaluate.units import true_scales
from osn.model.fields import trilinear, triplane
from osn.model.run import load_run
from scenecore import dataset as D
from scenecore.cameras import pixel_rays

#: Distance bins (px to the nearest other object's pixel) of the composite-against-alone split.
BINS = ((0.0, 1.5), (1.5, 3.0), (3.0, 6.0), (6.0, np.inf))


def depth_summary(rel: np.ndarray) -> str:
    """Signed relative depth errors ``(N,)`` as one line (median, 10th / 90th percentile, share within 3%)."""
    p10, p50, p90 = np.percentile(rel, [10, 50, 90])
    return f"signed median {p50:+.3f} (p10 {p10:+.3f}, p90 {p90:+.3f}), within 3%: {np.mean(np.abs(rel) < 0.03):.0%}"


def surface_points(K: np.ndarray, camera_to_world: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """World points ``(N, 3)`` of the pixels ``mask (H, W)`` at their planar ``depth (H, W)``."""
    H, W = depth.shape
    o, d = pixel_rays(K, camera_to_world, W, H)
    m = mask.reshape(-1)
    return o[m] + depth.reshape(-1)[m, None] * d[m]


def grid_ceiling(train_pts: np.ndarray, train_rgb: np.ndarray, test_pts: np.ndarray, test_rgb: np.ndarray,
                 resolution: int, iters: int = 400, planes: bool = False) -> tuple[float, float]:
    """PSNR (training, test) of an RGB grid (``planes``: three colour planes, ``resolution^2``
    texels each, on 0.5) fitted by Adam to ``train_rgb (N, 3)`` at ``train_pts``, over the
    training points' box (0.5th-99.5th percentiles, 5% margin)."""
    lo, hi = np.percentile(train_pts, 0.5, 0), np.percentile(train_pts, 99.5, 0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.05
    x = torch.from_numpy((train_pts - centre) / half).float()
    xt = torch.from_numpy((test_pts - centre) / half).float()
    y, yt = torch.from_numpy(train_rgb).float(), torch.from_numpy(test_rgb).float()
    if planes:
        table = torch.zeros(3 * resolution**2, 3, requires_grad=True)

        def colour(p: torch.Tensor) -> torch.Tensor:
            return 0.5 + triplane(table, resolution, p)
    else:
        table = torch.full((resolution**3, 3), 0.5, requires_grad=True)

        def colour(p: torch.Tensor) -> torch.Tensor:
            return trilinear(table, resolution, p)
    opt = torch.optim.Adam([table], lr=0.05)
    for _ in range(iters):
        opt.zero_grad()
        loss = (colour(x) - y).square().mean()
        loss.backward()
        opt.step()
    with torch.no_grad():
        fit = (colour(x) - y).square().mean().item()
        test = (colour(xt).clamp(0, 1) - yt).square().mean().item()
    return M.psnr_from_mse(fit), M.psnr_from_mse(test)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("dataset")
    p.add_argument("--configs", type=int, default=3, help="the first N ground-truth configurations")
    p.add_argument("--views", type=int, default=30, help="evaluated test views per configuration, evenly spread (0 = all)")
    p.add_argument("--training-views", action="store_true", help="also the anchor's depth error in the training frames")
    p.add_argument("--grid", default="", help="comma-separated colour-grid resolutions whose ceiling to fit (e.g. 64,128)")
    p.add_argument("--planes", default="", help="comma-separated colour-plane sizes whose ceiling to fit (e.g. 128,256,512); "
                   "the grids and planes are then also fitted in the run's anchor frame")
    args = p.parse_args(argv)
    print_command()
    truth = load_truth(args.dataset, args.views, workers=2)
    run = load_run(args.run)
    inp, a = run.inputs, run.anchor_pos
    anchor_id, unit = inp.objects[a].id, inp.objects[a].unit_to_world
    scene = truth.scene
    K = scene.intrinsics.matrix()
    sbar = true_scales(inp, truth.scales[:, [o.id for o in inp.objects]])
    n = min(args.configs, truth.num_configurations)
    stats = np.zeros((len(BINS), 3))  # pixels, squared error of the composite, of the anchor alone
    rel, test_pts, test_rgb = [], [], []
    alone_of_view: dict[int, dict] = {}  # the anchor alone is at scale 1 in every configuration
    for g in range(n):
        rgb, depth, ids = truth.views(g)
        for v, f in enumerate(truth.frames):
            mask = truth.masks(g)[v] & (ids[v] == anchor_id)
            if not mask.any():
                continue
            gt = rgb[v] / 255.0
            comp = run.render_view(f.camera_to_world, f.time_index, sbar[g])
            if v not in alone_of_view:
                alone_of_view[v] = run.render_view(f.camera_to_world, f.time_index, sbar[g], objects=[a])
            alone = alone_of_view[v]
            dist = distance_transform_edt(ids[v] == anchor_id)
            e_comp, e_alone = ((comp["rgb"] - gt) ** 2).mean(-1), ((alone["rgb"] - gt) ** 2).mean(-1)
            for i, (lo, hi) in enumerate(BINS):
                b = mask & (dist > lo) & (dist <= hi)
                stats[i] += [b.sum(), e_comp[b].sum(), e_alone[b].sum()]
            rel.append(alone["depth"][mask] * unit / depth[v][mask] - 1.0)
            if g == 0:  # the anchor does not move with a configuration: one set of test points
                test_pts.append(surface_points(K, f.camera_to_world, depth[v], mask))
                test_rgb.append(gt[mask])
    total = stats.sum(0)
    excess = total[1] - total[2]
    print(f"anchor ({inp.objects[a].name}) on the co-visible test pixels of the first {n} ground truths x "
          f"{truth.num_views} views, at their exact scales: composite {M.psnr_from_mse(total[1] / total[0]):.2f} dB, "
          f"anchor alone {M.psnr_from_mse(total[2] / total[0]):.2f} dB")
    print("| px to the nearest other object | share of anchor pixels | composite dB | anchor alone dB | share of the composite's excess error |")
    print("|---|---|---|---|---|")
    for (lo, hi), (px, sc, sa) in zip(BINS, stats):
        if px:
            share = (sc - sa) / excess if excess > 0 else float("nan")
            print(f"| ({lo:g}, {hi:g}] | {px / total[0]:.1%} | {M.psnr_from_mse(sc / px):.2f} | "
                  f"{M.psnr_from_mse(sa / px):.2f} | {share:.1%} |")
    print("anchor depth in the test views (rendered / true - 1): " + depth_summary(np.concatenate(rel)))
    if args.training_views or args.grid or args.planes:
        t_rgb, t_depth, t_ids = D.read_training_video(args.dataset, scene)
        train = sorted(scene.train_frames, key=lambda fr: fr.time_index)
    if args.training_views:
        rel_t, dist_t = [], []
        for i, f in enumerate(train):
            mask = (t_ids[i] == anchor_id) & np.isfinite(t_depth[i])
            r = run.render_view(None, f.time_index, np.ones(inp.num_objects), objects=[a])
            rel_t.append(r["depth"][mask] * unit / t_depth[i][mask] - 1.0)
            dist_t.append(distance_transform_edt(t_ids[i] == anchor_id)[mask])
        rel_t, dist_t = np.concatenate(rel_t), np.concatenate(dist_t)
        print("anchor depth in the training frames: " + depth_summary(rel_t))
        # Next to the objects is where the contact bounds are read: a surface pulled toward the
        # camera there cuts them tight.
        for lo, hi in BINS:
            b = (dist_t > lo) & (dist_t <= hi)
            if b.any():
                print(f"  ({lo:g}, {hi:g}] px from another object ({b.mean():.1%} of its pixels): " + depth_summary(rel_t[b]))
    if args.grid or args.planes:
        pts, cols = [], []
        for i, f in enumerate(train):
            mask = (t_ids[i] == anchor_id) & np.isfinite(t_depth[i])
            pts.append(surface_points(K, f.camera_to_world, t_depth[i], mask))
            cols.append(t_rgb[i][mask] / 255.0)
        tp, tc, P, C = np.concatenate(test_pts), np.concatenate(test_rgb), np.concatenate(pts), np.concatenate(cols)
        W = inp.world_to_anchor
        frames = [("world", lambda x: x)]
        if args.planes and W is not None:
            frames.append(("the run's anchor frame", lambda x: x @ W[:3, :3].T + W[:3, 3]))
        fits = [(int(r), False) for r in args.grid.split(",") if r] + [(int(r), True) for r in args.planes.split(",") if r]
        for frame, to in frames:
            for r, planes in fits:
                fit, test = grid_ceiling(to(P), C, to(tp), tc, r, planes=planes)
                what = f"three {r}^2 colour planes" if planes else f"a {r}^3 colour grid"
                print(f"{what} at the true surface points ({frame}): training frames {fit:.2f} dB, "
                      f"test pixels (first ground truth) {test:.2f} dB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
