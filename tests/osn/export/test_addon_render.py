"""The add-on's Cycles render of an export reproduces OSN's own render of the same view.

A tiny training (the ``tiny`` benchgen dataset, 32 px, a dense field with colour planes on the
anchor) is exported; Blender imports the export with the checkout's add-on and Cycles renders
the training camera and a test camera at a sampled configuration (volumes only, one sample per
pixel); each is compared with ``TrainedRun.render_view`` of the same camera, time and scales.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

#: Lowest PSNR (dB) of the add-on's volume render against OSN's render of the same view.
MIN_PSNR = 35.0


@pytest.fixture(scope="module")
def tiny_export(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A few seconds of training on the tiny dataset (colour planes on), exported."""
    from osn.export.from_run import export_run
    from osn.model.fields import FieldConfig
    from osn.preprocess.oracle import oracle_inputs
    from osn.train.loop import train
    from tests.osn.train.common import small_config

    work = tmp_path_factory.mktemp("addon_render")
    fcfg = FieldConfig(kind="dense", resolution=24, initial_resolution=16, upsample_steps=1, anchor_planes=32)
    cfg = small_config(field=fcfg, stage1_iters=40, rounds=1, final_scale_iters=5)
    run = train(work / "run", cfg, inputs=oracle_inputs(tiny_dataset), progress=False)
    export_run(run, work / "export", dataset=tiny_dataset, echo=lambda _m: None)
    return run, work / "export"


def test_volume_render_matches_osn_from_training_and_test_cameras(tiny_export, tiny_dataset: Path) -> None:
    from benchgen.score.metrics import psnr
    from osn.export.blender_render import View, render_export
    from osn.export.from_run import rig_cameras
    from osn.model.run import load_run
    from scenecore import export_format as core

    run_dir, export = tiny_export
    data = core.read_export(str(export))
    assert data.objects[data.anchor_index].field.planes is not None  # the anchor's colour planes are exported
    sample = data.samples[0]
    views = [View("train", 1), View(0, 2, list(sample))]
    out = render_export(export, views, parts=("volumes",), samples=1)
    run = load_run(run_dir)
    rig = rig_cameras(tiny_dataset, data.num_frames)
    got = []
    for v, img, sbar in zip(views, out["images"]["volumes"], out["sbar"]["volumes"]):
        cam = None if v.camera == "train" else rig[int(v.camera), v.time]
        ref = run.render_view(cam, v.time, np.asarray(sbar))["rgb"]
        assert ref.mean() > 0.05  # something is seen
        got.append(float(psnr(img, ref)))
    print(f"PSNR against OSN: training camera {got[0]:.2f} dB, test camera {got[1]:.2f} dB; "
          f"render seconds {out['seconds']['volumes']}")
    np.testing.assert_allclose(out["sbar"]["volumes"][1], sample, rtol=1e-9)  # the configuration rendered
    assert min(got) >= MIN_PSNR, got
