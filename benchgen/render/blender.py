"""The Cycles renderer: the only module of the project that imports ``bpy``.

One ``Renderer`` builds the Blender scene once (per process) from a ``BuiltScene`` and then only
moves the camera and the objects between renders. Choices that keep the benchmark exact (see
"The benchmark construction" in DESIGN):

* emission-only materials whose colour is an object-space procedural texture times a fixed
  function of the world normal: scaling an object about the camera centre leaves every camera
  ray's colour unchanged (no lights, shadows or bounces, ``max_bounces = 0``);
* pixel-centre rays: a pixel filter of ``PIXEL_FILTER_WIDTH`` px puts every sample on the pixel
  centre, so colour, depth and object index of a pixel all come from the same ray (the one the
  exact bounds are computed from), as in NeRF-style renderers. Cycles' default (Blackman-Harris,
  1.5 px) mixes rays up to 0.75 px off-centre into a pixel's colour: neither the bounds nor the
  ids constrain those rays, and near silhouettes they hit surfaces at grazing angles;
* band-limited textures (``TEXTURE_OCTAVES``, node scale 1): colour must not vary much below the
  pixel scale, because a rescaled object's hit points move by float32 rounding (~1e-7 m, up to
  ~1e-4 m at grazing angles) and the texture gradient multiplies that into a colour difference;
* no denoiser, no adaptive sampling, fixed seed, Standard view transform, no dither;
* depth (planar), object index and normal come from the view-layer passes of a multilayer EXR
  written to a temporary directory (``Render Result`` pixels are empty in background mode).
"""

from __future__ import annotations

import contextlib
import errno
import math
import multiprocessing.util
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scenecore.cameras import fov_from_intrinsics, opengl_from_opencv, pixel_rays
from scenecore.dataset import NO_OBJECT
from benchgen.scene.geometry import BuiltScene, ObjectGeometry
from benchgen.scene.spec import Texture

#: Fixed direction of the normal-dependent shading term (world space, normalised below).
SHADE_DIRECTION = np.array([0.35, -0.55, 0.76])
#: Depth values at or above this are the background (Cycles writes 1e10).
BACKGROUND_DEPTH = 1e9
#: Pixel filter width (px). Tiny, so that every sample is (to 0.005 px) the pixel-centre ray:
#: the colour is then a function of exactly the ray behind the depth and index passes, which
#: makes the per-pixel bounds exact and tight for the colour too. Extra samples only repeat that
#: ray, so 1 sample per pixel is exact; the price is aliasing (no anti-aliasing at silhouettes).
PIXEL_FILTER_WIDTH = 0.01
#: Fractal noise octaves above the base frequency (Blender's default detail is 2; 8 would put the
#: finest octave at 0.1 mm, far below a pixel): 3 octaves = features down to 1/8 of the
#: base wavelength, about a pixel at 128 px for the presets' scales.
TEXTURE_OCTAVES = 3.0


@dataclass
class RenderOutput:
    """One rendered view: scene-linear RGB, planar depth (+inf = nothing), ids (255 = nothing).

    ``facing`` is ``|cos|`` of the angle between the pixel-centre ray and the surface normal
    (0 where nothing is hit): float rounding of hit points grows like ``1 / facing``.
    """

    rgb: np.ndarray
    depth: np.ndarray
    ids: np.ndarray
    facing: np.ndarray | None = None

    def rgb8(self) -> np.ndarray:
        return linear_to_srgb8(self.rgb)


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB to 8-bit sRGB (the standard piecewise transfer curve)."""
    x = np.clip(rgb, 0.0, 1.0).astype(np.float64)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


@contextlib.contextmanager
def _quiet():
    """Silence Blender's per-render log lines (written to the process's stdout/stderr fds)."""
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


class Renderer:
    """A Blender scene for one ``BuiltScene``; ``render`` draws any camera and object poses."""

    def __init__(self, built: BuiltScene, threads: int | None = None):
        import bpy

        self.bpy = bpy
        self.built = built
        self.render_seconds = 0.0
        self.render_calls = 0
        tmp = tempfile.mkdtemp(prefix="benchgen-render-")
        # multiprocessing's Finalize (unlike TemporaryDirectory's weakref finaliser) also runs
        # when a Pool worker exits through os._exit, so spawned renderers do not leak this dir.
        multiprocessing.util.Finalize(self, shutil.rmtree, args=(tmp,), kwargs={"ignore_errors": True}, exitpriority=0)
        self._exr = str(Path(tmp) / "frame.exr")
        with _quiet():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self._configure(threads)
        self.objects = [self._add_object(k, g) for k, g in enumerate(built.objects)]
        self._hidden: list[bool] = [False] * len(self.objects)
        # Last matrix assigned per object (camera last): assigning even an unchanged matrix tags
        # the object for a re-sync, and with persistent data an untouched object costs nothing.
        self._matrices: list[bytes | None] = [None] * (len(self.objects) + 1)
        cam = bpy.data.cameras.new("camera")
        cam.sensor_fit = "HORIZONTAL"
        cam.angle = math.radians(fov_from_intrinsics(built.scene.intrinsics.matrix(), built.scene.width))
        cam.clip_start, cam.clip_end = 1e-3, 1e4  # configurations bring objects close to the camera
        self.camera = bpy.data.objects.new("camera", cam)
        self.scene.collection.objects.link(self.camera)
        self.scene.camera = self.camera

    def _configure(self, threads: int | None) -> None:
        sc, spec = self.scene, self.built.spec
        sc.render.engine = "CYCLES"
        sc.cycles.device = "CPU"
        sc.cycles.use_adaptive_sampling = False
        sc.cycles.use_denoising = False
        sc.cycles.max_bounces = 0
        sc.cycles.seed = spec.seed
        sc.cycles.filter_width = PIXEL_FILTER_WIDTH
        sc.render.resolution_x, sc.render.resolution_y = spec.width, spec.height
        sc.render.resolution_percentage = 100
        sc.render.dither_intensity = 0.0
        # Keep Cycles' scene between renders: only what moved is re-synced (a small frame where only
        # the camera moves renders several times faster). Renders stay bit-identical to a fresh scene's
        # whatever was rendered before (tests/benchgen/test_render.py), so sharding still does
        # not change results.
        sc.render.use_persistent_data = True
        sc.view_settings.view_transform = "Standard"
        if threads:
            sc.render.threads_mode = "FIXED"
            sc.render.threads = threads
        vl = sc.view_layers[0]
        vl.use_pass_z = True
        vl.use_pass_object_index = True
        vl.use_pass_normal = True
        im = sc.render.image_settings
        im.media_type = "MULTI_LAYER_IMAGE"
        im.file_format = "OPEN_EXR_MULTILAYER"
        im.color_depth = "32"
        im.exr_codec = "NONE"  # the file lives for one read; compression only costs time
        sc.render.filepath = self._exr

    def _add_object(self, index: int, geom: ObjectGeometry):
        bpy = self.bpy
        mesh = bpy.data.meshes.new(geom.name)
        mesh.from_pydata(geom.mesh.vertices.tolist(), [], geom.mesh.faces.tolist())
        for i, tex in enumerate(geom.textures):
            mesh.materials.append(self._material(f"{geom.name}.{i}", tex, geom.seed + 7919 * i))
        if geom.face_texture is not None:
            mesh.polygons.foreach_set("material_index", geom.face_texture.astype(np.int32))
        mesh.update()
        obj = bpy.data.objects.new(geom.name, mesh)
        obj.pass_index = index + 1  # 0 is "nothing" in the Object Index pass
        self.scene.collection.objects.link(obj)
        return obj

    def _material(self, name: str, tex: Texture, seed: int):
        """Emission = texture(object coords) x (0.55 + 0.45 |n . l|)."""
        mat = self.bpy.data.materials.new(name)
        nt = mat.node_tree if mat.node_tree is not None else None
        if nt is None:
            mat.use_nodes = True
            nt = mat.node_tree
        nt.nodes.clear()
        g = _Nodes(nt)
        rng = np.random.default_rng(seed if tex.seed is None else tex.seed)
        coord = g.new("ShaderNodeTexCoord")
        mapping = g.new("ShaderNodeMapping")
        mapping.inputs["Location"].default_value = rng.uniform(-50, 50, 3).tolist()
        mapping.inputs["Scale"].default_value = [tex.scale] * 3
        g.link(coord.outputs["Object"], mapping.inputs["Vector"])
        vec = mapping.outputs["Vector"]
        noise = g.new("ShaderNodeTexNoise")
        # Node scale 1: the spec's `scale` (the mapping) is the frequency in cycles per metre.
        noise.inputs["Scale"].default_value = 1.0
        noise.inputs["Detail"].default_value = TEXTURE_OCTAVES
        noise.inputs["Roughness"].default_value = 0.65
        g.link(vec, noise.inputs["Vector"])
        base = _pattern_colour(g, tex, vec, noise.outputs["Fac"])
        # Fine noise detail on every kind, so that feature detectors find corners everywhere.
        detail = g.math("MULTIPLY_ADD", noise.outputs["Fac"], 0.6)
        detail.node.inputs[2].default_value = 0.7
        factor = g.math("MULTIPLY", detail, _normal_shading(g))
        mix = g.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.blend_type = "MULTIPLY"
        mix.inputs["Factor"].default_value = 1.0
        g.link(base, mix.inputs[6])
        g.link(factor, mix.inputs[7])
        emission = g.new("ShaderNodeEmission")
        g.link(mix.outputs[2], emission.inputs["Color"])
        out = g.new("ShaderNodeOutputMaterial")
        g.link(emission.outputs["Emission"], out.inputs["Surface"])
        return mat

    def render(self, camera_to_world: np.ndarray, poses: np.ndarray, samples: int | None = None, only: int | None = None) -> RenderOutput:
        """Render one view.

        Args:
            camera_to_world: 4x4 OpenCV camera pose.
            poses: ``(K, 4, 4)`` object-to-world poses (may include a uniform scale).
            samples: Cycles samples per pixel (default: the spec's).
            only: render this object alone (the others hidden), e.g. for per-object depth.
        """
        from mathutils import Matrix

        if len(poses) != len(self.objects):
            raise ValueError(f"render: {len(poses)} poses for {len(self.objects)} objects")
        for k, (obj, m) in enumerate([*zip(self.objects, poses), (self.camera, opengl_from_opencv(camera_to_world))]):
            m = np.asarray(m, dtype=np.float64)
            if self._matrices[k] != m.tobytes():
                obj.matrix_world = Matrix(m.tolist())
                self._matrices[k] = m.tobytes()
        for k, obj in enumerate(self.objects):
            hide = only is not None and k != only
            if hide != self._hidden[k]:
                obj.hide_render = hide
                self._hidden[k] = hide
        self.scene.cycles.samples = samples or self.built.spec.samples
        t0 = time.perf_counter()
        with _quiet():
            self.bpy.ops.render.render(write_still=True)
        self.render_seconds += time.perf_counter() - t0
        self.render_calls += 1
        out, normal = self._read_render()
        _, dirs = pixel_rays(self.built.scene.intrinsics.matrix(), camera_to_world, self.built.spec.width, self.built.spec.height)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        out.facing = np.abs(np.einsum("pc,pc->p", normal.reshape(-1, 3), dirs)).reshape(out.ids.shape).astype(np.float32)
        return out

    def _read_render(self) -> tuple[RenderOutput, np.ndarray]:
        """The EXR Blender just wrote. Blender reports a failed write on its (silenced) console
        only, so a full disk shows here, as a truncated file: an ``OSError`` naming it, not the
        reader's messages about missing passes."""
        try:
            with _quiet():  # the reader prints its complaints about a truncated file itself
                return read_multilayer_exr(self._exr)
        except Exception as e:
            raise OSError(errno.EIO, f"cannot read back Blender's render ({type(e).__name__}: {e}); is the disk full?",
                          self._exr) from None


def read_multilayer_exr(path: str) -> tuple[RenderOutput, np.ndarray]:
    """Read Combined, Depth, Object Index and Normal passes in dataset conventions.

    Returns the view (``facing`` unset: it needs the camera) and the ``(H, W, 3)`` world normals.
    """
    import OpenEXR

    ch: dict[str, np.ndarray] = {}
    with OpenEXR.File(path, separate_channels=True) as f:
        for part in f.parts:
            for name, c in part.channels.items():
                ch[name.split(".", 1)[-1]] = np.array(c.pixels)
    rgb = np.stack([ch["Combined.R"], ch["Combined.G"], ch["Combined.B"]], axis=-1).astype(np.float32)
    depth = ch["Depth.Z"].astype(np.float32)
    depth[depth >= BACKGROUND_DEPTH] = np.inf
    index = np.rint(ch["Object Index.X"]).astype(np.int64)
    ids = np.where(index > 0, index - 1, NO_OBJECT).astype(np.uint8)
    normal = np.stack([ch["Normal.X"], ch["Normal.Y"], ch["Normal.Z"]], axis=-1).astype(np.float64)
    return RenderOutput(rgb, depth, ids), normal


class _Nodes:
    """Adds and links the nodes of one material's node tree (``new``, ``link`` and two shorthands)."""

    def __init__(self, node_tree: Any):
        self.new, self.link = node_tree.nodes.new, node_tree.links.new

    def ramp(self, fac: Any, colors: list[list[float]]) -> Any:
        """A two-colour ramp (stops at 0.3 and 0.7) of the scalar socket ``fac``; returns its colour socket."""
        r = self.new("ShaderNodeValToRGB")
        r.color_ramp.elements[0].position, r.color_ramp.elements[1].position = 0.3, 0.7
        r.color_ramp.elements[0].color = [*colors[0], 1.0]
        r.color_ramp.elements[1].color = [*colors[1], 1.0]
        self.link(fac, r.inputs["Fac"])
        return r.outputs["Color"]

    def math(self, operation: str, a: Any, b: Any) -> Any:
        """A Math node of sockets or constants ``a``, ``b``; returns its output socket."""
        m = self.new("ShaderNodeMath")
        m.operation = operation
        for sock, v in zip(m.inputs, (a, b)):
            if isinstance(v, (int, float)):
                sock.default_value = v
            else:
                self.link(v, sock)
        return m.outputs[0]


def _pattern_colour(g: _Nodes, tex: Texture, vec: Any, noise_fac: Any) -> Any:
    """The texture's base colour socket at object coordinates ``vec`` (noise, checker or voronoi)."""
    if tex.kind == "noise":
        return g.ramp(noise_fac, tex.colors)
    if tex.kind == "checker":
        pat = g.new("ShaderNodeTexChecker")
        pat.inputs["Color1"].default_value = [*tex.colors[0], 1.0]
        pat.inputs["Color2"].default_value = [*tex.colors[1], 1.0]
        pat.inputs["Scale"].default_value = 1.0
        g.link(vec, pat.inputs["Vector"])
        return pat.outputs["Color"]
    pat = g.new("ShaderNodeTexVoronoi")  # voronoi
    pat.inputs["Scale"].default_value = 1.0
    g.link(vec, pat.inputs["Vector"])
    return g.ramp(pat.outputs["Distance"], tex.colors)


def _normal_shading(g: _Nodes) -> Any:
    """The socket ``0.55 + 0.45 |n . SHADE_DIRECTION|`` of the world normal: a fixed function of it."""
    geo = g.new("ShaderNodeNewGeometry")
    dot = g.new("ShaderNodeVectorMath")
    dot.operation = "DOT_PRODUCT"
    g.link(geo.outputs["Normal"], dot.inputs[0])
    dot.inputs[1].default_value = (SHADE_DIRECTION / np.linalg.norm(SHADE_DIRECTION)).tolist()
    shade = g.math("MULTIPLY_ADD", g.math("ABSOLUTE", dot.outputs["Value"], 0.0), 0.45)
    shade.node.inputs[2].default_value = 0.55
    return shade
