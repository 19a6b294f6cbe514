"""``kill -9`` at a random moment of each stage of ``osn demo``, rerun, compare ``metrics.json``.

Runs one uninterrupted ``osn demo`` (a subprocess, like a user) into ``ROOT/reference``; then for
each stage: a fresh demo in ``ROOT/kill-STAGE``, wait for the stage's ``.done/STAGE.started.json``
marker (written just before the stage starts), sleep a seeded random fraction of the stage's
uninterrupted duration (the reference's ``stages.json``), SIGKILL the whole process group (the
demo runs in its own session, so benchgen's Blender render workers die too; the benchmark checks
that no process of the session survives), check the stage was interrupted (no ``.done/STAGE.json``),
run the same command again to completion and compare its ``report/metrics.json`` with the
reference's, value by value after flattening (dicts and lists).

Compared: every value, floats exactly (``==``; NaN equals NaN), except the timing fields
``timings.*``, ``train_seconds`` and ``curves.search_seconds_per_view_vs_n.*`` (wall times).
``command`` is compared after replacing each run's ``--work`` directory with ``WORK``. A key
present on one side only counts as a difference. The rerun must also resume the killed stage
(its ``(resuming after ...)`` line) and skip every stage before it (``already done``).

When the stage finished before the kill (very short stages: sample, addon), the attempt is
discarded and retried with a new random fraction (``--attempts``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_kill_demo.py --seed 0 --out /tmp/kill_demo.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchutil import print_command

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("generate", "preprocess", "ground-truth", "train", "sample", "evaluate", "export", "addon")
DEFAULT_STAGES = STAGES[:-1]
# Wall-time fields of metrics.json (osn/evaluate/bestofn.py, osn/evaluate/report.py): never compared.
TIMING = re.compile(r"^(timings\..*|train_seconds|curves\.search_seconds_per_view_vs_n\..*)$")


def demo_cmd(args: argparse.Namespace, work: Path) -> list[str]:
    return [sys.executable, "-m", "osn.cli", "demo", "--preset", args.preset, "--inputs-from", "oracle", *shlex.split(args.demo_args),
            "--work", str(work)]


def flatten(x: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts and lists -> ``{"a.b.0": value}``."""
    if isinstance(x, dict):
        items = x.items()
    elif isinstance(x, list):
        items = enumerate(x)
    else:
        return {prefix[:-1]: x}
    out: dict[str, Any] = {}
    for k, v in items:
        out.update(flatten(v, f"{prefix}{k}."))
    return out


def same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def compare(ref_work: Path, work: Path) -> tuple[int, list[str]]:
    """(values compared, keys that differ) between two demos' metrics.json."""
    ref = flatten(json.loads((ref_work / "report" / "metrics.json").read_text()))
    got = flatten(json.loads((work / "report" / "metrics.json").read_text()))
    for m, w in ((ref, ref_work), (got, work)):
        if isinstance(m.get("command"), str):
            m["command"] = m["command"].replace(shlex.quote(str(w)), "WORK")
    keys = sorted(k for k in set(ref) | set(got) if not TIMING.match(k))
    return len(keys), [k for k in keys if k not in ref or k not in got or not same(ref[k], got[k])]


def session_processes(sid: int) -> list[int]:
    """Pids whose session or process group is ``sid`` (the killed demo's)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            rest = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if rest[0] != "Z" and sid in (int(rest[2]), int(rest[3])):
            out.append(int(d.name))
    return out


def run_to_end(cmd: list[str], log: Path, timeout: float) -> tuple[int, float, str]:
    t0 = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"\n$ {shlex.join(cmd)}\n")
        f.flush()
        r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=f, text=True, cwd=ROOT, timeout=timeout,
                           start_new_session=True)
        f.write(r.stdout)
    return r.returncode, time.perf_counter() - t0, r.stdout


def kill_during(cmd: list[str], work: Path, stage: str, delay: float, log: Path, timeout: float) -> dict[str, Any]:
    """Start ``cmd``, SIGKILL its process group ``delay`` s after ``stage`` started; what happened."""
    started, done = work / ".done" / f"{stage}.started.json", work / ".done" / f"{stage}.json"
    with open(log, "a") as f:
        f.write(f"$ {shlex.join(cmd)}  # killed {delay:.3f} s into {stage}\n")
        f.flush()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
    deadline = time.monotonic() + timeout
    while not started.exists():
        if proc.poll() is not None:
            return {"error": f"the demo ended (rc {proc.returncode}) before {stage} started"}
        if time.monotonic() > deadline:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return {"error": f"{stage} did not start within {timeout:.0f} s"}
        time.sleep(0.002)
    t_start = time.monotonic()
    time.sleep(max(0.0, t_start + delay - time.monotonic()))
    os.killpg(proc.pid, signal.SIGKILL)
    kill_s = time.monotonic() - t_start
    proc.wait()
    t0 = time.monotonic()
    while (left := session_processes(proc.pid)) and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    return {"kill_s": kill_s, "interrupted": not done.exists(), "survivors": len(left), "rc": proc.returncode}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0, help="seed of the random kill moments")
    ap.add_argument("--stages", default=",".join(DEFAULT_STAGES), help=f"comma-separated, from {', '.join(STAGES)}")
    ap.add_argument("--preset", default="tiny", help="benchgen preset given to `osn demo`")
    ap.add_argument("--demo-args", default="", help="more `osn demo` options, e.g. '--field-iterations 150 -n 60'")
    ap.add_argument("--root", default=None, help="where the work directories go (default: a new temporary directory)")
    ap.add_argument("--reference", default=None,
                    help="a finished demo's work directory, made by the same options, to use instead of running one")
    ap.add_argument("--attempts", type=int, default=3, help="tries per stage when the stage ends before the kill")
    ap.add_argument("--timeout", type=float, default=3600, help="seconds allowed for one demo invocation")
    ap.add_argument("--keep", action="store_true", help="keep the work directories (default: remove those that passed)")
    ap.add_argument("--out", default=None, help="also write the table (and the command) as JSON to this file")
    args = ap.parse_args()
    stages = args.stages.split(",")
    if unknown := [s for s in stages if s not in STAGES]:
        sys.exit(f"bench_kill_demo: unknown stage(s) {', '.join(unknown)} (choose from {', '.join(STAGES)})")
    print_command()
    print(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '(unset)')}, cpus {os.cpu_count()}", flush=True)
    root = Path(args.root or tempfile.mkdtemp(prefix="kill_demo_"))
    root.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)

    if args.reference:
        ref, ref_s = Path(args.reference), None
    else:
        ref = root / "reference"
        shutil.rmtree(ref, ignore_errors=True)
        rc, ref_s, _ = run_to_end(demo_cmd(args, ref), root / "reference.log", args.timeout)
        if rc != 0:
            sys.exit(f"bench_kill_demo: the uninterrupted demo failed (rc {rc}); see {root / 'reference.log'}")
    durations = {k: r["seconds"] for k, r in json.loads((ref / "stages.json").read_text()).items()}
    print(f"reference: {ref}" + (f", {ref_s:.1f} s" if ref_s else "") + "; stage seconds: "
          + ", ".join(f"{k} {v:.2f}" for k, v in durations.items()), flush=True)
    print(f"demo: {shlex.join(demo_cmd(args, Path('WORK')))}", flush=True)

    rows = []
    t_all = time.perf_counter()
    for stage in stages:
        row: dict[str, Any] = {"stage": stage, "stage_s": round(durations[stage], 3)}
        for attempt in range(1, args.attempts + 1):
            work, log = root / f"kill-{stage}", root / f"kill-{stage}.log"
            shutil.rmtree(work, ignore_errors=True)
            log.unlink(missing_ok=True)
            fraction = rng.random()
            k = kill_during(demo_cmd(args, work), work, stage, fraction * durations[stage], log, args.timeout)
            row.update(attempts=attempt, fraction=round(fraction, 4), **k)
            if "error" in k or k["interrupted"]:
                break
        if "error" in row:
            row["verdict"] = "ERROR: " + row["error"]
        elif not row["interrupted"]:
            row["verdict"] = "NOT INTERRUPTED (the stage ended before the kill)"
        elif row["survivors"]:
            row["verdict"] = f"FAIL: {row['survivors']} process(es) survived the kill"
        else:
            rc, secs, out = run_to_end(demo_cmd(args, work), log, args.timeout)
            row.update(rerun_rc=rc, rerun_s=round(secs, 2))
            lines = out.splitlines()
            i = STAGES.index(stage)
            row["resumed"] = any(re.match(rf"\[{i + 1}/\d+\] {stage}: .*\(resuming after", ln) for ln in lines)
            row["skipped_before"] = sum("already done" in ln for ln in lines)
            if rc != 0:
                row["verdict"] = f"FAIL: rerun exit code {rc} (see {log})"
            else:
                n, diff = compare(ref, work)
                row.update(compared=n, differing=len(diff), differing_keys=diff[:20])
                if diff:
                    row["verdict"] = f"FAIL: {len(diff)} value(s) differ, e.g. {', '.join(diff[:3])}"
                # At least the stages before it; a background stage (ground-truth) has stages after
                # it that may have finished before the kill.
                elif not row["resumed"] or row["skipped_before"] < i:
                    row["verdict"] = "FAIL: the rerun did not resume the killed stage / skip the ones before"
                else:
                    row["verdict"] = "equal"
                    if not args.keep:
                        shutil.rmtree(work, ignore_errors=True)
        row["kill_s"] = round(row.get("kill_s", float("nan")), 3)
        rows.append(row)
        print(json.dumps(row), flush=True)
    total = time.perf_counter() - t_all

    head = f"{'stage':<11}{'stage s':>9}{'kill at s':>11}{'tries':>7}{'rerun s':>9}{'compared':>10}{'differing':>11}  verdict"
    print()
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['stage']:<11}{r['stage_s']:>9.2f}{r['kill_s']:>11.3f}{r.get('attempts', 0):>7}"
              f"{r.get('rerun_s', float('nan')):>9.1f}{r.get('compared', '-'):>10}{r.get('differing', '-'):>11}  {r['verdict']}")
    print(f"kill-and-rerun total {total:.0f} s" + (f", reference {ref_s:.0f} s" if ref_s else "")
          + f"; work directories under {root}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({
            "command": shlex.join(["python", *sys.argv]), "demo": shlex.join(demo_cmd(args, Path("WORK"))),
            "seed": args.seed, "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "reference": str(ref),
            "reference_s": ref_s, "stage_s": durations, "excluded_keys": TIMING.pattern, "rows": rows,
            "total_s": total}, indent=1) + "\n")
    if any(r["verdict"] != "equal" for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
