"""Benchmark of the synthetic scan generator: time per 6-object TSDF scene, points per scene, point spacing.

Usage: python -m bench.generate [--seeds 3] [--objects 6] [--mode tsdf]
Writes bench/results/generate/latest.json and prints a table (medians over the seeds, per configuration).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

from bench.common import result_path, write_result  # first: the OpenMP wait policy, before torch
import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3, help="scenes per configuration (seeds 0..n-1)")
    ap.add_argument("--objects", type=int, default=6, help="mugs per scene")
    ap.add_argument("--mode", choices=["tsdf", "points"], default="tsdf")
    ap.add_argument("--out", type=Path, default=result_path("generate"))
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from efem_viz.geometry.knn import point_spacing

    from efem_viz.data.synth import generate_scene

    generate_scene("z", seed=999, n_objects=1, image_size=(64, 48))  # warm-up: imports, caches
    results: dict[str, dict[str, object]] = {}
    for config in ("z", "so3", "pile"):
        rows = []
        for seed in range(args.seeds):
            stages: dict[str, float] = {}
            t0 = time.perf_counter()
            scene = generate_scene(
                config,  # type: ignore[arg-type]
                seed=seed,
                n_objects=args.objects,
                mode=args.mode,
                timings=stages,
            )
            dt = time.perf_counter() - t0
            spacing = point_spacing(scene.points)
            rows.append(
                {
                    "seed": seed,
                    "seconds": round(dt, 3),
                    "points": scene.num_points,
                    "faces": int(len(scene.faces)) if scene.faces is not None else 0,
                    "labelled_fraction": round(float((scene.instance > 0).mean()), 4),
                    "median_nn_spacing_mm": round(float(np.median(spacing)) * 1e3, 3),
                    "max_penetration_mm": round(scene.provenance["max_penetration_m"] * 1e3, 3),
                    "drops": scene.provenance["drops"],
                    "stages_s": stages,
                }
            )
            print(f"{config:>5} seed {seed}: {dt:6.2f} s  {scene.num_points:6d} points  stages {stages}")
        results[config] = {
            "median_seconds": statistics.median(r["seconds"] for r in rows),
            "median_points": statistics.median(r["points"] for r in rows),
            "median_nn_spacing_mm": statistics.median(r["median_nn_spacing_mm"] for r in rows),
            "scenes": rows,
        }
    print()
    print(f"{'config':>6} | {'median s':>8} | {'points':>7} | {'spacing mm':>10}")
    for config, r in results.items():
        sec, pts, spc = r["median_seconds"], r["median_points"], r["median_nn_spacing_mm"]
        print(f"{config:>6} | {sec:8.2f} | {pts:7.0f} | {spc:10.2f}")
    payload = {
        "benchmark": "generate",
        "mode": args.mode,
        "objects": args.objects,
        "seeds": args.seeds,
        "voxel_m": 0.004,
        "image_size": [640, 480],
        "cameras": 4,
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "note": "wall-clock on a shared 2-core machine; other jobs were running",
        "results": results,
    }
    write_result(args.out, payload, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
