"""what bf16 (AMX autocast) buys a training step, and what it changes in the loss curve.

Every candidate starts from the same prior (the shipped `mug.pt`, grown function-preservingly to the candidate's
decoder with `prior.widen`), trains `--iterations` steps on the same batches (same seed, same data recipe as the
shipped run: sensor inputs, fixed-point examples) and records seconds per iteration (median after a warm-up) and
the training SDF loss of every step. Candidates: decoder width x blocks, fp32 or bf16.

On a CPU without AMX or AVX-512 BF16 (`efem_viz.prior.config.fast_cpu_bf16()` False, recorded in the JSON) the
bf16 rows are 5-12x *slower* than float32: run them only where the hardware has bf16 matrix units.

Usage: python -m bench.train_precision [--threads 1] [--iterations 40] [--candidates 128x2:float32 ...]
Writes bench/results/train_precision/latest.json (after every candidate). Say the thread count and what else ran.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
from pathlib import Path

import numpy as np

from bench.common import ROOT, result_path  # first: the OpenMP wait policy, before torch

DEFAULT = ("128x2:float32", "128x2:bfloat16", "256x4:float32", "256x4:bfloat16", "256x5:bfloat16",
           "384x5:bfloat16")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5, help="iterations left out of the timing median")
    ap.add_argument("--prior", default=str(ROOT / "efem_viz" / "weights" / "mug.pt"))
    ap.add_argument("--n-train", type=int, default=400)
    ap.add_argument("--candidates", nargs="+", default=list(DEFAULT), help="WIDTHxBLOCKS:DTYPE")
    ap.add_argument("--out", type=Path, default=result_path("train_precision"))
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from bench.common import machine, write_result
    from efem_viz.prior.config import fast_cpu_bf16
    from efem_viz.prior.train import TrainArgs, train

    rows = []
    for cand in a.candidates:
        size, dtype = cand.split(":")
        hidden, blocks = (int(v) for v in size.split("x"))
        with tempfile.TemporaryDirectory() as tmp:
            args = TrainArgs(category="mug", n_train=a.n_train, n_val=8, out_dir=Path(tmp) / "run",
                             export=Path(tmp) / "mug.pt", cache_dir=ROOT / "runs" / "cache", batch_size=16,
                             iterations=10**6, val_every=10**6, threads=a.threads, progress=False, log_every=1,
                             lr=3e-5, init_from=Path(a.prior), grow_decoder_hidden=hidden,
                             grow_decoder_blocks=blocks, matmul_dtype=dtype, min_views=1, sensor_p=0.75,
                             fixed_point_p=0.25, seed=4242)
            res = train(args, max_iterations=a.iterations)
        secs = [c["sec"] for c in res["curve"]][a.warmup:]
        sdf = [c["sdf"] for c in res["curve"]]
        row = {"candidate": cand, "hidden": hidden, "blocks": blocks, "dtype": dtype,
               "sec_per_iter_median": statistics.median(secs), "sdf_first10": float(np.mean(sdf[:10])),
               "sdf_last10": float(np.mean(sdf[-10:])), "sdf_curve": sdf}
        rows.append(row)
        print(f"{cand:>16}: {row['sec_per_iter_median']:.3f} s/iter; train SDF loss first 10 "
              f"{row['sdf_first10']:.4f}, last 10 {row['sdf_last10']:.4f}", flush=True)
        # after every candidate: a run stopped part-way keeps the rows it has
        write_result(a.out, {"machine": machine(a.threads) | {"fast_cpu_bf16": fast_cpu_bf16()},
                           "iterations": a.iterations, "rows": rows}, archive=len(rows) == 1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
