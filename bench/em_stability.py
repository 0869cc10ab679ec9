"""Stability bench: does one EM proposal keep its grip on a mug? (the development metric of real scans)

For every object of every set, `efem_viz.em.probe.track_proposal` runs one proposal through phase 1 of the
solver's own code (M-step, encode, E-step in the r_err ball, annealing; 15 steps) and its phase-end review:

(a) **oracle crop**: exactly the object's points, weights 1. Step 0 reports the inlier fraction (and SDF-only /
    normal-only fractions) and Θ_s against the true size; after phase 1, the fraction of the object still
    explained ("kept") and Θ_s.
(b) **anchor balls** (``--anchors`` per object, radius r_init around an object point, as real proposals start):
    kept fraction, inliers, Θ_s ratio, alive (passed the size rule at every step), output-mask IoU;
    "alive with a good mask" = alive and IoU ≥ 0.5.

Sets:
* ``single-view``: held-out procedural mugs (test split) on a table, one depth camera 0.5-0.9 m away
  (elevation 30-60°, fx 600 at 640×480), the hits measured by `prior.data.SensorModel` — isotropic σ ∈
  {0, 1, 2, 3, 5} mm and the RealSense model (``sensor``) — then imported exactly like a real frame
  (`data.rgbd.import_rgbd`: RANSAC table, 4 mm voxels, estimated normals);
* ``real-tune`` / ``real-judge``: the labelled mugs and non-mug objects of the UOIS RealSense frames
  (bench/real.py's split: tune 0, 1, 6; judge 2, 3, 4, 5, 7, 8).

Usage: python -m bench.em_stability [--config "NAME=key=value;key=value" ...] [--mugs 8] [--anchors 2]
       [--sets single-view real-tune real-judge] [--levels 0 1 2 3 5 sensor] [--prior PATH] [--tag NAME]
Configs: "base" (the `--preset`, default `real`) is always run; each --config adds one (overrides on the
preset by the solver settings' dotted names, e.g. "band=elimination.min_size_on='band'"). `real` holds the
measured changes; the earliest tables (docs/BENCHMARKS.md) used what is now `real_paper`.
Writes bench/results/em_stability/em_stability_<tag>.json and prints one table per set. 1 torch thread by default
(``--threads``), so that it can run beside a training job.
"""

from __future__ import annotations

import argparse
import ast
import platform
import sys
import time
from typing import Any

import numpy as np

from bench.common import result_path, write_result  # first: the OpenMP wait policy, before torch

LEVELS = ("0", "1", "2", "3", "5", "sensor")


def parse_config(spec: str) -> tuple[str, dict[str, Any]]:
    """``"NAME=key=value;key=value"`` (values are Python literals) -> (NAME, EMConfig overrides)."""
    name, _, kv = spec.partition("=")
    changes: dict[str, Any] = {}
    for part in filter(None, kv.split(";")):
        k, _, v = part.partition("=")
        changes[k.strip()] = ast.literal_eval(v.strip())
    return name, changes


# ---------------------------------------------------------------------------------------------- scenes
def render_single_view(mesh: Any, level: str, rng: np.random.Generator, *, name: str) -> tuple[Any, np.ndarray, float]:
    """One depth frame of ``mesh`` (metres, upright, random yaw) on a table, imported like a real frame.

    Returns:
        (scene, (N,) bool mug mask, true size = longest side of the mug in metres).
    """
    import open3d as o3d
    import trimesh

    from efem_viz._typeshims import o3d_tensor
    from efem_viz.data.rgbd import import_rgbd
    from efem_viz.geometry.camera import look_at
    from efem_viz.prior.data import SensorModel

    m = mesh.copy()
    yaw = rng.uniform(0, 2 * np.pi)
    m.apply_transform(trimesh.transformations.rotation_matrix(yaw, [0, 0, 1]))
    m.apply_translation([0.0, 0.0, -m.bounds[0, 2]])
    size = float(np.max(m.bounds[1] - m.bounds[0]))
    table = trimesh.creation.box(extents=[0.8, 0.8, 0.02])
    table.apply_translation([0.0, 0.0, -0.01])
    sc = o3d.t.geometry.RaycastingScene()
    for mm in (m, table):
        sc.add_triangles(o3d_tensor(np.asarray(mm.vertices, np.float32)), o3d_tensor(np.asarray(mm.faces, np.uint32)))
    dist = rng.uniform(0.5, 0.9)
    el = np.deg2rad(rng.uniform(30, 60))
    az = rng.uniform(0, 2 * np.pi)
    target = np.array([0.0, 0.0, (m.bounds[1, 2]) / 2])
    eye = target + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    Rwc = look_at(eye, target)[:3, :3]  # columns: right, down, forward
    f_ = Rwc[:, 2]
    w, h, fx = 640, 480, 600.0
    K = np.array([[fx, 0, (w - 1) / 2], [0, fx, (h - 1) / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / fx, (v - K[1, 2]) / fx, np.ones_like(u)], -1)
    d_world = d_cam @ Rwc.T
    rays = np.concatenate([np.broadcast_to(eye, d_world.shape), d_world], -1).astype(np.float32)
    ans = sc.cast_rays(o3d_tensor(rays))
    t = ans["t_hit"].numpy().astype(np.float64)
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    nrm = ans["primitive_normals"].numpy().astype(np.float64)
    hit = np.isfinite(t) & (t < 3.0)
    pts = eye + d_world[hit] * t[hit, None]
    dun = d_world[hit] / np.linalg.norm(d_world[hit], axis=1, keepdims=True)
    cos = np.abs((nrm[hit] * dun).sum(1))
    if level == "sensor":
        sensor = SensorModel(kind="realsense", k=1.0, fx=fx)
    else:
        sensor = SensorModel(kind="isotropic", k=float(level))
    noisy, keep = sensor.apply(pts, eye, cos, rng)
    z = (noisy - eye) @ f_  # camera-frame depth
    depth = np.zeros((h, w), np.float32)
    hv, hu = np.nonzero(hit)
    depth[hv[keep], hu[keep]] = z.astype(np.float32)
    label_img = np.where(hit, gid, -1)
    scene = import_rgbd(depth, K, name=name, voxel=0.004, seed=0)
    T = np.asarray(scene.provenance["T_world_camera"], np.float64)
    p_cam = (scene.points.astype(np.float64) - T[:3, 3]) @ T[:3, :3]
    uu = np.clip(np.round(p_cam[:, 0] / p_cam[:, 2] * fx + K[0, 2]).astype(int), 0, w - 1)
    vv = np.clip(np.round(p_cam[:, 1] / p_cam[:, 2] * fx + K[1, 2]).astype(int), 0, h - 1)
    mug = label_img[vv, uu] == 0
    return scene, mug, size


def single_view_objects(n_mugs: int, levels: list[str], seed: int) -> dict[str, list[dict[str, Any]]]:
    """Per level: [{scene, mask, size, is_mug, name}] for the first ``n_mugs`` held-out test mugs."""
    from efem_viz.data.procedural import make_shape, split_seeds

    out: dict[str, list[dict[str, Any]]] = {}
    seeds = list(split_seeds("mug", "test"))[:n_mugs]
    for level in levels:
        items = []
        for i, s in enumerate(seeds):
            rng = np.random.default_rng(seed * 1000 + i)  # same camera for every level
            scene, mask, size = render_single_view(make_shape("mug", s), level, rng, name=f"mug{s}_{level}")
            if mask.sum() < 50:
                continue
            items.append({"scene": scene, "mask": mask, "size": size, "is_mug": True, "name": scene.name})
        out[f"single-view {level}"] = items
    return out


def real_objects(frames: tuple[int, ...]) -> list[dict[str, Any]]:
    """Every labelled object (mugs and non-mugs) of the given UOIS frames."""
    from bench.real import load_frame

    items = []
    for k in frames:
        scene = load_frame(k)
        for i in scene.instance_ids():
            mask = scene.instance == i
            cat = scene.categories.get(int(i), "")
            if mask.sum() < 50:
                continue
            ext = scene.points[mask].max(0) - scene.points[mask].min(0)
            items.append({"scene": scene, "mask": mask, "size": float(np.max(ext)), "is_mug": cat == "mug",
                          "name": f"{scene.name}#{int(i)}:{cat}"})
    return items


# ---------------------------------------------------------------------------------------------- probe
def probe_object(item: dict[str, Any], prior: Any, cfg: Any, *, anchors: int, rng: np.random.Generator
                 ) -> dict[str, Any]:
    """Oracle track + anchor-ball tracks of one object."""
    from efem_viz.em.probe import track_proposal

    scene, mask = item["scene"], item["mask"]
    n_obj = int(mask.sum())
    res: dict[str, Any] = {"name": item["name"], "is_mug": item["is_mug"], "points": n_obj}
    if item["is_mug"]:
        tr = track_proposal(scene, prior, cfg, object_mask=mask, start="oracle", steps=cfg.steps.t1, seed=0)
        # step-0 split of the inlier test into its SDF and normal parts (the oracle crop's own E-step)
        res["oracle"] = {"inlier_frac0": tr.explained[0], "sdf_frac0": tr.explained_band[0],
                         "kept": tr.explained[-1], "kept_band": tr.explained_band[-1],
                         "inliers0": tr.inliers[0], "inliers": tr.inliers[-1],
                         "scale_ratio0": tr.scale[0] / item["size"], "scale_ratio": tr.scale[-1] / item["size"],
                         "alive": tr.alive, "iou": tr.output_iou}
    runs = []
    idx = np.flatnonzero(mask)
    for a in range(anchors):
        start = int(idx[rng.integers(len(idx))])
        tr = track_proposal(scene, prior, cfg, object_mask=mask, start=start, steps=cfg.steps.t1, seed=a)
        runs.append({"kept": tr.explained[-1], "inliers": tr.inliers[-1], "size_count": tr.size_count[-1],
                     "min_size": tr.min_size[-1], "scale_ratio": tr.scale[-1] / item["size"], "alive": tr.alive,
                     "iou": tr.output_iou, "good": bool(tr.alive and tr.output_iou >= 0.5)})
    res["anchor"] = runs
    return res


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    mugs = [r for r in rows if r["is_mug"]]
    others = [r for r in rows if not r["is_mug"]]
    ma = [a for r in mugs for a in r["anchor"]]
    oa = [a for r in others for a in r["anchor"]]

    def med(v: list[float]) -> float:
        return float(np.median(v)) if v else float("nan")

    out = {"n_mugs": len(mugs), "n_other": len(others),
           "oracle_inlier_frac0": med([r["oracle"]["inlier_frac0"] for r in mugs]),
           "oracle_sdf_frac0": med([r["oracle"]["sdf_frac0"] for r in mugs]),
           "oracle_kept": med([r["oracle"]["kept"] for r in mugs]),
           "oracle_scale_ratio": med([r["oracle"]["scale_ratio"] / max(r["oracle"]["scale_ratio0"], 1e-9)
                                      for r in mugs]),
           "anchor_kept": med([a["kept"] for a in ma]),
           "anchor_scale_ratio": med([a["scale_ratio"] for a in ma]),
           "mug_alive_good": float(np.mean([a["good"] for a in ma])) if ma else float("nan"),
           "mug_alive": float(np.mean([a["alive"] for a in ma])) if ma else float("nan"),
           "other_alive": float(np.mean([a["alive"] for a in oa])) if oa else float("nan")}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", action="append", default=[],
                    help="NAME=key=value;key=value (EMConfig overrides, Python literals)")
    ap.add_argument("--preset", default="real")
    ap.add_argument("--sets", nargs="+", default=["single-view", "real-tune", "real-judge"])
    ap.add_argument("--levels", nargs="+", default=list(LEVELS))
    ap.add_argument("--mugs", type=int, default=8)
    ap.add_argument("--anchors", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--prior", default=None, help="prior file (default: the shipped mug prior)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default="latest")
    ap.add_argument("--no-base", action="store_true", help="skip the unchanged preset")
    args = ap.parse_args()

    import torch

    from efem_viz.em.config import preset
    from efem_viz.prior.model import load_prior

    torch.set_num_threads(args.threads)
    prior = load_prior(args.prior or "mug")
    base = preset(args.preset)
    configs: dict[str, Any] = {} if args.no_base else {"base": base}
    for spec in args.config:
        name, changes = parse_config(spec)
        configs[name] = base.with_values(changes)
    t0 = time.time()
    sets: dict[str, list[dict[str, Any]]] = {}
    if "single-view" in args.sets:
        sets.update(single_view_objects(args.mugs, args.levels, args.seed))
    from bench.real import JUDGE, TUNE

    if "real-tune" in args.sets:
        sets["real-tune"] = real_objects(TUNE)
    if "real-judge" in args.sets:
        sets["real-judge"] = real_objects(JUDGE)
    print(f"[scenes ready in {time.time() - t0:.0f} s]", flush=True)
    results: dict[str, Any] = {}
    for cname, cfg in configs.items():
        results[cname] = {}
        for sname, items in sets.items():
            t1 = time.time()
            rng = np.random.default_rng(args.seed)
            rows = [probe_object(it, prior, cfg, anchors=args.anchors, rng=rng) for it in items]
            summ = summarise(rows)
            summ["seconds"] = round(time.time() - t1, 1)
            results[cname][sname] = {"summary": summ, "rows": rows}
            print(f"{cname:>14} | {sname:<18} | oracle inl0 {summ['oracle_inlier_frac0']:.2f} "
                  f"(sdf {summ['oracle_sdf_frac0']:.2f}) kept {summ['oracle_kept']:.2f} "
                  f"Θs× {summ['oracle_scale_ratio']:.2f} | anchors kept {summ['anchor_kept']:.2f} "
                  f"Θs/size {summ['anchor_scale_ratio']:.2f} mug alive+good {summ['mug_alive_good']:.2f} "
                  f"(alive {summ['mug_alive']:.2f}) other alive {summ['other_alive']:.2f} "
                  f"[{summ['seconds']:.0f}s]", flush=True)
    out = {"command": " ".join(sys.argv), "machine": platform.processor() or platform.machine(),
           "threads": args.threads, "prior": args.prior or "mug (shipped)", "preset": args.preset,
           "configs": {k: {"tau_d": v.steps.tau_d, "tau_n": v.steps.tau_n, "min_size": v.elimination.min_size,
                           "min_size_on": v.elimination.min_size_on,
                           "min_size_spacing": v.elimination.min_size_spacing,
                           "m_step_replace": v.steps.m_step_replace} for k, v in configs.items()},
           "results": results, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    write_result(result_path("em_stability", args.tag), out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
