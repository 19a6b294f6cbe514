"""The learned valid set against the exact region, on a tiny training whose inputs left an object out."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from osn.evaluate.report import LIMIT_SHARE, limits_lines
from osn.evaluate.units import dataset_box
from osn.evaluate.valid_set import valid_set_accuracy
from osn.model.run import load_run
from osn.preprocess.inputs import IGNORE_ID
from osn.preprocess.oracle import oracle_inputs
from osn.train.loop import record_final_pool, train
from scenecore import dataset as D
from scenecore.validity import ValidRegion
from tests.osn.train.common import small_config


def test_bounds_against_an_object_the_inputs_left_out_are_named_as_the_dataset_names_it(
        tiny_dataset: Path, tmp_path: Path) -> None:
    """Preprocessing dropped an object (as SfM does one it cannot register): the run never sees it,
    yet the exact region bounds it, so the report's limits name it; from the dataset, not as an id."""
    inputs = oracle_inputs(tiny_dataset)
    dropped = int(inputs.objects[-1].id)
    inputs = dataclasses.replace(inputs, meta={**inputs.meta, "dropped_objects": [dropped]},
                                 objects=[o for o in inputs.objects if o.id != dropped],
                                 masks=np.where(inputs.masks == dropped, IGNORE_ID, inputs.masks))
    # 150 stage-1 steps make the tiny scene's fields opaque enough for contested label rays.
    train(tmp_path / "r", small_config(stage1_iters=150, rounds=1), inputs=inputs, progress=False)
    run = load_run(tmp_path / "r")
    scene = D.load_scene(tiny_dataset)
    region = D.load_valid_region(tiny_dataset, scene.num_objects)
    name = scene.objects[dropped].name
    acc = valid_set_accuracy(run, region, points=2000, names={o.id: o.name for o in scene.objects})
    pairs = [e for e in acc["limits"] if dropped in (e["i"], e["j"])]
    assert pairs and all(name in e["pair"] and f"object {dropped}" not in e["pair"] for e in pairs)
    # The final label pool's rays per bound: none for the dropped object's pairs (it trains
    # nothing), the recorded count for the others; the report's table says so.
    written = (tmp_path / "r" / "label_pool.json").read_bytes()
    pool = json.loads(written)
    # A run trained before training wrote the record gets the same one from its checkpoint.
    (tmp_path / "r" / "label_pool.json").unlink()
    assert record_final_pool(tmp_path / "r") and (tmp_path / "r" / "label_pool.json").read_bytes() == written
    rays = {(i, j): n for i, j, n in pool["pairs"]}
    assert rays and all(dropped not in p for p in rays)
    assert all(e["pool_rays"] == 0 and not e["pool_minority"] for e in pairs)
    assert all(e["pool_rays"] == rays.get((e["i"], e["j"]), 0) for e in acc["limits"])
    shown = [e for e in acc["limits"] if max(e["missed"], e["excess"]) >= LIMIT_SHARE]
    assert shown and all(f"| {e['pair']} | {e['bound']:.4f} | {e['missed']:.3f} | {e['excess']:.3f} | {e['pool_rays']} |"
                         in "\n".join(limits_lines(acc["limits"], rows=len(shown))) for e in shown)
    unnamed = valid_set_accuracy(run, region, points=2000)  # without names: the id, as before
    assert any(f"object {dropped}" in e["pair"] for e in unnamed["limits"])
    # What these inputs allow at best: the region without the dropped object's bounds, held at
    # scale 1 like the evaluation's box holds it; the other free object's share of its line,
    # counted on a fine grid, against the stratified estimate.
    box = dataset_box(run.inputs, run.ranges, region.num_objects)
    (free,) = [k for k in range(region.num_objects) if box[k, 0] < box[k, 1]]
    line = np.ones((100_001, region.num_objects))
    line[:, free] = np.linspace(*box[free], len(line))
    bounds = region.ratio_bounds.copy()
    bounds[dropped, :] = bounds[:, dropped] = np.inf
    blind = ValidRegion.from_bounds(bounds, region.anchor).contains(line)
    exact = region.contains(line)
    assert exact.any() and (blind >= exact).all()
    assert acc["iou_without_dropped"] == pytest.approx(exact.sum() / blind.sum(), abs=0.02) and acc["iou_without_dropped"] < 0.98


def test_a_label_pool_record_that_is_not_one_is_refused_naming_the_file(tmp_path: Path) -> None:
    """A shared run's record is untrusted: malformed or oversized, one error naming it; absent, None."""
    import pytest
    from scenecore.errors import DatasetError
    from osn.train import labels

    assert labels.read_pool_record(tmp_path) is None
    path = tmp_path / labels.POOL_FILE
    for bad in ('{"pairs": [[0, 1]], "minority": []}', '{"pairs": [[0, 1, -2]], "minority": []}',
                '{"pairs": [[0, 1, true]], "minority": []}', '{"pairs": []}', "[1, 2", '"text"'):
        path.write_text(bad)
        with pytest.raises(DatasetError, match=f"^{path}: not a label pool record"):
            labels.read_pool_record(tmp_path)
    path.write_text('{"pairs": [[2, 0, 7]], "minority": [[0, 2, 1]]}')
    assert labels.read_pool_record(tmp_path) == {(2, 0): (7, False), (0, 2): (1, True)}
    path.write_bytes(b" " * (labels.MAX_POOL_BYTES + 1))
    with pytest.raises(DatasetError, match="more than the"):
        labels.read_pool_record(tmp_path)


def test_an_unfinished_run_has_no_final_label_pool(tiny_dataset: Path, tmp_path: Path) -> None:
    train(tmp_path / "r", small_config(), inputs=oracle_inputs(tiny_dataset), max_iterations=20, progress=False)
    assert not (tmp_path / "r" / "label_pool.json").exists()
    import pytest
    with pytest.raises(ValueError, match="training stopped at iteration 20 of 80; its final label pool does not exist yet"):
        record_final_pool(tmp_path / "r")


def test_a_run_left_with_the_anchor_alone_measures_no_valid_set(tiny_dataset: Path, tmp_path: Path) -> None:
    """Preprocessing dropped every mover: the run learned no scale, so its valid set is not
    measured (NaN and why), not the 1.0 of a scene that has one object."""
    import math

    from osn.evaluate.report import summary_lines

    inputs = oracle_inputs(tiny_dataset)
    movers = [int(o.id) for o in inputs.objects if o.id != inputs.objects[inputs.anchor_pos].id]
    anchor = inputs.objects[inputs.anchor_pos]
    inputs = dataclasses.replace(inputs, meta={**inputs.meta, "dropped_objects": movers}, objects=[anchor],
                                 masks=np.where(np.isin(inputs.masks, movers), IGNORE_ID, inputs.masks))
    train(tmp_path / "r", small_config(stage1_iters=5), inputs=inputs, progress=False)
    scene = D.load_scene(tiny_dataset)
    acc = valid_set_accuracy(load_run(tmp_path / "r"), D.load_valid_region(tiny_dataset, scene.num_objects), points=500)
    assert all(math.isnan(acc[k]) for k in ("precision", "recall", "iou")) and "dropped every object" in acc["not_measured"]
    assert "valid-set IoU nan" in summary_lines({}, acc, [])[1]
