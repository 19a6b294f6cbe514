"""Soft Z-buffer vs H separate composite renders for scale-label generation, side by side.

For one ray batch of a dataset's training frames and H sampled scale vectors, labels are made
two ways from the same fields:

* soft Z-buffer (paper Eq. 16-18): every object's depth rendered once per ray, then the H
  segmentations from the scaled depth order;
* composite: H scaled composite renders, segmentation = argmax of each object's weight share.

Both label a sample valid when its error rate on the batch is within ``--tolerance`` of the
batch's best (the noise floor, as in training). Prints the time of each, the speed-up, and how
often the two agree (per sample label and per ray segmentation).

    .venv/bin/python benchmarks/bench_softz.py RUN [--rays 1024] [--H 64 256]

RUN is an ``osn train`` run directory: its checkpoint's fields give realistic depths.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from osn.preprocess.inputs import load_inputs
from osn.model.scale_net import full_sbar
from osn.model.softz import implied_segmentation, sample_accuracy, validity_labels
from osn.train import TrainConfig, Trainer, pick_device
from osn.model.volume import render

from benchutil import print_command


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="osn train run directory (config.yaml, inputs/, checkpoint.pt)")
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--H", type=int, nargs="+", default=[64, 256])
    ap.add_argument("--tolerance", type=float, default=2e-3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print_command()

    run = Path(args.run)
    cfg = TrainConfig.from_yaml(run / "config.yaml")
    dev = pick_device(cfg.device)
    tr = Trainer(load_inputs(run / "inputs"), cfg, dev)
    tr.load_state_dict(torch.load(run / "checkpoint.pt", map_location=dev, weights_only=False))
    print(f"fields of {run} at iteration {tr.iteration}; {cfg.samples} samples per object and ray")
    st = tr.st
    g = torch.Generator().manual_seed(args.seed)
    labelled = torch.nonzero(st.labels.reshape(-1) >= 0)[:, 0]
    flat = labelled[torch.randperm(len(labelled), generator=g)[: args.rays].to(dev)]
    frames, pix = flat // (st.H * st.W), flat % (st.H * st.W)
    gt = st.labels.reshape(-1)[flat]
    results = []
    for H in args.H:
        s = torch.rand(H, st.K - 1, generator=g, dtype=torch.float64).to(dev)
        sbar = full_sbar(s, st.ranges, st.anchor)
        with torch.no_grad():
            t = time.perf_counter()
            depth = torch.zeros(len(flat), st.K, device=dev)
            covered = torch.zeros(len(flat), st.K, dtype=torch.bool, device=dev)
            one = torch.ones(st.K, device=dev)
            for k in range(st.K):
                out = render(st.object_rays(tr.fields, frames, one, [k]), st.dirs[pix], cfg.samples, None, None, cfg.skip_occluded)
                depth[:, k] = out.normalised_depth()
                covered[:, k] = out.acc > cfg.coverage_threshold
            seg_z = implied_segmentation(depth, covered, sbar)
            t_softz = time.perf_counter() - t

            t = time.perf_counter()
            seg_c = torch.stack(
                [render(st.object_rays(tr.fields, frames, sbar[h]), st.dirs[pix], cfg.samples, None, None, cfg.skip_occluded).log_seg.argmax(1) for h in range(H)]
            )
            t_comp = time.perf_counter() - t
        labels = []
        for seg in (seg_z, seg_c):
            err = 1.0 - sample_accuracy(seg, gt)
            labels.append(validity_labels(1.0 - err, args.tolerance, topk=0, noise_floor=float(err.min()))[0])
        rec = {
            "H": H,
            "rays": len(flat),
            "softz_s": round(t_softz, 4),
            "composite_s": round(t_comp, 3),
            "speedup": round(t_comp / t_softz, 1),
            "label_agreement": float((labels[0] == labels[1]).float().mean()),
            "segmentation_agreement": float((seg_z == seg_c).float().mean()),
            "valid_softz": int(labels[0].sum()),
            "valid_composite": int(labels[1].sum()),
        }
        results.append(rec)
        print(json.dumps(rec))


if __name__ == "__main__":
    main()
