"""Benchmark of scene IO and real RGB-D import.

1. Save and load a point cloud of `--points` points (with normals, colours and labels) in every format; median of
   `--repeats` runs each, plus file sizes. The rows `.ply mesh` and `.ply ascii mesh` do the same for a
   labelled triangle mesh (a height-field grid) with about `--points` vertices and twice as many faces.
2. Import each real tabletop frame (`shared/data/real_tabletop/*.npz`): time, points, plane residual.

Prints medians and writes bench/results/io/latest.json. `--only` runs just the named format rows (no RGB-D import)
and updates those rows in an existing io/latest.json measured at the same `--points`.

3. `--normals N [N ...]` runs only the point-cloud-without-normals benchmark: a binary PLY
   of N points on a random surface (a wavy table plus 8 spheres, 1 mm noise, seed 0) and no normals; each
   measurement runs in a fresh 1-thread process (so peak RSS is its own): `info` = `load_scene` + `summary`
   (what `efem-viz info` does), `normals` = that plus reading `scene.normals`. `--root DIR` measures another
   checkout (e.g. the previous commit unpacked with `git archive HEAD | tar -x -C DIR`). Results go to the
   "normals" record of io/latest.json, keyed by root label and N.

Usage: python -m bench.io [--points 200000] [--repeats 3] [--only ".ply ascii" ".ply ascii mesh"]
       python -m bench.io --normals 550000 2000000 [--root /tmp/before --label before]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_tabletop"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real_tabletop")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", nargs="+", metavar="ROW", default=None,
                    help="format rows to run, e.g. '.ply ascii' '.ply ascii mesh'; skips the RGB-D import")
    ap.add_argument("--normals", nargs="+", type=int, metavar="N", default=None,
                    help="only the bare-point-cloud benchmark (info time vs normals time) at these sizes")
    ap.add_argument("--root", type=Path, default=ROOT, help="with --normals: the checkout to measure")
    ap.add_argument("--label", default="current", help="with --normals: the name of this run in io/latest.json")
    ap.add_argument("--child", nargs=3, metavar=("ROOT", "PLY", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        _normals_child(*args.child)
        return
    if args.normals is not None:
        _bench_normals(args.normals, root=args.root, label=args.label)
        return
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.data.rgbd import import_rgbd, load_rgbd_npz
    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(0)
    n = args.points
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    scene = Scene.create(
        "bench",
        pts,
        normals=pts / np.linalg.norm(pts, axis=1, keepdims=True),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        instance=rng.integers(0, 10, n),
        categories={i: "mug" for i in range(1, 10)},
        max_points=max(n, 1),
    )
    mesh = _grid_mesh(Scene, n, rng)
    rows = [
        (".ply", scene, {}), (".ply ascii", scene, {"ascii": True}), (".npz", scene, {}), (".glb", scene, {}),
        (".obj", scene, {}), (".off", scene, {}),
        (".ply mesh", mesh, {}), (".ply ascii mesh", mesh, {"ascii": True}),
    ]
    if args.only is not None:
        unknown = set(args.only) - {label for label, _, _ in rows}
        if unknown:
            ap.error(f"unknown rows {sorted(unknown)}; choose from {[label for label, _, _ in rows]}")
        rows = [r for r in rows if r[0] in args.only]
    out: dict = {"platform": platform.platform(), "points": n, "formats": {}, "rgbd": {}}
    print(f"scene IO, {n:,} points (median of {args.repeats})")
    print(f"{'format':<16}{'save s':>10}{'load s':>10}{'MB':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        for label, sc, kw in rows:
            suffix = label.split()[0]
            p = Path(tmp) / f"s{suffix}"
            t_save, t_load = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                save_scene(sc, p, **kw)
                t_save.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                load_scene(p, max_points=sc.num_points)
                t_load.append(time.perf_counter() - t0)
            mb = p.stat().st_size / 1e6
            out["formats"][label] = {"save_s": float(np.median(t_save)), "load_s": float(np.median(t_load)), "mb": mb}
            print(f"{label:<16}{np.median(t_save):>10.3f}{np.median(t_load):>10.3f}{mb:>10.2f}")
    if REAL.is_dir() and args.only is None:
        print("\nreal RGB-D import (voxel 4 mm)")
        print(f"{'frame':<16}{'points':>10}{'time s':>10}{'plane rms mm':>14}")
        for f in sorted(REAL.glob("*.npz")):
            rgb, depth, K = load_rgbd_npz(f)
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                s = import_rgbd(depth, K, rgb, name=f.stem)
                times.append(time.perf_counter() - t0)
            rms = s.provenance["plane_residual_rms_m"] * 1000
            out["rgbd"][f.stem] = {"points": s.num_points, "time_s": float(np.median(times)), "plane_rms_mm": rms}
            print(f"{f.stem:<16}{s.num_points:>10,}{np.median(times):>10.2f}{rms:>14.2f}")
    res = result_path("io")
    if args.only is not None and res.is_file():  # a partial run updates its rows of the full record
        previous = json.loads(res.read_text())
        if previous.get("points") == n:
            previous["formats"].update(out["formats"])
            out = previous
    write_result(res, out, archive=False)


def random_surface(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) float32 points: half on a wavy 2 x 2 m table, half on 8 spheres of 0.1 m above it, 1 mm noise."""
    rng = np.random.default_rng(seed)
    m = n // 2
    uv = rng.uniform(-1, 1, (m, 2))
    table = np.c_[uv, 0.05 * np.sin(4 * uv[:, 0]) * np.cos(3 * uv[:, 1])]
    k = n - m
    centres = rng.uniform(-0.8, 0.8, (8, 2))
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    spheres = np.c_[centres[rng.integers(0, 8, k)], np.full(k, 0.2)] + 0.1 * d
    return (np.concatenate([table, spheres]) + 0.001 * rng.standard_normal((n, 3))).astype(np.float32)


def _bench_normals(sizes: list[int], *, root: Path, label: str) -> None:
    """Time and peak RSS of `info` and of `info` + normals on bare point clouds, one fresh process each."""
    import plyfile

    out: dict = {"platform": platform.platform(), "threads": 1, "root": str(root), "runs": {}}
    print(f"bare point cloud PLY (no normals), {label} ({root}), 1 thread, fresh process per row")
    print(f"{'points':>10}{'mode':>9}{'time s':>10}{'peak MB':>10}")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            pts = random_surface(n)
            v = np.empty(n, [("x", "f4"), ("y", "f4"), ("z", "f4")])
            v["x"], v["y"], v["z"] = pts.T
            ply = Path(tmp) / f"surface_{n}.ply"
            plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(ply))
            for mode in ("info", "normals"):
                proc = subprocess.run(
                    [sys.executable, "-m", "bench.io", "--child", str(root), str(ply), mode],
                    capture_output=True, text=True, env=env, cwd=ROOT,
                )
                if proc.returncode != 0:
                    raise SystemExit(proc.stderr[-2000:])
                rec = json.loads(proc.stdout.strip().splitlines()[-1])
                out["runs"][f"{n} {mode}"] = rec
                print(f"{n:>10,}{mode:>9}{rec['time_s']:>10.2f}{rec['peak_mb']:>10.0f}")
    res = result_path("io")

    record = json.loads(res.read_text()) if res.is_file() else {}
    record.setdefault("normals", {})[label] = out
    write_result(res, record, archive=False)


def _normals_child(root: str, ply: str, mode: str) -> None:
    """One measurement in this (fresh) process: print {"time_s", "peak_mb"} as JSON."""
    import resource

    sys.path.insert(0, root)
    for name in [m for m in sys.modules if m == "efem_viz" or m.startswith("efem_viz.")]:
        del sys.modules[name]  # measure `root`'s code, not this checkout's
    from efem_viz.data.io import load_scene

    t0 = time.perf_counter()
    scene = load_scene(ply, max_points=10_000_000)
    scene.summary()
    if mode == "normals":
        np.asarray(scene.normals).sum()
    dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"time_s": dt, "peak_mb": peak}))


def _grid_mesh(scene_cls, n: int, rng: np.random.Generator):
    """A labelled height-field triangle mesh with about `n` vertices (two triangles per grid cell)."""
    w = max(2, int(round(np.sqrt(n))))
    h = max(2, n // w)
    u, v = np.meshgrid(np.linspace(0.0, 1.0, w), np.linspace(0.0, 1.0, h))
    z = 0.05 * np.sin(6 * u) * np.cos(5 * v)
    pts = np.stack([u.ravel(), v.ravel(), z.ravel()], axis=1)
    ids = np.arange(w * h).reshape(h, w)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel(), ids[1:, 1:].ravel(), ids[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([a, c, d], axis=1)])
    return scene_cls.create(
        "bench_mesh",
        pts,
        faces=faces,
        colors=rng.integers(0, 256, (len(pts), 3)).astype(np.uint8),
        instance=(pts[:, 0] * 4).astype(np.int64),
        categories={i: "mug" for i in range(1, 5)},
        max_points=len(pts),
    )


if __name__ == "__main__":
    main()
