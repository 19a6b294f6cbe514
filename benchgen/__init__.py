"""benchgen: multi-ground-truth benchmark generation for dynamic monocular scenes.

Importing the package is cheap: numpy-only modules (``dataset``, ``cameras``, ``validity``) do not
import bpy; only the renderer does, when it is used.
"""

__version__ = "0.1.0"
