"""EFEM on a GPU against the CPU, in one run: the same solves on both devices, timed, with the answers compared.

For each scene (default: the bundled real frames `real_tabletop_{0,6,8}` with the `real` preset and the fixed
synthetic scene `z_7000` of bench/em.py with the `synthetic` preset, as `bench/speed.py` runs them) the solver runs
once on the CPU and `--repeats` times on `--device` (the first GPU run includes CUDA's warm-up and is reported on
its own), with the same seed. Reported per scene: seconds on each device and their ratio (the median of the warm
GPU runs), the solver's per-phase seconds on both, instances, AP50 against the scene's ground truth, and how
alike the answers are: the mean best mask IoU of the CPU's instances among the GPU's (confidence >= `--cut`,
`bench.speed.mask_iou_to`; 1.0 = the same masks) and the largest confidence difference of matched instances.
Rounding differs between the devices and the solver is chaotic to rounding, so a scene may end differently; the
summary line counts the scenes whose masks agree (IoU >= 0.9).

On the GPU machine (torch, numpy, scipy and scikit-image; no open3d, pybullet or network) `scripts/gpu_check.sh`
runs it: `--prepare` here writes the synthetic scene and the pure-Python wheels it needs into the carried folder.
Without open3d the reviews keep their meshes undecimated on both devices (`efem_viz.prior.meshing.simplify_mesh`),
so its seconds are not this machine's. Here, `--device cpu` runs the same comparison CPU against CPU (a check of
the script, and of determinism: the masks must agree exactly).

Usage: python -m bench.gpu_check [--device cuda] [--scenes real_tabletop_0 z_7000] [--scene-dir DIR] [--repeats 2]
       [--threads N] [--proposals N] [--out FILE]
Writes bench/results/gpu_check/latest.json (or --out).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import machine, result_path, write_result  # first: the OpenMP wait policy, before torch

DEFAULT_SCENES = ["real_tabletop_0", "real_tabletop_6", "real_tabletop_8", "z_7000"]


def load_scene(name: str, scene_dir: Path | None) -> tuple[Any, str, str]:
    """A scene by name with its preset and prior: `<scene_dir>/<name>.npz` where it was prepared (a machine
    without pybullet cannot generate the synthetic scenes), else as `bench.speed.load`."""
    from bench.speed import load

    if scene_dir is not None and (scene_dir / f"{name}.npz").is_file():
        from efem_viz.data.io import load_scene as read

        return read(scene_dir / f"{name}.npz"), "real" if name.startswith("real_") else "synthetic", "mug"
    return load(name)


def solve(scene: Any, prior_name: str, preset_name: str, device: str, seed: int, proposals: int | None = None
          ) -> tuple[Any, float]:
    """One solve on a device; its result and wall seconds (the device synchronised before and after)."""
    import torch

    from efem_viz.em.config import preset
    from efem_viz.em.solver import run_em
    from efem_viz.prior.model import load_prior

    prior = load_prior(prior_name)
    cfg = preset(preset_name) if proposals is None else preset(preset_name).with_proposals(int(proposals))
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()
    t0 = time.perf_counter()
    res = run_em(scene, prior, cfg, seed=seed, device=device)
    sync()
    return res, time.perf_counter() - t0


def confidence_gap(base: Any, other: Any, cut: float) -> float:
    """The largest confidence difference between a base instance (>= cut) and its best-IoU match in `other`
    (0 when either has none)."""
    a, b = base.instances.above(cut), other.instances.above(cut)
    if not len(a.masks) or not len(b.masks):
        return 0.0
    sets = [set(np.asarray(m).tolist()) for m in b.masks]
    gap = 0.0
    for m, c in zip(a.masks, np.asarray(a.confidence, np.float64)):
        s = set(np.asarray(m).tolist())
        ious = [len(s & o) / max(1, len(s | o)) for o in sets]
        j = int(np.argmax(ious))
        gap = max(gap, abs(float(c) - float(np.asarray(b.confidence, np.float64)[j])))
    return gap


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES)
    ap.add_argument("--scene-dir", type=Path, default=None, help="prepared scenes (<name>.npz)")
    ap.add_argument("--repeats", type=int, default=2, help="runs on --device (the first one warms it up)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proposals", type=int, default=None, help="proposals per scene (default: the preset's)")
    ap.add_argument("--cut", type=float, default=0.1, help="confidence cut of the masks compared")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()

    import torch

    from bench.speed import ap50, mask_iou_to, masks_of

    if a.threads:
        torch.set_num_threads(a.threads)
    if a.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"no CUDA device visible to torch {torch.__version__}: nothing to check (--device cpu checks the "
              "script here)")
        return 1
    gpu_name = torch.cuda.get_device_name(0) if a.device.startswith("cuda") else "cpu"
    print(f"CPU ({torch.get_num_threads()} threads) against {a.device} ({gpu_name}), seed {a.seed}", flush=True)
    rows: dict[str, Any] = {}
    agree = 0
    for name in a.scenes:
        scene, preset_name, prior_name = load_scene(name, a.scene_dir)
        cpu, cpu_s = solve(scene, prior_name, preset_name, "cpu", a.seed, a.proposals)
        runs = [solve(scene, prior_name, preset_name, a.device, a.seed, a.proposals) for _ in range(max(1, a.repeats))]
        dev, _ = runs[-1]
        warm = [s for _, s in runs[1:]] or [runs[0][1]]
        dev_s = statistics.median(warm)
        iou = mask_iou_to(masks_of(cpu, a.cut), masks_of(dev, a.cut))
        agree += iou >= 0.9
        row = {"points": int(scene.num_points), "preset": preset_name, "prior": prior_name,
               "cpu_s": cpu_s, "device_s": dev_s, "device_first_s": runs[0][1], "ratio": dev_s / cpu_s,
               "cpu_phases": dict(cpu.timings), "device_phases": dict(dev.timings),
               "instances": {"cpu": len(cpu.instances), "device": len(dev.instances)},
               "ap50": {"cpu": ap50(scene, cpu), "device": ap50(scene, dev)},
               "mask_iou_cpu_to_device": iou, "max_confidence_gap": confidence_gap(cpu, dev, a.cut)}
        rows[name] = row
        ap_txt = ("" if row["ap50"]["cpu"] is None else
                  f", AP50 {row['ap50']['cpu']:.1f} / {row['ap50']['device']:.1f}")
        print(f"{name:>16} ({preset_name}, {row['points']} points): CPU {cpu_s:.1f} s, {a.device} {dev_s:.1f} s "
              f"(first {runs[0][1]:.1f} s), ratio {row['ratio']:.2f}; instances {len(cpu.instances)} / "
              f"{len(dev.instances)}{ap_txt}; mask IoU {iou:.3f}, confidence gap {row['max_confidence_gap']:.3f}",
              flush=True)
    print(f"{agree} of {len(a.scenes)} scenes with the same masks (IoU >= 0.9) on both devices", flush=True)
    out = a.out or result_path("gpu_check")
    write_result(out, {"machine": machine(torch.get_num_threads()) | {"device": a.device, "device_name": gpu_name},
                       "seed": a.seed, "proposals": a.proposals, "cut": a.cut, "repeats": a.repeats, "scenes": rows,
                       "agree": agree})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
