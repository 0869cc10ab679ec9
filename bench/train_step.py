"""What a training step of each shipped prior costs with the fused training kernels and with the eager graph.

The kernels (`efem_viz.prior.fused`: the encoder's edge mean, every edge's activation in the chair design's
attention, and the VN activation, each with a fused backward) are on unless `EFEM_VIZ_FUSED_TRAINING=0`. Each
prior trains `--iterations` steps from its shipped weights with its own recipe (the preset and input settings of
its training notes; bf16 matrix work where the CPU has it natively, else float32) on the same batches (same seed)
once per variant; the bench records seconds per step (median after `--warmup` steps), the ratio, and the training
SDF loss of every step (the two curves differ by rounding only).

Usage: python -m bench.train_step [--threads 1] [--iterations 40] [--priors kitchen chair mug] [--tag T]
Writes bench/results/train_step/<tag or latest>.json. Say the thread count and what else ran.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import tempfile
from pathlib import Path

import numpy as np

from bench.common import ROOT, result_path  # first: the OpenMP wait policy, before torch

RECIPES = {  # the training notes' settings: preset, and what the inputs look like
    "mug": {"preset": "cpu"},
    "kitchen": {"preset": "cpu", "neighbour_p": 0.5, "top_only_p": 0.25, "table_side_p": 0.5},
    "chair": {"preset": "cpu-chair", "neighbour_p": 0.5, "top_only_p": 0.25, "table_side_p": 0.5},
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5, help="steps left out of the timing median")
    ap.add_argument("--priors", nargs="+", default=["kitchen", "chair"], choices=sorted(RECIPES))
    ap.add_argument("--n-train", type=int, default=400)
    ap.add_argument("--tag", default=None)
    a = ap.parse_args()
    if a.iterations <= a.warmup:
        ap.error("--iterations must exceed --warmup")
    logging.basicConfig(level=logging.WARNING)
    from bench.common import machine, write_result
    from efem_viz.prior import fused
    from efem_viz.prior.config import fast_cpu_bf16
    from efem_viz.prior.train import TrainArgs, train

    dtype = "bfloat16" if fast_cpu_bf16() else "float32"
    out = result_path("train_step", a.tag)
    rows = []
    for name in a.priors:
        recipe = dict(RECIPES[name])
        by_variant = {}
        for variant in ("kernels", "eager"):
            os.environ["EFEM_VIZ_FUSED_TRAINING"] = "1" if variant == "kernels" else "0"
            with tempfile.TemporaryDirectory() as tmp:
                args = TrainArgs(category=name, n_train=a.n_train, n_val=8, out_dir=Path(tmp) / "run",
                                 export=Path(tmp) / f"{name}.pt", cache_dir=ROOT / "runs" / "cache", batch_size=16,
                                 iterations=10**6, val_every=10**6, threads=a.threads, progress=False, log_every=1,
                                 lr=1e-6, init_from=ROOT / "efem_viz" / "weights" / f"{name}.pt", init_matching=True,
                                 matmul_dtype=dtype, min_views=1, sensor_p=0.75, fixed_point_p=0.25, seed=4242,
                                 **recipe)
                res = train(args, max_iterations=a.iterations)
            secs = [c["sec"] for c in res["curve"]][a.warmup:]
            by_variant[variant] = {"sec_per_step_median": statistics.median(secs),
                                   "sdf_curve": [c["sdf"] for c in res["curve"]]}
        os.environ.pop("EFEM_VIZ_FUSED_TRAINING", None)
        k, e = by_variant["kernels"], by_variant["eager"]
        row = {"prior": name, "dtype": dtype, **recipe, "kernels": k, "eager": e,
               "speedup": e["sec_per_step_median"] / k["sec_per_step_median"],
               "sdf_mean_abs_diff": float(np.mean(np.abs(np.subtract(k["sdf_curve"], e["sdf_curve"])))),
               "sdf_mean": float(np.mean(e["sdf_curve"]))}
        rows.append(row)
        print(f"{name:>8} ({dtype}): {k['sec_per_step_median']:.3f} s/step with the kernels, "
              f"{e['sec_per_step_median']:.3f} eager: {row['speedup']:.2f}x; train SDF loss mean "
              f"{row['sdf_mean']:.4f}, mean |difference| {row['sdf_mean_abs_diff']:.5f}", flush=True)
        write_result(out, {"machine": machine(a.threads) | {"fast_cpu_bf16": fast_cpu_bf16(),
                                                            "kernels_built": bool(fused.load())},
                           "iterations": a.iterations, "warmup": a.warmup, "rows": rows}, archive=False)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
