"""Which inputs ``auto`` treats as noisy: every object's contradicted share, against the source label.

For each inputs directory given (``osn preprocess`` / ``osn oracle`` output, or a run's
``inputs/``), prints each object's share of depth-against-frame tests in which a depth lies in
front of what another frame saw (:func:`osn.preprocess.depth_noise.depth_consistency`), the
worst, the verdict, and the source the inputs were written with (not read by the rule), then
how many inputs of each source fall on each side of the threshold and the margins. Run:

    .venv/bin/python benchmarks/bench_depth_noise.py DIR [DIR ...] [--out JSON]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from results_json import table, write_results

from benchutil import command_line, print_command, print_tables

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    from osn.preprocess.depth_noise import NOISY_SHARE, depth_consistency
    from osn.preprocess.inputs import load_inputs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="inputs directories (holding inputs.json)")
    ap.add_argument("--out", type=Path, default=None, help="results JSON (default: print only)")
    args = ap.parse_args()
    print_command()
    rows, data = [], []
    for d in args.dirs:
        inputs = load_inputs(d)
        c = depth_consistency(inputs)
        names = [o.name for o in inputs.objects]
        worst = names[max(range(len(names)), key=lambda k: c.shares[k])]
        data.append({"inputs": str(d), "source": inputs.source, "size": [inputs.width, inputs.height],
                     "objects": dict(zip(names, c.shares)), "worst": c.worst, "noisy": c.noisy})
        rows.append([str(d), inputs.source, f"{inputs.width}x{inputs.height}", str(len(names)),
                     f"{100 * c.worst:.2f} ({worst})", "noisy" if c.noisy else "exact"])
        print(" | ".join(rows[-1]), flush=True)
    summary = []
    for source in sorted({r["source"] for r in data}):
        xs = [r["worst"] for r in data if r["source"] == source]
        summary.append([source, str(len(xs)), str(sum(r["noisy"] for r in data if r["source"] == source)),
                        f"{100 * min(xs):.2f}", f"{100 * max(xs):.2f}"])
    ts = {"depth_noise": table(["inputs", "source label", "size", "objects", "worst object's contradicted share (%)",
                                "auto treats them as"], rows),
          "depth_noise_summary": table(["source label", "inputs", f"noisy (worst > {100 * NOISY_SHARE:g}%)",
                                        "lowest worst share (%)", "highest worst share (%)"], summary)}
    print_tables(ts)
    if args.out:
        write_results(args.out, "depth_noise", command_line(), ts, {"inputs": data}, ROOT)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
