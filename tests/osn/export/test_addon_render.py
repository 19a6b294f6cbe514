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
#: Lowest PSNR (dB) of its meshes (fused from the training views), from the training camera.
MIN_MESH_PSNR = 14.0


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
    out = render_export(export, views, parts=("volumes", "meshes"), samples=1)
    run = load_run(run_dir)
    rig = rig_cameras(tiny_dataset, data.num_frames)
    got: dict[str, list[float]] = {"volumes": [], "meshes": []}
    for part in got:
        for v, img, sbar in zip(views, out["images"][part], out["sbar"][part]):
            cam = None if v.camera == "train" else rig[int(v.camera), v.time]
            ref = run.render_view(cam, v.time, np.asarray(sbar))["rgb"]
            assert ref.mean() > 0.05  # something is seen
            got[part].append(float(psnr(img, ref)))
    print(f"PSNR against OSN (training camera, test camera): {got}; render seconds {out['seconds']}")
    np.testing.assert_allclose(out["sbar"]["volumes"][1], sample, rtol=1e-9)  # the configuration rendered
    assert min(got["volumes"]) >= MIN_PSNR, got
    assert data.manifest["objects"][0]["mesh_source"] == "training views"
    assert got["meshes"][0] >= MIN_MESH_PSNR, got


def _field_on_nodes(data, i: int, scale: int = 1):
    """The exported field of object ``i`` evaluated as the manifest says, at points between its
    nodes (``scale`` sub-steps per voxel): ``(points (N, 3) object coordinates, density, colour)``."""
    from scipy.ndimage import map_coordinates

    from osn.export.writer import _openvdb

    o = data.objects[i]
    f = o.field
    vdb = _openvdb()
    grids = {g.name: g for g in vdb.readAll(o.volume_path)[0]}
    Dn, Hn, Wn = o.grid_shape
    raw = np.zeros((Wn, Hn, Dn), np.float32)
    grids[f.density_grid].copyToArray(raw)
    col = np.zeros((Wn, Hn, Dn, 3), np.float32)
    grids[f.color_grid].copyToArray(col)
    rng = np.random.default_rng(0)
    idx = rng.random((500, 3)) * (np.array([Wn, Hn, Dn]) - 1)  # [x, y, z] index coordinates
    sigma_raw = map_coordinates(raw, idx.T, order=1) + f.density_offset
    c = np.stack([map_coordinates(col[..., k], idx.T, order=1) for k in range(3)], 1)
    if f.planes is not None:
        from scenecore.export_format import PLANE_AXES

        P = f.planes.shape[1]
        u = idx / (np.array([Wn, Hn, Dn]) - 1) * (P - 1)
        for plane, (a, b) in zip(f.planes, PLANE_AXES):
            c += np.stack([map_coordinates(plane[..., k], np.stack([u[:, b], u[:, a]]), order=1) for k in range(3)], 1)
    lo, hi = o.bbox
    pts = lo + idx / (np.array([Wn, Hn, Dn]) - 1) * (hi - lo)
    return pts, np.logaddexp(0.0, sigma_raw), 1.0 / (1.0 + np.exp(-c))


def test_exported_field_is_the_trained_field(tiny_export) -> None:
    """Between the nodes, the field the manifest describes (softplus of the trilinear raw density,
    sigmoid of the raw colour plus the bilinear planes) equals the trained field's own lookups;
    the node values alone (``density``) interpolate to something else."""
    import torch

    from osn.model.run import load_run
    from scenecore import export_format as core

    run_dir, export = tiny_export
    run, data = load_run(run_dir), core.read_export(str(export))
    for i, (o, fld) in enumerate(zip(data.objects, run.fields)):
        pts, dens, col = _field_on_nodes(data, i)
        with torch.no_grad():
            x = torch.from_numpy(pts).float()
            ref_d = fld.density(x).double().numpy()
            ref_c = fld.color(x, torch.zeros_like(x)).double().numpy()
        np.testing.assert_allclose(dens, ref_d, rtol=1e-4, atol=1e-4, err_msg=o.name)
        np.testing.assert_allclose(col, ref_c, atol=1e-4, err_msg=o.name)
    assert data.objects[data.anchor_index].field.planes is not None


@pytest.mark.parametrize("keys,value,names", [
    (("density", "activation"), "relu", "object 0: field: activations"),
    (("density", "offset"), "low", "object 0: field: density offset"),
    (("color", "planes", "size"), 1, "object 0: field: color planes: size"),
    (("color", "planes", "axes"), [[0, 1], [1, 2], [0, 2]], "object 0: field: color planes: axes"),
    (("color", "planes", "file"), "objects/9_planes.npz", "colour planes file 'objects/9_planes.npz' is not among"),
])
def test_malformed_field_entries_are_one_line_format_errors(tiny_export, tmp_path: Path, keys, value, names) -> None:
    import json
    import shutil

    from scenecore import export_format as core

    _, export = tiny_export
    d = tmp_path / "export"
    shutil.copytree(export, d)
    m = json.loads((d / "osn_export.json").read_text())
    entry = m["objects"][0]["field"]
    for k in keys[:-1]:
        entry = entry[k]
    entry[keys[-1]] = value
    (d / "osn_export.json").write_text(json.dumps(m))
    with pytest.raises(core.ExportFormatError) as e:
        core.read_export(str(d))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{d / 'osn_export.json'}: ") and names in msg, msg
