"""Per-object SfM accuracy and time of preprocessing variants, side by side on one dataset.

For each variant, runs ``osn.preprocess.preprocess_dataset`` on a benchgen dataset (objects that
fail are skipped, not fatal) and prints one JSON line per object: frames registered of those
visible, rotation error max / mean (degrees) and camera-centre error mean (metres) after a
per-object similarity alignment to ground truth, plus the variant's wall time and its ratio to
the first variant's. The target: every object registered in >= 90% of its visible frames with
rotation error <= 1 degree.

    .venv/bin/python benchmarks/bench_preprocess.py DATASET [--variants previous,default]

Variants: ``default`` (PreprocessConfig()), ``previous`` (``grey: luminance``, ``guided_matching:
false``, ``mapper_restarts: 1``, ``epipolar_error: 2``, i.e. COLMAP's 4 px at 2x upsampling), and the
single-change variants ``no-guided``, ``luminance``, ``one-run``, ``loose-epipolar``,
``no-check`` (no registration check, osn.preprocess.repair) and ``no-robust-ba`` (no final Cauchy BA).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from osn.preprocess.sfm import PreprocessConfig
from osn.preprocess.video import preprocess_dataset

from benchutil import print_command

VARIANTS: dict[str, dict] = {
    "default": {},
    "previous": {"grey": "luminance", "guided_matching": False, "mapper_restarts": 1, "epipolar_error": 2.0},
    "no-guided": {"guided_matching": False},
    "luminance": {"grey": "luminance"},
    "one-run": {"mapper_restarts": 1},
    "loose-epipolar": {"epipolar_error": 2.0},
    "no-check": {"min_epipolar_consistency": 0.0},
    "no-robust-ba": {"final_cauchy_px": 0.0},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", help="benchgen dataset (its ground truth measures the accuracy)")
    ap.add_argument("--variants", default="previous,default", help=f"comma-separated, from {', '.join(VARIANTS)}")
    args = ap.parse_args()
    print_command()
    names = args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        sys.exit(f"bench_preprocess: unknown variant(s) {', '.join(unknown)} (choose from {', '.join(VARIANTS)})")
    first = None
    for name in names:
        cfg = PreprocessConfig(on_failure="skip", **VARIANTS[name])
        t0 = time.perf_counter()
        _, report = preprocess_dataset(args.dataset, cfg)
        secs = time.perf_counter() - t0
        first = first or secs
        for r in report.objects:
            row = {"variant": name, "object": r["name"]}
            if "error" in r:
                row["dropped"] = r["error"]
            elif "rotation_error_deg_max" not in r:
                row["registered"] = r["registered_frames"]
                row["alignment"] = r.get("alignment", "not measured")
            else:
                row.update(
                    registered=f"{r['registered_frames']}/{r['gt_visible_frames']}",
                    rotation_deg_max=round(r["rotation_error_deg_max"], 2),
                    rotation_deg_mean=round(r["rotation_error_deg_mean"], 2),
                    centre_m_mean=round(r["center_error_m_mean"], 4),
                    meets_target=r["registered_fraction"] >= 0.9 and r["rotation_error_deg_max"] <= 1.0,
                    repaired=[f"{f['frame']} {f['action']}" for f in r.get("repaired_frames", [])],
                )
            print(json.dumps(row), flush=True)
        print(json.dumps({"variant": name, "seconds": round(secs, 1), "time_vs_first": round(secs / first, 2)}), flush=True)


if __name__ == "__main__":
    main()
