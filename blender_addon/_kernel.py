"""The shared numpy-only kernel (``scenecore``): export format and camera conventions.

The built extension carries a copy of ``scenecore/`` as a sub-package (``osn.export.addon_build``);
in a checkout the repository's own ``scenecore`` is imported.
"""

try:
    from .scenecore import cameras, export_format  # inside the built extension
except ImportError:
    from scenecore import cameras, export_format  # noqa: F401 - a checkout, e.g. the tests

__all__ = ["cameras", "export_format"]
