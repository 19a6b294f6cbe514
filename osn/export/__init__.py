"""Export (``osn export``): a trained run for Blender, and the add-on that imports it.

Modules:

* :mod:`~osn.export.writer`: the ``osn-export`` format's writer (:class:`ExportScene`,
  :class:`ExportObject`, :class:`ScaleNetwork`, :func:`write_export`, written atomically).
* :mod:`~osn.export.from_run`: an :class:`ExportScene` from a trained run (:func:`export_run`:
  grids sampled from the fields, the folded scale network, poses, configurations, test cameras).
* :mod:`~osn.export.addon_build`: the installable Blender extension zip (``python -m
  osn.export.addon_build``; not imported here, so running it as a module stays clean).

The read side of the format (``read_export``, ``ExportFormatError``, the numpy scale network) is
the kernel's :mod:`scenecore.export_format`, which the add-on ships.
"""

from osn.export.from_run import (
    DEFAULT_EXPORT_SAMPLES,
    export_layers_from_torch,
    export_run,
    export_scene_from_inputs,
    exported_samples,
    field_grids,
    rig_cameras,
    scale_network_from_torch,
)
from osn.export.writer import ExportObject, ExportScene, ScaleNetwork, object_mesh, write_export

__all__ = [
    "DEFAULT_EXPORT_SAMPLES", "ExportObject", "ExportScene", "ScaleNetwork", "export_layers_from_torch",
    "export_run", "export_scene_from_inputs", "exported_samples", "field_grids", "object_mesh", "rig_cameras",
    "scale_network_from_torch", "write_export",
]
