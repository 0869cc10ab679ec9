"""Is the depth-sensor model of the training inputs (`prior.data.SensorModel`) like the real frames?

For every real frame (the nine UOIS RealSense frames and the PCL textured-stereo frame of ``../shared/data``):
back-project the full-resolution depth, fit the table plane (`data.rgbd.find_support_plane`), and measure on the
table's pixels, per 10 cm depth bin: the noise across the flat patch (robust std of the residual to the plane,
1.4826·MAD), the point spacing (median nearest-neighbour distance) and edge artefacts (flying pixels: a depth
more than 2 cm from both horizontal neighbours, among all valid pixels).
Then the same table pixels are generated: the exact plane depth along each pixel's ray, measured by the sensor
model (RealSense and Kinect, k = 1, the frame's own intrinsics and incidence angles), and measured the same way.

Usage: python -m bench.sensor_check   → bench/results/sensor_check/latest.json, docs/img/sensor_noise.svg
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
DATA = Path(os.environ.get("EFEM_SHARED_DATA", ROOT.parent / "shared" / "data"))
BINS = np.arange(0.4, 1.6, 0.1)


def _robust_std(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")


def _per_bin(z: np.ndarray, res: np.ndarray) -> list[dict[str, float]]:
    out = []
    for lo in BINS:
        sel = (z >= lo) & (z < lo + 0.1)
        if sel.sum() >= 200:
            out.append({"z": round(float(lo + 0.05), 2), "noise_mm": 1e3 * _robust_std(res[sel]), "n": int(sel.sum())})
    return out


def _flying_fraction(depth: np.ndarray) -> float:
    d = depth.astype(np.float64)
    c, left, right = d[:, 1:-1], d[:, :-2], d[:, 2:]
    ok = (c > 0) & (left > 0) & (right > 0)
    fly = ok & (np.abs(c - left) > 0.02) & (np.abs(c - right) > 0.02)
    return float(fly.sum() / max(1, ok.sum()))


def analyse_frame(path: Path, seed: int = 0) -> dict[str, Any]:
    from efem_viz.data.rgbd import backproject, find_support_plane, load_rgbd_npz
    from efem_viz.prior.data import SensorModel

    _, depth, K = load_rgbd_npz(path)
    pts, _ = backproject(depth, K, max_depth=2.5)
    rng = np.random.default_rng(seed)
    sub = pts[rng.choice(len(pts), min(len(pts), 40000), replace=False)]
    plane = find_support_plane(sub, seed=seed)
    n, d0 = plane.normal, plane.offset
    res_all = pts @ n + d0
    table = np.abs(res_all) < 0.02
    q = pts[table]
    # local flatness: refit on the patch so a slightly curved or tilted table does not count as noise
    c0 = q.mean(0)
    _, _, vt = np.linalg.svd(q - c0, full_matrices=False)
    n2 = vt[2] if vt[2] @ (-c0) > 0 else -vt[2]
    res = (q - c0) @ n2
    real = {"bins": _per_bin(q[:, 2], res), "flying": _flying_fraction(depth),
            "spacing_mm": _spacing_mm(q)}
    # generated: the exact plane depth along each table pixel's ray, measured by the sensor model
    u = q / np.linalg.norm(q, axis=1, keepdims=True)
    t = (c0 @ n2) / (u @ n2)  # the ray u·t meets the plane n2·x = n2·c0
    exact = u * t[:, None]
    cos = np.abs(u @ n2)
    gen = {}
    for kind in ("realsense", "kinect"):
        model = SensorModel(kind=kind, k=1.0, fx=float(K[0, 0]))  # type: ignore[arg-type]
        noisy, keep = model.apply(exact, np.zeros(3), cos, rng)
        r = (noisy - c0) @ n2
        gen[kind] = {"bins": _per_bin(noisy[:, 2], r), "spacing_mm": _spacing_mm(noisy),
                     "kept": float(keep.mean())}
    return {"frame": path.parent.name + "/" + path.name, "fx": float(K[0, 0]), "real": real, "generated": gen,
            "plane_rms_mm": 1e3 * plane.residual_rms}


def _spacing_mm(p: np.ndarray) -> float:
    from efem_viz.geometry.knn import point_spacing

    return float(1e3 * np.median(point_spacing(p)))


def svg_plot(series: list[tuple[str, str, list[tuple[float, float]], bool]], path: Path, *, title: str) -> None:
    """A small line plot (noise in mm against depth in m) as SVG: (label, colour, points, dashed)."""
    w, h, ml, mb, mt, mr = 640, 400, 60, 50, 40, 190
    xs = [x for _, _, pts, _ in series for x, _ in pts] or [0.4, 1.6]
    ys = [y for _, _, pts, _ in series for _, y in pts] or [0, 1]
    x0, x1 = 0.4, max(1.3, max(xs) + 0.05)
    y0, y1 = 0.0, max(ys) * 1.1 + 0.1

    def px(x: float, y: float) -> tuple[float, float]:
        return ml + (x - x0) / (x1 - x0) * (w - ml - mr), h - mb - (y - y0) / (y1 - y0) * (h - mb - mt)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" '
           f'font-size="12"><rect width="{w}" height="{h}" fill="white"/>',
           f'<text x="{w / 2}" y="20" text-anchor="middle" font-size="14">{title}</text>']
    for k in range(6):
        y = y0 + k * (y1 - y0) / 5
        a, b = px(x0, y)
        out.append(f'<line x1="{ml}" y1="{b:.1f}" x2="{w - mr}" y2="{b:.1f}" stroke="#ddd"/>'
                   f'<text x="{ml - 6}" y="{b + 4:.1f}" text-anchor="end">{y:.1f}</text>')
    for xv in np.arange(0.4, x1 + 1e-9, 0.2):
        a, b = px(float(xv), y0)
        out.append(f'<text x="{a:.1f}" y="{h - mb + 18}" text-anchor="middle">{xv:.1f}</text>')
    out.append(f'<text x="{(ml + w - mr) / 2}" y="{h - 10}" text-anchor="middle">depth (m)</text>')
    out.append(f'<text x="16" y="{h / 2}" transform="rotate(-90 16 {h / 2})" text-anchor="middle">'
               f'noise across the table (mm, robust std)</text>')
    for i, (label, colour, pts, dashed) in enumerate(series):
        if pts:
            path_d = " ".join(f"{'M' if j == 0 else 'L'}{px(x, y)[0]:.1f},{px(x, y)[1]:.1f}"
                              for j, (x, y) in enumerate(pts))
            dash = ' stroke-dasharray="6,4"' if dashed else ""
            out.append(f'<path d="{path_d}" fill="none" stroke="{colour}" stroke-width="2"{dash}/>')
        ly = mt + 16 * i
        dash = ' stroke-dasharray="6,4"' if dashed else ""
        out.append(f'<line x1="{w - mr + 10}" y1="{ly}" x2="{w - mr + 34}" y2="{ly}" stroke="{colour}" '
                   f'stroke-width="2"{dash}/><text x="{w - mr + 40}" y="{ly + 4}">{label}</text>')
    out.append("</svg>")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(out) + "\n", encoding="utf-8")


def main() -> int:
    frames = sorted((DATA / "real_tabletop").glob("image_*.npz")) + [DATA / "pcl_tutorial_mug" / "frame.npz"]
    rows = []
    for f in frames:
        if not f.is_file():
            continue
        r = analyse_frame(f)
        rows.append(r)
        rb = ", ".join(f"{b['z']:.2f} m {b['noise_mm']:.1f}" for b in r["real"]["bins"])
        gb = ", ".join(f"{b['z']:.2f} m {b['noise_mm']:.1f}" for b in r["generated"]["realsense"]["bins"])
        print(f"{r['frame']}: real [{rb}] mm; generated RealSense [{gb}] mm; spacing real "
              f"{r['real']['spacing_mm']:.2f} / gen {r['generated']['realsense']['spacing_mm']:.2f} mm; flying "
              f"{100 * r['real']['flying']:.2f} %", flush=True)
    write_result(result_path("sensor_check"), rows)

    def pooled(getter: Any, subset: list[dict[str, Any]]) -> list[tuple[float, float]]:
        acc: dict[float, list[tuple[float, int]]] = {}
        for r in subset:
            for b in getter(r):
                acc.setdefault(b["z"], []).append((b["noise_mm"], b["n"]))
        return [(z, float(np.average([v for v, _ in vals], weights=[n for _, n in vals])))
                for z, vals in sorted(acc.items())]

    uois = [r for r in rows if "real_tabletop" in r["frame"]]
    pcl = [r for r in rows if "pcl" in r["frame"]]
    series = [("UOIS RealSense, real", "#d62728", pooled(lambda r: r["real"]["bins"], uois), False),
              ("  generated RealSense", "#d62728", pooled(lambda r: r["generated"]["realsense"]["bins"], uois), True),
              ("  generated Kinect", "#ff9896", pooled(lambda r: r["generated"]["kinect"]["bins"], uois), True),
              ("PCL stereo, real", "#1f77b4", pooled(lambda r: r["real"]["bins"], pcl), False),
              ("  generated RealSense", "#1f77b4", pooled(lambda r: r["generated"]["realsense"]["bins"], pcl), True),
              ("  generated Kinect", "#aec7e8", pooled(lambda r: r["generated"]["kinect"]["bins"], pcl), True)]
    svg_plot(series, ROOT / "docs" / "img" / "sensor_noise.svg",
             title="Depth noise on the table plane: real frames vs the sensor model")
    print("wrote docs/img/sensor_noise.svg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
