"""The E-step decoder with and without its fused C++ pass, on the decode calls of real solves.

One solve of each scene (`bench/speed.py`'s scenes, presets and priors, seed 0) records every E-step decode call
(latents, neighbourhoods, points, normals, band); the calls are then replayed through `decode_rows` with the fused
pass (`efem_viz.prior.fused.decoder_band`) and with the eager tiles it replaces (``EFEM_VIZ_FUSED_DECODER=0``),
alternating, `--repeats` times each. Reported per scene: the median seconds of both, their ratio, GFLOP/s achieved
against this machine's GEMM peak (`bench.speed.gemm_peak`: every query's forward plus the band queries' backward,
the products only), and the largest difference of the SDF (relative where |sdf| > 1: degenerate latents of tiny
scale put queries at |q| ~ 1e6) and of the normal angles between the two (float32 rounding: the same math summed
in another order; an angle moves where a unit sits at its ReLU kink), with the band entries that differ.

Usage: python -m bench.decoder_kernel [--scenes real_tabletop_0 z_7000] [--repeats 3] [--threads 1] [--tag NAME]
Writes bench/results/decoder_kernel/latest.json (decoder_kernel_<TAG>.json with --tag).
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np

from bench.common import machine, result_path, write_result  # first: the OpenMP wait policy, before torch


def record_calls(name: str) -> tuple[Any, list[tuple[Any, ...]]]:
    """One solve of the scene; its prior and every E-step decode call's arguments."""
    from efem_viz.em import decoding
    from efem_viz.em.config import preset
    from efem_viz.em.solver import run_em
    from efem_viz.prior.model import load_prior
    from bench.speed import load

    scene, pname, prior_name = load(name)
    prior = load_prior(prior_name)
    calls: list[tuple[Any, ...]] = []
    plain = decoding.decode_rows

    def recording(pr: Any, latent: Any, rag: Any, pts: np.ndarray, nrm: np.ndarray, **kw: Any) -> Any:
        band = kw.get("normals_within")
        if isinstance(latent, dict) and band is not None and band > 0:  # the E-steps (reviews decode grids)
            kept = {k: v for k, v in kw.items() if k != "stats"}
            calls.append(({k: np.array(v) for k, v in latent.items()}, rag, pts, nrm, kept))
        return plain(pr, latent, rag, pts, nrm, **kw)

    decoding.decode_rows = recording
    try:
        run_em(scene, prior, preset(pname), seed=0)
    finally:
        decoding.decode_rows = plain
    return prior, calls


def replay(prior: Any, calls: list[tuple[Any, ...]], fused_on: bool) -> tuple[float, list[Any], dict[str, float]]:
    """Seconds to decode every recorded call (fused pass on or off), the results and the query counts."""
    import os

    from efem_viz.em.decoding import decode_rows

    os.environ["EFEM_VIZ_FUSED_DECODER"] = "1" if fused_on else "0"
    try:
        stats: dict[str, float] = {}
        out = []
        t0 = time.perf_counter()
        for lat, rag, pts, nrm, kw in calls:
            out.append(decode_rows(prior, lat, rag, pts, nrm, stats=stats, **kw))
        seconds = time.perf_counter() - t0
    finally:
        os.environ.pop("EFEM_VIZ_FUSED_DECODER", None)
    stats["decoder_queries"] = float(sum(len(c[1].idx) for c in calls))
    return seconds, out, stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["real_tabletop_0", "z_7000"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default=None)
    a = ap.parse_args()

    import torch

    from efem_viz.prior import fused
    from bench.speed import decoder_flops, gemm_peak

    torch.set_num_threads(a.threads)
    if not fused.load():
        print("the fused kernels are unavailable on this machine: nothing to compare")
        return 1
    rows: dict[str, Any] = {}
    peak = None
    for name in a.scenes:
        prior, calls = record_calls(name)
        if peak is None:
            peak = gemm_peak(decoder_flops(prior)[2])
            print(f"GEMM peak (1,024 x 128 times 128 x 128, {a.threads} threads): float32 {peak:.0f} GFLOP/s",
                  flush=True)
        times: dict[bool, list[float]] = {False: [], True: []}
        results: dict[bool, Any] = {}
        stats: dict[str, float] = {}
        with torch.no_grad():
            for _ in range(a.repeats):
                for on in (False, True):
                    sec, results[on], stats = replay(prior, calls, on)
                    times[on].append(sec)
        f_fwd, f_bwd, _ = decoder_flops(prior)
        flops = stats["decoder_queries"] * f_fwd + stats.get("normal_queries", 0.0) * f_bwd
        d_diff = max(float((np.abs(e[0] - f[0]) / np.maximum(1.0, np.abs(e[0]))).max(initial=0.0))
                     for e, f in zip(results[False], results[True]))
        both = [(e[1] < 180) & (f[1] < 180) for e, f in zip(results[False], results[True])]
        g_diff = max(float(np.abs(e[1] - f[1])[b].max(initial=0.0))
                     for e, f, b in zip(results[False], results[True], both))
        band_moved = sum(int(((e[1] < 180) != (f[1] < 180)).sum()) for e, f in zip(results[False], results[True]))
        eager, fast = statistics.median(times[False]), statistics.median(times[True])
        assert peak is not None
        row = {"calls": len(calls), "queries": stats["decoder_queries"],
               "band_queries": stats.get("normal_queries", 0.0),
               "eager_s": eager, "fused_s": fast, "ratio": fast / eager,
               "eager_share_of_peak": flops / eager / 1e9 / peak, "fused_share_of_peak": flops / fast / 1e9 / peak,
               "floor_s": flops / 1e9 / peak, "max_rel_sdf_diff": d_diff, "max_angle_diff_deg": g_diff,
               "band_entries_moved": band_moved, "times": {"eager": times[False], "fused": times[True]}}
        rows[name] = row
        print(f"{name:>16}: {len(calls)} E-step decodes, {row['queries'] / 1e6:.2f} M queries "
              f"({row['band_queries'] / 1e6:.2f} M in the band): eager {eager:.2f} s "
              f"({100 * row['eager_share_of_peak']:.0f} % of peak), fused {fast:.2f} s "
              f"({100 * row['fused_share_of_peak']:.0f} %), ratio {row['ratio']:.2f}; floor {row['floor_s']:.2f} s; "
              f"max |Δsdf| / max(1, |sdf|) {d_diff:.1e}, max |Δangle| {g_diff:.1e}°, "
              f"band entries moved {band_moved}", flush=True)
    write_result(result_path("decoder_kernel", a.tag),
                 {"machine": machine(a.threads) | {"gemm_peak_gflops": peak}, "repeats": a.repeats,
                  "tile": fused.DECODER_TILE, "scenes": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
