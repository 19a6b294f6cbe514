"""Render the README picture: an `osn export` imported by the add-on in headless Blender.

Installs the add-on zip into a temporary Blender user directory, imports the export, and renders
(Cycles) the training camera and a test-rig camera at one frame for two sampled valid
configurations: a 2 x 2 grid whose training-camera column is identical and whose novel-view
column differs. Usage (from the checkout, with the venv's bpy):

    python scripts/render_addon_picture.py EXPORT_DIR ADDON_ZIP OUT.png [--frame 8] [--size 256]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("export")
    p.add_argument("zip")
    p.add_argument("out")
    p.add_argument("--frame", type=int, default=8, help="video frame (1-based)")
    p.add_argument("--size", type=int, default=256, help="render width and height")
    p.add_argument("--test-camera", type=int, default=0, help="index of the test-rig camera")
    args = p.parse_args()
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="osn_blender_user_")
    import bpy

    bpy.ops.extensions.package_install_files(filepath=str(Path(args.zip).resolve()), repo="user_default", enable_on_install=True)
    sb = sys.modules["bl_ext.user_default.osn_import"].scene_build
    bpy.ops.import_scene.osn(filepath=str(Path(args.export).resolve() / "osn_export.json"))
    scene = bpy.context.scene
    coll = scene.osn_collection
    for o in coll.objects:  # the volumes are slow in Cycles; the meshes carry the picture
        if o.type == "VOLUME":
            o.hide_render = True
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", 16, False
    scene.view_settings.view_transform = "Standard"
    r.resolution_x = r.resolution_y = args.size
    r.image_settings.file_format, r.image_settings.color_depth = "OPEN_EXR", "32"
    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    scene.world = world
    scene.frame_set(args.frame)
    cams = [scene.objects["OSN training camera"], scene.objects[f"OSN test camera {args.test_camera}"]]
    tiles = []
    tmp = Path(tempfile.mkdtemp(prefix="osn_pic_"))
    samples = sb.export_data(coll).samples
    if samples is None or len(samples) < 2:
        raise SystemExit(f"{args.export}: the export holds fewer than 2 sampled configurations")
    # The two samples furthest apart in log scale: the clearest contrast between configurations.
    spread = np.log(samples).std(0)
    k_obj = int(np.argmax(spread))
    picks = (int(np.argmin(samples[:, k_obj])), int(np.argmax(samples[:, k_obj])))
    for k in picks:
        sb.apply_sample(coll, k)
        scene.frame_set(args.frame)
        row = []
        for c in cams:
            scene.camera = c
            path = tmp / f"{k}_{c.name}.exr"
            r.filepath = str(path)
            bpy.ops.render.render(write_still=True)
            img = bpy.data.images.load(str(path))
            px = np.zeros(args.size * args.size * 4, np.float32)
            img.pixels.foreach_get(px)
            bpy.data.images.remove(img)
            row.append(px.reshape(args.size, args.size, 4)[::-1, :, :3])
        tiles.append(np.concatenate(row, axis=1))
    grid = np.concatenate(tiles, axis=0)
    import imageio.v3 as iio

    iio.imwrite(args.out, (np.clip(grid, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8))
    diff_train = float(np.abs(tiles[0][:, : args.size] - tiles[1][:, : args.size]).max())
    diff_test = float(np.abs(tiles[0][:, args.size :] - tiles[1][:, args.size :]).max())
    print(f"wrote {args.out}: configurations {picks} (scales {samples[picks[0]].round(3)} vs {samples[picks[1]].round(3)}); "
          f"training camera max difference {diff_train:.2e}, test camera {diff_test:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
