"""``benchgen suite`` on a small real run: the table, resuming, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from scenecore import dataset as D
from scenecore.scale_space import eq1_box
from benchgen.cli import main as cli_main
from benchgen.render.suite import SUITE_PRESETS, depth_ranges
from benchgen.scene.spec import load_preset

pytestmark = pytest.mark.slow


def test_suite_presets_exist_and_cover_the_three_protocols():
    protocols = {load_preset(p).rig.protocol for p in SUITE_PRESETS}
    assert protocols == {"orbit", "stereo", "multi-camera"}
    cb8 = load_preset("chessboard-8")
    assert len(cb8.objects) == 8 and cb8.rig.views == cb8.rig.times == 15


def test_suite_generates_tabulates_and_resumes(tmp_path, capsys):
    out = tmp_path / "suite"
    args = ["suite", "--out", str(out), "--presets", "occlusion-tower", "--resolution", "32", "--configs", "2", "--quiet"]
    assert cli_main(args) == 0
    text = capsys.readouterr().out
    assert "| occlusion-tower | stereo | 2 | 15 / 15 | 32 |" in text and "| 2/2 |" in text
    row = D.read_json(out / "suite.json")["rows"][0]
    assert (out / "suite.md").read_text().splitlines()[2].startswith("| occlusion-tower |")
    # The share is the Eq. 1 box's valid fraction: check it against plain uniform sampling of the box.
    region = D.load_valid_region(out / "occlusion-tower")
    box = eq1_box(*depth_ranges(out / "occlusion-tower"))
    rng = np.random.default_rng(1)
    s = np.ones((400_000, 3))
    s[:, 1:] = box[1:, 0] + (box[1:, 1] - box[1:, 0]) * rng.random((400_000, 2))
    plain = float(np.mean(region.contains(s)))
    assert 0 < row["share"] < 1 and abs(row["share"] - plain) < 4 * (row["share_stderr"] + np.sqrt(plain * (1 - plain) / 4e5))
    # Rerun: nothing rendered again, the row's time adds up.
    assert cli_main(args) == 0
    assert "rendered 0 frames" in capsys.readouterr().out
    assert D.read_json(out / "suite.json")["rows"][0]["seconds"] >= row["seconds"]


def test_suite_rejects_an_unknown_preset_before_rendering(tmp_path, capsys):
    assert cli_main(["suite", "--out", str(tmp_path / "s"), "--presets", "gnome-house,nope", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown preset 'nope'" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s" / "gnome-house").exists()
