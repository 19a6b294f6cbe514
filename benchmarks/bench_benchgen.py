"""benchgen speed: wall time of ``generate`` against the time spent inside Cycles render calls.

Reports (a) wall / sum of pure ``bpy.ops.render.render`` calls (target <= 1.3 with one worker),
(b) frames per second at 128x128 on gnome-house, (c) growth with G and with resolution (on a
reduced 5x5 rig so the sweep stays short), and with ``--demo`` (d) the full ``gnome-house-demo``
generation (15x15, 64 px, G=50) with the load average, since the machine may be shared. Run:

    .venv/bin/python benchmarks/bench_benchgen.py [--configs 2] [--skip-sweep] [--demo]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from benchgen.render.generate import generate
from benchgen.scene.spec import load_preset, spec_from_dict

from benchutil import print_command


def run(spec, label: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        s = generate(spec, Path(tmp) / "ds", progress=False)
    ratio = s.wall_seconds / s.render_seconds
    print(
        f"{label:38s} frames={s.frames_rendered:5d} wall={s.wall_seconds:7.1f}s render={s.render_seconds:7.1f}s "
        f"wall/render={ratio:.2f} fps={s.frames_rendered / s.wall_seconds:.2f} verified={s.passed}"
    )
    return {"wall": s.wall_seconds, "render": s.render_seconds, "frames": s.frames_rendered}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", type=int, default=2, help="G for the full 15x15 gnome-house run")
    ap.add_argument("--skip-sweep", action="store_true", help="only the full gnome-house run")
    ap.add_argument("--demo", action="store_true", help="also time the full gnome-house-demo preset (G=50)")
    args = ap.parse_args()
    print_command()
    if args.demo:
        before = os.getloadavg()
        run(load_preset("gnome-house-demo"), "gnome-house-demo 15x15 64px G=50")
        print(f"load average (1 min) before {before[0]:.2f}, after {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    base = load_preset("gnome-house")
    run(base.with_overrides(configs=args.configs), f"gnome-house 15x15 128px G={args.configs}")
    if args.skip_sweep:
        return
    small = base.to_dict()
    small["rig"].update(views=5, times=5)
    small = spec_from_dict(small, "gnome-house-5x5")
    for g in (1, 2, 4):
        run(small.with_overrides(configs=g, resolution=64), f"gnome-house 5x5 64px G={g}")
    for res in (32, 64, 128):
        run(small.with_overrides(configs=1, resolution=res), f"gnome-house 5x5 {res}px G=1")


if __name__ == "__main__":
    main()
