"""What the training video alone can give a test view: a reprojection ceiling, next to a run's fields.

Each co-visible test pixel of a ground-truth configuration takes its colour from the training
video itself, reprojected with that configuration's exact geometry (its planar depth, each object
moving with its own pose; :mod:`benchgen.score.covisibility`) and sampled bilinearly from the
training frame whose camera centre is nearest the test camera's among the frames that see the
point. No method can be given that geometry, so this is not a method: it says how much of a test
view's error is missing information (what no renderer trained on the video could recover) and how
much is the fields'. With ``--run`` the same configurations are rendered by the run's fields at
their exact scales (``osn evaluate``'s "true scales" row) and both are split by object on the same
pixels (PSNR on the object's co-visible pixels, pooled over the chosen ground truths).

    python benchmarks/bench_reprojection_ceiling.py DATASET [--configs 5] [--views 30] [--run RUN]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from benchutil import print_command

from benchgen.score import metrics as M
from benchgen.score.covisibility import (
    configuration_poses, configured_depth, covisibility_transforms, move_with_objects, seen_in_frame,
)
from benchgen.score.truth import Truth, load_truth
from scenecore import dataset as D
from scenecore.cameras import invert_pose, pixel_rays


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colour ``(N, 3)`` of ``image (H, W, 3)`` at pixel coordinates ``uv (N, 2)`` (centres at .5),
    bilinear, clamped at the border."""
    H, W = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, W - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, H - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def reprojected_view(truth: Truth, g: int, v: int, video: tuple[np.ndarray, np.ndarray, np.ndarray],
                     poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """View ``v`` of configuration ``g`` rebuilt from the training video: colour ``(P, 3)`` in [0, 1]
    of its co-visible pixels ``(P,)`` (flat indices), from the nearest training camera that sees each."""
    scene, frame = truth.scene, truth.frames[v]
    K, H, W = scene.intrinsics.matrix(), scene.height, scene.width
    _, depth, ids = truth.views(g)
    pix = np.flatnonzero(truth.masks(g)[v].reshape(-1))
    origins, dirs = pixel_rays(K, frame.camera_to_world, W, H)
    z = depth[v].reshape(-1)[pix]
    points = origins[pix] + z[:, None] * dirs[pix]
    obj = ids[v].reshape(-1)[pix].astype(np.int64)
    moves = covisibility_transforms(scene, truth.scales[g], frame.time_index, poses)
    t_rgb, t_depth, t_ids = video
    train = sorted(scene.train_frames, key=lambda f: f.time_index)
    colour = np.full((len(pix), 3), np.nan)
    nearest = np.full(len(pix), np.inf)
    centre = frame.camera_to_world[:3, 3]
    for i, f in enumerate(train):
        d = configured_depth(t_depth[i], t_ids[i], truth.scales[g])
        A = moves[f.time_index]
        uv, seen = seen_in_frame(move_with_objects(points, obj, A), K, f.camera_to_world, d)
        # Distance in each object's own frame: the training camera brought back to the test time
        # by the inverse of the object's motion (the room does not move).
        cams = np.stack([(invert_pose(A[k]) @ np.append(f.camera_to_world[:3, 3], 1.0))[:3] for k in range(len(A))])
        dist = np.linalg.norm(cams[obj] - centre, axis=1)
        take = seen & (dist < nearest)
        colour[take] = bilinear(t_rgb[i].astype(np.float64) / 255.0, uv[take])
        nearest[take] = dist[take]
    return colour, pix


def psnr_by_object(sse: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """PSNR per object from :func:`benchgen.score.metrics.squared_error_by_id`'s summed error and
    pixel count (NaN where no pixel)."""
    sse, pixels = np.atleast_1d(sse), np.atleast_1d(pixels)
    return np.array([M.psnr_from_mse(e / n) if n > 0 else np.nan for e, n in zip(sse, pixels)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset")
    p.add_argument("--configs", type=int, default=5, help="the first N ground-truth configurations (0 = all)")
    p.add_argument("--views", type=int, default=30, help="evaluated test views per configuration, evenly spread (0 = all)")
    p.add_argument("--run", help="a trained run: also its fields at the same configurations' exact scales")
    args = p.parse_args(argv)
    print_command()
    truth = load_truth(args.dataset, args.views, workers=2)
    if args.configs < 0:
        sys.exit("--configs must be >= 0")
    n = min(args.configs or truth.num_configurations, truth.num_configurations)
    # The first n: Truth reads configuration g's views by its index, so a prefix stays consistent.
    truth = Truth(truth.root, truth.scene, truth.frames, truth.scales[:n], truth.masked_rgb[:, :n], truth.mask[:, :n])
    gs = list(range(n))
    scene = truth.scene
    video = D.read_training_video(args.dataset, scene)
    K, H, W = scene.num_objects, scene.height, scene.width
    sse, count, missing = np.zeros(K + 1), np.zeros(K + 1), 0
    for g in gs:
        rgb, _, ids = truth.views(g)
        poses = configuration_poses(scene, truth.scales[g])
        for v in range(truth.num_views):
            colour, pix = reprojected_view(truth, g, v, video, poses)
            # Co-visible by the mask's own test, so none is expected; one would make its object's sum NaN.
            missing += int(np.isnan(colour).any(1).sum())
            pred, mask = np.zeros((H * W, 3)), np.zeros(H * W, dtype=bool)
            pred[pix], mask[pix] = colour, True
            e, n_px = M.squared_error_by_id(pred.reshape(H, W, 3), rgb[v] / 255.0, ids[v], K, mask.reshape(H, W))
            sse += e
            count += n_px
    names = [o.name for o in scene.objects] + ["no object"]
    rows = {"reprojected training video (exact geometry)": psnr_by_object(sse, count)}
    overall = {"reprojected training video (exact geometry)": psnr_by_object(sse.sum(), count.sum())[0]}
    if args.run:
        from benchgen.score.scorer import score
        from osn.evaluate.exact import RenderedCandidates
        from osn.evaluate.units import true_scales
        from osn.model.run import load_run

        run = load_run(args.run)
        sbar = true_scales(run.inputs, truth.scales[:, [o.id for o in run.inputs.objects]])
        res = score(truth, RenderedCandidates(run, truth, {f"true_scales_{g:03d}": s for g, s in zip(gs, sbar)}), False)
        own = np.mean([r["match_index"] == i for i, r in enumerate(res.per_ground_truth)])
        fsse = np.sum([r["object_sse"] for r in res.per_ground_truth], axis=0)
        fpx = np.sum([r["object_pixels"] for r in res.per_ground_truth], axis=0).astype(np.float64)
        label = f"the run's fields at the exact scales ({own:.0%} matched to their own)"
        rows[label] = psnr_by_object(fsse, fpx)
        overall[label] = psnr_by_object(fsse.sum(), fpx.sum())[0]
    print(f"the first {n} ground truths x {truth.num_views} views; co-visible pixels without a "
          f"reprojected colour: {missing}")
    print("| test views rebuilt by | all | " + " | ".join(n for n, c in zip(names, count) if c) + " |")
    print("|---|---|" + "---|" * int((count > 0).sum()))
    for label, vals in rows.items():
        cells = " | ".join(f"{x:.2f}" for x, c in zip(vals, count) if c)
        print(f"| {label} | {float(overall[label]):.2f} | {cells} |")
    print("(PSNR in dB on co-visible test pixels, by the ground truth's object; pixels: "
          + ", ".join(f"{n} {c / count.sum():.1%}" for n, c in zip(names, count) if c) + ")")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
