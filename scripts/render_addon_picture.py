"""Render the README's add-on picture from a finished ``osn demo`` work directory.

    python scripts/render_addon_picture.py --work runs/demo [--reexport [--scratch DIR]]
        [--out docs/img/addon_configurations.png] [--time 7] [--test-view 0] [--samples 4] [--zoom 4]

Imports the export (``WORK/export``, or with ``--reexport`` the run exported again with this
checkout's code, as the demo's export stage does) through the add-on's own import and renders the
volumes with Cycles under the add-on's render settings (``osn.export.blender_render``) for two of
the export's sampled valid configurations (the pair furthest apart in log scale): the training
camera at frame ``--time`` and one test-rig (novel) camera at the same time. Tiles one labelled
PNG, a row per camera: the training video frame (training row only) / configuration A /
configuration B, upscaled ``--zoom`` times with nearest-neighbour. A valid configuration leaves the
training row unchanged while the novel row changes; the largest pixel difference per row is printed.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
LABEL_H = 30  # pixels of caption above each tile: two lines of the default font


def farthest_pair(samples: np.ndarray) -> tuple[int, int]:
    """Indices ``(i, j)``, ``i < j``, of the two configurations ``samples (N, K)`` (positive
    scales) furthest apart in log scale: the clearest visible contrast. Ties go to the lowest
    indices, so the choice is deterministic."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 2 or len(s) < 2:
        raise ValueError(f"need at least 2 sampled configurations, got shape {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError("sampled configurations must be finite positive scales")
    logs = np.log(s)
    d = ((logs[:, None, :] - logs[None, :, :]) ** 2).sum(-1)
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)  # first maximum in row-major order
    return (int(min(i, j)), int(max(i, j)))


def tile_picture(rows: list[list[np.ndarray | None]], labels: list[list[str]], zoom: int = 4) -> "Image.Image":
    """One RGB image: ``rows`` of tiles (float RGB ``(H, W, 3)`` in [0, 1], or None for an empty
    tile), each upscaled ``zoom`` times (nearest-neighbour) under its caption ``labels[r][c]``
    (lines split on ``\\n``). Every tile has the shape of the first one."""
    from PIL import Image, ImageDraw

    first = next(t for row in rows for t in row if t is not None)
    h, w = first.shape[0] * zoom, first.shape[1] * zoom
    cols = max(len(r) for r in rows)
    canvas = Image.new("RGB", (cols * w, len(rows) * (h + LABEL_H)), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, row in enumerate(rows):
        for c, tile in enumerate(row):
            x, y = c * w, r * (h + LABEL_H)
            draw.multiline_text((x + 4, y + 2), labels[r][c], fill=(0, 0, 0), spacing=2)
            if tile is None:
                canvas.paste((40, 40, 40), (x, y + LABEL_H, x + w, y + LABEL_H + h))
                continue
            if tile.shape != first.shape:
                raise ValueError(f"tile ({r}, {c}) has shape {tile.shape}, expected {first.shape}")
            px = (np.clip(tile, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            canvas.paste(Image.fromarray(px).resize((w, h), Image.NEAREST), (x, y + LABEL_H))
    return canvas


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", required=True, type=Path, help="finished osn demo work directory (run/, dataset/, export/)")
    p.add_argument("--out", type=Path, default=REPO / "docs" / "img" / "addon_configurations.png")
    p.add_argument("--reexport", action="store_true", help="export WORK/run again with this checkout (an older export/)")
    p.add_argument("--scratch", type=Path, default=None, help="where --reexport writes (default: a temporary directory)")
    p.add_argument("--time", type=int, default=7, help="time index (0-based) of both cameras")
    p.add_argument("--test-view", type=int, default=0, help="index of the test-rig (novel) camera")
    p.add_argument("--samples", type=int, default=4, help="Cycles samples per pixel")
    p.add_argument("--zoom", type=int, default=4, help="nearest-neighbour upscale of each tile")
    args = p.parse_args(argv)
    print("command: " + shlex.join(["python", "scripts/render_addon_picture.py", *(sys.argv[1:] if argv is None else argv)]),
          flush=True)
    from osn.export.blender_render import View, render_export
    from osn.export.from_run import export_run
    from scenecore import dataset as D
    from scenecore import export_format as core

    dataset = args.work / "dataset"
    missing = [d for d in ("run", "dataset") if not (args.work / d).is_dir()]
    if missing:
        raise SystemExit(f"{args.work}: not a finished osn demo work directory (no {', '.join(d + '/' for d in missing)})")
    with tempfile.TemporaryDirectory(prefix="osn-addon-picture-") as tmp:
        export = args.work / "export"
        if args.reexport:
            export = (args.scratch or Path(tmp)) / "export"
            export_run(args.work / "run", export, dataset=dataset, echo=lambda _m: None)  # as the demo's export stage
        data = core.read_export(str(export))
        if data.samples is None or len(data.samples) < 2:
            raise SystemExit(f"{export}: the export holds fewer than 2 sampled configurations")
        if data.test_cameras is None or not 0 <= args.test_view < len(data.test_cameras):
            raise SystemExit(f"{export}: no test camera {args.test_view}")
        if not 0 <= args.time < data.num_frames:
            raise SystemExit(f"{export}: time {args.time} is outside its {data.num_frames} frames")
        a, b = farthest_pair(data.samples)
        views = [View(cam, args.time, list(data.samples[k])) for cam in ("train", args.test_view) for k in (a, b)]
        images = render_export(export, views, parts=("volumes",), samples=args.samples)["images"]["volumes"]
    video, _, _ = D.read_training_video(dataset, D.load_scene(dataset))
    frame = video[args.time] / 255.0
    names = [o.name for o in data.objects]
    rows = [[frame, images[0], images[1]], [None, images[2], images[3]]]
    # The anchor's scale is fixed: only the free objects' scales tell the configurations apart.
    scales = {k: ", ".join(f"{names[i]} {data.samples[k][i]:.2f}" for i in data.free_indices) for k in (a, b)}
    labels = [[f"training frame, t = {args.time}\n(the video)", f"training camera, configuration {a}\n{scales[a]}",
               f"training camera, configuration {b}\n{scales[b]}"],
              [f"test camera {args.test_view}, t = {args.time}\n(novel view: no video)",
               f"test camera {args.test_view}, configuration {a}", f"test camera {args.test_view}, configuration {b}"]]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tile_picture(rows, labels, args.zoom).save(args.out)
    for k in (a, b):
        print(f"configuration {k}: {scales[k]}")
    for cam, (x, y) in (("training camera", images[:2]), (f"test camera {args.test_view}", images[2:])):
        print(f"{cam}: pixel difference between the configurations mean {np.abs(x - y).mean():.4f}, "
              f"largest {np.abs(x - y).max():.3f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
