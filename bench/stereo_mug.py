"""EFEM on the textured-stereo mug frame (PCL tutorial data): is the mug found, and is it the most confident fit?

The frame (`../shared/data/pcl_tutorial_mug/frame.npz`, a different sensor from the RealSense frames of
bench/real.py) holds one mug on a table. It is imported like every real frame (`import_rgbd_file`, 4 mm voxels,
seed 0); the mug is the largest connected cluster of points more than 1 cm above the table (1 cm linking
distance), which is how it was checked by eye in the viewer. Per configuration and seed: the best IoU of an
instance with the mug, that instance's confidence and rank, and the number of instances.

Usage: python -m bench.stereo_mug [--preset real] [--proposals 400] [--seeds 0] [--config "NAME=k=v;k=v" ...]
Writes bench/results/stereo_mug/stereo_mug_<tag>.json.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
FRAME = Path(os.environ.get("EFEM_STEREO_FRAME", ROOT.parent / "shared" / "data" / "pcl_tutorial_mug" / "frame.npz"))


def mug_mask(points: np.ndarray, *, above: float = 0.01, link: float = 0.01) -> np.ndarray:
    """The largest connected cluster (linking distance ``link``) of the points higher than ``above``."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(points[:, 2] > above)
    pairs = cKDTree(points[idx]).query_pairs(link, output_type="ndarray")
    from scipy.sparse import coo_matrix

    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    _, lab = connected_components(g, directed=False)
    big = np.bincount(lab).argmax()
    out = np.zeros(len(points), bool)
    out[idx[lab == big]] = True
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prior", default="mug")
    ap.add_argument("--preset", default="real")
    ap.add_argument("--proposals", type=int, default=400)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--config", action="append", default=[],
                    help="NAME=key=value;key=value (EMConfig overrides, as bench/em_stability.py)")
    ap.add_argument("--no-base", action="store_true", help="skip the unchanged preset")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default="latest")
    a = ap.parse_args()
    import torch

    from bench.em_stability import parse_config

    from efem_viz.data.rgbd import import_rgbd_file
    from efem_viz.em import preset, run_em
    from efem_viz.prior.model import load_prior

    torch.set_num_threads(a.threads)
    if not FRAME.is_file():
        raise SystemExit(f"no stereo frame at {FRAME} (set EFEM_STEREO_FRAME)")
    scene = import_rgbd_file(FRAME, name="pcl_tutorial_mug", voxel=0.004, seed=0)
    gt = mug_mask(scene.points)
    print(f"{scene.num_points} points, mug {int(gt.sum())} points", flush=True)
    prior = load_prior(a.prior)
    configs = ([] if a.no_base else [("base", {})]) + [parse_config(c) for c in a.config]
    rows = []
    for name, over in configs:
        cfg = preset(a.preset).with_proposals(a.proposals).with_values(over)
        for seed in a.seeds:
            t0 = time.perf_counter()
            res = run_em(scene, prior, cfg, seed=seed)
            conf = np.asarray(res.instances.confidence, np.float64)
            ious = [float((b & gt).sum() / max(1, (b | gt).sum())) for b in res.instances.bool_masks(scene.num_points)]
            best = int(np.argmax(ious)) if ious else -1
            rank = int((conf > conf[best]).sum()) + 1 if best >= 0 else None
            row = {"config": name, "overrides": over, "seed": seed, "instances": len(ious),
                   "best_iou": round(ious[best], 3) if best >= 0 else 0.0,
                   "confidence": round(float(conf[best]), 3) if best >= 0 else None, "rank": rank,
                   "top_confidence": round(float(conf.max()), 3) if len(conf) else None,
                   "seconds": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            print(f"{name:>14} seed {seed}: best IoU {row['best_iou']}, confidence {row['confidence']}, "
                  f"rank {rank} of {len(ious)} (top {row['top_confidence']}) [{row['seconds']} s]", flush=True)

    out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {a.threads} torch threads", "prior": a.prior,
           "preset": a.preset, "proposals": a.proposals, "mug_points": int(gt.sum()), "rows": rows}
    write_result(result_path("stereo_mug", a.tag), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
