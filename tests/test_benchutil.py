"""The command a benchmark records with its results: one a shell can run again."""

import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from benchutil import command_line  # noqa: E402


def test_the_recorded_command_runs_again_in_a_shell(monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_ablation.py", "--families", "", "--root", "/tmp/a b"])
    assert command_line() == "python benchmarks/bench_ablation.py --families '' --root '/tmp/a b'"
    assert shlex.split(command_line())[1:] == sys.argv
    # A main(argv) called from Python: its own script and arguments, not the caller's.
    assert command_line("benchmarks/bench_fidelity.py", ["--out", "x y.json"]) == "python benchmarks/bench_fidelity.py --out 'x y.json'"
    assert command_line("benchmarks/bench_fidelity.py", []) == "python benchmarks/bench_fidelity.py"
