"""OSN scene importer for Blender: learned objects, trajectories, scale sliders, valid configurations.

This file must stay importable without ``bpy`` (tests import the package), so everything that
needs Blender is imported inside :func:`register`. The export format and camera conventions come
from the shared kernel ``scenecore`` (bundled into the built extension, see ``_kernel.py``).
"""

bl_info = {
    "name": "OSN scene importer",
    "author": "OSN toolkit",
    "version": (1, 0, 0),
    "blender": (4, 2, 0),
    "location": "File > Import > OSN scene; View3D > Sidebar > OSN",
    "description": "Import OSN exports: learned volumes and meshes, trajectories, valid scale configurations",
    "category": "Import-Export",
}


def register() -> None:
    from . import ui

    ui.register()


def unregister() -> None:
    from . import ui

    ui.unregister()
