"""The ``osn-export`` format's writer: :class:`ExportScene` (plain numpy) to a directory, atomically.

:func:`write_export` writes a versioned JSON manifest naming every file with its size and sha256,
one OpenVDB file per object (grids ``density`` and ``color``, via bpy's bundled OpenVDB), a
PLY mesh with vertex colours per object (the exporter's surface, else the density's marching
cubes), the poses in ``arrays.npz`` and the
scale network in ``scale_net.npz``. Everything is written into a temporary sibling directory
that is renamed into place at the end, so a killed export leaves no half-written directory.
Building an :class:`ExportScene` from a trained run is :mod:`osn.export.from_run`'s job.

The format's read side, the numpy scale-network evaluator and the configuration maths live in
the kernel's ``scenecore/export_format.py`` (the add-on ships a copy; Blender may use nothing but
its own numpy). Format description: docs/export-and-addon.md.
"""

from __future__ import annotations

import errno
import io
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from scenecore import dataset as D
from scenecore import export_format as core
from scenecore.atomic import atomic_dir
from scenecore.export_format import ExportFormatError
from scenecore.lock import output_lock


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
        density_raw: optional ``(D, H, W)`` pre-activation density on the same nodes:
            ``density = softplus(density_raw)`` at the nodes, and between them the field
            interpolates ``density_raw``, not ``density``; with it the export carries the field
            itself (the manifest's ``field`` entry), not a resampling of its outputs.
        colour_raw: optional ``(D, H, W, 3)`` pre-sigmoid colour on the same nodes (needs
            ``density_raw``): the display colour is ``sigmoid(colour_raw + planes)``.
        colour_planes: optional ``(3, P, P, 3)`` pre-sigmoid colour planes over the box, added to
            ``colour_raw``: planes xy, xz, yz (``scenecore.export_format.PLANE_AXES``), ``[i, v, u]`` at box-normalised
            ``(u, v) = -1 + 2 (col, row) / (P - 1)`` along the plane's first and second axis.
        surface: optional ``(vertices (V, 3) object coordinates, faces (F, 3), colours (V, 3)
            display values)`` written as the mesh instead of the density's marching-cubes
            surface (``osn.export.from_run.view_mesh``).
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
    density_raw: np.ndarray | None = None
    colour_raw: np.ndarray | None = None
    colour_planes: np.ndarray | None = None
    surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

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
            _check_appearance(o, where)
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


def _check_appearance(o: ExportObject, where: str) -> None:
    """Raise ``ExportFormatError`` when ``o``'s optional field grids do not fit its density grid."""
    if o.density_raw is None:
        if o.colour_raw is not None or o.colour_planes is not None:
            raise ExportFormatError(f"{where}: colour_raw / colour_planes need density_raw")
        return
    shape = o.density.shape
    if np.shape(o.density_raw) != shape or (o.colour_raw is not None and np.shape(o.colour_raw) != shape + (3,)):
        raise ExportFormatError(f"{where}: density_raw {np.shape(o.density_raw)} / colour_raw {np.shape(o.colour_raw)} "
                                f"do not match the density grid {shape}")
    if o.colour_raw is None:
        raise ExportFormatError(f"{where}: density_raw needs colour_raw")
    p = o.colour_planes
    if p is not None and (np.ndim(p) != 4 or np.shape(p)[0] != 3 or np.shape(p)[1] != np.shape(p)[2] or np.shape(p)[1] < 2
                          or np.shape(p)[3] != 3):
        raise ExportFormatError(f"{where}: colour_planes has shape {np.shape(p)}, expected (3, P, P, 3)")
    for name, a in (("density_raw", o.density_raw), ("colour_raw", o.colour_raw), ("colour_planes", p)):
        if a is not None and not np.all(np.isfinite(a)):
            raise ExportFormatError(f"{where}: non-finite {name} values")


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _openvdb() -> Any:
    """bpy's bundled OpenVDB (the only OpenVDB Python module pip can provide here)."""
    try:
        import bpy  # noqa: F401 - heavy, and the optional [render] extra; only the VDB writer needs it
    except ImportError:
        raise ValueError("writing OpenVDB volumes needs bpy's bundled OpenVDB: install the render extra "
                         "(pip install -e '.[render]', Python 3.11)") from None

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
    grids = [dens, col] + _field_grids(vdb, obj, M)
    with D.atomic_path(path, suffix=".vdb") as tmp:
        vdb.write(str(tmp), grids=grids)
        _check_vdb(vdb, tmp, grids)


def density_offset(obj: ExportObject) -> float:
    """What the ``density_raw`` grid is stored relative to: one below its minimum, so every voxel
    holds at least 1 (Blender clips voxels under its volume clipping value as empty space)."""
    return float(np.floor(np.min(obj.density_raw))) - 1.0 if obj.density_raw is not None else 0.0


def _field_grids(vdb: Any, obj: ExportObject, M: list[list[float]]) -> list[Any]:
    """The field's own grids (``ExportObject.density_raw`` and ``colour_raw``) as OpenVDB grids on
    the node grid of ``density``. Its colour planes go to a separate ``.npz`` (:func:`_write_object`):
    as 2D textures they cost Blender a lookup each, as VDB grids a much slower volume."""
    if obj.density_raw is None:
        return []
    raw = vdb.FloatGrid()
    raw.copyFromArray(np.ascontiguousarray((obj.density_raw - density_offset(obj)).transpose(2, 1, 0), dtype=np.float32))
    raw.name, raw.transform = core.DENSITY_RAW_GRID, vdb.createLinearTransform(M)
    col = vdb.Vec3SGrid()
    col.copyFromArray(np.ascontiguousarray(obj.colour_raw.transpose(2, 1, 0, 3), dtype=np.float32))
    col.name, col.transform = core.COLOR_RAW_GRID, vdb.createLinearTransform(M)
    return [raw, col]


def _check_vdb(vdb: Any, path: Path, grids: list[Any]) -> None:
    """Read ``path`` back and compare it with the ``grids`` written: OpenVDB's writer returns
    normally on a full disk, leaving a truncated file that no reader opens.

    Raises:
        OSError: naming ``path``; the write is then abandoned (the caller removes the file).
    """
    try:
        back, _ = vdb.readAll(str(path))
        same = sorted((g.name, g.activeVoxelCount()) for g in back) == sorted((g.name, g.activeVoxelCount()) for g in grids)
    except Exception as e:  # OpenVDB raises KeyError, RuntimeError ... on a damaged file
        raise OSError(errno.EIO, f"OpenVDB wrote a file that does not read back ({type(e).__name__}); is the disk full?",
                      str(path)) from None
    if not same:
        raise OSError(errno.EIO, "OpenVDB wrote a file whose grids differ from those written; is the disk full?", str(path))


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


def write_export(out_dir: str | Path, scene: ExportScene, echo: Callable[[str], None] | None = None) -> Path:
    """Write ``scene`` to ``out_dir`` atomically; returns the manifest path.

    ``out_dir`` must not exist or be a previous export (which is replaced); any other existing
    path is refused so an export never overwrites unrelated files.
    """
    scene.check()
    out = Path(out_dir).resolve()
    say = echo or (lambda _msg: None)
    t0 = time.perf_counter()
    with output_lock(out):  # another export's temporary siblings are live until it ends
        if out.exists() and not (out / core.MANIFEST_NAME).is_file():
            raise ExportFormatError(f"{out}: exists and is not an OSN export; choose another --out")
        with atomic_dir(out) as tmp:  # a killed export leaves the previous one, or none
            _write_contents(tmp, scene, say)
    say(f"export: wrote {out} in {time.perf_counter() - t0:.1f} s")
    return out / core.MANIFEST_NAME


def _write_contents(tmp: Path, scene: ExportScene, say: Callable[[str], None]) -> None:
    """Every file of the export into the empty directory ``tmp``, the manifest last."""
    arrays: dict[str, np.ndarray] = {"camera_to_scene": np.asarray(scene.camera_to_scene, np.float64)}
    if scene.test_cameras is not None:
        arrays["test_cameras"] = np.asarray(scene.test_cameras, np.float64)
    if scene.samples is not None:
        arrays["samples_sbar"] = np.asarray(scene.samples, np.float64)
    (tmp / "objects").mkdir()
    objects = []
    for o in scene.objects:
        objects.append(_write_object(tmp, o))
        arrays[f"obj{o.id}_frames"] = np.asarray(o.frames, np.int64)
        arrays[f"obj{o.id}_object_to_scene"] = np.asarray(o.object_to_scene, np.float64)
        say(f"export: object {o.id} ({o.name}) grid {o.density.shape}, mesh {objects[-1]['mesh_faces']} faces")
    D.atomic_write_bytes(tmp / "arrays.npz", _npz_bytes(arrays))
    net = _write_scale_network(tmp, scene.scale_network)
    files = []
    for p in sorted(tmp.rglob("*")):
        if p.is_file():
            rel = p.relative_to(tmp).as_posix()
            files.append({"path": rel, "bytes": p.stat().st_size, "sha256": core.sha256_file(str(p))})
    D.atomic_write_json(tmp / core.MANIFEST_NAME, _manifest(scene, objects, net, files))


def _write_object(tmp: Path, o: ExportObject) -> dict[str, Any]:
    """Write one object's volume (and mesh, unless empty) under ``tmp``; returns its manifest entry."""
    vol_rel = f"objects/{o.id}.vdb"
    _write_vdb(tmp / vol_rel, o)
    planes_rel = None
    if o.colour_planes is not None:
        planes_rel = f"objects/{o.id}_planes.npz"
        D.atomic_write_bytes(tmp / planes_rel, _npz_bytes({"planes": np.asarray(o.colour_planes, np.float32)}))
    mesh = o.surface if o.surface is not None else object_mesh(o)
    mesh_rel = None
    if mesh is not None:
        mesh_rel = f"objects/{o.id}.ply"
        D.atomic_write_bytes(tmp / mesh_rel, _ply_bytes(*mesh))
    return {
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
        "mesh_source": "training views" if o.surface is not None else "marching cubes",
        "field": _field_entry(o, planes_rel),
    }


def _field_entry(o: ExportObject, planes_rel: str | None) -> dict[str, Any] | None:
    """The manifest's ``field`` entry of an object (None when the export has no field grids)."""
    if o.density_raw is None:
        return None
    return {
        "density": {"grid": core.DENSITY_RAW_GRID, "offset": density_offset(o), "activation": "softplus"},
        "color": {"grid": core.COLOR_RAW_GRID, "activation": "sigmoid",
                  "planes": None if planes_rel is None else {"file": planes_rel, "array": "planes",
                                                             "size": int(o.colour_planes.shape[1]), "axes": [list(x) for x in core.PLANE_AXES]}},
        "outside_bbox": "zero density",
    }


def _write_scale_network(tmp: Path, sn: ScaleNetwork | None) -> dict[str, Any] | None:
    """Write ``scale_net.npz`` under ``tmp``; returns its manifest entry (None without a network)."""
    if sn is None:
        return None
    D.atomic_write_bytes(
        tmp / "scale_net.npz",
        _npz_bytes({f"{p}{i}": np.asarray(a, np.float64) for i, (W, b) in enumerate(sn.layers) for p, a in (("W", W), ("b", b))}),
    )
    return {
        "file": "scale_net.npz",
        "layers": len(sn.layers),
        "layout": "y = act(x @ W{i}.T + b{i})",
        "hidden_activation": sn.hidden_activation,
        "output_activation": sn.output_activation,
        "threshold": float(sn.threshold),
        "input": "normalised scales (Eq. 1) of the non-anchor objects, in manifest object order",
    }


def _manifest(scene: ExportScene, objects: list[dict], net: dict | None, files: list[dict]) -> dict[str, Any]:
    """The ``osn_export.json`` content (docs/export-and-addon.md)."""
    return {
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
            "field": "object.field: density = softplus(grid + offset) inside bbox, 0 outside; display colour = "
                     "sigmoid(color grid + planes), trilinear between nodes; planes[i, v, u] bilinear at box-normalised "
                     "-1 + 2 (u, v) / (P - 1) along axes[i] (the learned field itself)",
            "mesh": "binary PLY in object coordinates, uchar sRGB vertex colours; mesh_source: the marching-cubes "
                    "surface at mesh_level, or the object's training-view renders fused (depth and colour)",
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
