"""is the mug prior capacity-bound, and where on a mug does its error sit?

For each prior given (default: the shipped `mug.pt`) and for training objects and held-out objects alike (the first
`--n` of each procedural split, the same data recipe as training), with clean multi-view inputs and with the
depth-sensor model's single-view inputs:

* volumetric IoU (iso-offset calibrated, as `train.validate` reports it) and SDF L1 on uniform queries;
* the near-surface SDF error split by region of the mug, in its canonical frame (+Z up, handle toward +X): the
  **bottom** (lowest 8 % of its height), the **rim** (highest 8 %), the **handle** (farther than 1.5 % of the size
  outside the body's radius) and the **walls** (the rest); for each, the mean |SDF error| and the fraction of
  queries on the wrong side of the surface.

A prior whose training error equals its held-out error is not overfitting: more capacity or more optimisation, not
more data or regularisation, is what it lacks.

Usage: python -m bench.prior_diagnosis [--prior efem_viz/weights/mug.pt runs/cap_256x4/mug.pt ...] [--n 48]
       [--threads 1] [--tag NAME]
Writes bench/results/prior_diagnosis/latest.json (prior_diagnosis_<TAG>.json with --tag).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch

REGIONS = ("walls", "bottom", "rim", "handle")


def regions_of(obj: Any, xyz: np.ndarray) -> np.ndarray:
    """(Q,) int index into `REGIONS` of canonical query points of one normalised mug."""
    s = obj.surface
    zb, zt = float(s[:, 2].min()), float(s[:, 2].max())
    y0, y1 = float(s[:, 1].min()), float(s[:, 1].max())
    r_body = (y1 - y0) / 2.0  # the handle lies in the x-z plane: the y extent is the body's diameter
    cx, cy = float(s[:, 0].min()) + r_body, (y0 + y1) / 2.0
    rho = np.hypot(xyz[:, 0] - cx, xyz[:, 1] - cy)
    h = zt - zb
    out = np.zeros(len(xyz), np.int64)
    out[xyz[:, 2] < zb + 0.08 * h] = 1
    out[xyz[:, 2] > zt - 0.08 * h] = 2
    out[(rho > r_body + 0.015) & (xyz[:, 0] > cx)] = 3
    return out


def region_errors(prior: Any, objs: list[Any], clouds: np.ndarray) -> dict[str, dict[str, float]]:
    """Mean |SDF error| and wrong-side fraction of the near-surface queries, per region."""
    import torch

    err: dict[int, list[np.ndarray]] = {i: [] for i in range(len(REGIONS))}
    flip: dict[int, list[np.ndarray]] = {i: [] for i in range(len(REGIONS))}
    with torch.no_grad():
        for s in range(0, len(objs), 8):
            part = objs[s:s + 8]
            lat = prior.encode(torch.as_tensor(clouds[s:s + 8], dtype=torch.float32))
            q = np.stack([o.nss[:8000] for o in part])
            pred = prior.sdf(torch.as_tensor(q[..., :3]), lat).numpy()
            for b, o in enumerate(part):
                reg = regions_of(o, q[b, :, :3])
                e = np.abs(pred[b] - q[b, :, 3])
                wrong = (pred[b] < 0) != (q[b, :, 3] < 0)
                for i in range(len(REGIONS)):
                    err[i].append(e[reg == i])
                    flip[i].append(wrong[reg == i])
    out = {}
    for i, name in enumerate(REGIONS):
        e, f = np.concatenate(err[i]), np.concatenate(flip[i])
        out[name] = {"sdf_l1": float(e.mean()) if len(e) else float("nan"),
                     "wrong_side": float(f.mean()) if len(f) else float("nan"), "queries": int(len(e))}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prior", nargs="+", default=[str(ROOT / "efem_viz" / "weights" / "mug.pt")])
    ap.add_argument("--n", type=int, default=48, help="objects of each split")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default="")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(a.threads)
    from bench.common import machine

    from efem_viz.prior.data import input_cloud, sensor_cloud
    from efem_viz.prior.model import load_prior
    from efem_viz.prior.train import TrainArgs, load_objects, validate

    targs = TrainArgs(category="mug", n_train=a.n, n_val=a.n, cache_dir=ROOT / "runs" / "cache", min_views=1,
                      sensor_p=0.75)
    splits = {"train": load_objects(targs, "train"), "held-out": load_objects(targs, "val")}
    rows = []
    for path in a.prior:
        prior = load_prior(path, load_codebook=False).eval()
        scfg = targs.sample_config(prior.config.n_pcl)
        for split, objs in splits.items():
            for inputs in ("clean", "sensor"):
                m = validate(prior, objs, scfg, seed=targs.seed + 99, sensor=inputs == "sensor")
                rng = np.random.default_rng(targs.seed + 99)
                make = sensor_cloud if inputs == "sensor" else input_cloud
                clouds = np.stack([make(o, scfg, rng) for o in objs])
                reg = region_errors(prior, objs, clouds)
                row = {"prior": path, "decoder": f"{prior.config.decoder_hidden}x{prior.config.decoder_blocks}",
                       "split": split, "inputs": inputs, "iou_cal": m["iou_cal"], "sdf_l1": m["sdf_l1"],
                       "regions": reg}
                rows.append(row)
                print(f"{Path(path).parent.name}/{Path(path).name} {row['decoder']} {split:>8} {inputs:>6}: IoU "
                      f"{m['iou_cal']:.3f}, SDF L1 {m['sdf_l1']:.4f}; near-surface |err| / wrong side: "
                      + ", ".join(f"{k} {v['sdf_l1']:.4f} / {v['wrong_side']:.3f}" for k, v in reg.items()),
                      flush=True)
    write_result(result_path("prior_diagnosis", a.tag), {"machine": machine(a.threads), "n": a.n, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
