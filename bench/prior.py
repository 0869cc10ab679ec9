"""Benchmark of the shipped shape prior: reconstruction, codebook pose, and throughput.

For held-out procedural mugs (test split) and the real scanned YCB mug (never trained on), each normalised
like the training meshes (bbox centre at the origin, longest side 1; both are +Z up with the handle toward
+X):

1. render one depth view (open3d ray casting, the training camera model, elevation 30-60°, random azimuth),
   draw `n_pcl` points with replacement + Gaussian noise σ = 0.01, apply a random SIM(3) (Haar rotation,
   scale log-uniform in [0.05, 0.3] — metre-sized objects — and a Gaussian shift),
2. encode, extract the mesh (`extract_mesh`, world frame), map it back to the canonical frame with the inverse
   SIM(3), and score it against the ground-truth mesh:
   * volumetric IoU on points uniform in the union of both bounding boxes (inside = negative signed distance
     of each watertight mesh, open3d),
   * Chamfer-L1 distance in canonical units: ½ (mean NN distance pred→GT + mean GT→pred) on surface samples,
3. estimate the pose from the codebook (`estimate_pose` on samples of the extracted mesh) and compare with the
   applied rotation: the up-axis angle (all mugs) and the full geodesic rotation angle (mugs with a handle
   only; a handle-less mug is rotationally symmetric about its axis, so only its up axis is defined),
4. throughput at the shipped size: encoder proposals/s (batch of 16 clouds of n_pcl points) and decoder SDF
   and SDF+normal queries/s (ragged batch with `index`, as the EM E-step calls it), mesh and pose times.

Prints medians and writes bench/results/prior/latest.json.

Usage: python -m bench.prior [--prior efem_viz/weights/mug.pt] [--n-test 50] [--ycb-trials 20]
       python -m bench.prior --prior efem_viz/weights/kitchen.pt --category kitchen  (a table per member; a can's
       up error modulo its top-bottom flip)
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
YCB_MUG = ROOT.parent / "shared" / "data" / "ycb" / "025_mug" / "nontextured.ply"  # ../shared beside the repo
if not YCB_MUG.exists():
    YCB_MUG = Path("/work/shared/data/ycb/025_mug/nontextured.ply")


def _sd_scene(mesh: Any) -> Any:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene


def _inside(scene: Any, pts: np.ndarray) -> np.ndarray:
    import open3d as o3d

    return scene.compute_signed_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy() < 0


def volumetric_iou(pred: Any, gt: Any, *, n: int, rng: np.random.Generator) -> float:
    """IoU of two watertight meshes on `n` points uniform in the union of their bounding boxes (padded)."""
    if len(pred.faces) == 0:
        return 0.0
    lo = np.minimum(pred.bounds[0], gt.bounds[0]) - 0.02
    hi = np.maximum(pred.bounds[1], gt.bounds[1]) + 0.02
    pts = rng.uniform(lo, hi, size=(n, 3))
    a = _inside(_sd_scene(pred), pts)
    b = _inside(_sd_scene(gt), pts)
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0


def chamfer_l1(pred: Any, gt: Any, *, n: int, seed: int) -> float:
    """½ (mean NN distance pred→gt + gt→pred) on `n` surface samples each."""
    import trimesh
    from scipy.spatial import cKDTree

    if len(pred.faces) == 0:
        return float("nan")
    a = trimesh.sample.sample_surface(pred, n, seed=seed)[0]
    b = trimesh.sample.sample_surface(gt, n, seed=seed + 1)[0]
    return float(0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()))


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    c = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def evaluate_object(prior: Any, gt: Any, *, has_handle: bool, rng: np.random.Generator,
                    args: argparse.Namespace, name: str, flip_symmetric: bool = False) -> dict[str, Any]:
    """One reconstruction + pose trial on a normalised GT mesh (`flip_symmetric`: the shape is the same upside
    down, a closed can: its up error is taken modulo the flip)."""
    import torch
    import trimesh

    from efem_viz.geometry.transforms import random_rotation, rotation_angle_deg
    from efem_viz.prior.data import PrepConfig, render_views
    from efem_viz.prior.meshing import MeshStats, extract_mesh
    from efem_viz.prior.pose import estimate_pose

    cam = PrepConfig(n_views=1, n_top_views=1, resolution=128)
    views, elev = render_views(gt, cam, rng=rng)
    view = views[0].astype(np.float64)
    n_pcl = prior.config.n_pcl
    x = view[rng.integers(0, len(view), n_pcl)] + rng.normal(0.0, 0.01, (n_pcl, 3))
    R = random_rotation(rng)
    s = float(np.exp(rng.uniform(np.log(0.05), np.log(0.3))))
    t = rng.normal(0.0, 1.0, 3)
    xw = s * x @ R.T + t
    with torch.no_grad():
        lat = prior.encode(torch.as_tensor(xw, dtype=torch.float32)[None])
    t0 = time.perf_counter()
    mesh_stats = MeshStats()
    mesh_w = extract_mesh(prior, lat, resolution=args.resolution, coarse=args.coarse, world=True,
                          max_faces=args.max_faces, stats=mesh_stats)
    t_mesh = time.perf_counter() - t0
    queries = mesh_stats.queries
    rec: dict[str, Any] = {"name": name, "handle": has_handle, "view_points": len(view),
                           "elevation_deg": float(elev[0]), "scale": s, "t_mesh_s": t_mesh,
                           "mesh_queries": queries, "faces": len(mesh_w.faces)}
    if len(mesh_w.faces) == 0:
        rec.update(iou=0.0, chamfer=float("nan"), up_err_deg=float("nan"), rot_err_deg=float("nan"))
        return rec
    mesh_c = trimesh.Trimesh((mesh_w.vertices - t) @ R / s, mesh_w.faces, process=False)
    rec["watertight"] = bool(mesh_c.is_watertight)
    rec["iou"] = volumetric_iou(mesh_c, gt, n=args.iou_points, rng=rng)
    rec["chamfer"] = chamfer_l1(mesh_c, gt, n=args.chamfer_points, seed=int(rng.integers(2**31)))
    center = lat.center.numpy()[0].astype(np.float64)
    samples = trimesh.sample.sample_surface(mesh_w, args.pose_samples, seed=int(rng.integers(2**31)))[0]
    samples = samples - center
    for key, proper in (("", False), ("_proper_search", True)):
        t0 = time.perf_counter()
        est = estimate_pose(prior, lat, samples, proper_search=proper)
        rec[f"t_pose_s{key}"] = time.perf_counter() - t0
        up = _angle_deg(est.R[:, 2], R[:, 2])
        rec[f"up_err_deg{key}"] = min(up, 180.0 - up) if flip_symmetric else up
        rec[f"rot_err_deg{key}"] = float(rotation_angle_deg(est.R, R)) if has_handle else float("nan")
        rec[f"score_db_sim{key}"] = est.score_db_sim
        rec[f"reflected{key}"] = est.reflected
    # canonical units; the GT centre is the bbox centre (the origin)
    rec["center_err"] = float(np.linalg.norm(((center - t) @ R) / s))
    rec["scale_ratio"] = float(lat.scale.numpy()[0] / s)
    return rec


def throughput(prior: Any, *, reps: int = 3) -> dict[str, float]:
    """Encoder proposals/s and decoder queries/s at the shipped size (median of `reps`)."""
    import torch

    n_pcl = prior.config.n_pcl
    g = torch.Generator().manual_seed(0)
    B = 16
    clouds = torch.randn(B, n_pcl, 3, generator=g) * torch.tensor([0.05, 0.05, 0.04])
    times = []
    with torch.no_grad():
        prior.encode(clouds[:2])
        for _ in range(reps):
            t0 = time.perf_counter()
            lat = prior.encode(clouds)
            times.append(time.perf_counter() - t0)
    enc = B / float(np.median(times))
    Q = 32768
    x = lat.center[torch.randint(0, B, (Q,), generator=g)] + 0.05 * torch.randn(Q, 3, generator=g)
    idx = torch.randint(0, B, (Q,), generator=g)
    t_sdf, t_nrm = [], []
    for _ in range(reps):
        with torch.no_grad():
            t0 = time.perf_counter()
            prior.sdf(x, lat, idx, chunk=4096)
            t_sdf.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        prior.sdf_and_normals(x, lat, idx, chunk=4096)
        t_nrm.append(time.perf_counter() - t0)
    return {"encoder_proposals_per_s": enc, "encoder_batch": B,
            "decoder_sdf_queries_per_s": Q / float(np.median(t_sdf)),
            "decoder_sdf_normals_queries_per_s": Q / float(np.median(t_nrm)),
            "torch_threads": torch.get_num_threads()}


def _median(records: list[dict[str, Any]], key: str) -> float:
    vals = np.array([r[key] for r in records if key in r and r[key] is not None], dtype=np.float64)
    vals = vals[np.isfinite(vals)]
    return float(np.median(vals)) if len(vals) else float("nan")


def _summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    keys = ["iou", "chamfer", "up_err_deg", "rot_err_deg", "up_err_deg_proper_search",
            "rot_err_deg_proper_search", "score_db_sim", "t_mesh_s", "mesh_queries", "t_pose_s",
            "center_err", "scale_ratio"]
    out: dict[str, Any] = {f"median_{k}": _median(records, k) for k in keys}
    out["n"] = len(records)
    out["mean_iou"] = float(np.mean([r["iou"] for r in records]))
    ups = np.array([r["up_err_deg"] for r in records], dtype=np.float64)
    rots = np.array([r["rot_err_deg"] for r in records if r["handle"]], dtype=np.float64)
    out["frac_up_err_below_15deg"] = float(np.mean(ups < 15.0))
    out["frac_rot_err_below_30deg"] = float(np.mean(rots < 30.0)) if len(rots) else float("nan")
    out["frac_reflected"] = float(np.mean([r.get("reflected", False) for r in records]))
    out["frac_watertight"] = float(np.mean([r.get("watertight", False) for r in records]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--prior", default=str(ROOT / "efem_viz/weights/mug.pt"))
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--ycb-trials", type=int, default=20)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--coarse", type=int, default=16)
    ap.add_argument("--max-faces", type=int, default=5000)
    ap.add_argument("--iou-points", type=int, default=100_000)
    ap.add_argument("--chamfer-points", type=int, default=10_000)
    ap.add_argument("--pose-samples", type=int, default=2000)
    # 1 thread: on this 2-core machine shared with other jobs, 2 torch threads were 5-10x *slower* (spinning)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--category", default="mug",
                    help="the test objects: a category, or a family (kitchen: its members interleaved, a summary "
                         "per member)")
    ap.add_argument("--out", default=None,
                    help="JSON (default bench/results/prior/latest.json, or prior_<category>.json)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import torch
    import trimesh

    from efem_viz.data.procedural import family_seeds, make_shape, sample_mug_params
    from efem_viz.prior.data import normalize_mesh
    from efem_viz.prior.model import load_prior

    torch.set_num_threads(args.threads)
    prior = load_prior(args.prior)
    if prior.codebook is None or not prior.codebook.matches(prior):
        raise SystemExit(f"{args.prior} has no codebook next to it, or one built from other weights: "
                         f"run `efem-viz build-codebook --prior {args.prior}`")
    rng = np.random.default_rng(args.seed)
    t_start = time.perf_counter()

    proc: list[dict[str, Any]] = []
    for cat, seed in family_seeds(args.category, "test", args.n_test):
        gt = normalize_mesh(make_shape(cat, seed))
        handle = cat == "mug" and sample_mug_params(seed).handle != "none"  # the others: only the up axis
        proc.append(evaluate_object(prior, gt, has_handle=handle, rng=rng, args=args, name=f"{cat}_{seed}",
                                    flip_symmetric=cat == "can"))
    members = sorted({r["name"].rsplit("_", 1)[0] for r in proc})
    ycb_gt = normalize_mesh(trimesh.load(YCB_MUG, force="mesh"))
    ycb = [evaluate_object(prior, ycb_gt, has_handle=True, rng=rng, args=args, name=f"ycb_025_mug_trial{i}")
           for i in range(args.ycb_trials)]
    thr = throughput(prior)

    result = {
        "prior": str(args.prior),
        "prior_config": prior.config.to_dict(),
        "prior_metadata": {k: v for k, v in prior.metadata.items() if k != "val_metrics"},
        "codebook_entries": len(prior.codebook),
        "settings": {k: v for k, v in vars(args).items() if k != "out"},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "category": args.category,
        "procedural_test": _summary(proc),
        "procedural_test_per_category": ({c: _summary([r for r in proc if r["name"].rsplit("_", 1)[0] == c])
                                          for c in members} if len(members) > 1 else {}),
        "ycb_mug": _summary(ycb),
        "throughput": thr,
        "records": {"procedural_test": proc, "ycb_mug": ycb},
        "wall_s": time.perf_counter() - t_start,
    }
    out = Path(args.out) if args.out else result_path("prior", None if args.category == "mug" else args.category)
    write_result(out, result)

    def line(name: str, s: dict[str, Any]) -> str:
        return (f"{name:<18} n={s['n']:<3} IoU {s['median_iou']:.3f} (mean {s['mean_iou']:.3f})  "
                f"Chamfer-L1 {s['median_chamfer']:.4f}  up err {s['median_up_err_deg']:.1f}°  "
                f"rot err {s['median_rot_err_deg']:.1f}° "
                f"(proper search: up {s['median_up_err_deg_proper_search']:.1f}°, "
                f"rot {s['median_rot_err_deg_proper_search']:.1f}°)  "
                f"up<15°: {s['frac_up_err_below_15deg']:.2f}  "
                f"rot<30°: {s['frac_rot_err_below_30deg']:.2f}  mesh {s['median_t_mesh_s'] * 1e3:.0f} ms "
                f"({s['median_mesh_queries']:.0f} q)  pose {s['median_t_pose_s'] * 1e3:.0f} ms")

    print(f"prior {args.prior} ({len(prior.codebook)} codebook entries), medians:")
    print(line("procedural test", result["procedural_test"]))
    for c, summ in result["procedural_test_per_category"].items():
        print(line(f"  {c}", summ))
    print(line("YCB 025_mug", result["ycb_mug"]))
    print(f"encoder {thr['encoder_proposals_per_s']:.1f} proposals/s (batch {thr['encoder_batch']}, "
          f"{thr['torch_threads']} threads); "
          f"decoder {thr['decoder_sdf_queries_per_s'] / 1e3:.0f} k SDF queries/s, "
          f"{thr['decoder_sdf_normals_queries_per_s'] / 1e3:.0f} k SDF+normal queries/s")
    print(f"wrote {out} ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
