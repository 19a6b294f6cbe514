"""Build the installable Blender extension zip: ``python -m osn.export.addon_build [--out DIR]``.

Stages ``blender_addon/`` plus a copy of the numpy-only kernel ``scenecore/`` as its sub-package
(the one owner of the export format and camera conventions, which the add-on cannot import from
the project inside Blender) and
runs Blender's own extension tool (shipped in the bpy wheel) to validate and build it, so the
zip is exactly what Blender's "Install from Disk" accepts.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ADDON_DIR = ROOT / "blender_addon"
KERNEL_DIR = ROOT / "scenecore"


def blender_ext_tool() -> Path:
    """``blender_ext.py`` from the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        raise FileNotFoundError("the bpy wheel is not installed; it ships Blender's extension build tool")
    hits = sorted(glob.glob(os.path.join(os.path.dirname(spec.origin), "*", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")))
    if not hits:
        raise FileNotFoundError(f"no blender_ext.py under {os.path.dirname(spec.origin)}")
    return Path(hits[-1])


def build_addon_zip(out_dir: str | Path) -> Path:
    """Validate and build the extension into ``out_dir``; returns the zip's path."""
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    tool = blender_ext_tool()
    with tempfile.TemporaryDirectory(prefix="osn-addon-") as tmp:
        stage = Path(tmp) / "osn_import"
        shutil.copytree(ADDON_DIR, stage, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        shutil.copytree(KERNEL_DIR, stage / "scenecore", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        for cmd in (["validate", str(stage)], ["build", "--source-dir", str(stage), "--output-dir", tmp]):
            r = subprocess.run([sys.executable, str(tool), *cmd], capture_output=True, text=True)
            if r.returncode != 0:
                raise RuntimeError(f"blender_ext {cmd[0]} failed:\n{r.stdout}{r.stderr}")
        built = sorted(Path(tmp).glob("*.zip"))
        if len(built) != 1:
            raise RuntimeError(f"blender_ext build produced {[p.name for p in built]}")
        # The zip is assembled in the temporary directory, so the rename publishes it whole.
        final = out / built[0].name
        tmp_final = out / f".{built[0].name}.partial"
        shutil.copy2(built[0], tmp_final)
        os.replace(tmp_final, final)
    return final


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m osn.export.addon_build", description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(ROOT / "dist"), help="directory for the zip")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    path = build_addon_zip(args.out)
    print(f"{path} ({path.stat().st_size / 1024:.0f} KiB, {time.perf_counter() - t0:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
