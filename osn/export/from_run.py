"""An :class:`~osn.export.writer.ExportScene` from a trained run (``osn export RUN --out DIR``).

:func:`export_run` reads an ``osn train`` run directory, samples every learned field onto a grid
(:func:`field_grids`), folds the scale network into plain layers (:func:`scale_network_from_torch`),
places the objects and cameras in the anchor's frame (:func:`export_scene_from_inputs`, poses
following :mod:`osn.preprocess.inputs`' conventions), adds valid configurations and, when the
caller names the run's dataset, its test-rig cameras; :func:`osn.export.writer.write_export`
writes the result.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn

from scenecore import dataset as D
from scenecore import export_format as core
from scenecore.cameras import invert_pose, pixel_rays
from scenecore.export_format import ExportFormatError
from scenecore.lock import output_lock
from osn.export.writer import ExportObject, ExportScene, ScaleNetwork, write_export
from osn.model.fields import DENSITY_SHIFT, PLANE_AXES, DenseGridField
from osn.model.placement import novel_to_training_camera, object_transforms
from osn.model.run import TrainedRun, load_run
from osn.model.scale_net import VALID_THRESHOLD
from osn.preprocess.inputs import SceneInputs
from osn.sample.configurations import Samples


def export_scene_from_inputs(
    inputs: SceneInputs,
    grids: dict[int, tuple[np.ndarray, np.ndarray]],
    scale_network: ScaleNetwork | None,
    samples_sbar: np.ndarray | None = None,
    test_camera_to_world: np.ndarray | None = None,
    source: str = "",
    interval_draws: int = 200_000,
) -> ExportScene:
    """Assemble an :class:`ExportScene` from per-object inputs and learned grids.

    Args:
        inputs: the per-object inputs the run was trained on (poses, boxes, near/far).
        grids: object id -> ``(density (D, H, W), colour (D, H, W, 3))`` sampled on its bbox,
            optionally followed by the field's parameters ``(density_raw, colour_raw, planes)``
            (:func:`field_parameters`).
        scale_network: the trained scale network (None for a single object).
        samples_sbar: optional ``(N, K)`` sampled valid configurations (actual scales).
        test_camera_to_world: optional ``(V, T, 4, 4)`` OpenCV test rig in dataset world
            coordinates; placed in the scene frame through ``inputs.world_to_anchor``.

    The scene frame is the anchor's frame, so the training camera at frame t is
    ``inv(anchor.cam_to_obj[t])`` composed into the anchor: ``camera_to_scene[t] =
    anchor.cam_to_obj[t]`` (it maps camera points to anchor points), and object k's pose at
    ``sbar = 1`` is ``camera_to_scene[t] @ inv(cam_to_obj_k[t])``. The anchor must be seen in
    every frame (it is the background).
    """
    anchor = inputs.object(inputs.anchor)
    T = len(inputs.timestamps)
    if len(anchor.frames) != T or not np.array_equal(np.sort(anchor.frames), np.arange(T)):
        raise ExportFormatError(f"the anchor ({anchor.name}) has poses at {len(anchor.frames)} of {T} frames; it must be seen in all")
    c2s = np.stack([anchor.cam_to_obj[anchor.frame_slot(t)] for t in range(T)])
    ranges = inputs.scale_ranges()
    anchor_index = inputs.anchor_pos
    sn = scale_network
    if sn is None:
        intervals = core.learned_intervals(None, ranges, anchor_index)
    else:
        intervals = core.learned_intervals(
            sn.layers, ranges, anchor_index, sn.threshold, sn.hidden_activation, sn.output_activation, draws=interval_draws
        )
    objects = []
    for i, o in enumerate(inputs.objects):
        if o.id not in grids:
            raise ExportFormatError(f"no grids for object {o.id} ({o.name})")
        density, colour, *params = grids[o.id]
        density_raw, colour_raw, planes = params if params else (None, None, None)
        poses = np.stack([c2s[t] @ invert_pose(M) for t, M in zip(o.frames, o.cam_to_obj)])
        objects.append(
            ExportObject(
                id=o.id, name=o.name, is_anchor=o.id == inputs.anchor, density=np.asarray(density, np.float32),
                colour=np.asarray(colour, np.float32), bbox=np.asarray(o.bbox, float), scale_range=tuple(ranges[i]),
                valid_interval=tuple(intervals[i]), frames=np.asarray(o.frames, np.int64), object_to_scene=poses,
                density_raw=density_raw, colour_raw=colour_raw, colour_planes=planes,
            )
        )
    test = None
    if test_camera_to_world is not None:
        test_c2w = np.asarray(test_camera_to_world, float)
        test = np.stack([np.stack([c2s[t] @ novel_to_training_camera(inputs, test_c2w[v, t], t) for t in range(T)]) for v in range(len(test_c2w))])
    return ExportScene(
        width=inputs.width, height=inputs.height, K=np.asarray(inputs.K, float), timestamps=np.asarray(inputs.timestamps, float),
        camera_to_scene=c2s, objects=objects, test_cameras=test, scale_network=sn, samples=samples_sbar, source=source,
        meta={"inputs_source": inputs.source},
    )


def field_grids(field_module: Any, resolution: int, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Sample an ``osn.model.fields.Field`` on a node-aligned ``resolution^3`` grid over its bbox.

    Colour is the field's colour seen along the six axis directions, averaged: exact for
    view-independent fields, the diffuse part for view-dependent ones. Returns ``density
    (R, R, R)`` and ``colour (R, R, R, 3)`` indexed ``[z, y, x]`` (:class:`ExportObject`).
    """
    bbox = field_module.bbox.detach().cpu().double().numpy()
    axes = [np.linspace(bbox[0, a], bbox[1, a], resolution) for a in range(3)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # (D, H, W) = (z, y, x)
    pts = torch.from_numpy(np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(np.float32))
    dirs = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32)
    sig, col = [], []
    with torch.no_grad():
        for p in pts.split(chunk):
            sig.append(field_module.density(p))
            if getattr(field_module, "view_dependent", False):
                col.append(torch.stack([field_module.color(p, d.expand_as(p)) for d in dirs]).mean(0))
            else:
                col.append(field_module.color(p, dirs[:1].expand_as(p)))
    shape = (resolution,) * 3
    return torch.cat(sig).numpy().reshape(shape), torch.cat(col).clamp(0, 1).numpy().reshape(shape + (3,))


def field_parameters(field_module: Any, resolution: int, colour: np.ndarray, chunk: int = 65536
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The field's own parameters on :func:`field_grids`' nodes: ``(density_raw (R, R, R), colour_raw
    (R, R, R, 3), planes (3, P, P, 3) or None)`` (:class:`~osn.export.writer.ExportObject`).

    ``density = softplus(density_raw)`` for every field (the activation is applied after the
    trilinear lookup, so the nodes' densities alone interpolate to a different field). A dense
    grid's colour is ``sigmoid(raw grid + colour planes)``: at its own resolution the raw nodes and
    the planes reproduce it exactly. Other fields' colour (``colour``, :func:`field_grids`, the
    view-averaged colour) is stored as its logit.
    """
    bbox = field_module.bbox.detach().cpu()
    axes = [torch.linspace(float(bbox[0, a]), float(bbox[1, a]), resolution, dtype=torch.float64) for a in range(3)]
    zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = torch.stack([xx, yy, zz], -1).reshape(-1, 3).float()
    dense = isinstance(field_module, DenseGridField)
    raw, col = [], []
    with torch.no_grad():
        for p in pts.split(chunk):
            xn = field_module.normalise(p)
            # The fields' pre-activation parts (Field's contract: density = softplus(raw + shift)).
            raw.append(field_module._density_raw(xn) + DENSITY_SHIFT)
            if dense:
                col.append(field_module._lookup(slice(1, 4), xn))
    shape = (resolution,) * 3
    density_raw = torch.cat(raw).numpy().reshape(shape)
    if not dense:
        c = np.clip(np.asarray(colour, np.float64), 1e-4, 1.0 - 1e-4)
        return density_raw, np.log(c / (1.0 - c)).astype(np.float32), None
    planes = None
    if field_module.planes is not None:
        if tuple(PLANE_AXES) != tuple(core.PLANE_AXES):
            raise ExportFormatError(f"the field's colour planes span {PLANE_AXES}, the export format {core.PLANE_AXES}")
        n = field_module.plane_size
        planes = field_module.planes.detach().cpu().numpy().reshape(3, n, n, 3)  # [plane, v, u] (u fastest)
    return density_raw, torch.cat(col).numpy().reshape(shape + (3,)), planes


#: Most training frames a view mesh is fused from (evenly spaced over the object's frames).
VIEW_MESH_FRAMES = 15
#: Neighbouring pixels are joined by a triangle when their depths differ by less than this share
#: (a fuzzy surface's rendered depth is noisy: a tighter bound tears holes into walls).
VIEW_MESH_DEPTH_STEP = 0.3
#: A pixel becomes a vertex where the object alone covers it at least this much.
VIEW_MESH_MIN_ACC = 0.5


def view_mesh(run: TrainedRun, position: int, frames: Sequence[int] | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A surface of object ``position`` fused from its training views: ``(vertices (V, 3) object
    coordinates, faces (F, 3), colours (V, 3) display values)`` or None when no view covers it.

    The object is rendered alone (``TrainedRun.render_view``, scale 1) from the training camera at
    up to :data:`VIEW_MESH_FRAMES` of its frames; every pixel it covers (opacity at least
    :data:`VIEW_MESH_MIN_ACC`) becomes a vertex at its rendered depth with its rendered colour
    (divided by the opacity: the colour of what it sees, not mixed with the black background), and
    neighbouring pixels are joined where their depths are close. Unlike a level set of the
    density, the surface is where OSN's renders put it, fog included, with the colour planes'
    detail; it is only as complete as the views (a side never filmed has no surface).
    """
    inp = run.inputs
    obj = inp.objects[position]
    own = np.asarray(obj.frames if frames is None else frames)
    if len(own) > VIEW_MESH_FRAMES:
        own = own[np.round(np.linspace(0, len(own) - 1, VIEW_MESH_FRAMES)).astype(int)]
    H, W = inp.height, inp.width
    _, dirs = pixel_rays(inp.K, np.eye(4), W, H)
    verts, faces, cols = [], [], []
    count = 0
    for t in own:
        r = run.render_view(None, int(t), np.ones(inp.num_objects), objects=[position])
        depth, acc = r["depth"].reshape(-1), r["acc"].reshape(-1)
        ok = np.isfinite(depth) & (acc >= VIEW_MESH_MIN_ACC)
        if not ok.any():
            continue
        T = object_transforms(inp, np.eye(4), int(t), np.ones(inp.num_objects))[position]
        pts = dirs[ok] * depth[ok, None]
        verts.append(pts @ T[:3, :3].T + T[:3, 3])
        cols.append(np.clip(r["rgb"].reshape(-1, 3)[ok] / acc[ok, None], 0.0, 1.0))
        index = np.full(H * W, -1)
        index[ok] = count + np.arange(int(ok.sum()))
        count += int(ok.sum())
        grid, d = index.reshape(H, W), np.where(ok, depth, 1.0).reshape(H, W)  # 1.0: never read (not ok)
        a, b, c, e = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
        da, db, dc, de = d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]
        for tri, dt in (((a, c, b), (da, dc, db)), ((b, c, e), (db, dc, de))):
            stack = np.stack(dt)
            close = stack.max(0) <= stack.min(0) * (1.0 + VIEW_MESH_DEPTH_STEP)
            keep = close & np.all(np.stack(tri) >= 0, axis=0)
            faces.append(np.stack([x[keep] for x in tri], 1))
    if not count:
        return None
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(cols)


def export_layers_from_torch(modules: Sequence[Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(W, b), ...]`` from a sequence of ``torch.nn.Linear`` modules, in order."""
    return [(m.weight.detach().cpu().double().numpy(), m.bias.detach().cpu().double().numpy()) for m in modules]


def scale_network_from_torch(net: Any, threshold: float) -> ScaleNetwork:
    """An ``osn.model.scale_net.ScaleNet`` as plain layers (ReLU hidden, sigmoid on the logit).

    ``ScaleNet`` centres its input (``s * 2 - 1``) before the first layer; that affine map is
    folded into the first layer (``W' = 2 W``, ``b' = b - W 1``) so the export's input is the
    normalised scale itself, as the manifest states.
    """
    mods = list(net.mlp)
    linears = [m for m in mods if isinstance(m, nn.Linear)]
    if any(not isinstance(m, (nn.Linear, nn.ReLU)) for m in mods) or not isinstance(mods[-1], nn.Linear):
        raise ExportFormatError(f"unexpected scale network layout {[type(m).__name__ for m in mods]}")
    layers = export_layers_from_torch(linears)
    W0, b0 = layers[0]
    layers[0] = (2.0 * W0, b0 - W0.sum(axis=1))
    return ScaleNetwork(layers=layers, hidden_activation="relu", output_activation="sigmoid", threshold=float(threshold))


def rig_cameras(dataset: str | Path, T: int) -> np.ndarray | None:
    """``(V, T, 4, 4)`` OpenCV test cameras of a benchgen dataset (world frame); None without test views.

    Every viewpoint with a test frame is kept; timestamps it is not listed at hold its nearest listed camera.
    """
    scene = D.load_scene(dataset)
    views = sorted({f.view for f in scene.test_frames})
    rig = np.full((len(views), T, 4, 4), np.nan)
    # A viewpoint's camera at the time it films the training video is a training frame.
    for f in scene.frames:
        if f.view in views:
            rig[views.index(f.view), f.time_index] = f.camera_to_world
    # Datasets may list a viewpoint at only some timestamps (rig.test_views); a viewpoint's camera
    # is held from its nearest listed time (benchgen's viewpoints do not move).
    for v in range(len(views)):
        known = np.nonzero(np.all(np.isfinite(rig[v]), axis=(1, 2)))[0]
        for t in range(T):
            if not np.all(np.isfinite(rig[v, t])):
                rig[v, t] = rig[v, known[np.argmin(np.abs(known - t))]]
    return rig if len(views) else None


#: Configurations drawn for an export when the run has no ``samples.npz`` and none are asked for.
DEFAULT_EXPORT_SAMPLES = 16


def export_run(
    run_dir: str | Path,
    out_dir: str | Path,
    resolution: int | None = None,
    samples: int | None = None,
    seed: int = 0,
    echo: Callable[[str], None] = print,
    dataset: str | Path | None = None,
    mesh: str = "views",
) -> Path:
    """Export an ``osn train`` run directory; returns the manifest path.

    Reads the run's ``inputs/`` and ``checkpoint.pt`` (fields at their trained resolutions, the
    scale network, the training config), samples every field on a ``resolution^3`` grid
    (default: the field's own resolution), derives the learned valid intervals from the scale
    network, adds the test rig of ``dataset`` (the benchgen dataset the run was trained on) when
    it is given and the inputs are aligned to it, and valid configurations
    (:func:`exported_samples`). ``mesh``: each object's surface fused from its training views
    (``"views"``, :func:`view_mesh`) or the density's marching-cubes level set (``"level"``).
    """
    if mesh not in ("views", "level"):
        raise ValueError(f"mesh must be 'views' or 'level', got {mesh!r}")
    if samples is not None and samples < 0:
        raise ValueError(f"the number of exported samples must be >= 0, got {samples}")
    with output_lock(out_dir):  # from the start, so a second export stops before its costly sampling
        return _export_run_locked(Path(run_dir), out_dir, resolution, samples, seed, echo, dataset, mesh)


def _export_run_locked(run: Path, out_dir: str | Path, resolution: int | None, samples: int | None, seed: int,
                       echo: Callable[[str], None], dataset: str | Path | None, mesh: str = "views") -> Path:
    trained = load_run(run)
    inputs = trained.inputs
    grids = {}
    for o, f in zip(inputs.objects, trained.fields):
        r = resolution or f.resolution
        density, colour = field_grids(f, r)
        grids[o.id] = (density, colour, *field_parameters(f, r, colour))
        echo(f"export: sampled object {o.id} ({o.name}) at {r}^3")
    # The learned valid set is the classifier's decision (score > 0.5), as in `osn sample` and the
    # valid-set IoU; training's stricter sampling threshold is a training setting.
    net = scale_network_from_torch(trained.net, VALID_THRESHOLD) if trained.net is not None else None
    test = None
    if dataset is not None and inputs.world_to_anchor is None:
        echo(f"export: no test cameras: the inputs are not aligned to {dataset} (no world-to-anchor similarity)")
    elif dataset is not None:
        test = rig_cameras(dataset, len(inputs.timestamps))
    scene = export_scene_from_inputs(inputs, grids, net, test_camera_to_world=test, source=str(run.resolve()))
    if mesh == "views":
        for k, o in enumerate(scene.objects):
            o.surface = view_mesh(trained, k)
        echo(f"export: meshes fused from the training views ({sum(len(o.surface[1]) for o in scene.objects if o.surface)} faces)")
    scene.meta.update({"name": run.name, "iteration": trained.iteration, "dataset": None if dataset is None else str(dataset)})
    scene.samples = exported_samples(run, scene, trained, samples, seed, echo)
    return write_export(out_dir, scene, echo=echo)


def exported_samples(
    run: Path, scene: ExportScene, trained: TrainedRun, samples: int | None, seed: int, echo: Callable[[str], None]
) -> np.ndarray | None:
    """The configurations ``(N, K)`` (actual scales) an export carries.

    With ``samples=None``: those of ``RUN/samples.npz`` (``osn sample``, the ones evaluated) when
    it exists, else ``DEFAULT_EXPORT_SAMPLES`` drawn through the exported scale network; with a
    number, that many drawn with ``seed`` (0: none). None without a scale network (one object).
    """
    if samples is None and (run / "samples.npz").is_file():
        sbar = Samples.load(run / "samples.npz").sbar
        echo(f"export: {len(sbar)} configurations from {run / 'samples.npz'}")
        return sbar
    if samples is None:
        samples = DEFAULT_EXPORT_SAMPLES
    net = scene.scale_network
    if not samples or net is None:
        return None
    ranges = np.array([o.scale_range for o in scene.objects])
    anchor_index = [o.is_anchor for o in scene.objects].index(True)

    def score(sbar: np.ndarray) -> np.ndarray:
        return core.scale_scores(net.layers, sbar, ranges, anchor_index, net.hidden_activation, net.output_activation)

    intervals = np.array([o.valid_interval for o in scene.objects])
    return core.sample_valid_configurations(score, intervals, net.threshold, samples, seed)
