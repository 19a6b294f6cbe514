"""Operators, sidebar panel, import menu entry and drag-and-drop handler of the OSN add-on."""

from __future__ import annotations

import bpy
from bpy.app.handlers import persistent
from bpy.props import IntProperty, PointerProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ._kernel import export_format as core
from . import scene_build as sb


class OSN_OT_import(bpy.types.Operator, ImportHelper):
    """Import an OSN export: learned objects, trajectories, cameras and scale ranges"""

    bl_idname = "import_scene.osn"
    bl_label = "Import OSN scene"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".json"
    filter_glob: StringProperty(default=f"*{core.MANIFEST_NAME}", options={"HIDDEN"})  # type: ignore[valid-type]
    directory: StringProperty(subtype="DIR_PATH", options={"SKIP_SAVE", "HIDDEN"})  # type: ignore[valid-type]

    def execute(self, context: bpy.types.Context) -> set[str]:
        path = self.filepath or self.directory
        if not path:
            self.report({"ERROR"}, f"OSN import: no export chosen (pass filepath= the export's {core.MANIFEST_NAME})")
            return {"CANCELLED"}
        try:
            coll = sb.import_export(context, path)
        except (core.ExportFormatError, OSError) as e:
            self.report({"ERROR"}, f"OSN import failed, scene unchanged: {e}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Imported {len(sb.osn_objects(coll))} objects into '{coll.name}'")
        return {"FINISHED"}

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if _manifest_given(self):  # a dropped file, or a script naming the manifest
            return self.execute(context)
        return ImportHelper.invoke(self, context, event)


def _manifest_given(op: bpy.types.Operator) -> bool:
    """Whether this call of ``op`` names an ``osn_export.json`` (:func:`scenecore.export_format.names_manifest`)."""
    return core.names_manifest(op.filepath, op.properties.is_property_set("filepath"))


class OSN_FH_import(bpy.types.FileHandler):
    """Drag an ``osn_export.json`` into the 3D viewport or outliner to import it."""

    bl_idname = "OSN_FH_import"
    bl_label = "OSN scene"
    bl_import_operator = "import_scene.osn"
    bl_file_extensions = ".json"

    @classmethod
    def poll_drop(cls, context: bpy.types.Context) -> bool:
        return context.area is not None and context.area.type in {"VIEW_3D", "OUTLINER"}


def _active(context: bpy.types.Context) -> bpy.types.Collection | None:
    coll = getattr(context.scene, "osn_collection", None)
    return coll if coll is not None and sb.P_MANIFEST in coll else None


class OSN_OT_sample(bpy.types.Operator):
    """Draw a valid configuration through the scale network (seeded rejection sampling) and apply it"""

    bl_idname = "osn.sample_configuration"
    bl_label = "Sample valid configuration"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _active(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        coll, scene = _active(context), context.scene
        try:
            index = sb.sample_and_store(coll, scene.osn_seed)
        except core.ExportFormatError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        scene.osn_seed += 1  # the next press gives a new configuration, reproducibly
        scene.osn_sample_index = index
        self.report({"INFO"}, f"Applied sampled configuration {index}")
        return {"FINISHED"}


class OSN_OT_apply(bpy.types.Operator):
    """Set every object's scale to the stored sampled configuration"""

    bl_idname = "osn.apply_configuration"
    bl_label = "Apply sampled configuration"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(name="Configuration", min=0)  # type: ignore[valid-type]

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _active(context) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            sb.apply_sample(_active(context), self.index)
        except IndexError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        return {"FINISHED"}


class OSN_PT_panel(bpy.types.Panel):
    """Scale sliders limited to the learned intervals, live validity and sampled configurations."""

    bl_label = "OSN configuration"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "OSN"

    def draw(self, context: bpy.types.Context) -> None:
        layout, coll = self.layout, _active(context)
        layout.prop(context.scene, "osn_collection", text="Export")
        if coll is None:
            layout.label(text="Import an OSN export (File > Import)")
            return
        col = layout.column(align=True)
        for obj in sb.osn_objects(coll):
            if sb.P_SCALE in obj:
                col.prop(obj, f'["{sb.P_SCALE}"]', text=obj.name, slider=True)
            else:
                col.label(text=f"{obj.name}: anchor, scale 1")
        score = sb.validity(coll)
        threshold = sb.export_data(coll).net_threshold
        box = layout.box()
        box.label(text=f"Validity {score:.3f} ({'valid' if score >= threshold else 'INVALID'})",
                  icon="CHECKMARK" if score >= threshold else "ERROR")
        row = layout.row(align=True)
        row.prop(context.scene, "osn_seed")
        row.operator(OSN_OT_sample.bl_idname, icon="SHADERFX")
        n = len(sb.export_data(coll).samples)
        row = layout.row(align=True)
        row.enabled = n > 0
        row.prop(context.scene, "osn_sample_index", text=f"K (of {n})")
        row.operator(OSN_OT_apply.bl_idname, text="Apply configuration K").index = context.scene.osn_sample_index


@persistent
def _on_depsgraph_update(scene: bpy.types.Scene, _depsgraph: bpy.types.Depsgraph) -> None:
    """Re-key trajectories when a slider moved (ID properties have no update callback)."""
    for coll in bpy.data.collections:
        if sb.P_MANIFEST in coll:
            sb.sync_scales(coll)


def _menu_import(self: bpy.types.Menu, _context: bpy.types.Context) -> None:
    self.layout.operator(OSN_OT_import.bl_idname, text="OSN scene (osn_export.json)")


CLASSES = (OSN_OT_import, OSN_FH_import, OSN_OT_sample, OSN_OT_apply, OSN_PT_panel)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.osn_collection = PointerProperty(type=bpy.types.Collection, name="OSN export", description="Imported OSN export the panel controls")
    bpy.types.Scene.osn_seed = IntProperty(name="Seed", default=0, min=0, description="Seed of the next sampled configuration")
    bpy.types.Scene.osn_sample_index = IntProperty(name="Configuration", default=0, min=0)
    bpy.types.TOPBAR_MT_file_import.append(_menu_import)
    bpy.app.handlers.depsgraph_update_post.append(_on_depsgraph_update)


def unregister() -> None:
    if _on_depsgraph_update in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(_on_depsgraph_update)
    bpy.types.TOPBAR_MT_file_import.remove(_menu_import)
    for name in ("osn_collection", "osn_seed", "osn_sample_index"):
        delattr(bpy.types.Scene, name)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
