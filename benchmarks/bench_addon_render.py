"""How closely the Blender add-on's Cycles render reproduces OSN's own render, on a finished demo.

    python benchmarks/bench_addon_render.py --work runs/demo --out benchmarks/results/addon_render.json \\
        [--scratch DIR] [--volume-samples 4] [--mesh-samples 16] [--test-view 0] [--test-time 7]

Reads a finished ``osn demo`` work directory (``run/``: the trained run, ``dataset/``: its
dataset, ``export/``: the demo's export). Exports the run again with this checkout's ``osn
export`` (into ``--scratch``), then renders with Cycles through the add-on
(``osn.export.blender_render``: black world, the import's render settings, volumes or meshes
shown alone) the training camera at t = 0, 7, 14 at the import's default configuration and one
test camera at the export's first sampled configuration, and compares each with OSN's render of
the same camera, time and configuration (``TrainedRun.render_view``) and, for the training
camera, with the video frame. The demo's own export is rendered the same way: an export made
before the field grids existed shows what re-exporting buys.

Writes a results JSON (``results_json``): table ``addon_render`` (PSNR against OSN and against
the video, Blender's and OSN's render seconds per view) and every figure under ``data``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import command_line, print_command  # noqa: E402
from results_json import table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TRAIN_TIMES = (0, 7, 14)


def osn_renders(run_dir: Path, dataset: Path, views: list, sbars: list) -> tuple[list[np.ndarray], list[float]]:
    """OSN's render (``TrainedRun.render_view``) of each view at the scales Blender rendered, and its seconds."""
    from osn.export.from_run import rig_cameras
    from osn.model.run import load_run

    run = load_run(run_dir)
    rig = rig_cameras(dataset, len(run.inputs.timestamps))
    images, seconds = [], []
    for v, sbar in zip(views, sbars):
        cam = None if v.camera == "train" else rig[int(v.camera), v.time]
        t0 = time.perf_counter()
        images.append(run.render_view(cam, v.time, np.asarray(sbar))["rgb"])
        seconds.append(time.perf_counter() - t0)
    return images, seconds


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", required=True, type=Path, help="finished osn demo work directory (run/, dataset/, export/)")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "addon_render.json")
    p.add_argument("--scratch", type=Path, default=None, help="where the fresh export goes (default: a temporary directory)")
    p.add_argument("--volume-samples", type=int, default=4)
    p.add_argument("--mesh-samples", type=int, default=16)
    p.add_argument("--test-view", type=int, default=0)
    p.add_argument("--test-time", type=int, default=7)
    p.add_argument("--note", default="", help="provenance note stored with the figures")
    args = p.parse_args(argv)
    print_command("benchmarks/bench_addon_render.py", argv)
    from benchgen.score.metrics import psnr
    from osn.export.blender_render import View, render_export
    from osn.export.from_run import export_run
    from scenecore import dataset as D
    from scenecore import export_format as core

    run_dir, dataset, old_export = args.work / "run", args.work / "dataset", args.work / "export"
    scratch = args.scratch or Path(tempfile.mkdtemp(prefix="bench-addon-render-"))
    fresh = scratch / "export"
    if fresh.exists():
        shutil.rmtree(fresh)
    t0 = time.perf_counter()
    export_run(run_dir, fresh, dataset=dataset, echo=lambda _m: None)
    export_s = time.perf_counter() - t0
    scene = D.load_scene(dataset)
    video, _, _ = D.read_training_video(dataset, scene)
    data = core.read_export(str(fresh))
    views = [View("train", t) for t in TRAIN_TIMES] + [View(args.test_view, args.test_time, list(data.samples[0]))]
    names = [f"training camera, t = {t}" for t in TRAIN_TIMES] + [f"test camera {args.test_view}, t = {args.test_time}, sample 0"]

    runs = [("volumes", fresh, "volumes", args.volume_samples), ("meshes", fresh, "meshes", args.mesh_samples),
            ("volumes, the demo's own export", old_export, "volumes", args.volume_samples)]
    rows, figures = [], []
    for label, export, part, samples in runs:
        out = render_export(export, views, parts=(part,), samples=samples)
        refs, osn_s = osn_renders(run_dir, dataset, views, out["sbar"][part])
        for name, v, img, ref, bs, os_ in zip(names, views, out["images"][part], refs, out["seconds"][part], osn_s):
            vs_osn = float(psnr(img, ref))
            vs_video = float(psnr(img, video[v.time] / 255.0)) if v.camera == "train" else None
            osn_video = float(psnr(ref, video[v.time] / 255.0)) if v.camera == "train" else None
            fig = {"render": label, "view": name, "samples": samples, "psnr_vs_osn_db": vs_osn, "psnr_vs_video_db": vs_video,
                   "osn_psnr_vs_video_db": osn_video, "blender_seconds": bs, "osn_seconds": os_}
            figures.append(fig)
            print(f"{label:32s} {name:40s} {samples:3d} spp  vs OSN {vs_osn:6.2f} dB  vs video "
                  f"{'-' if vs_video is None else f'{vs_video:.2f}'} (OSN {'-' if osn_video is None else f'{osn_video:.2f}'})  "
                  f"Blender {bs:.1f} s, OSN {os_:.2f} s", flush=True)
            rows.append([label, name, str(samples), f"{vs_osn:.2f}", "-" if vs_video is None else f"{vs_video:.2f}",
                         "-" if osn_video is None else f"{osn_video:.2f}", f"{bs:.1f}", f"{os_:.2f}"])
    tables = {"addon_render": table(
        ["render", "view", "samples / px", "PSNR vs OSN (dB)", "PSNR vs video (dB)", "OSN vs video (dB)", "Blender s", "OSN s"], rows)}
    W, H = data.width, data.height
    write_results(args.out, "addon_render", command_line("benchmarks/bench_addon_render.py", argv),
                  tables, {"work": str(args.work), "note": args.note, "resolution": [W, H], "export_seconds": export_s,
                           "renders": figures}, REPO)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
