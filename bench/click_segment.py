"""Click-to-segment on the real tabletop sample scenes: mask IoU with the annotated ground truth and seconds per click.

For every labelled mug of `sample_scenes/real_tabletop_{0,6,8}.ply` two clicks are simulated: the mug's point
nearest its centroid, and one random point of it (seeded). Each goes through `annotator.efem_runs.segment_at_point`
with the shipped prior (what the annotator's segment tool calls, in the calling thread, one torch thread).
Prints one row per click and the medians; writes bench/results/click_segment/latest.json.

Usage: `python -m bench.click_segment [--prior mug] [--seed 0]`.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
SCENES = ("real_tabletop_0", "real_tabletop_6", "real_tabletop_8")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prior", default="mug", help="a prior shipped in efem_viz/weights/ (name)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random clicks")
    ap.add_argument("--out", type=Path, default=result_path("click_segment"))
    args = ap.parse_args()

    import torch

    from annotator.efem_runs import get_prior, segment_at_point
    from efem_viz.data.io import load_scene

    torch.set_num_threads(1)
    prior = get_prior(args.prior)
    rng = np.random.default_rng(args.seed)
    rows = []
    for name in SCENES:
        scene = load_scene(ROOT / "sample_scenes" / f"{name}.ply")
        assert scene.instance is not None
        for g in scene.instance_ids():
            gt = scene.instance == g
            members = np.flatnonzero(gt)
            centre = scene.points[members].mean(axis=0)
            central = int(members[np.argmin(np.linalg.norm(scene.points[members] - centre, axis=1))])
            for kind, vertex in (("central", central), ("random", int(rng.choice(members)))):
                t0 = time.perf_counter()
                idx = segment_at_point(scene, vertex, prior=prior)
                dt = time.perf_counter() - t0
                pred = np.zeros(scene.num_points, bool)
                pred[idx] = True
                iou = float((pred & gt).sum() / max(int((pred | gt).sum()), 1))
                rows.append({"scene": name, "instance": int(g), "click": kind, "vertex": vertex,
                             "mask_points": int(len(idx)), "iou": iou, "seconds": dt})
                print(f"{name} mug {g} {kind:>7}: IoU {iou:.2f}, {len(idx):5d} points, {dt:.1f} s", flush=True)
    ious = [r["iou"] for r in rows]
    out = {
        "machine": {"platform": platform.platform(), "torch_threads": 1, "torch": torch.__version__},
        "prior": args.prior,
        "clicks": rows,
        "median_iou": statistics.median(ious),
        "clicks_with_iou_ge_0_5": sum(i >= 0.5 for i in ious),
        "clicks_with_a_mask": sum(r["mask_points"] > 0 for r in rows),
        "median_seconds": statistics.median(r["seconds"] for r in rows),
    }
    print(f"{len(rows)} clicks: {out['clicks_with_a_mask']} with a mask, "
          f"{out['clicks_with_iou_ge_0_5']} at IoU >= 0.5; "
          f"median IoU {out['median_iou']:.2f}, median {out['median_seconds']:.1f} s per click")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_result(args.out, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
