"""The command-line contract of ``benchgen`` and ``osn``: one meaning per flag name.

Every parser of both commands is built in-process and walked: a flag name has one type and one
destination in every command that takes it, the same thing is spelled the same way everywhere,
old spellings still parse for one release (hidden, with one warning line naming the new one),
``osn preprocess`` run by hand uses the demo's SfM settings, and ``osn demo --spec FILE`` runs the
whole pipeline on a user's own scene spec.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
import yaml

from benchgen.cli import build_parser as benchgen_parser
from benchgen.scene.spec import PRESET_DIR, dump_spec, load_preset, load_spec
from scenecore.cli import DeprecatedAlias

REPO = Path(__file__).resolve().parents[1]

#: Options every command shares; each must be the very same option wherever it appears.
COMMON = {"-h", "--help", "--debug", "--quiet"}


def _commands() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """``(command line prefix, parser)`` for both tools and every subcommand."""
    from osn.cli import build_parser as osn_parser

    def walk(name: str, p: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
        yield name, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub, sp in a.choices.items():
                    yield from walk(f"{name} {sub}", sp)

    yield from walk("benchgen", benchgen_parser())
    yield from walk("osn", osn_parser())


def _parser(command: str) -> argparse.ArgumentParser:
    return dict(_commands())[command]


def _kind(a: argparse.Action) -> tuple[Any, ...]:
    """What a value given to the option is: the action, its type, arity, choices and constant."""
    t = a.type
    type_name = None if t is None else f"{getattr(t, '__module__', '')}.{getattr(t, '__qualname__', repr(t))}"
    return (type(a).__name__, type_name, a.nargs, tuple(a.choices) if a.choices else None, a.const)


def _options() -> dict[str, list[tuple[str, argparse.Action]]]:
    """Flag name -> ``(command, action)`` for every option of every command, old spellings aside."""
    out: dict[str, list[tuple[str, argparse.Action]]] = defaultdict(list)
    for cmd, p in _commands():
        for a in p._actions:
            if a.option_strings and not isinstance(a, DeprecatedAlias):
                for o in a.option_strings:
                    out[o].append((cmd, a))
    return out


def test_every_flag_has_one_type_and_one_meaning() -> None:
    """A flag name has one type and one destination across all commands; the common flags are the
    same option everywhere; and a destination is spelled by the same flag names wherever it appears."""
    options = _options()
    assert len(options) > 40  # the walk reached every subcommand
    problems = []
    spellings: dict[str, set[tuple[str, ...]]] = defaultdict(set)
    for flag, uses in sorted(options.items()):
        kinds = defaultdict(list)
        for cmd, a in uses:
            sig = (a.dest, _kind(a)) + ((a.help, repr(a.default)) if flag in COMMON else ())
            kinds[sig].append(cmd)
            spellings[a.dest].add(tuple(a.option_strings))
        if len(kinds) > 1:
            problems.append(f"{flag}: " + "; ".join(f"{', '.join(c)} -> {s}" for s, c in kinds.items()))
    problems += [f"dest {d!r} spelled {sorted(s)}" for d, s in spellings.items() if len(s) > 1]
    assert not problems, "\n".join(problems)


def test_hidden_options_are_deprecated_aliases_of_an_option_beside_them() -> None:
    """Nothing is hidden but an old spelling, and each old spelling writes the new option's dest."""
    for cmd, p in _commands():
        for a in p._actions:
            if a.help == argparse.SUPPRESS and not isinstance(a, argparse._SubParsersAction):
                assert isinstance(a, DeprecatedAlias), (cmd, a.option_strings or a.dest)
            if isinstance(a, DeprecatedAlias):
                assert a.target in p._actions and a.dest == a.target.dest, (cmd, a.option_strings)
                assert a.target.help != argparse.SUPPRESS and a.new.split()[0] in a.target.option_strings


def _flags(command: str) -> dict[str, argparse.Action]:
    p = _parser(command)
    return {o: a for a in p._actions if not isinstance(a, DeprecatedAlias) for o in a.option_strings}


def _positionals(command: str) -> list[str]:
    return [a.dest for a in _parser(command)._actions
            if not a.option_strings and not isinstance(a, (DeprecatedAlias, argparse._SubParsersAction))]


def test_the_same_thing_is_spelled_the_same_way_in_every_command() -> None:
    # A dataset a command measures against (or takes cameras from) beside its subject: --data DATASET.
    for cmd in ("benchgen score", "osn evaluate", "osn export", "osn train"):
        assert _flags(cmd)["--data"].metavar == "DATASET", cmd
        assert "dataset" not in _positionals(cmd), cmd
    # A dataset that is the command's subject is positional.
    for cmd in ("benchgen validate", "benchgen verify", "osn oracle"):
        assert _positionals(cmd) == ["dataset"], cmd
    # A training config, a schedule scaled to N field iterations, N configurations, a samples file.
    for cmd in ("osn train", "osn demo"):
        assert {"--config", "--field-iterations"} <= set(_flags(cmd)), cmd
    for cmd in ("osn sample", "osn export", "osn demo"):
        assert _flags(cmd)["-n"].type is int, cmd
    assert _flags("osn evaluate")["--samples"].metavar == "FILE"
    # Image size, export grid and Cycles samples have names of their own.
    for cmd in ("benchgen generate", "benchgen suite", "osn demo"):
        assert "--resolution" in _flags(cmd), cmd
    assert "--grid-resolution" in _flags("osn export") and "--cycles-samples" in _flags("benchgen generate")
    # The scene: a preset or a spec file, in benchgen generate and in osn demo.
    assert {"--preset", "--spec"} <= set(_flags("osn demo"))
    # A training seed and a stop after N global iterations, as a command line.
    assert _flags("osn train")["--seed"].type is int and "--max-iterations" in _flags("osn train")


#: ``(command, old spelling, new spelling)``: old scripts keep running for one release.
ALIASES = [
    ("benchgen", ["generate", "--preset", "tiny", "--out", "o", "--samples", "3"],
     ["generate", "--preset", "tiny", "--out", "o", "--cycles-samples", "3"], "--cycles-samples"),
    ("osn", ["export", "R", "--out", "o", "--resolution", "32"], ["export", "R", "--out", "o", "--grid-resolution", "32"],
     "--grid-resolution"),
    ("osn", ["export", "R", "--out", "o", "--samples", "4"], ["export", "R", "--out", "o", "-n", "4"], "use -n"),
    ("osn", ["demo", "--iterations", "150"], ["demo", "--field-iterations", "150"], "--field-iterations"),
    ("osn", ["demo", "--train-config", "c.yaml"], ["demo", "--config", "c.yaml"], "use --config"),
    ("osn", ["demo", "--inputs", "oracle"], ["demo", "--inputs-from", "oracle"], "--inputs-from"),
    ("osn", ["train", "D", "--out", "o"], ["train", "--data", "D", "--out", "o"], "--data DATASET"),
]


@pytest.mark.parametrize("tool,old,new,named", ALIASES,
                         ids=["generate --samples", "export --resolution", "export --samples", "demo --iterations",
                              "demo --train-config", "demo --inputs", "train DATASET"])
def test_old_spellings_still_parse_and_warn_once(tool: str, old: list[str], new: list[str], named: str, capsys) -> None:
    from osn.cli import build_parser as osn_parser

    build = benchgen_parser if tool == "benchgen" else osn_parser
    want = vars(build().parse_args(new))
    assert capsys.readouterr().err == ""  # the new spelling says nothing
    got = vars(build().parse_args(old))
    err = capsys.readouterr().err.splitlines()
    assert got == want
    assert len(err) == 1 and err[0].startswith(f"WARNING {tool} {old[0]}: ") and "deprecated" in err[0] and named in err[0], err
    # Hidden from --help: only the new spelling is documented.
    helptext = _parser(f"{tool} {old[0]}").format_help()
    assert named.removeprefix("use ").split()[0] in helptext
    for flag in (a for a in old if a.startswith("-") and a not in new):
        assert not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", helptext), flag


def test_an_old_spelling_reaches_the_command(tmp_path: Path) -> None:
    """``benchgen generate --samples N`` (the old spelling) still renders with N Cycles samples."""
    out = tmp_path / "video"
    r = subprocess.run([sys.executable, "-m", "benchgen.cli", "generate", "--preset", "tiny", "--samples", "2", "--video-only",
                        "--quiet", "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert [ln for ln in r.stderr.splitlines() if "deprecated" in ln] == [
        "WARNING benchgen generate: --samples is deprecated and goes in the next release; use --cycles-samples"]
    assert yaml.safe_load((out / "spec.yaml").read_text())["samples"] == 2


# --------------------------------------------------------------------------------------------
# osn preprocess by hand = the demo's SfM
# --------------------------------------------------------------------------------------------


def _demo_args(*extra: str) -> argparse.Namespace:
    return _parser("osn demo").parse_args([*extra])


def test_preprocess_defaults_are_the_demos_sfm_settings() -> None:
    """For the demo's dataset (its SfM video with SfM inputs, its own frames with oracle inputs) and
    any other width, ``osn preprocess``'s defaults give the SfM settings the demo runs with."""
    from osn.cli.demo import DEFAULT_PRESET, demo_preprocess_config, sfm_width
    from osn.cli.preprocess import preprocess_config

    hand = _parser("osn preprocess").parse_args(["SOURCE", "--out", "o"])
    width = load_preset(DEFAULT_PRESET).width
    widths = {sfm_width(_demo_args(), width), sfm_width(_demo_args("--inputs-from", "oracle"), width), 32, 511, 512, 767,
              768, 1024, 2048}
    assert max(widths) >= 768 > min(widths)  # crops on and off, anchor downscale 1 to 4
    for w in sorted(widths):
        assert preprocess_config(hand, w) == demo_preprocess_config(_demo_args(), w), w
    # An option given to both is honoured by both alike.
    hand = _parser("osn preprocess").parse_args(["SOURCE", "--out", "o", "--crop-margin", "8", "--anchor-downscale", "2"])
    demo = _demo_args("--crop-margin", "8", "--anchor-downscale", "2")
    assert preprocess_config(hand, 1024) == demo_preprocess_config(demo, 1024)


@pytest.mark.slow
def test_preprocess_by_hand_reproduces_the_demos_sfm(tmp_path: Path) -> None:
    """The demo's SfM stage on the real ``tiny`` preset (its video rendered again at 768 px, one of
    its objects too small to register) and ``osn preprocess`` run by hand on the same video, with
    only the options that say where the benchmark is: the same inputs, value for value."""
    from osn.cli import main as osn_main
    from osn.cli.demo import DemoPaths, stage_generate, stage_preprocess, stage_sfm_video, sfm_width
    from osn.preprocess.inputs import load_inputs

    work = tmp_path / "work"
    args = _demo_args("--preset", "tiny", "--workers", "1", "--work", str(work))
    p = DemoPaths(work)
    stage_generate(args, p)
    px = sfm_width(args, 32)
    stage_sfm_video(args, p, px)
    demo = stage_preprocess(args, p)
    assert demo["dropped"], demo  # an object SfM does not register: the demo goes on without it
    hand = tmp_path / "hand"
    assert osn_main(["preprocess", str(p.sfm_video), "--out", str(hand), "--downscale", str(px // 32),
                     "--train-video", str(p.dataset), "--workers", "1"]) == 0
    a, b = load_inputs(p.sfm), load_inputs(hand)
    assert a.meta["preprocess"] == b.meta["preprocess"] and a.meta["preprocess"]["crop_margin"] > 0
    assert json.loads((hand / "preprocess_report.json").read_text())["dropped"] == demo["dropped"]
    za, zb = np.load(p.sfm / "inputs.npz"), np.load(hand / "inputs.npz")
    assert sorted(za.files) == sorted(zb.files)
    for k in za.files:
        np.testing.assert_array_equal(za[k], zb[k], err_msg=k)


# --------------------------------------------------------------------------------------------
# osn train --seed / --field-iterations
# --------------------------------------------------------------------------------------------


def test_train_seed_and_field_iterations_set_the_runs_config(tiny_dataset: Path, tmp_path: Path, capsys) -> None:
    """``osn train --seed`` overrides the config's seed, ``--field-iterations`` scales its schedule
    as ``osn demo`` does; a resumed run keeps its own and refuses them in one line."""
    from osn.cli import main as osn_main
    from osn.train import TrainConfig

    run = tmp_path / "run"
    assert osn_main(["train", "--data", str(tiny_dataset), "--out", str(run), "--seed", "7", "--field-iterations", "40",
                     "--max-iterations", "1"]) == 0
    cfg = TrainConfig.from_yaml(run / "config.yaml", run_config=True)
    assert cfg.seed == 7 and abs(cfg.stage1_iters + cfg.rounds * cfg.field_iters - 40) <= cfg.rounds
    capsys.readouterr()
    assert osn_main(["train", "--data", str(tiny_dataset), "--out", str(run), "--resume", "--seed", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(run) in err[0] and "drop --seed" in err[0], err
    assert TrainConfig.from_yaml(run / "config.yaml", run_config=True).seed == 7


# --------------------------------------------------------------------------------------------
# osn demo --spec FILE
# --------------------------------------------------------------------------------------------

DEMO_TINY = ["--inputs-from", "oracle", "--field-iterations", "150", "-n", "60", "--max-views", "3", "--workers", "1"]


def _demo(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "osn.cli", "demo", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=900)


@pytest.mark.slow
def test_demo_runs_the_whole_pipeline_on_a_users_spec(tmp_path: Path) -> None:
    """``osn demo --spec FILE`` (the tiny preset's YAML as a user's own file): every stage, the
    dataset rendered from that spec; the same file again resumes, an edited one is refused."""
    spec = tmp_path / "my_scene.yaml"
    shutil.copy(PRESET_DIR / "tiny.yaml", spec)
    work = tmp_path / "work"
    r = _demo("--spec", spec, *DEMO_TINY, "--work", work)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "best of 60" in r.stdout and "report:" in r.stdout
    stages = json.loads((work / "stages.json").read_text())
    assert list(stages) == ["generate", "preprocess", "ground-truth", "train", "sample", "evaluate", "export", "addon"]
    assert stages["ground-truth"]["summary"]["passed"]
    assert dump_spec(load_spec(work / "dataset" / "spec.yaml")) == dump_spec(load_spec(spec))
    assert (work / "report" / "report.md").is_file() and (work / "export" / "osn_export.json").is_file()
    metrics = json.loads((work / "report" / "metrics.json").read_text())
    assert f"--spec {spec}" in metrics["command"] and "--preset" not in metrics["command"]
    # The same file again: every stage done. An edited file is another scene: refused in one line.
    r = _demo("--spec", spec, *DEMO_TINY, "--work", work)
    assert r.returncode == 0 and r.stdout.count("already done") == len(stages), r.stdout[-2000:]
    spec.write_text(spec.read_text().replace("seed: 0", "seed: 1"))
    r = _demo("--spec", spec, *DEMO_TINY, "--work", work)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(err) == 1 and "stage 'generate' was run with other options" in err[0], r.stderr
    # A preset and a spec at once: one or the other.
    r = _demo("--spec", spec, "--preset", "tiny", "--work", tmp_path / "w2")
    assert r.returncode == 2 and "not allowed with argument" in r.stderr and not (tmp_path / "w2").exists()


def test_demo_spec_that_cannot_be_read_is_one_line(tmp_path: Path, capsys) -> None:
    """A missing or broken ``--spec`` stops before anything is written, in one line naming the file."""
    from osn.cli import main as osn_main

    bad = tmp_path / "broken.yaml"
    bad.write_text("objects: [\n")
    for spec, phrase in ((tmp_path / "missing.yaml", "spec file not found"), (bad, "not valid YAML")):
        work = tmp_path / f"work-{spec.stem}"
        assert osn_main(["demo", "--spec", str(spec), "--work", str(work)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{spec}: {phrase}" in err[0], err
        assert not work.exists()
