"""Benchmark of scene IO and real RGB-D import.

1. Save and load a point cloud of `--points` points (with normals, colours and labels) in every format; median of
   `--repeats` runs each, plus file sizes. The rows `.ply mesh` and `.ply ascii mesh` do the same for a
   labelled triangle mesh (a height-field grid) with about `--points` vertices and twice as many faces.
2. Import each real tabletop frame (`shared/data/real_tabletop/*.npz`): time, points, plane residual.

Prints medians and writes bench/results/io.json. `--only` runs just the named format rows (no RGB-D import)
and updates those rows in an existing io.json measured at the same `--points`.

Usage: python bench/io.py [--points 200000] [--repeats 3] [--only ".ply ascii" ".ply ascii mesh"]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_tabletop"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real_tabletop")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", nargs="+", metavar="ROW", default=None,
                    help="format rows to run, e.g. '.ply ascii' '.ply ascii mesh'; skips the RGB-D import")
    args = ap.parse_args()
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    from efem_viz.data.io import atomic_write_text, load_scene, save_scene
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
    res = ROOT / "bench" / "results" / "io.json"
    if args.only is not None and res.is_file():  # a partial run updates its rows of the full record
        previous = json.loads(res.read_text())
        if previous.get("points") == n:
            previous["formats"].update(out["formats"])
            out = previous
    atomic_write_text(res, json.dumps(out, indent=1))
    print(f"\nwrote {res}")


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
