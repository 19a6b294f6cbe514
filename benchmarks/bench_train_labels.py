"""Label quality of the scale phase from saved fields (measurements in docs/experiments/).

    python benchmarks/bench_train_labels.py RUN CHECKPOINT [--steps N] [--trims T,T,...] [--points N] [key=value ...]

``RUN`` is an ``osn train`` run directory (config, inputs, dataset with ``valid_region.json``);
``CHECKPOINT`` a checkpoint of it whose fields are to be labelled (for example a copy of
``checkpoint.pt`` taken after stage 1). ``key=value`` override the run's training config (label
pool options such as ``label_stride``, ``label_trim``,
``final_label_trim``). The fields are labelled as the final scale phase labels
them. Prints the pool size, per object pair the bound its rays set (trimmed by
``final_label_trim``, in dataset scales) next to the exact one, the violations of the
exact configurations against the lowest (the noise floor), the IoU / precision / recall of the
*labelled* set (``depth_order.trimmed_labels`` on the whole pool) on the monitor's Monte-Carlo
samples, then trains a fresh scale network for ``--steps`` scale steps on those fields and
prints its IoU every 50 steps.

``--trims`` labels the same pool at each of several trims instead and prints, per trim, the
labelled set's IoU / precision / recall on ``osn evaluate``'s stratified points (``--points``
per stratum, seed 0; :func:`osn.evaluate.valid_set.valid_set_accuracy`'s estimator) and the
pair bounds it misses or reaches past most (``missed`` / ``excess``, shares of the region's
volume): how tight the final phase's labels should be on these fields (docs/training.md).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import torch
import yaml

from osn.preprocess.inputs import load_inputs
from osn.model.scale_net import full_sbar
from osn.model.depth_order import trimmed_labels
from scenecore.validity import limiting_bounds, set_accuracy, set_samples
from osn.evaluate.units import dataset_box, free_normalised
from osn.cli.train import dataset_region
from osn.train import Phase, TrainConfig, Trainer, TrainingMonitor

from benchutil import print_command


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("checkpoint")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--trims", default=None, help="comma-separated trims: the labelled set at each (no network trained)")
    ap.add_argument("--points", type=int, default=200_000, help="stratified points per stratum for --trims")
    ap.add_argument("overrides", nargs="*", help="key=value training-config overrides")
    a = ap.parse_intermixed_args()
    print_command()
    logging.basicConfig(level=logging.ERROR)
    run = Path(a.run)
    d = TrainConfig.from_yaml(run / "config.yaml", run_config=True).to_dict()
    for kv in a.overrides:
        k, v = kv.split("=", 1)
        d[k] = yaml.safe_load(v)
    cfg = TrainConfig.from_dict(d)
    tr = Trainer(load_inputs(run / "inputs"), cfg, torch.device("cpu"))
    fresh = {k: v.clone() for k, v in tr.net.state_dict().items()}
    tr.load_state_dict(torch.load(a.checkpoint, weights_only=True))
    tr.net.load_state_dict(fresh)  # the fields are the checkpoint's, the network starts untrained
    tr.net_opt = torch.optim.Adam(tr.net.parameters(), lr=cfg.scale_lr)
    ev = TrainingMonitor(tr, dataset_region(json.loads((run / "run.json").read_text())["dataset"]))
    if ev.region is None:
        raise SystemExit(f"{run}: the dataset has no valid_region.json")
    phase = Phase("scale", 10**9, 10**9 + a.steps, cfg.rounds + 1)  # the final scale phase
    trim = tr.label_trim_at(phase)
    tr.ensure_cache(phase)
    exact = torch.from_numpy(ev.points.exact)
    st, cons = tr.st, tr.cache["constraints"]
    units = np.array([o.unit_to_world for o in st.inputs.objects])
    ids = [o.id for o in st.inputs.objects]
    for (i, j), thr in zip(cons.pairs, cons.thresholds):
        b = np.exp(thr.numpy()) * units[j] / units[i]  # bound on actual_i / actual_j
        exact_b = ev.region.ratio_bounds[ids[i]][ids[j]]
        print(f"pair {ids[i]} in front of {ids[j]}: {len(b)} rays, bound min {b[0]:.3f} trimmed {b[int(trim * len(b))]:.3f} exact {exact_b}")
    if a.trims:
        sweep_trims(tr, ev.region, [float(t) for t in a.trims.split(",")], a.points)
        return
    s_all = torch.cat(ev.s_mc).float()  # the monitor's uniform, inner and near points (stratified)
    pv = cons.pair_violations(full_sbar(s_all, st.ranges, st.anchor))
    err = pv.sum(1)
    lab = trimmed_labels(pv, cons.sizes(), trim).bool().numpy()
    n = len(ev.s_mc[0])
    acc = set_accuracy(ev.points, lab[:n], lab[n:2 * n], lab[2 * n:])
    inner_err = err[n:2 * n][exact]
    spread = f"{float(inner_err.min()):.0f}-{float(inner_err.max()):.0f}" if len(inner_err) else "n/a (no region point drawn)"
    print(
        f"pool {cons.rays} rays, {cons.count} constraints; exact configurations violate {spread}, "
        f"lowest {float(err.min()):.0f}; labelled set {acc['learned_fraction']:.3g} of the box (exact {acc['exact_fraction']:.3g}, "
        f"{acc['exact_points']} points): IoU {acc['iou']:.3f} precision {acc['precision']:.3f} recall {acc['recall']:.3f}",
        flush=True,
    )
    tr.gen.manual_seed(cfg.seed)
    for i in range(a.steps):
        out = tr.step_scale(phase)
        if (i + 1) % 50 == 0:
            m = ev()
            print(f"step {i + 1}: IoU {m['iou']:.3f} precision {m['precision']:.3f} recall {m['recall']:.3f} noise floor {out['noise_floor']:.4f} valid fraction {out['valid_frac']:.4f}", flush=True)


def sweep_trims(tr: Trainer, region, trims: list[float], points: int) -> None:
    """The pool's labelled set at each trim, on ``osn evaluate``'s stratified points."""
    st, cons = tr.st, tr.cache["constraints"]
    ranges = st.ranges.cpu().numpy()
    pts = set_samples(region, dataset_box(st.inputs, ranges, region.num_objects), points, 0)
    free = [torch.from_numpy(free_normalised(st.inputs, ranges, x)).float() for x in pts.strata]
    pv = cons.pair_violations(full_sbar(torch.cat(free), st.ranges, st.anchor))
    names = {o.id: o.name for o in st.inputs.objects}
    for trim in trims:
        # One noise floor for all points of every stratum, as a scale step takes it among its samples.
        lab = np.split(trimmed_labels(pv, cons.sizes(), trim).bool().numpy(), 3)
        acc = set_accuracy(pts, *lab)
        worst = sorted(limiting_bounds(region, pts, *lab), key=lambda e: -(e["missed"] + e["excess"]))[:3]
        bounds = ", ".join(f"{names.get(e['i'])} < {names.get(e['j'])} missed {e['missed']:.3f} excess {e['excess']:.3f}"
                           for e in worst)
        print(f"trim {trim:g}: labelled set IoU {acc['iou']:.3f} precision {acc['precision']:.3f} "
              f"recall {acc['recall']:.3f}; {bounds}", flush=True)


if __name__ == "__main__":
    main()
