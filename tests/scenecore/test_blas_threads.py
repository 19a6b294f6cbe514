"""The command-line entry points run numpy's OpenBLAS on one thread (scenecore.cli.blas_on_one_thread)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: Runs in a fresh interpreter: the entry point first, then numpy; prints what OpenBLAS runs on.
PROBE = """
import ctypes, glob, os, sys
import {module}
import numpy
libs = glob.glob(os.path.join(os.path.dirname(numpy.__file__), os.pardir, "numpy.libs", "libopenblas*"))
names = ("openblas_get_num_threads64_", "openblas_get_num_threads", "scipy_openblas_get_num_threads64_")
fns = [getattr(ctypes.CDLL(libs[0]), n, None) for n in names] if libs else []
fns = [f for f in fns if f is not None]
print(os.environ.get("OPENBLAS_NUM_THREADS"), fns[0]() if fns else "unknown")
"""


@pytest.mark.parametrize("module", ["osn.cli", "benchgen.cli"])
def test_entry_points_run_openblas_on_one_thread_unless_the_user_chose(module: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", PROBE.format(module=module)], capture_output=True, text=True, env=env,
                         check=True).stdout.split()
    assert out[0] == "1"
    if out[1] != "unknown":  # numpy's own OpenBLAS, found next to it (wheels from PyPI)
        assert out[1] == "1"
    mine = subprocess.run([sys.executable, "-c", PROBE.format(module=module)], capture_output=True, text=True,
                          env={**env, "OPENBLAS_NUM_THREADS": "2"}, check=True).stdout.split()
    assert mine[0] == "2"  # the user's value is kept
