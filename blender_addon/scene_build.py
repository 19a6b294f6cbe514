"""Build and update the Blender scene of an OSN export (bpy; Blender 4.2 to 5.0).

Layout of an imported export: a collection ``OSN <name>`` holding, per learned object, an empty
``<name>`` that carries the keyed trajectory and the scale slider, parented to it a volume object
(the learned grids, emission-absorption material) and a mesh object (marching-cubes surface,
vertex-colour emission material); plus the training camera and the test-rig cameras, keyed per
frame. Everything the add-on needs later (base poses, camera centres, the scale network, the
sampled configurations) is stored as ID properties, so a saved .blend works without the export.
"""

from __future__ import annotations

import json
from typing import Any

import bpy
import numpy as np
from mathutils import Matrix

from ._kernel import export_format as core
from .materials import P_INV, mesh_material, plane_images, volume_material

#: Layered actions (slot -> layer -> strip -> channelbag) replace ``Action.fcurves`` from 4.4 on.
LAYERED_ACTIONS = bpy.app.version >= (4, 4, 0)
#: Custom property names (kept short and prefixed so they never clash with a user's).
P_SCALE, P_KEYED, P_INDEX = "osn_scale", "osn_keyed_scale", "osn_index"
P_BASE, P_FRAMES, P_MANIFEST, P_CENTRES = "osn_base_pose", "osn_frames", "osn_manifest", "osn_camera_centres"
P_SAMPLES = "osn_samples"
_INTERP_CONSTANT, _INTERP_LINEAR = 0, 1  # keyframe interpolation enum index: CONSTANT 0, LINEAR 1, BEZIER 2


# --------------------------------------------------------------------------------------------
# Keyframes
# --------------------------------------------------------------------------------------------


def _fcurve_collection(obj: bpy.types.Object, create: bool, made: _Created | None = None) -> Any:
    """The F-curve collection animating ``obj`` (its slot's channelbag on 4.4+, the action on 4.2).

    A new action is recorded in ``made`` (when given) so a failed import removes it again.
    """
    ad = obj.animation_data or (obj.animation_data_create() if create else None)
    if ad is None:
        return None
    if ad.action is None:
        if not create:
            return None
        action = bpy.data.actions.new(f"{obj.name} OSN")
        if made is not None:
            made.add(action)
        ad.action = action
    action = ad.action
    if not LAYERED_ACTIONS:
        return action.fcurves
    if ad.action_slot is None:
        ad.action_slot = action.slots.new(id_type="OBJECT", name=obj.name)
    layer = action.layers[0] if action.layers else action.layers.new("Layer")
    strip = layer.strips[0] if layer.strips else layer.strips.new(type="KEYFRAME")
    return strip.channelbag(ad.action_slot, ensure=True).fcurves


def key_matrices(obj: bpy.types.Object, frames: np.ndarray, matrices: np.ndarray, made: _Created | None = None) -> None:
    """Key ``obj``'s location, quaternion and scale to ``matrices (F, 4, 4)`` at Blender ``frames``.

    Writes whole F-curves with ``foreach_set`` (one call per channel, far faster than
    ``keyframe_insert``); existing curves are overwritten in place, so re-keying keeps the action.
    An action created here is recorded in ``made`` (the import's rollback record) when given.
    """
    obj.rotation_mode = "QUATERNION"
    loc, quat, scl = np.zeros((len(frames), 3)), np.zeros((len(frames), 4)), np.zeros((len(frames), 3))
    prev = None
    for i, M in enumerate(matrices):
        t, q, s = Matrix(M.tolist()).decompose()
        if prev is not None:
            q.make_compatible(prev)  # shortest-path interpolation between keys
        prev = q
        loc[i], quat[i], scl[i] = t, q, s
    fcurves = _fcurve_collection(obj, create=True, made=made)
    f = np.asarray(frames, dtype=np.float64)
    for path, values in (("location", loc), ("rotation_quaternion", quat), ("scale", scl)):
        for idx in range(values.shape[1]):
            fc = fcurves.find(path, index=idx) or fcurves.new(path, index=idx, **({} if LAYERED_ACTIONS else {"action_group": "Object Transforms"}))
            kp = fc.keyframe_points
            if len(kp) != len(f):
                kp.clear()
                kp.add(len(f))
            co = np.empty(2 * len(f))
            co[0::2], co[1::2] = f, values[:, idx]
            kp.foreach_set("co", co)
            kp.foreach_set("handle_left", co)
            kp.foreach_set("handle_right", co)
            kp.foreach_set("interpolation", np.full(len(f), _INTERP_LINEAR, dtype=np.int32))
            fc.update()


def key_presence(obj: bpy.types.Object, num_frames: int, present: np.ndarray, made: _Created | None = None,
                 paths: tuple[str, ...] = ("hide_viewport", "hide_render")) -> None:
    """Hide ``obj`` (``paths``: viewport and render, constant keys) at the Blender frames where its
    object has no pose: it left the training view then, so the export knows nowhere to put it, and
    holding its last pose would show it where it never was. ``present`` holds 0-based time indices."""
    hidden = np.ones(num_frames)
    hidden[np.asarray(present, dtype=np.int64)] = 0.0
    fcurves = _fcurve_collection(obj, create=True, made=made)
    f = np.arange(num_frames, dtype=np.float64) + 1.0
    co = np.empty(2 * num_frames)
    co[0::2], co[1::2] = f, hidden
    for path in paths:
        fc = fcurves.find(path) or fcurves.new(path)
        fc.keyframe_points.clear()
        fc.keyframe_points.add(num_frames)
        fc.keyframe_points.foreach_set("co", co)
        fc.keyframe_points.foreach_set("interpolation", np.full(num_frames, _INTERP_CONSTANT, dtype=np.int32))
        fc.update()


# --------------------------------------------------------------------------------------------
# Import
# --------------------------------------------------------------------------------------------


class _Created:
    """Every datablock made during an import, so a failure can remove them all (scene untouched)."""

    def __init__(self) -> None:
        self.ids: list[Any] = []

    def add(self, idblock: Any) -> Any:
        self.ids.append(idblock)
        return idblock

    def remove_all(self) -> None:
        for idb in reversed(self.ids):
            try:
                idb.user_clear()
                bpy.data.batch_remove([idb])
            except ReferenceError:
                pass  # already freed with its owner


def _mesh_data(name: str, mesh: dict[str, np.ndarray]) -> bpy.types.Mesh:
    me = bpy.data.meshes.new(name)
    v, f = mesh["vertices"], mesh["faces"]
    me.vertices.add(len(v))
    me.vertices.foreach_set("co", v.astype(np.float32).ravel())
    me.loops.add(3 * len(f))
    me.loops.foreach_set("vertex_index", f.astype(np.int32).ravel())
    me.polygons.add(len(f))
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * len(f), 3, dtype=np.int32))
    me.update(calc_edges=True)
    attr = me.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    # PLY colours are display (sRGB) bytes; they are emitted as they are, like the volumes'
    # colours, and the Raw view transform shows them unchanged (import_export).
    attr.data.foreach_set("color", (mesh["colors"].astype(np.float32) / 255.0).ravel())
    me.validate()
    return me


def _camera_data(name: str, data: core.ExportData) -> bpy.types.Camera:
    """Pinhole camera matching pixel intrinsics ``K`` with the render size (square pixels)."""
    cam = bpy.data.cameras.new(name)
    W, H, K = data.width, data.height, data.K
    cam.sensor_fit = "HORIZONTAL" if W >= H else "VERTICAL"
    cam.sensor_width = cam.sensor_height = 36.0
    size = max(W, H)
    cam.lens = float(K[0, 0]) * cam.sensor_width / size
    # Blender's shift is in units of the larger image side; +y is up in Blender, down in OpenCV.
    cam.shift_x = (W / 2.0 - float(K[0, 2])) / size
    cam.shift_y = (float(K[1, 2]) - H / 2.0) / size
    cam.clip_start, cam.clip_end = 1e-3, 1e4
    return cam


def _check_volume(vol: bpy.types.Volume, path: str, field: core.FieldGrids | None = None) -> None:
    if not vol.grids.load():
        raise core.ExportFormatError(f"{path}: Blender cannot load the volume ({vol.grids.error_message or 'unknown error'})")
    names = {g.name for g in vol.grids}
    need = {"density", "color"} | (set() if field is None else {field.density_grid, field.color_grid})
    if not need <= names:
        raise core.ExportFormatError(f"{path}: volume lacks grids {sorted(need - names)} (has {sorted(names)})")


def import_export(context: bpy.types.Context, path: str) -> bpy.types.Collection:
    """Import the export at ``path`` (directory or manifest) into the scene; return its collection.

    All-or-nothing: the export is fully validated (``scenecore.export_format.read_export``, then Blender loads
    every volume) before anything is linked into the scene, and every datablock made is removed
    again if any step fails; the exception propagates with a message naming the bad file.
    """
    data = core.read_export(path)
    made = _Created()
    scene = context.scene
    try:
        coll = _export_collection(data, made)
        for i, o in enumerate(data.objects):
            _import_object(coll, data, i, o, made)
        cam_objs = _import_cameras(coll, data, made)
    except BaseException:
        made.remove_all()
        raise
    scene.collection.children.link(coll)
    scene.camera = cam_objs[0]
    _render_settings(scene, data)
    scene.osn_collection = coll
    return coll


def _export_collection(data: core.ExportData, made: _Created) -> bpy.types.Collection:
    """The export's collection, holding its manifest, camera centres, scale network and samples
    as custom properties (what the panel's sampling and ranges read back)."""
    meta = data.manifest.get("meta")
    title = (meta.get("name") if isinstance(meta, dict) else None) or "export"
    coll = made.add(bpy.data.collections.new(f"OSN {title}"))
    coll[P_MANIFEST] = json.dumps(data.manifest)
    coll[P_CENTRES] = data.camera_to_scene[:, :3, 3].ravel().tolist()
    if data.net_layers is not None:
        for i, (W, b) in enumerate(data.net_layers):
            coll[f"osn_net_W{i}"] = W.ravel().tolist()
            coll[f"osn_net_b{i}"] = b.ravel().tolist()
    samples = data.samples if data.samples is not None else np.zeros((0, len(data.objects)))
    coll[P_SAMPLES] = samples.ravel().tolist()
    return coll


def _import_object(coll: bpy.types.Collection, data: core.ExportData, i: int, o: core.ExportObjectData,
                   made: _Created) -> None:
    """Object ``i`` of the export: an empty carrying its pose, frames and scale (a property bounded
    by its learned valid interval), parent of its volume and, when exported, its preview mesh;
    keyed at its scale."""
    empty = made.add(bpy.data.objects.new(o.name, None))
    empty.empty_display_type = "CUBE"
    empty.empty_display_size = float(np.abs(o.bbox).max())
    coll.objects.link(empty)
    empty[P_INDEX] = i
    empty[P_BASE] = o.object_to_scene.ravel().tolist()
    empty[P_FRAMES] = o.frames.tolist()
    empty[P_KEYED] = 1.0
    if not o.is_anchor:
        lo, hi = o.valid_interval
        empty[P_SCALE] = float(np.clip(1.0, lo, hi))
        ui = empty.id_properties_ui(P_SCALE)
        ui.update(min=lo, max=hi, soft_min=lo, soft_max=hi, default=float(np.clip(1.0, lo, hi)),
                  description=f"Actual scale of {o.name} (learned valid interval [{lo:.4g}, {hi:.4g}])")
    vol = made.add(bpy.data.volumes.new(f"{o.name} volume"))
    vol.filepath = o.volume_path
    _check_volume(vol, o.volume_path, o.field)
    # Density per world unit (osn_inv_scale compensates the object's scale); full float
    # precision: the pre-activation density goes through an exponential.
    vol.render.space, vol.render.precision = "WORLD", "FULL"
    planes = None
    if o.field is not None and o.field.planes is not None:
        planes = [made.add(img) for img in plane_images(f"OSN {o.name}", o.field.planes)]
    vol.materials.append(made.add(volume_material(f"OSN {o.name} volume", o, planes)))
    vobj = made.add(bpy.data.objects.new(f"{o.name} volume", vol))
    vobj[P_INV] = 1.0
    parts = [vobj]
    if o.mesh is not None and len(o.mesh["faces"]):
        me = made.add(_mesh_data(f"{o.name} mesh", o.mesh))
        me.materials.append(made.add(mesh_material(f"OSN {o.name} surface", "Col")))
        parts.append(made.add(bpy.data.objects.new(f"{o.name} mesh", me)))
    for part in parts:
        coll.objects.link(part)
        part.parent = empty
        # The mesh is a viewport preview, not rendered: renders show the volume, the
        # learned field (docs/export-and-addon.md has both measured). render_meshes()
        # lets them into renders.
        part.hide_render = part.type == "MESH"
        if len(o.frames) < data.num_frames:
            key_presence(part, data.num_frames, o.frames, made, _presence_paths(part))
    _apply_scale(empty, coll, float(empty.get(P_SCALE, 1.0)), made)  # keys the poses at that scale


def _import_cameras(coll: bpy.types.Collection, data: core.ExportData, made: _Created) -> list[bpy.types.Object]:
    """The training camera and, when exported, each test camera, keyed at every frame; the
    training camera first."""
    frames_all = np.arange(data.num_frames) + 1.0
    cams = [("OSN training camera", data.camera_to_scene)]
    if data.test_cameras is not None:
        cams += [(f"OSN test camera {v}", c) for v, c in enumerate(data.test_cameras)]
    cam_objs = []
    for name, c2s in cams:
        cobj = made.add(bpy.data.objects.new(name, made.add(_camera_data(name, data))))
        coll.objects.link(cobj)
        key_matrices(cobj, frames_all, core.blender_camera_matrices(c2s), made)
        cam_objs.append(cobj)
    return cam_objs


def _render_settings(scene: bpy.types.Scene, data: core.ExportData) -> None:
    """The scene renders as OSN does: the export's image size, its colours shown unchanged, Cycles
    ray-marching the volumes with pixel-centre rays, the video's frame range."""
    scene.render.resolution_x, scene.render.resolution_y = data.width, data.height
    scene.render.resolution_percentage = 100
    # The learned colours are display values composited as they are (as OSN renders): shown
    # unchanged, not treated as scene-linear light and encoded again.
    scene.view_settings.view_transform, scene.view_settings.look = "Raw", "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    cycles = getattr(scene, "cycles", None)
    if cycles is not None:
        # Ray marching integrates emission-absorption with little noise (null scattering, the
        # default, needs many times the samples), and pixel-centre rays are what OSN renders
        # (the default 1.5 px filter blurs a low-resolution view).
        if hasattr(cycles, "volume_biased"):
            cycles.volume_biased = True
        # Steps of a quarter voxel: a density that rises within a voxel (a surface) is missed
        # or smeared by steps of a whole one.
        cycles.volume_step_rate = 0.25
        cycles.filter_width = 0.01
    scene.frame_start, scene.frame_end = 1, data.num_frames


# --------------------------------------------------------------------------------------------
# Configurations
# --------------------------------------------------------------------------------------------


def _presence_paths(part: bpy.types.Object) -> tuple[str, ...]:
    """What presence keys hide: a mesh's render visibility is left off (a viewport preview)."""
    return ("hide_viewport",) if part.type == "MESH" and part.hide_render else ("hide_viewport", "hide_render")


def render_meshes(coll: bpy.types.Collection, on: bool = True) -> None:
    """Let the meshes into renders (``on``) or keep them out, hidden where their object has no pose."""
    num_frames = len(manifest(coll)["timestamps"])
    for empty in osn_objects(coll):
        frames = np.asarray(empty[P_FRAMES], dtype=np.int64)
        for part in empty.children:
            if part.type != "MESH":
                continue
            fcurves = _fcurve_collection(part, create=False)
            keyed = fcurves.find("hide_render") if fcurves is not None else None
            if keyed is not None:
                fcurves.remove(keyed)
            part.hide_render = not on
            if on and len(frames) < num_frames:
                key_presence(part, num_frames, frames, paths=("hide_render",))


def osn_objects(coll: bpy.types.Collection) -> list[bpy.types.Object]:
    """The per-object empties of an imported export, in manifest order."""
    return sorted((o for o in coll.objects if P_INDEX in o), key=lambda o: o[P_INDEX])


def manifest(coll: bpy.types.Collection) -> dict[str, Any]:
    return json.loads(coll[P_MANIFEST])


def _apply_scale(empty: bpy.types.Object, coll: bpy.types.Collection, sbar: float, made: _Created | None = None) -> None:
    """Re-key ``empty`` at scale ``sbar`` about each frame's training camera centre."""
    base = np.asarray(empty[P_BASE], dtype=np.float64).reshape(-1, 4, 4)
    frames = np.asarray(empty[P_FRAMES], dtype=np.float64)
    centres = np.asarray(coll[P_CENTRES], dtype=np.float64).reshape(-1, 3)[frames.astype(int)]
    key_matrices(empty, frames + 1.0, core.configured_poses(base, centres, sbar), made)
    empty[P_KEYED] = sbar
    for child in empty.children:
        if P_INV in child:
            child[P_INV] = 1.0 / sbar


def current_scales(coll: bpy.types.Collection) -> np.ndarray:
    """``(K,)`` actual scales of the sliders (the anchor's is 1)."""
    return np.array([float(o.get(P_SCALE, 1.0)) for o in osn_objects(coll)])


def sync_scales(coll: bpy.types.Collection) -> int:
    """Re-key every object whose slider moved since it was last keyed; returns how many."""
    n = 0
    for o in osn_objects(coll):
        if P_SCALE in o and abs(float(o[P_SCALE]) - float(o[P_KEYED])) > 0.0:
            _apply_scale(o, coll, float(o[P_SCALE]))
            n += 1
    return n


def set_scales(coll: bpy.types.Collection, sbar: np.ndarray) -> None:
    """Move the sliders to actual scales ``sbar (K,)`` (clamped to the learned intervals) and re-key."""
    for o, s in zip(osn_objects(coll), np.asarray(sbar, dtype=np.float64)):
        if P_SCALE in o:
            ui = o.id_properties_ui(P_SCALE).as_dict()
            o[P_SCALE] = float(np.clip(s, ui["min"], ui["max"]))
    sync_scales(coll)


def export_data(coll: bpy.types.Collection) -> core.ExportData:
    """The scale-related part of the export, rebuilt from the collection's properties."""
    m = manifest(coll)
    net = m.get("scale_network")
    layers = None
    if net is not None:
        layers, width = [], len(m["objects"]) - 1
        for i in range(int(net["layers"])):
            W = np.asarray(coll[f"osn_net_W{i}"], dtype=np.float64)
            b = np.asarray(coll[f"osn_net_b{i}"], dtype=np.float64)
            layers.append((W.reshape(len(b), width), b))
            width = len(b)
    objs = [
        core.ExportObjectData(
            id=o["id"], name=o["name"], is_anchor=o["is_anchor"], bbox=np.asarray(o["bbox"]), grid_shape=tuple(o["grid_shape"]),
            scale_range=tuple(o["scale_range"]), valid_interval=tuple(o["valid_interval"]), frames=np.zeros(0, int),
            object_to_scene=np.zeros((0, 4, 4)), volume_path="", mesh_path=None,
        )
        for o in m["objects"]
    ]
    K = len(objs)
    return core.ExportData(
        root="", manifest=m, width=m["camera"]["width"], height=m["camera"]["height"], K=np.asarray(m["camera"]["K"]),
        timestamps=np.asarray(m["timestamps"]), camera_to_scene=np.zeros((0, 4, 4)), test_cameras=None, objects=objs,
        anchor_index=[o.is_anchor for o in objs].index(True), net_layers=layers,
        net_hidden=net["hidden_activation"] if net else "relu", net_output=net["output_activation"] if net else "sigmoid",
        net_threshold=float(net["threshold"]) if net else 0.5,
        samples=np.asarray(coll[P_SAMPLES], dtype=np.float64).reshape(-1, K),
    )


def validity(coll: bpy.types.Collection) -> float:
    """Scale-network score of the sliders' current configuration."""
    return float(export_data(coll).validity(current_scales(coll)))


def sample_and_store(coll: bpy.types.Collection, seed: int) -> int:
    """Draw one valid configuration (seeded rejection sampling), append it, apply it; return its index."""
    data = export_data(coll)
    sbar = data.sample(1, seed)[0]
    samples = np.concatenate([data.samples, sbar[None]])
    coll[P_SAMPLES] = samples.ravel().tolist()
    set_scales(coll, sbar)
    return len(samples) - 1


def apply_sample(coll: bpy.types.Collection, index: int) -> np.ndarray:
    """Apply stored configuration ``index``; returns its scales. Raises IndexError when absent."""
    samples = export_data(coll).samples
    if not 0 <= index < len(samples):
        raise IndexError(f"configuration {index} does not exist ({len(samples)} stored)")
    set_scales(coll, samples[index])
    return samples[index]
