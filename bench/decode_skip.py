"""How much of the E-step's decoding a Lipschitz bound could skip, and how often the bound would be wrong.

An E-step decodes the SDF of every (proposal, point) entry of the error balls, although only entries within the
SDF band (`normals_within`, the widest threshold any later test applies) change a result. A skip would decode one
representative per (proposal, grid cell) first and leave out every other entry of the cell whose bound
``|d(rep)| - L * |x - rep| / scale`` is above the band: with ``L`` at least the decoder's Lipschitz constant, such
an entry cannot be in the band.

This bench runs one solve of each scene (`bench/speed.py`'s scenes and presets), records the decode calls, and
for each cell size and ``L`` counts, over every E-step entry:

* `reps`: representatives decoded first (a share of the entries),
* `skipped`: entries the bound leaves out,
* `wrong`: skipped entries whose true |d| is within the band (each one would change a weight),
* `forward_evals`: decoder forward passes with the skip, as a share of today's (representatives plus the entries
  still decoded),
* the largest measured slope ``|d(x) - d(rep)| / |x - rep|`` between entries of a cell (the decoder's empirical
  Lipschitz constant in canonical units) and its 99.99th percentile.

Usage: python -m bench.decode_skip [--scenes real_tabletop_0 z_7000] [--cells 0.01 0.02 0.03] [--lipschitz 1.5 2]
       [--threads 1] [--tag NAME]
Writes bench/results/decode_skip/latest.json (decode_skip_<TAG>.json with --tag).
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from bench.common import result_path, write_result  # first: the OpenMP wait policy, before torch


def record_decodes(name: str, threads: int) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """One solve of the scene (its `bench/speed.py` preset and prior, seed 0); the scene points the E-steps
    decoded and every decode call's rows, scales, SDF values and band."""
    import torch

    from efem_viz.em import decoding
    from efem_viz.em.config import preset
    from efem_viz.em.solver import run_em
    from efem_viz.prior.model import load_prior
    from bench.speed import load

    torch.set_num_threads(threads)
    scene, pname, prior_name = load(name)
    prior = load_prior(prior_name)
    calls: list[dict[str, Any]] = []
    points: list[np.ndarray] = []
    plain = decoding.decode_rows

    def recording(pr: Any, latent: Any, rag: Any, pts: np.ndarray, nrm: np.ndarray, **kw: Any) -> Any:
        d, g = plain(pr, latent, rag, pts, nrm, **kw)
        band = kw.get("normals_within")
        if isinstance(latent, dict) and band is not None and band > 0:  # the E-steps (reviews decode full scans)
            if not points:
                points.append(np.asarray(pts, np.float64).copy())
            if len(pts) == len(points[0]):
                calls.append({"idx": rag.idx.copy(), "row": rag.row.copy(), "d": d.copy(), "band": float(band),
                              "scale": np.asarray(latent["scale"], np.float64).reshape(-1)})
        return d, g

    decoding.decode_rows = recording
    try:
        run_em(scene, prior, preset(pname), seed=0)
    finally:
        decoding.decode_rows = plain
    return points[0], calls


def skip_counts(points: np.ndarray, calls: list[dict[str, Any]], cell: float, lipschitz: float) -> dict[str, float]:
    """The counts above for one cell size (m) and Lipschitz constant, over every recorded call."""
    ids = np.unique(np.floor(points / cell).astype(np.int64), axis=0, return_inverse=True)[1].reshape(-1)
    n_cells = int(ids.max()) + 1
    total = reps = skipped = wrong = evals = 0
    slope_max, slope_hi = 0.0, 0.0
    for c in calls:
        idx, row, d, band = c["idx"], c["row"], c["d"], c["band"]
        key = row.astype(np.int64) * n_cells + ids[idx]
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
        rep = first[inv]
        dist = np.linalg.norm(points[idx] - points[idx[rep]], axis=1) / c["scale"][row]
        skip = (np.abs(d[rep]) - lipschitz * dist > band) & (np.arange(len(idx)) != rep)
        is_rep = np.zeros(len(idx), bool)
        is_rep[first] = True
        total += len(idx)
        reps += len(first)
        skipped += int(skip.sum())
        wrong += int((skip & (np.abs(d) <= band)).sum())
        evals += len(first) + int((~skip & ~(is_rep & (np.abs(d) > band))).sum())  # band reps decode again
        apart = dist > 1e-6
        if apart.any():
            slope = np.abs(d[apart] - d[rep][apart]) / dist[apart]
            slope_max = max(slope_max, float(slope.max()))
            slope_hi = max(slope_hi, float(np.quantile(slope, 0.9999)))
    return {"cell_m": cell, "lipschitz": lipschitz, "entries": total, "reps": reps / total,
            "skipped": skipped / total, "wrong": wrong, "forward_evals": evals / total,
            "slope_max": slope_max, "slope_p9999": slope_hi}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["real_tabletop_0", "z_7000"])
    ap.add_argument("--cells", type=float, nargs="+", default=[0.01, 0.02, 0.03], help="grid cell sizes, m")
    ap.add_argument("--lipschitz", type=float, nargs="+", default=[1.5, 2.0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default=None)
    a = ap.parse_args()
    from bench.common import machine

    rows: list[dict[str, Any]] = []
    for name in a.scenes:
        points, calls = record_decodes(name, a.threads)
        in_band = sum(int((np.abs(c["d"]) <= c["band"]).sum()) for c in calls)
        n = sum(len(c["d"]) for c in calls)
        print(f"{name}: {n / 1e6:.2f} M E-step entries, {100 * in_band / n:.0f} % in the band", flush=True)
        for cell in a.cells:
            for lip in a.lipschitz:
                r = {"scene": name, "in_band": in_band / n, **skip_counts(points, calls, cell, lip)}
                rows.append(r)
                print(f"  cell {1000 * cell:.0f} mm, L {lip:g}: reps {100 * r['reps']:.1f} %, skipped "
                      f"{100 * r['skipped']:.1f} %, wrong {r['wrong']}, forward passes {100 * r['forward_evals']:.0f} "
                      f"% of today's; slope max {r['slope_max']:.2f} (99.99 % {r['slope_p9999']:.2f})", flush=True)
    write_result(result_path("decode_skip", a.tag), {"machine": machine(a.threads), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
