"""Export learned objects, trajectories and scale ranges for Blender (``osn export``).

Two layers:

* :func:`write_export` writes an :class:`ExportScene` (plain numpy) to a directory in the
  ``osn-export`` format: a versioned JSON manifest naming every file with its size and sha256,
  one OpenVDB file per object (grids ``density`` and ``color``, via bpy's bundled OpenVDB), a
  marching-cubes PLY mesh with vertex colours per object, the poses in ``arrays.npz`` and the
  scale network in ``scale_net.npz``. Everything is written into a temporary sibling directory
  that is renamed into place at the end, so a killed export leaves no half-written directory.
* :func:`export_scene_from_inputs` builds an :class:`ExportScene` from per-object inputs, learned
  grids and a scale network (the poses follow ``osn.inputs``' conventions), and
  :func:`field_grids` samples a trained field onto a grid.

The format's read side, the numpy scale-network evaluator and the configuration maths live in
the kernel's ``scenecore/export_format.py`` (the add-on ships a copy; Blender may use nothing but
its own numpy); this module imports them from there. Format description: docs/export-and-addon.md.
"""

from __future__ import annotations

import io
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from scenecore import dataset as D
from scenecore import export_format as core
from scenecore.cameras import invert_pose

from osn.preprocess.inputs import SceneInputs
from osn.model.placement import novel_to_training_camera


ExportFormatError = core.ExportFormatError
scale_net_numpy = core.scale_net_numpy
read_export = core.read_export

__all__ = [
    "ExportObject", "ScaleNetwork", "ExportScene", "write_export", "object_mesh", "export_scene_from_inputs",
    "field_grids", "scale_net_numpy", "read_export", "ExportFormatError",
]


@dataclass
class ExportObject:
    """One learned object, in its own coordinates and unit.

    Attributes:
        id, name: as in the inputs; ``is_anchor`` marks the object fixed at ``sbar = 1``.
        density: ``(D, H, W)`` volume density per object unit of length. Voxel ``[d, h, w]``
            samples the point ``bbox[0] + (w, h, d) / (W-1, H-1, D-1) * (bbox[1] - bbox[0])``
            (node-aligned: the grid's corner samples sit on the box corners).
        colour: ``(D, H, W, 3)`` RGB in [0, 1], display-referred (sRGB) like the training images.
        bbox: ``(2, 3)`` min / max corner of the object's box.
        scale_range: ``(lo, hi)`` = Eq. 1's ``sbar`` at normalised scale 0 and 1.
        valid_interval: learned ``(min, max)`` actual scale over valid configurations.
        frames: ``(F,)`` time indices where the object has a pose.
        object_to_scene: ``(F, 4, 4)`` object-to-scene pose at ``sbar = 1`` (see module docs of
            ``scenecore/export_format.py``: a configuration scales it about the camera centre).
        mesh_level: density of the marching-cubes surface; None = ``ln 2 / voxel size`` capped
            at half the peak density.
    """

    id: int
    name: str
    is_anchor: bool
    density: np.ndarray
    colour: np.ndarray
    bbox: np.ndarray
    scale_range: tuple[float, float]
    valid_interval: tuple[float, float]
    frames: np.ndarray
    object_to_scene: np.ndarray
    mesh_level: float | None = None

    def voxel_size(self) -> np.ndarray:
        """``(3,)`` spacing of the samples along x, y, z in object units."""
        D_, H, W = self.density.shape
        return (np.asarray(self.bbox[1], float) - np.asarray(self.bbox[0], float)) / (np.array([W, H, D_]) - 1)

    def surface_level(self) -> float:
        """The mesh's iso-density. Default: where one voxel of material is half opaque
        (``1 - exp(-sigma * voxel) = 0.5``), a resolution-aware stand-in for "the surface";
        capped at half the peak density, because a coarse field (a CPU grid trained with few
        samples per ray) spreads its opacity over several voxels and never gets that dense."""
        if self.mesh_level is not None:
            return float(self.mesh_level)
        per_voxel = math.log(2.0) / float(self.voxel_size().mean())
        peak = float(np.max(self.density)) if np.size(self.density) else 0.0
        return min(per_voxel, 0.5 * peak) if peak > 0 else per_voxel


@dataclass
class ScaleNetwork:
    """The object scale network as numpy arrays: ``layers = [(W (out, in), b (out,)), ...]``.

    Its input is the normalised scales (Eq. 1) of the non-anchor objects in object order; a
    configuration is valid when the output is at least ``threshold``.
    """

    layers: list[tuple[np.ndarray, np.ndarray]]
    hidden_activation: str = "relu"
    output_activation: str = "sigmoid"
    threshold: float = 0.5


@dataclass
class ExportScene:
    """Everything the Blender add-on needs, in the scene frame (the anchor's frame and unit).

    Attributes:
        width, height, K: training camera image size and pixel intrinsics.
        timestamps: ``(T,)`` time of every frame of the video.
        camera_to_scene: ``(T, 4, 4)`` OpenCV training camera poses.
        objects: the learned objects; exactly one has ``is_anchor``.
        test_cameras: optional ``(V, T, 4, 4)`` OpenCV test-rig poses (viewpoint, time).
        scale_network: None when the scene has a single object.
        samples: optional ``(N, K)`` sampled valid configurations as actual scales ``sbar``.
        source: what was exported (run directory); ``meta``: free-form provenance.
    """

    width: int
    height: int
    K: np.ndarray
    timestamps: np.ndarray
    camera_to_scene: np.ndarray
    objects: list[ExportObject]
    test_cameras: np.ndarray | None = None
    scale_network: ScaleNetwork | None = None
    samples: np.ndarray | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def check(self) -> None:
        """Raise ``ExportFormatError`` on shapes, ranges or ids that the reader would reject."""
        T = len(self.timestamps)
        if np.shape(self.camera_to_scene) != (T, 4, 4):
            raise ExportFormatError(f"camera_to_scene has shape {np.shape(self.camera_to_scene)}, expected {(T, 4, 4)}")
        if self.test_cameras is not None and (np.ndim(self.test_cameras) != 4 or np.shape(self.test_cameras)[1:] != (T, 4, 4)):
            raise ExportFormatError(f"test_cameras has shape {np.shape(self.test_cameras)}, expected (V, {T}, 4, 4)")
        if sum(o.is_anchor for o in self.objects) != 1:
            raise ExportFormatError("exactly one object must be the anchor")
        if len({o.id for o in self.objects}) != len(self.objects):
            raise ExportFormatError("object ids must be unique")
        for o in self.objects:
            where = f"object {o.id} ({o.name})"
            if o.density.ndim != 3 or min(o.density.shape) < 2 or o.colour.shape != o.density.shape + (3,):
                raise ExportFormatError(f"{where}: density {o.density.shape} / colour {o.colour.shape} grids do not match")
            if not (np.all(np.isfinite(o.density)) and np.all(np.isfinite(o.colour))):
                raise ExportFormatError(f"{where}: non-finite grid values")
            if not np.all(np.asarray(o.bbox)[1] > np.asarray(o.bbox)[0]):
                raise ExportFormatError(f"{where}: empty bbox {np.asarray(o.bbox).tolist()}")
            if np.shape(o.object_to_scene) != (len(o.frames), 4, 4) or not len(o.frames):
                raise ExportFormatError(f"{where}: object_to_scene {np.shape(o.object_to_scene)} does not match {len(o.frames)} frames")
            if np.min(o.frames) < 0 or np.max(o.frames) >= T:
                raise ExportFormatError(f"{where}: frames outside 0..{T - 1}")
            lo, hi = o.scale_range
            vlo, vhi = o.valid_interval
            if not (0 < lo < hi and 0 < vlo <= vhi):
                raise ExportFormatError(f"{where}: scale_range {o.scale_range} or valid_interval {o.valid_interval} is empty or inverted")
        if self.samples is not None and np.shape(self.samples)[1:] != (len(self.objects),):
            raise ExportFormatError(f"samples have shape {np.shape(self.samples)}, expected (N, {len(self.objects)})")


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _openvdb() -> Any:
    """bpy's bundled OpenVDB (the only OpenVDB Python module pip can provide here)."""
    import bpy  # noqa: F401 - heavy; only the VDB writer needs it

    bpy.utils.expose_bundled_modules()
    import openvdb  # type: ignore[import-not-found]

    return openvdb


def _write_vdb(path: Path, obj: ExportObject) -> None:
    """Grids ``density`` (float) and ``color`` (vec3, linear RGB) in object coordinates.

    OpenVDB indexes ``[x, y, z]`` and maps index ``ijk`` to ``ijk * voxel + bbox_min`` (row-vector
    matrix), which is exactly the node-aligned sampling of :class:`ExportObject`.
    """
    vdb = _openvdb()
    dx, dy, dz = obj.voxel_size()
    lo = np.asarray(obj.bbox, dtype=np.float64)[0]
    M = [[dx, 0.0, 0.0, 0.0], [0.0, dy, 0.0, 0.0], [0.0, 0.0, dz, 0.0], [lo[0], lo[1], lo[2], 1.0]]
    dens = vdb.FloatGrid()
    # A non-contiguous array is written wrong without error (DESIGN.md): always copy contiguous.
    dens.copyFromArray(np.ascontiguousarray(obj.density.transpose(2, 1, 0), dtype=np.float32))
    dens.name = "density"
    dens.transform = vdb.createLinearTransform(M)
    col = vdb.Vec3SGrid()
    col.copyFromArray(np.ascontiguousarray(_srgb_to_linear(obj.colour).transpose(2, 1, 0, 3), dtype=np.float32))
    col.name = "color"
    col.transform = vdb.createLinearTransform(M)
    vdb.write(str(path), grids=[dens, col])


def object_mesh(obj: ExportObject) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Marching-cubes surface of the density at :meth:`ExportObject.surface_level`.

    Returns ``(vertices (V, 3) object coordinates, faces (F, 3), colours (V, 3) sRGB in [0, 1])``
    with outward-facing triangles, or None when the density never reaches the level.
    """
    from scipy.ndimage import map_coordinates
    from skimage.measure import marching_cubes

    level = obj.surface_level()
    dens = np.asarray(obj.density, dtype=np.float32)
    if not (dens.min() < level < dens.max()):
        return None
    verts_dhw, faces, _, _ = marching_cubes(dens, level=level)
    xyz_index = verts_dhw[:, ::-1]  # (d, h, w) -> (x, y, z) index coordinates
    verts = np.asarray(obj.bbox, float)[0] + xyz_index * obj.voxel_size()
    # Reversing the axes mirrors the index space, which flips the triangles' orientation.
    faces = faces[:, ::-1]
    colours = np.stack([map_coordinates(obj.colour[..., c], verts_dhw.T, order=1, mode="nearest") for c in range(3)], axis=1)
    return verts, faces.astype(np.int64), np.clip(colours, 0.0, 1.0)


def _ply_bytes(verts: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> bytes:
    import trimesh

    rgba = np.concatenate([np.round(colours * 255.0), np.full((len(colours), 1), 255.0)], axis=1).astype(np.uint8)
    mesh = trimesh.Trimesh(vertices=verts.astype(np.float32), faces=faces, vertex_colors=rgba, process=False)
    return mesh.export(file_type="ply", encoding="binary")


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def write_export(out_dir: str | Path, scene: ExportScene, echo: Any = None) -> Path:
    """Write ``scene`` to ``out_dir`` atomically; returns the manifest path.

    ``out_dir`` must not exist or be a previous export (which is replaced); any other existing
    path is refused so an export never overwrites unrelated files.
    """
    scene.check()
    out = Path(out_dir).resolve()
    if out.exists() and not (out / core.MANIFEST_NAME).is_file():
        raise ExportFormatError(f"{out}: exists and is not an OSN export; choose another --out")
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_siblings(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}.", suffix=".partial", dir=out.parent))
    say = echo or (lambda _msg: None)
    t0 = time.perf_counter()
    try:
        arrays: dict[str, np.ndarray] = {"camera_to_scene": np.asarray(scene.camera_to_scene, np.float64)}
        if scene.test_cameras is not None:
            arrays["test_cameras"] = np.asarray(scene.test_cameras, np.float64)
        if scene.samples is not None:
            arrays["samples_sbar"] = np.asarray(scene.samples, np.float64)
        (tmp / "objects").mkdir()
        objects = []
        for o in scene.objects:
            vol_rel = f"objects/{o.id}.vdb"
            _write_vdb(tmp / vol_rel, o)
            mesh = object_mesh(o)
            mesh_rel = None
            if mesh is not None:
                mesh_rel = f"objects/{o.id}.ply"
                D.atomic_write_bytes(tmp / mesh_rel, _ply_bytes(*mesh))
            arrays[f"obj{o.id}_frames"] = np.asarray(o.frames, np.int64)
            arrays[f"obj{o.id}_object_to_scene"] = np.asarray(o.object_to_scene, np.float64)
            objects.append(
                {
                    "id": int(o.id),
                    "name": o.name,
                    "is_anchor": bool(o.is_anchor),
                    "bbox": np.asarray(o.bbox, float).tolist(),
                    "grid_shape": list(o.density.shape),
                    "scale_range": [float(x) for x in o.scale_range],
                    "valid_interval": [float(x) for x in o.valid_interval],
                    "volume": vol_rel,
                    "mesh": mesh_rel,
                    "mesh_level": o.surface_level(),
                    "mesh_faces": 0 if mesh is None else int(len(mesh[1])),
                }
            )
            say(f"export: object {o.id} ({o.name}) grid {o.density.shape}, mesh {objects[-1]['mesh_faces']} faces")
        D.atomic_write_bytes(tmp / "arrays.npz", _npz_bytes(arrays))
        net = None
        if scene.scale_network is not None:
            sn = scene.scale_network
            D.atomic_write_bytes(
                tmp / "scale_net.npz",
                _npz_bytes({f"{p}{i}": np.asarray(a, np.float64) for i, (W, b) in enumerate(sn.layers) for p, a in (("W", W), ("b", b))}),
            )
            net = {
                "file": "scale_net.npz",
                "layers": len(sn.layers),
                "layout": "y = act(x @ W{i}.T + b{i})",
                "hidden_activation": sn.hidden_activation,
                "output_activation": sn.output_activation,
                "threshold": float(sn.threshold),
                "input": "normalised scales (Eq. 1) of the non-anchor objects, in manifest object order",
            }
        files = []
        for p in sorted(tmp.rglob("*")):
            if p.is_file():
                rel = p.relative_to(tmp).as_posix()
                files.append({"path": rel, "bytes": p.stat().st_size, "sha256": core.sha256_file(str(p))})
        manifest = {
            "format": core.EXPORT_FORMAT,
            "version": core.EXPORT_VERSION,
            "created_by": "osn export",
            "source": scene.source,
            "conventions": {
                "scene_frame": "the anchor object's frame and unit (anchor sbar = 1)",
                "camera_to_scene": "OpenCV camera-to-scene (+x right, +y down, +z forward), per frame",
                "object_to_scene": "object-to-scene pose at sbar = 1, at the object's frames",
                "configuration": "object k at frame t: scale_about(camera_to_scene[t][:3, 3], sbar_k) @ object_to_scene_k[t]",
                "normalised_scale": "sbar = scale_range[0] * (1 - s) + scale_range[1] * s (Eq. 1)",
                "grid": "density[d, h, w] at bbox_min + (w, h, d) * voxel, voxel = (bbox_max - bbox_min) / (W-1, H-1, D-1)",
                "volume": "OpenVDB grids 'density' (per object unit) and 'color' (linear RGB), index [x, y, z]",
                "mesh": "binary PLY in object coordinates, uchar sRGB vertex colours",
                "blender_frame": "frame = 1 + time index",
            },
            "timestamps": np.asarray(scene.timestamps, float).tolist(),
            "camera": {"width": int(scene.width), "height": int(scene.height), "K": np.asarray(scene.K, float).tolist()},
            "arrays": "arrays.npz",
            "anchor": next(int(o.id) for o in scene.objects if o.is_anchor),
            "objects": objects,
            "scale_network": net,
            "samples": None if scene.samples is None else {"count": int(len(scene.samples)), "array": "samples_sbar"},
            "test_cameras": None if scene.test_cameras is None else {"count": int(len(scene.test_cameras)), "array": "test_cameras"},
            "files": files,
            "meta": scene.meta,
        }
        D.atomic_write_json(tmp / core.MANIFEST_NAME, manifest)
        _swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    say(f"export: wrote {out} in {time.perf_counter() - t0:.1f} s")
    return out / core.MANIFEST_NAME


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove_stale_siblings(out: Path) -> None:
    """Delete temporary siblings of ``out`` left by a killed export (``kill -9`` skips cleanup).

    ``.NAME.PID.*.partial`` (being written) and ``.NAME.old-PID`` (the previous export during
    the swap) are removed when process PID no longer exists, so a concurrent export to the same
    directory keeps its own files.
    """
    for p in out.parent.glob(f".{out.name}.*"):
        rest = p.name[len(out.name) + 2 :]
        if rest.endswith(".partial"):
            pid_text = rest.split(".", 1)[0]
        elif rest.startswith("old-"):
            pid_text = rest[4:]
        else:
            continue
        if not pid_text.isdigit() or not _pid_alive(int(pid_text)):
            shutil.rmtree(p, ignore_errors=True)


def _swap_into_place(tmp: Path, out: Path) -> None:
    """Rename the finished temporary directory to ``out``, replacing a previous export."""
    os.chmod(tmp, 0o755)  # mkdtemp makes it private; an export is meant to be shared
    if not out.exists():
        os.rename(tmp, out)
        return
    old = out.with_name(f".{out.name}.old-{os.getpid()}")
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------------------------
# From per-object inputs and trained fields
# --------------------------------------------------------------------------------------------


def export_scene_from_inputs(
    inputs: SceneInputs,
    grids: dict[int, tuple[np.ndarray, np.ndarray]],
    scale_network: ScaleNetwork | None,
    samples_sbar: np.ndarray | None = None,
    test_camera_to_world: np.ndarray | None = None,
    source: str = "",
    interval_draws: int = 200_000,
) -> ExportScene:
    """Assemble an :class:`ExportScene` from per-object inputs and learned grids.

    Args:
        inputs: the per-object inputs the run was trained on (poses, boxes, near/far).
        grids: object id -> ``(density (D, H, W), colour (D, H, W, 3))`` sampled on its bbox.
        scale_network: the trained scale network (None for a single object).
        samples_sbar: optional ``(N, K)`` sampled valid configurations (actual scales).
        test_camera_to_world: optional ``(V, T, 4, 4)`` OpenCV test rig in dataset world
            coordinates; placed in the scene frame through ``inputs.world_to_anchor``.

    The scene frame is the anchor's frame, so the training camera at frame t is
    ``inv(anchor.cam_to_obj[t])`` composed into the anchor: ``camera_to_scene[t] =
    anchor.cam_to_obj[t]`` (it maps camera points to anchor points), and object k's pose at
    ``sbar = 1`` is ``camera_to_scene[t] @ inv(cam_to_obj_k[t])``. The anchor must be seen in
    every frame (it is the background).
    """
    anchor = inputs.object(inputs.anchor)
    T = len(inputs.timestamps)
    if len(anchor.frames) != T or not np.array_equal(np.sort(anchor.frames), np.arange(T)):
        raise ExportFormatError(f"the anchor ({anchor.name}) has poses at {len(anchor.frames)} of {T} frames; it must be seen in all")
    c2s = np.stack([anchor.cam_to_obj[anchor.frame_slot(t)] for t in range(T)])
    ranges = inputs.scale_ranges()
    anchor_index = inputs.anchor_pos
    sn = scale_network
    if sn is None:
        intervals = core.learned_intervals(None, ranges, anchor_index)
    else:
        intervals = core.learned_intervals(
            sn.layers, ranges, anchor_index, sn.threshold, sn.hidden_activation, sn.output_activation, draws=interval_draws
        )
    objects = []
    for i, o in enumerate(inputs.objects):
        if o.id not in grids:
            raise ExportFormatError(f"no grids for object {o.id} ({o.name})")
        density, colour = grids[o.id]
        poses = np.stack([c2s[t] @ invert_pose(M) for t, M in zip(o.frames, o.cam_to_obj)])
        objects.append(
            ExportObject(
                id=o.id, name=o.name, is_anchor=o.id == inputs.anchor, density=np.asarray(density, np.float32),
                colour=np.asarray(colour, np.float32), bbox=np.asarray(o.bbox, float), scale_range=tuple(ranges[i]),
                valid_interval=tuple(intervals[i]), frames=np.asarray(o.frames, np.int64), object_to_scene=poses,
            )
        )
    test = None
    if test_camera_to_world is not None:
        test_c2w = np.asarray(test_camera_to_world, float)
        test = np.stack([np.stack([c2s[t] @ novel_to_training_camera(inputs, test_c2w[v, t], t) for t in range(T)]) for v in range(len(test_c2w))])
    return ExportScene(
        width=inputs.width, height=inputs.height, K=np.asarray(inputs.K, float), timestamps=np.asarray(inputs.timestamps, float),
        camera_to_scene=c2s, objects=objects, test_cameras=test, scale_network=sn, samples=samples_sbar, source=source,
        meta={"inputs_source": inputs.source},
    )


def field_grids(field_module: Any, resolution: int, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Sample an ``osn.fields.Field`` on a node-aligned ``resolution^3`` grid over its bbox.

    Colour is the field's colour seen along the six axis directions, averaged: exact for
    view-independent fields, the diffuse part for view-dependent ones.
    """
    import torch

    bbox = field_module.bbox.detach().cpu().double().numpy()
    axes = [np.linspace(bbox[0, a], bbox[1, a], resolution) for a in range(3)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # (D, H, W) = (z, y, x)
    pts = torch.from_numpy(np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(np.float32))
    dirs = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32)
    sig, col = [], []
    with torch.no_grad():
        for p in pts.split(chunk):
            sig.append(field_module.density(p))
            if getattr(field_module, "view_dependent", False):
                col.append(torch.stack([field_module.color(p, d.expand_as(p)) for d in dirs]).mean(0))
            else:
                col.append(field_module.color(p, dirs[:1].expand_as(p)))
    shape = (resolution,) * 3
    return torch.cat(sig).numpy().reshape(shape), torch.cat(col).clamp(0, 1).numpy().reshape(shape + (3,))


def export_layers_from_torch(modules: Sequence[Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(W, b), ...]`` from a sequence of ``torch.nn.Linear`` modules, in order."""
    return [(m.weight.detach().cpu().double().numpy(), m.bias.detach().cpu().double().numpy()) for m in modules]


# --------------------------------------------------------------------------------------------
# From a trained run (``osn train`` run directory)
# --------------------------------------------------------------------------------------------


def scale_network_from_torch(net: Any, threshold: float) -> ScaleNetwork:
    """An ``osn.scale_net.ScaleNet`` as plain layers (ReLU hidden, sigmoid on the logit).

    ``ScaleNet`` centres its input (``s * 2 - 1``) before the first layer; that affine map is
    folded into the first layer (``W' = 2 W``, ``b' = b - W 1``) so the export's input is the
    normalised scale itself, as the manifest states.
    """
    from torch import nn

    mods = list(net.mlp)
    linears = [m for m in mods if isinstance(m, nn.Linear)]
    if any(not isinstance(m, (nn.Linear, nn.ReLU)) for m in mods) or not isinstance(mods[-1], nn.Linear):
        raise ExportFormatError(f"unexpected scale network layout {[type(m).__name__ for m in mods]}")
    layers = export_layers_from_torch(linears)
    W0, b0 = layers[0]
    layers[0] = (2.0 * W0, b0 - W0.sum(axis=1))
    return ScaleNetwork(layers=layers, hidden_activation="relu", output_activation="sigmoid", threshold=float(threshold))


def _test_rig(dataset: str | None, T: int) -> np.ndarray | None:
    """``(V, T, 4, 4)`` OpenCV test cameras of the run's dataset (world frame), if it is reachable.

    Every viewpoint with a test frame is kept; timestamps it is not listed at hold its nearest listed camera.
    """
    if not dataset or not (Path(dataset) / "scene.json").is_file():
        return None
    scene = D.load_scene(dataset)
    views = sorted({f.view for f in scene.test_frames})
    rig = np.full((len(views), T, 4, 4), np.nan)
    # A viewpoint's camera at the time it films the training video is a training frame.
    for f in scene.frames:
        if f.view in views:
            rig[views.index(f.view), f.time_index] = f.camera_to_world
    # Datasets may list a viewpoint at only some timestamps (rig.test_views); a viewpoint's camera
    # is held from its nearest listed time (benchgen's viewpoints do not move).
    for v in range(len(views)):
        known = np.nonzero(np.all(np.isfinite(rig[v]), axis=(1, 2)))[0]
        for t in range(T):
            if not np.all(np.isfinite(rig[v, t])):
                rig[v, t] = rig[v, known[np.argmin(np.abs(known - t))]]
    return rig if len(views) else None


#: Configurations drawn for an export when the run has no ``samples.npz`` and none are asked for.
DEFAULT_EXPORT_SAMPLES = 16


def export_run(
    run_dir: str | Path,
    out_dir: str | Path,
    resolution: int | None = None,
    samples: int | None = None,
    seed: int = 0,
    echo: Any = print,
) -> Path:
    """Export an ``osn train`` run directory; returns the manifest path.

    Reads the run's ``inputs/`` and ``checkpoint.pt`` (fields at their trained resolutions, the
    scale network, the training config), samples every field on a ``resolution^3`` grid
    (default: the field's own resolution), derives the learned valid intervals from the scale
    network, adds the dataset's test rig when the dataset is reachable, and valid configurations:
    with ``samples=None`` those of ``RUN/samples.npz`` (``osn sample``, the ones evaluated) when
    it exists, else ``DEFAULT_EXPORT_SAMPLES`` drawn through the scale network; with a number,
    that many drawn through the network with ``seed`` (0: none).
    """
    from osn.model.run import load_run
    from osn.model.scale_net import VALID_THRESHOLD

    if samples is not None and samples < 0:
        raise ValueError(f"the number of exported samples must be >= 0, got {samples}")
    run = Path(run_dir)
    trained = load_run(run)
    inputs = trained.inputs
    grids = {}
    for o, f in zip(inputs.objects, trained.fields):
        grids[o.id] = field_grids(f, resolution or f.resolution)
        echo(f"export: sampled object {o.id} ({o.name}) at {resolution or f.resolution}^3")
    # The learned valid set is the classifier's decision (score > 0.5), as in `osn sample` and the
    # valid-set IoU; training's stricter sampling threshold is a training setting.
    net = scale_network_from_torch(trained.net, VALID_THRESHOLD) if trained.net is not None else None
    dataset = None
    if (run / "run.json").is_file():
        dataset = D.read_json(run / "run.json").get("dataset")
    test = _test_rig(dataset, len(inputs.timestamps)) if inputs.world_to_anchor is not None else None
    scene = export_scene_from_inputs(inputs, grids, net, test_camera_to_world=test, source=str(run.resolve()))
    scene.meta.update({"name": run.name, "iteration": trained.iteration, "dataset": dataset})
    if samples is None and (run / "samples.npz").is_file():
        from osn.evaluate.evaluation import Samples

        scene.samples = Samples.load(run / "samples.npz").sbar
        echo(f"export: {len(scene.samples)} configurations from {run / 'samples.npz'}")
    elif samples is None:
        samples = DEFAULT_EXPORT_SAMPLES
    if samples and net is not None:
        ranges = np.array([o.scale_range for o in scene.objects])
        anchor_index = [o.is_anchor for o in scene.objects].index(True)

        def score(sbar: np.ndarray) -> np.ndarray:
            return core.scale_scores(net.layers, sbar, ranges, anchor_index, net.hidden_activation, net.output_activation)

        intervals = np.array([o.valid_interval for o in scene.objects])
        scene.samples = core.sample_valid_configurations(score, intervals, net.threshold, samples, seed)
    return write_export(out_dir, scene, echo=echo)


def add_export_parser(sub: Any) -> None:
    """Register ``osn export RUN --out DIR`` on the ``osn`` command's subparsers."""
    from scenecore.cli import subcommand

    def _cmd(args: Any) -> int:
        export_run(args.run, args.out, resolution=args.resolution, samples=args.samples, seed=args.seed)
        return 0

    p = subcommand(
        sub, "export", _cmd, "export a trained run for Blender (OpenVDB volumes, meshes, trajectories, scale network)",
        description="Write a versioned export directory (docs/export-and-addon.md) that the Blender add-on imports: "
        "per object an OpenVDB volume and a marching-cubes PLY, per-frame poses and cameras, the scale network and "
        "its learned valid intervals, and optionally sampled valid configurations. Written atomically.",
    )
    p.add_argument("run", help="osn train run directory (config.yaml, inputs/, checkpoint.pt)")
    p.add_argument("--out", required=True, help="export directory (created, or replaces a previous export)")
    p.add_argument("--resolution", type=int, help="grid samples per axis (default: each field's trained resolution)")
    p.add_argument("--samples", type=int, default=None,
                   help="valid configurations to draw through the scale network (0: none); default: the run's "
                   f"samples.npz from `osn sample` when present, else {DEFAULT_EXPORT_SAMPLES}")
    p.add_argument("--seed", type=int, default=0, help="seed of the configurations drawn (unused for samples.npz)")
