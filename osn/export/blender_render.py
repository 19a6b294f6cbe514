"""Cycles renders of an export as the Blender add-on builds it, to compare with OSN's own renders.

:func:`render_export` runs one background Python process with bpy (``python -m
osn.export.blender_render SPEC``: bpy holds one global Blender session per process) that imports
the export with the checkout's add-on (``blender_addon/``), applies :func:`fidelity_settings`
and renders each requested view, showing the volumes or the meshes only. The images come back
as float arrays in display values (the add-on's Raw view transform), ready for a PSNR against
``TrainedRun.render_view`` of the same camera, time and configuration.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
#: What a render shows: the learned volumes or the surface meshes.
PARTS = ("volumes", "meshes")


@dataclass
class View:
    """One render: ``camera`` is ``"train"`` or a test-rig viewpoint index, at time index
    ``time``, with the objects at actual scales ``sbar (K,)`` (None: the import's defaults)."""

    camera: str | int
    time: int
    sbar: Sequence[float] | None = None


def fidelity_settings(scene: Any, samples: int) -> None:
    """Cycles settings under which the add-on's volumes render as OSN renders its fields.

    On top of what the import sets (Raw view transform, ray-marched volumes, pixel-centre
    rays): CPU, a fixed sample count without adaptive sampling or denoising (deterministic), a
    black world (OSN's default background) and no dithering.
    """
    import bpy

    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device, cy.samples, cy.use_adaptive_sampling, cy.use_denoising, cy.seed = "CPU", int(samples), False, False, 0
    world = bpy.data.worlds.new("OSN black")
    world.color = (0.0, 0.0, 0.0)
    if world.node_tree is not None:  # Blender 5 worlds always have nodes
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    scene.world = world
    scene.render.dither_intensity = 0.0


def _show_only(coll: Any, part: str, sb: Any) -> None:
    """Hide the meshes (``part == "volumes"``) or the volumes. The import keys ``hide_render``
    where an object has no pose; that key wins at render time, so it is kept only where it
    hides the part that is shown (and the part not shown is unkeyed and hidden). The meshes,
    kept out of renders by the import, are let in (``render_meshes``)."""
    if part == "meshes":
        sb.render_meshes(coll)
    for o in coll.objects:
        if o.type not in {"MESH", "VOLUME"}:
            continue
        shown = (o.type == "VOLUME") == (part == "volumes")
        fcurves = sb._fcurve_collection(o, create=False)
        keyed = fcurves.find("hide_render") if fcurves is not None else None
        if not shown and keyed is not None:
            fcurves.remove(keyed)
        if keyed is None or not shown:
            o.hide_render = not shown


def _blender_main(spec: dict[str, Any]) -> None:
    """The bpy side: import, render every view of every part, save ``.npy`` images and timings."""
    sys.path.insert(0, str(ROOT))
    import bpy

    import blender_addon
    from blender_addon import scene_build as sb

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    scene = bpy.context.scene
    t0 = time.perf_counter()
    coll = sb.import_export(bpy.context, spec["export"])
    result: dict[str, Any] = {"import_s": time.perf_counter() - t0, "renders": []}
    fidelity_settings(scene, spec["samples"])
    out = Path(spec["out"])
    scene.render.image_settings.file_format, scene.render.image_settings.color_depth = "OPEN_EXR", "32"
    defaults = sb.current_scales(coll)
    for part in spec["parts"]:
        _show_only(coll, part, sb)
        for i, v in enumerate(spec["views"]):
            sb.set_scales(coll, np.asarray(v["sbar"]) if v["sbar"] is not None else defaults)
            cam = "OSN training camera" if v["camera"] == "train" else f"OSN test camera {int(v['camera'])}"
            scene.camera = bpy.data.objects[cam]
            scene.frame_set(int(v["time"]) + 1)
            path = out / f"{part}_{i}.exr"
            scene.render.filepath = str(path)
            t = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            seconds = time.perf_counter() - t
            img = bpy.data.images.load(str(path))
            px = np.zeros(img.size[0] * img.size[1] * 4, np.float32)
            img.pixels.foreach_get(px)
            np.save(out / f"{part}_{i}.npy", px.reshape(img.size[1], img.size[0], 4)[::-1, :, :3])
            bpy.data.images.remove(img)
            result["renders"].append({"part": part, "view": i, "seconds": seconds, "sbar": list(sb.current_scales(coll))})
    (out / "result.json").write_text(json.dumps(result))


def render_export(export: str | Path, views: Sequence[View], parts: Sequence[str] = ("volumes",), samples: int = 4,
                  timeout: float = 3600.0) -> dict[str, Any]:
    """Render ``views`` of the export at ``export`` with Cycles through the add-on (one subprocess).

    Returns ``{"images": {part: [rgb (H, W, 3) in [0, 1] per view]}, "seconds": {part: [render
    seconds per view]}, "sbar": {part: [the scales rendered]}, "import_s": float}``.

    Raises:
        RuntimeError: the Blender process failed (its output's tail in the message).
    """
    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise ValueError(f"unknown parts {bad}, expected some of {PARTS}")
    with tempfile.TemporaryDirectory(prefix="osn-blender-render-") as tmp:
        spec = {"export": str(Path(export).resolve()), "out": tmp, "samples": int(samples), "parts": list(parts),
                "views": [{"camera": v.camera, "time": int(v.time), "sbar": None if v.sbar is None else [float(s) for s in v.sbar]}
                          for v in views]}
        # Blender writes its user settings under BLENDER_USER_RESOURCES: keep them in the temporary directory.
        env = dict(os.environ, BLENDER_USER_RESOURCES=str(Path(tmp) / "user"), PYTHONPATH=str(ROOT))
        r = subprocess.run([sys.executable, "-m", "osn.export.blender_render", json.dumps(spec)], env=env, cwd=str(ROOT),
                           capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0 or not (Path(tmp) / "result.json").is_file():
            raise RuntimeError(f"Blender render of {export} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
        res = json.loads((Path(tmp) / "result.json").read_text())
        images = {p: [np.clip(np.load(Path(tmp) / f"{p}_{i}.npy"), 0.0, 1.0) for i in range(len(views))] for p in parts}
    seconds = {p: [x["seconds"] for x in res["renders"] if x["part"] == p] for p in parts}
    sbar = {p: [x["sbar"] for x in res["renders"] if x["part"] == p] for p in parts}
    return {"images": images, "seconds": seconds, "sbar": sbar, "import_s": res["import_s"]}


if __name__ == "__main__":
    _blender_main(json.loads(sys.argv[1]))
