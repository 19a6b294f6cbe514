"""The layout's dependency rules, checked in a fresh interpreter where ``bpy`` cannot be imported.

Training, sampling, scoring and export install and import without bpy (it is the ``[render]``
extra): every module of ``scenecore``, ``osn`` and ``benchgen.score`` must import with bpy
blocked, and the kernel must not import torch either (the Blender add-on bundles it).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

BLOCK_BPY = textwrap.dedent(
    """
    import importlib.abc, sys

    class NoBpy(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "bpy" or name.startswith("bpy.") or name in ("mathutils", "openvdb"):
                raise ImportError(f"{name} is blocked: this code must not need bpy")
            return None

    sys.meta_path.insert(0, NoBpy())
    """
)


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK_BPY + textwrap.dedent(code)], capture_output=True, text=True, timeout=300)


def test_method_and_scoring_import_without_bpy() -> None:
    r = _run(
        """
        import importlib, pkgutil, sys
        import scenecore, osn, benchgen.score
        names = []
        for pkg in (scenecore, osn, benchgen.score):
            for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
                if m.name.endswith("__main__"):
                    continue
                importlib.import_module(m.name)
                names.append(m.name)
        assert "bpy" not in sys.modules
        print(len(names), " ".join(names))
        """
    )
    assert r.returncode == 0, r.stderr
    count, names = r.stdout.split(" ", 1)
    # The stages are really there (a walk that found nothing would pass vacuously).
    assert int(count) >= 20 and "osn.train" in names and "osn.evaluate" in names and "benchgen.score.metrics" in names


def test_cli_help_works_without_bpy() -> None:
    r = _run(
        """
        import sys
        from osn.cli import main
        try:
            main(["--help"])
        except SystemExit as e:
            assert e.code == 0
        assert "bpy" not in sys.modules
        """
    )
    assert r.returncode == 0, r.stderr
    assert "train" in r.stdout and "evaluate" in r.stdout


def test_kernel_imports_numpy_only() -> None:
    """The add-on bundles scenecore/: inside Blender only numpy and the standard library exist."""
    r = _run(
        """
        import importlib, pkgutil, sys
        import scenecore
        for m in pkgutil.walk_packages(scenecore.__path__, "scenecore."):
            importlib.import_module(m.name)
        heavy = sorted(n for n in ("torch", "scipy", "skimage", "trimesh", "imageio", "OpenEXR", "yaml", "matplotlib", "bpy")
                       if n in sys.modules)
        print(heavy)
        """
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_export_without_bpy_says_what_to_install(tmp_path) -> None:
    """The one step that needs bpy outside rendering (OpenVDB volumes) fails with one clear line."""
    r = _run(
        """
        from osn.export.writer import _openvdb
        try:
            _openvdb()
        except ValueError as e:
            print(e)
        """
    )
    assert r.returncode == 0, r.stderr
    assert "render extra" in r.stdout
