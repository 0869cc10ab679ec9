"""Profile first: does bf16 pay for the shipped prior's decoder and encoder on this CPU, and what does it
change?

The EM E-step decodes (proposal, scene point) queries in padded groups, `ShapePrior.sdf(x (B, Q, 3), latent)`;
the M-step encodes batches of `n_pcl`-point clouds. This bench times both on the shipped prior, fp32 against
`torch.autocast("cpu", dtype=torch.bfloat16)`, in one run with the same inputs (real encodings of held-out
procedural mugs, queries around their surfaces as an E-step sees them), and reports the SDF error bf16 makes:
the median and 99th percentile |Δ SDF| (canonical units) and the fraction of queries within the solver's bands
(|SDF| ≤ 0.15) whose inside/outside or in-band verdict flips. No solver change: this decides whether the
decoder's matrix work can move to bf16 (`EMConfig` knob).

Usage: python bench/decoder_bf16.py [--threads 2] [--repeats 5] [--profile]
Writes bench/results/decoder_bf16/latest.json. Run on a quiet machine; say the thread count with the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--proposals", type=int, default=30,
                    help="latents per decode batch (EMConfig.compute.encode_batch)")
    ap.add_argument("--queries", type=int, default=10000,
                    help="queries per decode call (EMConfig.compute.decode_chunk)")
    ap.add_argument("--profile", action="store_true", help="print the torch profiler's top ops for both paths")
    a = ap.parse_args()
    import torch

    from efem_viz.prior.data import PrepConfig, SampleConfig, input_cloud, load_or_prepare, procedural_sources
    from efem_viz.prior.model import load_prior

    torch.set_num_threads(a.threads)
    prior = load_prior("mug")
    prior.eval()
    cfg = SampleConfig(n_pcl=prior.config.n_pcl, min_views=1)
    rng = np.random.default_rng(0)
    srcs = procedural_sources("mug", "test", a.proposals)
    cache = ROOT / "runs" / "cache" / "bench_decoder_bf16"
    objs = [load_or_prepare(s, cache_dir=cache, cfg=PrepConfig(), seed=i) for i, s in enumerate(srcs)]
    clouds = torch.as_tensor(np.stack([input_cloud(o, cfg, rng) for o in objs]), dtype=torch.float32)
    with torch.no_grad():
        lat = prior.encode(clouds)
    # E-step-like queries: each proposal's own near-surface points (jittered), ragged by index
    per = a.queries // a.proposals
    q = np.concatenate([o.nss[rng.integers(0, len(o.nss), per), :3] for o in objs]).astype(np.float32)
    q += rng.normal(0, 0.01, q.shape).astype(np.float32)
    # world frame of each latent: x_world = Θ_s · x + Θ_c (the encoder saw canonical clouds); the solver decodes
    # rows padded into dense (B, Q, 3) groups (`em/decoding._decode_padded`), i.e. `sdf(x, latent)` batched
    idx = torch.as_tensor(np.repeat(np.arange(a.proposals), per), dtype=torch.int64)
    xq = (torch.as_tensor(q) * lat.scale[idx, None] + lat.center[idx]).reshape(a.proposals, per, 3)

    def timed(fn):  # noqa: ANN001, ANN202
        out = fn()  # warm-up
        ts = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            out = fn()
            ts.append(time.perf_counter() - t0)
        return out, statistics.median(ts)

    def dec32():  # noqa: ANN202
        with torch.no_grad():
            return prior.sdf(xq, lat)

    def dec16():  # noqa: ANN202
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            return prior.sdf(xq, lat).float()

    def enc32():  # noqa: ANN202
        with torch.no_grad():
            return prior.encode(clouds).scale

    def enc16():  # noqa: ANN202
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            return prior.encode(clouds).scale.float()

    d32, t_d32 = timed(dec32)
    d16, t_d16 = timed(dec16)
    s32, t_e32 = timed(enc32)
    s16, t_e16 = timed(enc16)
    err = (d16 - d32).abs().numpy()
    band = (d32.abs() <= 0.15).numpy()
    flips_sign = float(np.mean((np.sign(d16.numpy()) != np.sign(d32.numpy()))[band]))
    flips_band = {tau: float(np.mean(((d16.abs() <= tau) != (d32.abs() <= tau)).numpy()[band]))
                  for tau in (0.03, 0.07, 0.15)}
    res = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {a.threads} torch threads",
        "torch": torch.__version__, "proposals": a.proposals, "queries": int(len(idx)), "repeats": a.repeats,
        "decode_s": {"fp32": round(t_d32, 4), "bf16": round(t_d16, 4), "speedup": round(t_d32 / t_d16, 2)},
        "encode_s": {"fp32": round(t_e32, 4), "bf16": round(t_e16, 4), "speedup": round(t_e32 / t_e16, 2)},
        "sdf_abs_err": {"median": float(np.median(err)), "p99": float(np.quantile(err, 0.99)),
                        "max": float(err.max())},
        "in_band_sign_flips": flips_sign, "band_verdict_flips": flips_band,
        "scale_rel_err_max": float(((s16 - s32).abs() / s32).max()),
    }
    print(json.dumps(res, indent=1))
    if a.profile:
        from torch.profiler import ProfilerActivity, profile

        for name, fn in (("decode fp32", dec32), ("decode bf16", dec16)):
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                fn()
            print(f"--- {name}")
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=8))

    write_result(result_path("decoder_bf16"), res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
