"""EFEM in seconds: per-phase seconds of one solve, before and after the speed work, same answers.

For each scene (default: the bundled real frames `real_tabletop_{0,6,8}` with the `real` preset, 120 proposals
spread over the frame above its table, and the fixed synthetic scene `z_7000` of bench/em.py with the `synthetic`
preset, 400 proposals; `chair_z_7000` is its chair scene with the chair prior and the `chairs` preset) and each
variant, runs the solver `--repeats` times and reports the median seconds per phase (the solver's own
`EMResult.timings`), the total, and what the answers are:

* `AP50` against the scene's ground truth (where it has one),
* `mask IoU to baseline`: for each instance of the baseline run of the same seed (confidence >= `--cut`), the
  best mask IoU among the variant's instances above the same cut, averaged: 1.0 = the same masks.

Variants:
* `baseline`: the landed main's code paths: eager VN encoder (`EFEM_VIZ_FUSED=0`), pose search on every
  sample (`review.pose_points=None`);
* `two_pass`: fused VN kernels, pose search on 1000 samples, the E-step's SDF and band normals in two decoder
  passes (an SDF pass, then autograd on the band: `EFEM_VIZ_ONE_PASS=0`);
* `fast`: as `two_pass`, with one decoder pass and a hand-made backward on the band (`EFEM_VIZ_ONE_PASS=1`,
  the default: see `efem_viz.em.decoding.one_pass_enabled`);
* `bf16`: as `fast`, the EM steps' encoder and decoder under bf16 autocast (`compute.matmul_dtype="bfloat16"`);
* `bf16_decoder`: as `fast`, the decoder alone in bf16 (`compute.encoder_dtype="float32"`);
* `random400`: as `fast`, with 400 proposals drawn uniformly (the `real` preset's anchors before they were spread).

The decode phase is also set against its floor on the machine it runs on: the decoder's FLOPs (every query's
forward, the band queries' input-gradient backward) at this machine's measured GEMM peak for the decoder's tile
(float32, and bfloat16 where the CPU has native bf16), printed and written as `decode_vs_floor`.

`--busy N` runs N one-thread busy loops beside the solves (a solve must slow down by about its
fair share). `--profile` prints the top functions of one run per variant.

Usage: python -m bench.speed [--threads 2] [--repeats 3] [--scenes real_tabletop_0 z_7000] [--busy 1]
       [--variants baseline fast] [--tag NAME]
Writes bench/results/speed/latest.json (speed_<TAG>.json with --tag). Say the threads, and what else ran, with
every number.
"""

from __future__ import annotations

import argparse
import cProfile
import multiprocessing as mp
import os
import pstats
import statistics
import time
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch

VARIANTS: dict[str, tuple[dict[str, str], dict[str, Any]]] = {
    "baseline": ({"EFEM_VIZ_FUSED": "0", "EFEM_VIZ_ONE_PASS": "0"}, {"review.pose_points": None}),
    "two_pass": ({"EFEM_VIZ_FUSED": "1", "EFEM_VIZ_ONE_PASS": "0"}, {}),
    "fast": ({"EFEM_VIZ_FUSED": "1", "EFEM_VIZ_ONE_PASS": "1"}, {}),
    "bf16": ({"EFEM_VIZ_FUSED": "1", "EFEM_VIZ_ONE_PASS": "1"}, {"compute.matmul_dtype": "bfloat16"}),
    "bf16_decoder": ({"EFEM_VIZ_FUSED": "1", "EFEM_VIZ_ONE_PASS": "1"},
                     {"compute.matmul_dtype": "bfloat16", "compute.encoder_dtype": "float32"}),
    "random400": ({"EFEM_VIZ_FUSED": "1", "EFEM_VIZ_ONE_PASS": "1"}, {"proposals.anchors": "random",
                                                                           "proposals.n_init": (400,)}),
}
"""name -> (environment, solver settings by dotted name)."""


def _busy() -> None:
    x = 0
    while True:
        x += 1


def load(name: str) -> tuple[Any, str, str]:
    """A scene by name (a bundled sample, a bench/em.py fixed-set scene `<config>_<seed>`, or one of its chair or
    kitchen scenes `chair_<config>_<seed>`, `kitchen_<config>_<seed>`), its preset and its prior."""
    from efem_viz.data.io import load_scene

    p = ROOT / "sample_scenes" / f"{name}.ply"
    if p.is_file():
        return load_scene(p), "real" if name.startswith("real_") else "synthetic", "mug"
    from bench.em import get_scene

    if name.startswith("chair_"):
        config, seed = name.removeprefix("chair_").rsplit("_", 1)
        return get_scene(config, int(seed), "tsdf", targets="chair"), "chairs", "chair"
    if name.startswith("kitchen_"):  # merged points like the mug scenes (about 60k), for a like-for-like cost
        config, seed = name.removeprefix("kitchen_").rsplit("_", 1)
        return get_scene(config, int(seed), "points", targets="kitchen"), "synthetic", "kitchen"
    config, seed = name.rsplit("_", 1)
    return get_scene(config, int(seed), "points"), "synthetic", "mug"


def gemm_peak(width: int, dtype: str = "float32", rows: int = 1024) -> float:
    """GFLOP/s of the decoder's hidden product on this machine at the set torch threads: (rows x width) times
    (width x width) plus bias, the decoder's tile shape (`efem_viz.prior.decoder.TILE_ROWS`); the best of three
    timings of 200 products (a measured ceiling, not the data sheet's). With T threads the ceiling is T times the
    one-thread tile's: the decoder runs one tile per thread, while torch splits a single product of this size
    across threads at a loss (0.3-0.4x of one thread on 2 threads), which would put the ceiling under what the
    decoder reaches."""
    import torch

    threads = torch.get_num_threads()
    dt = getattr(torch, dtype)
    x = torch.randn(rows, width).to(dt)
    w = torch.randn(width, width).to(dt)
    b = torch.randn(width).to(dt)
    best = float("inf")
    torch.set_num_threads(1)
    try:
        for _ in range(3):
            torch.nn.functional.linear(x, w, b)
            t0 = time.perf_counter()
            for _ in range(200):
                torch.nn.functional.linear(x, w, b)
            best = min(best, (time.perf_counter() - t0) / 200)
    finally:
        torch.set_num_threads(threads)
    return threads * 2.0 * rows * width * width / best / 1e9


def decoder_flops(prior: Any) -> tuple[float, float, int]:
    """(FLOPs of one SDF query's forward, FLOPs of one band query's input-gradient backward, hidden width) of a
    prior's decoder: the first layer, the residual blocks' products and the output (the products dominate; the
    element-wise work is not counted, so the floor below is a floor)."""
    dec = prior.decoder
    h = int(dec.fc_in.out_features)
    blocks = 2 * int(dec.n_blocks) * 2 * h * h  # two products per block, 2 FLOPs per multiply-add
    return float(2 * 5 * h + blocks + 2 * h), float(blocks + 2 * h + 2 * 4 * h), h


def decode_row(phases: dict[str, float], prior: Any, peaks: dict[str, float], dtype: str) -> dict[str, float]:
    """The decode phase against its floor: GFLOP/s achieved (forward of every query, backward of the band
    queries), the share of the machine's measured GEMM peak for the run's precision, and the seconds the same
    products would take at that peak."""
    f_fwd, f_bwd, _ = decoder_flops(prior)
    flops = phases.get("decoder_queries", 0.0) * f_fwd + phases.get("normal_queries", 0.0) * f_bwd
    peak = peaks.get(dtype, peaks["float32"])
    seconds = max(phases.get("decode", 0.0), 1e-9)
    return {"decode_gflop": flops / 1e9, "decode_gflops": flops / seconds / 1e9, "peak_gflops": peak,
            "share_of_peak": flops / seconds / 1e9 / peak, "decode_floor_s": flops / 1e9 / peak}


def masks_of(res: Any, cut: float) -> list[np.ndarray]:
    """The masks of the instances a confidence cut keeps (`Instances.above`, the one thresholding rule)."""
    return [np.asarray(m) for m in res.instances.above(cut).masks]


def mask_iou_to(base: list[np.ndarray], other: list[np.ndarray]) -> float:
    """Mean over the baseline's masks of the best IoU with any of the other run's masks (1.0 when both empty)."""
    if not base:
        return 1.0 if not other else 0.0
    sets = [set(m.tolist()) for m in other]
    out = []
    for m in base:
        s = set(m.tolist())
        out.append(max((len(s & o) / max(1, len(s | o)) for o in sets), default=0.0))
    return float(np.mean(out))


def ap50(scene: Any, res: Any) -> float | None:
    if scene.instance is None or not len(scene.instance_ids()):
        return None
    from efem_viz.eval.ap import evaluate_instances

    classes = tuple(sorted({str(c) for c in dict(scene.categories).values()})) or ("mug",)
    return float(evaluate_instances(res.instances, scene, class_names=classes).ap50) * 100.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proposals", type=int, default=None, help="proposals per scene (default: the preset's)")
    ap.add_argument("--scenes", nargs="+", default=["real_tabletop_0", "real_tabletop_6", "real_tabletop_8",
                                                    "z_7000"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--busy", type=int, default=0, help="one-thread busy loops running beside the solves")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--cut", type=float, default=0.1, help="confidence cut of the masks compared to the baseline")
    ap.add_argument("--tag", default="")
    a = ap.parse_args()
    from efem_viz.cpu import configure_openmp

    configure_openmp()  # the CLIs' OpenMP wait policy, before torch starts its threads
    import torch

    torch.set_num_threads(a.threads)
    from bench.common import machine

    from efem_viz.em import run_em
    from efem_viz.em.config import preset
    from efem_viz.prior.model import load_prior

    priors: dict[str, Any] = {}
    try:
        from efem_viz.prior import fused

        fused.load()  # a first build is not a solve's time
    except ImportError:  # a checkout from before the fused kernels
        pass
    import importlib

    for mod in ("open3d", "skimage.measure", "scipy.sparse.csgraph", "scipy.ndimage", "trimesh"):
        importlib.import_module(mod)  # the solver's lazy imports: a process's first solve would pay them
    from efem_viz.prior.config import fast_cpu_bf16

    peaks: dict[str, float] = {}
    busy = [mp.Process(target=_busy, daemon=True) for _ in range(a.busy)]
    for p in busy:
        p.start()
    rows: list[dict[str, Any]] = []
    try:
        for name in a.scenes:
            scene, pname, prior_name = load(name)
            prior = priors.setdefault(prior_name, load_prior(prior_name))
            width = decoder_flops(prior)[2]
            if "float32" not in peaks:  # the machine's ceiling for the decoder's products, once per process
                peaks["float32"] = gemm_peak(width)
                if fast_cpu_bf16():
                    peaks["bfloat16"] = gemm_peak(width, "bfloat16")
                print("GEMM peak (%d x %d, %d threads): %s" % (width, width, a.threads, ", ".join(
                    f"{k} {v:.0f} GFLOP/s" for k, v in peaks.items())), flush=True)
            cfg0 = preset(pname)
            if a.proposals is not None:
                cfg0 = cfg0.replace(proposals={"n_init": (a.proposals, *cfg0.proposals.n_init[1:])})
            base_masks: list[np.ndarray] | None = None
            for var in a.variants:
                env, over = VARIANTS[var]
                os.environ.update(env)
                cfg = cfg0.with_values(over)
                runs, res = [], None
                for r in range(a.repeats):
                    prof = cProfile.Profile() if (a.profile and r == 0) else None
                    t0, c0 = time.perf_counter(), time.process_time()
                    if prof is not None:
                        prof.enable()
                    res = run_em(scene, prior, cfg, seed=a.seed)
                    if prof is not None:
                        prof.disable()
                        print(f"--- profile {name} {var}")
                        pstats.Stats(prof).sort_stats("tottime").print_stats(15)
                    runs.append({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0, **res.timings})
                assert res is not None
                masks = masks_of(res, a.cut)
                if base_masks is None:
                    base_masks = masks
                phases = {k: statistics.median(float(x.get(k, 0.0)) for x in runs)
                          for k in runs[0] if isinstance(runs[0][k], (int, float))}
                floor = decode_row(phases, prior, peaks, cfg.compute.matmul_dtype)
                row = {"scene": name, "preset": pname, "variant": var, "points": scene.num_points,
                       "median": phases, "runs": runs, "instances": len(masks), "decode_vs_floor": floor,
                       "mask_iou_to_baseline": mask_iou_to(base_masks, masks), "ap50": ap50(scene, res)}
                rows.append(row)
                ph = " ".join(f"{k} {phases[k]:.1f}" for k in ("encode", "decode", "review_mesh", "review_pose")
                              if k in phases)
                ap50_txt = "–" if row["ap50"] is None else f"{row['ap50']:.1f}"
                print(f"{name:>16} {var:>9}: {phases['wall']:6.1f} s ({phases['cpu']:.1f} CPU-s) median of "
                      f"{a.repeats} ({ph}); "
                      f"{len(masks)} instances, AP50 {ap50_txt}, mask IoU to baseline "
                      f"{row['mask_iou_to_baseline']:.3f}", flush=True)
                print(f"{'':>27}decode {phases.get('decode', 0.0):.1f} s for "
                      f"{phases.get('decoder_queries', 0.0) / 1e6:.2f} M queries "
                      f"({phases.get('normal_queries', 0.0) / 1e6:.2f} M with normals): "
                      f"{floor['decode_gflops']:.0f} GFLOP/s, {100 * floor['share_of_peak']:.0f} % of the "
                      f"{cfg.compute.matmul_dtype} peak; floor {floor['decode_floor_s']:.1f} s; encode "
                      f"{phases.get('encode', 0.0):.1f} s for {phases.get('encoded_sets', 0.0):.0f} point sets",
                      flush=True)
    finally:
        for p in busy:
            p.terminate()
    write_result(result_path("speed", a.tag), {
        "machine": machine(a.threads) | {"busy_loops": a.busy, "gemm_peak_gflops": peaks},
        "proposals": a.proposals, "seed": a.seed, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
