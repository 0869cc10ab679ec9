"""The E-step decoder with and without its fused C++ pass, in float32 and bf16, on the decode calls of real solves.

One solve of each scene (`bench/speed.py`'s scenes, presets and priors, seed 0) records every E-step decode call
(latents, neighbourhoods, points, normals, band); the calls are then replayed through `decode_rows` in each mode,
alternating, `--repeats` times each: the eager tiles (``EFEM_VIZ_FUSED_DECODER=0``), the fused pass
(`efem_viz.prior.fused.decoder_band`), and, where the CPU has native bf16, both under the bf16 autocast of
`compute.matmul_dtype="bfloat16"` (the eager tiles' whole stream in bf16; the fused pass's products only).
Reported per scene and mode: the median seconds, the ratio to the eager float32 tiles, GFLOP/s achieved against this
machine's GEMM peak of the mode's precision (`bench.speed.gemm_peak`: every query's forward plus the band queries'
backward, the products only), and the differences from the eager float32 decodes: the largest SDF difference
(relative where |sdf| > 1: degenerate latents of tiny scale put queries at |q| ~ 1e6), the 99th percentile and the
largest normal angle difference (an angle moves where a unit sits at its ReLU kink), and the band entries that
differ.

Usage: python -m bench.decoder_kernel [--scenes real_tabletop_0 z_7000] [--repeats 3] [--threads 1]
       [--modes eager fused fused_bf16] [--tag NAME]
Writes bench/results/decoder_kernel/latest.json (decoder_kernel_<TAG>.json with --tag).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

# first: the OpenMP wait policy, before torch
from bench.common import kernels_or_say, machine, replay_parser, result_path, write_result


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


MODES: dict[str, tuple[bool, str]] = {"eager": (False, "float32"), "fused": (True, "float32"),
                                      "eager_bf16": (False, "bfloat16"), "fused_bf16": (True, "bfloat16")}
"""Replay modes: (fused pass on, `EMConfig.compute.matmul_dtype` of the E-steps' decode)."""


def replay(prior: Any, calls: list[tuple[Any, ...]], mode: str) -> tuple[float, list[Any], dict[str, float]]:
    """Seconds to decode every recorded call in a `MODES` mode, the results and the query counts."""
    import os

    from efem_viz.em.decoding import decode_rows, matmul_precision

    fused_on, dtype = MODES[mode]
    os.environ["EFEM_VIZ_FUSED_DECODER"] = "1" if fused_on else "0"
    try:
        stats: dict[str, float] = {}
        out = []
        t0 = time.perf_counter()
        with matmul_precision(dtype, prior):
            for lat, rag, pts, nrm, kw in calls:
                out.append(decode_rows(prior, lat, rag, pts, nrm, stats=stats, **kw))
        seconds = time.perf_counter() - t0
    finally:
        os.environ.pop("EFEM_VIZ_FUSED_DECODER", None)
    stats["decoder_queries"] = float(sum(len(c[1].idx) for c in calls))
    return seconds, out, stats


def differences(ref: list[Any], got: list[Any]) -> dict[str, float]:
    """How far one mode's decodes are from the reference's: the largest SDF difference (relative where
    |sdf| > 1), the largest and the 99th-percentile normal angle difference over entries in both bands, and the
    band entries that differ."""
    d_diff = max(float((np.abs(e[0] - f[0]) / np.maximum(1.0, np.abs(e[0]))).max(initial=0.0))
                 for e, f in zip(ref, got))
    angles = np.concatenate([np.abs(e[1] - f[1])[(e[1] < 180) & (f[1] < 180)] for e, f in zip(ref, got)])
    moved = sum(int(((e[1] < 180) != (f[1] < 180)).sum()) for e, f in zip(ref, got))
    return {"max_rel_sdf_diff": d_diff, "max_angle_diff_deg": float(angles.max(initial=0.0)),
            "p99_angle_diff_deg": float(np.percentile(angles, 99)) if len(angles) else 0.0,
            "band_entries_moved": moved}


def main() -> int:
    ap = replay_parser(__doc__)
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=None,
                    help="default: eager and fused, and their bf16 modes where the CPU has native bf16")
    a = ap.parse_args()
    if not kernels_or_say(a.threads):
        return 1
    import torch

    from efem_viz.prior import fused
    from efem_viz.prior.config import fast_cpu_bf16
    from bench.speed import decoder_flops, gemm_peak

    modes = a.modes or ["eager", "fused", *(["eager_bf16", "fused_bf16"] if fast_cpu_bf16() else [])]
    if "eager" not in modes:
        modes = ["eager", *modes]  # the reference of every difference and ratio
    rows: dict[str, Any] = {}
    peaks: dict[str, float] = {}
    for name in a.scenes:
        prior, calls = record_calls(name)
        if not peaks:
            dims = decoder_flops(prior)[2]
            peaks = {"float32": gemm_peak(dims), **({"bfloat16": gemm_peak(dims, "bfloat16")}
                                                    if any(MODES[m][1] == "bfloat16" for m in modes) else {})}
            print(f"GEMM peak ({a.threads} threads): " + ", ".join(f"{k} {v:.0f} GFLOP/s" for k, v in peaks.items()),
                  flush=True)
        times: dict[str, list[float]] = {m: [] for m in modes}
        results: dict[str, Any] = {}
        stats: dict[str, float] = {}
        with torch.no_grad():
            for _ in range(a.repeats):
                for m in modes:
                    sec, results[m], stats = replay(prior, calls, m)
                    times[m].append(sec)
        f_fwd, f_bwd, _ = decoder_flops(prior)
        flops = stats["decoder_queries"] * f_fwd + stats.get("normal_queries", 0.0) * f_bwd
        med = {m: statistics.median(times[m]) for m in modes}
        row: dict[str, Any] = {"calls": len(calls), "queries": stats["decoder_queries"],
                               "band_queries": stats.get("normal_queries", 0.0), "modes": {}}
        for m in modes:
            peak = peaks[MODES[m][1]]
            row["modes"][m] = {"seconds": med[m], "ratio_to_eager": med[m] / med["eager"],
                               "share_of_peak": flops / med[m] / 1e9 / peak, "floor_s": flops / 1e9 / peak,
                               "times": times[m], **(differences(results["eager"], results[m]) if m != "eager"
                                                     else {})}
        rows[name] = row
        print(f"{name:>16}: {len(calls)} E-step decodes, {row['queries'] / 1e6:.2f} M queries "
              f"({row['band_queries'] / 1e6:.2f} M in the band)", flush=True)
        for m, r in row["modes"].items():
            diff = ("" if m == "eager" else f"; against eager: max |Δsdf| / max(1, |sdf|) {r['max_rel_sdf_diff']:.1e}, "
                    f"Δangle p99 {r['p99_angle_diff_deg']:.2f}° max {r['max_angle_diff_deg']:.1f}°, "
                    f"band entries moved {r['band_entries_moved']}")
            print(f"{'':>18}{m:>11}: {r['seconds']:.2f} s, ratio {r['ratio_to_eager']:.2f}, "
                  f"{100 * r['share_of_peak']:.0f} % of its peak (floor {r['floor_s']:.2f} s){diff}", flush=True)
    write_result(result_path("decoder_kernel", a.tag),
                 {"machine": machine(a.threads) | {"gemm_peak_gflops": peaks}, "repeats": a.repeats,
                  "tile": {"float32": fused.DECODER_TILE, "bfloat16": fused.bf16_tile()}, "scenes": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
