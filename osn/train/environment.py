"""What a run was computed on: library versions, device and the CPU's kernel set (``run.json``).

A training is bit-for-bit reproducible on the same kind of processor with the same torch build.
Another kernel set (AVX2 against AVX-512, a GPU) rounds differently, training carries the
difference on, and the run lands elsewhere within the seed spread (docs/training.md, "Known
limitations"); the record says which kind produced a figure.
"""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Any

import numpy as np
import torch


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name (Linux ``/proc/cpuinfo``; ``platform.processor()`` elsewhere)."""
    try:
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def environment(device: torch.device) -> dict[str, Any]:
    """The record: Python, torch and numpy versions, the device (a GPU's name), the CPU model,
    torch's CPU kernel set (``torch.backends.cpu.get_cpu_capability()``) and its thread count."""
    rec: dict[str, Any] = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "device": str(device),
        "cpu": cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        rec["gpu"] = torch.cuda.get_device_name(device)
    return rec


def same_kernels(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two records compute alike: the same torch and numpy builds, device type, GPU model and
    CPU kernel set. Thread counts are not compared: a CPU training is bit for bit the same on one
    thread or two (README, the demo's times)."""
    keys = ("torch", "numpy", "gpu", "cpu_capability")
    kind = lambda r: str(r.get("device", "")).split(":")[0]  # noqa: E731 - cuda:0 and cuda:1 of one model compute alike
    return kind(a) == kind(b) and all(a.get(k) == b.get(k) for k in keys)


def describe(rec: dict[str, Any]) -> str:
    """One line for reports: ``torch 2.13.0+cpu on cpu (AMD EPYC, AVX2 kernels, 2 threads)``."""
    n = rec.get("threads", "?")
    where = rec.get("gpu") or f"{rec.get('cpu', '?')}, {rec.get('cpu_capability', '?')} kernels, {n} thread{'' if n == 1 else 's'}"
    return f"torch {rec.get('torch', '?')} on {rec.get('device', '?')} ({where})"
