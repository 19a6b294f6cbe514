"""Label quality of the scale phase from saved fields (docs/training.md, "Label quality").

    python benchmarks/bench_train_labels.py RUN CHECKPOINT [--steps N] [key=value ...]

``RUN`` is an ``osn train`` run directory (config, inputs, dataset with ``valid_region.json``);
``CHECKPOINT`` a checkpoint of it whose fields are to be labelled (for example a copy of
``checkpoint.pt`` taken after stage 1). ``key=value`` override the run's training config (label
pool options such as ``coverage_threshold``, ``uncertain_acc``, ``label_stride``,
``label_erode``, ``label_tolerance``). Prints the pool size, the segmentation error of the exact
configurations against the best of random ones (the noise floor), the IoU / precision / recall
of the *labelled* set (error within ``label_tolerance`` of the lowest one on the whole pool) on
the evaluator's Monte-Carlo samples, then trains a fresh scale network for ``--steps`` scale
steps on those fields and prints its IoU every 50 steps.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import torch
import yaml

from osn.inputs import load_inputs
from osn.scale_net import full_sbar
from osn.softz import implied_segmentation, sample_accuracy
from osn.train import Evaluator, Phase, TrainConfig, Trainer


def pool_error(tr: Trainer, s: torch.Tensor, chunk: int = 2000) -> torch.Tensor:
    """Error rate ``(N,)`` of normalised scale samples ``s (N, K-1)`` on the whole cached pool."""
    c, st = tr.cache, tr.st
    gt = st.labels.reshape(-1)[c["flat"]]
    errs = [1 - sample_accuracy(implied_segmentation(c["depth"], c["covered"], full_sbar(s[a : a + chunk], st.ranges, st.anchor)), gt) for a in range(0, len(s), chunk)]
    return torch.cat(errs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("checkpoint")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("overrides", nargs="*", help="key=value training-config overrides")
    a = ap.parse_intermixed_args()
    logging.basicConfig(level=logging.ERROR)
    run = Path(a.run)
    d = yaml.safe_load((run / "config.yaml").read_text())
    for kv in a.overrides:
        k, v = kv.split("=", 1)
        d[k] = yaml.safe_load(v)
    cfg = TrainConfig.from_dict(d)
    tr = Trainer(load_inputs(run / "inputs"), cfg, torch.device("cpu"))
    fresh = {k: v.clone() for k, v in tr.net.state_dict().items()}
    tr.load_state_dict(torch.load(a.checkpoint, weights_only=False))
    tr.net.load_state_dict(fresh)  # the fields are the checkpoint's, the network starts untrained
    tr.net_opt = torch.optim.Adam(tr.net.parameters(), lr=cfg.scale_lr)
    ev = Evaluator(tr, json.loads((run / "run.json").read_text())["dataset"])
    if ev.region is None:
        raise SystemExit(f"{run}: the dataset has no valid_region.json")
    phase = Phase("scale", 10**9, 10**9 + a.steps, 1)
    tr.ensure_cache(phase)
    exact = torch.from_numpy(ev.exact)
    err = pool_error(tr, ev.s_mc.float())
    lab = err <= err.min() + cfg.label_tolerance + 1e-12
    inter = float((lab & exact).sum())
    print(
        f"pool {len(tr.cache['flat'])} rays; exact configurations' error {float(err[exact].min()):.4f}-{float(err[exact].max()):.4f}, "
        f"lowest {float(err.min()):.4f}; labelled set {float(lab.double().mean()):.4f} of the box (exact {float(exact.double().mean()):.4f}): "
        f"IoU {inter / max(float((lab | exact).sum()), 1):.3f} precision {inter / max(float(lab.sum()), 1):.3f} recall {inter / max(float(exact.sum()), 1):.3f}",
        flush=True,
    )
    tr.gen.manual_seed(cfg.seed)
    for i in range(a.steps):
        out = tr.step_scale(phase)
        if (i + 1) % 50 == 0:
            m = ev()
            print(f"step {i + 1}: IoU {m['iou']:.3f} precision {m['precision']:.3f} recall {m['recall']:.3f} noise floor {out['noise_floor']:.4f} valid fraction {out['valid_frac']:.4f}", flush=True)


if __name__ == "__main__":
    main()
