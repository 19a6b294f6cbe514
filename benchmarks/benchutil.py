"""What every benchmark prints first: the exact command, so a figure can be reproduced."""

from __future__ import annotations

import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any


def command_line(script: str | None = None, argv: list[str] | None = None) -> str:
    """``python benchmarks/NAME.py ARGS`` as a shell would need it (an empty argument quoted): the
    process's own command line, or ``script`` with ``argv`` where a ``main(argv)`` was called."""
    return shlex.join(["python", *(sys.argv if argv is None else [script or sys.argv[0], *argv])])


def print_command(script: str | None = None, argv: list[str] | None = None) -> None:
    """Print ``command: python benchmarks/NAME.py ARGS`` (:func:`command_line`; flushed, before any figure)."""
    print("command: " + command_line(script, argv), flush=True)


def print_tables(tables: dict) -> None:
    """Print each ``{name: {"columns", "rows"}}`` table as markdown under its name."""
    for name, t in tables.items():
        print(f"\n{name}:\n| " + " | ".join(t["columns"]) + " |\n" + "\n".join("| " + " | ".join(r) + " |" for r in t["rows"]))


def add_executor_args(ap) -> None:
    """``--jobs``, ``--executor`` and ``--address``: how :func:`run_parallel` spreads the runs."""
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (local processes; cores shared out)")
    ap.add_argument("--executor", choices=("local", "ray"), default="local", help="local processes or Ray tasks")
    ap.add_argument("--address", default=None, help="Ray cluster address (default: a local Ray instance)")


def run_parallel(fn, calls, jobs: int, executor: str, threads: int):
    """Yield ``(tag, fn(*args))`` for each ``(tag, args)`` of ``calls`` as it finishes: in ``jobs``
    local threads (each ``fn`` runs its own subprocess), or as Ray tasks of ``threads`` CPUs each
    (``executor == "ray"``; ``ray.init`` called by the caller)."""
    if executor == "ray":
        import ray

        remote = ray.remote(num_cpus=threads)(fn)
        refs = {remote.remote(*a): tag for tag, a in calls}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending)
            for ref in done:
                yield refs[ref], ray.get(ref)
    else:
        from concurrent.futures import ThreadPoolExecutor, as_completed

        with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
            futures = {pool.submit(fn, *a): tag for tag, a in calls}
            for f in as_completed(futures):
                yield futures[f], f.result()


def compare_renders(run, truth, sbar, modes, install) -> None:
    """Print evaluation's two render workloads under two implementations, side by side.

    ``modes``: ``[(name, impl), (name, impl)]``, the reference first; ``install(impl)`` makes
    ``run.render_view`` use ``impl``. Per view of ``truth`` both workloads run under each mode in
    turn, so machine noise hits both alike: candidates (whole configurations ``sbar (C, K)``, the
    anchor shaded once per view: exact scoring) and layers (one object alone at a time: the
    layered search). Prints seconds, their ratio and the largest difference of colour, opacity and
    depth (over pixels both renders hit; a hole in one render only counts as inf).
    """
    import time

    import numpy as np

    free = [k for k in range(run.inputs.num_objects) if k != run.anchor_pos]
    works = ("candidates", "layers")
    seconds = {(w, m): 0.0 for w in works for m, _ in modes}
    diff = {(w, key): 0.0 for w in works for key in ("rgb", "acc", "depth")}
    for f in truth.frames:
        for work in works:
            out = {}
            for mode, impl in modes:
                install(impl)
                t0 = time.perf_counter()
                anchor = run.shade_anchor(f.camera_to_world, f.time_index) if work == "candidates" else None
                out[mode] = [run.render_view(f.camera_to_world, f.time_index, s, anchor=anchor,
                                             objects=None if work == "candidates" else [free[c % len(free)]])
                             for c, s in enumerate(sbar)]
                seconds[(work, mode)] += time.perf_counter() - t0
            for a, b in zip(*(out[m] for m, _ in modes)):
                for key in ("rgb", "acc", "depth"):
                    finite = np.isfinite(a[key])
                    if not np.array_equal(finite, np.isfinite(b[key])):
                        diff[(work, key)] = float("inf")
                    elif finite.any():
                        diff[(work, key)] = max(diff[(work, key)], float(np.max(np.abs(a[key][finite] - b[key][finite]))))
    install(modes[1][1])
    (ref, _), (new, _) = modes
    print(f"{len(truth.frames) * len(sbar)} renders per workload ({len(truth.frames)} views x {len(sbar)} configurations)")
    print(f"| workload | {ref} | {new} | ratio | largest difference: colour / opacity / depth |")
    print("|---|---|---|---|---|")
    for work in works:
        a, b = seconds[(work, ref)], seconds[(work, new)]
        d = " / ".join(f"{diff[(work, key)]:.1e}" for key in ("rgb", "acc", "depth"))
        print(f"| {work} | {a:.2f} s | {b:.2f} s | {a / b:.2f}x | {d} |")


def render_bench_inputs(doc: str):
    """Parse ``RUN DATASET [--views V] [--configs C]``, print the command, and return the trained run,
    V test views of the dataset spread over it and C configurations sampled from the run."""
    import argparse

    from benchgen.score.truth import load_truth
    from osn.model.run import load_run
    from osn.sample.configurations import sample_configurations

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="osn train run directory")
    ap.add_argument("dataset", help="its benchgen dataset (test views)")
    ap.add_argument("--views", type=int, default=10, help="test views, evenly spread")
    ap.add_argument("--configs", type=int, default=10, help="sampled configurations rendered per view")
    args = ap.parse_args()
    print_command()
    run = load_run(args.run)
    return run, load_truth(args.dataset, args.views), sample_configurations(run, args.configs, 0.5, 0).sbar


def finish_parallel(out: Path, benchmark: str, tables: dict, data: dict[str, Any], t0: float, jobs: int, root: Path,
                    runs: list[dict]) -> int:
    """End a benchmark whose runs went through :func:`run_parallel`: print its tables, write the
    results JSON with its wall time, ``jobs`` and the load at the end (the machine was shared),
    and return the exit status (1 when a run failed)."""
    from results_json import write_results

    print_tables(tables)
    write_results(out, benchmark, command_line(), tables,
                  {**data, "runs": runs, "wall_seconds": time.perf_counter() - t0, "jobs": jobs,
                   "load_average_at_end": os.getloadavg()[0]}, root)
    print(f"wrote {out}")
    return 1 if any("error" in r for r in runs) else 0
