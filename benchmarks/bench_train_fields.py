"""Which field reaches a given training PSNR sooner on this machine: dense grid or TensoRF VM?

Runs stage 1 (every object alone, RGB + depth losses) of the CPU config with each field kind
for the same wall-time budget, evaluating every few seconds the PSNR of each labelled pixel
rendered by its own object (fixed pixel subset, interval midpoints). Prints one JSON line per
evaluation and, per kind, the time to reach ``--target`` dB.

    .venv/bin/python benchmarks/bench_train_fields.py DATASET [--seconds 90] [--target 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import torch
import torch.nn.functional as F

from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, Trainer, pick_device
from osn.model.volume import render

from benchutil import print_command


@torch.no_grad()
def alone_psnr(tr: Trainer, flat: torch.Tensor) -> float:
    st = tr.st
    frames, pix = flat // (st.H * st.W), flat % (st.H * st.W)
    lab = st.labels.reshape(-1)[flat]
    se, n = 0.0, 0
    one = torch.ones(st.K, device=tr.device)
    for k in range(st.K):
        m = lab == k
        if not m.any():
            continue
        out = render(st.object_rays(tr.fields, frames[m], one, [k]), st.dirs[pix[m]], tr.cfg.samples, None, tr.bg)
        se += float(F.mse_loss(out.rgb, st.images[frames[m], pix[m]], reduction="sum"))
        n += int(m.sum()) * 3
    return -10 * math.log10(max(se / n, 1e-12))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--config", default="configs/osn-cpu.yaml")
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--target", type=float, default=20.0)
    ap.add_argument("--eval-every", type=float, default=10.0, help="seconds of training between evaluations")
    args = ap.parse_args()
    print_command()
    base = TrainConfig.from_yaml(args.config)
    inputs = oracle_inputs(args.dataset)
    kinds = {
        "dense": base.field,
        # TensoRF at the same final resolution, the paper's 16 / 48 components.
        "tensorf": dataclasses.replace(base.field, kind="tensorf"),
    }
    summary = {}
    for name, fcfg in kinds.items():
        cfg = dataclasses.replace(base, field=fcfg, stage1_iters=10**6)
        tr = Trainer(inputs, cfg, pick_device(cfg.device))
        g = torch.Generator().manual_seed(0)
        labelled = torch.nonzero(tr.st.labels.reshape(-1) >= 0)[:, 0]
        flat = labelled[torch.randperm(len(labelled), generator=g)[:4096].to(tr.device)]
        trained, reached, it = 0.0, None, 0
        while trained < args.seconds:
            t = time.perf_counter()
            while time.perf_counter() - t < args.eval_every:
                tr.step()
                it += 1
            trained += time.perf_counter() - t
            p = alone_psnr(tr, flat)
            if reached is None and p >= args.target:
                reached = round(trained, 1)
            print(json.dumps({"field": name, "seconds": round(trained, 1), "iteration": it, "psnr": round(p, 2)}), flush=True)
        summary[name] = {"psnr_at_end": round(p, 2), "iterations": it, f"seconds_to_{args.target:g}dB": reached}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
