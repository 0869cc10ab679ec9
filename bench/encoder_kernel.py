"""The encoder on the point sets of real solves: eager, with the fused kernels as they were, and as they are.

One solve of each scene (`bench/speed.py`'s scenes, presets and priors, seed 0) records every batch of point sets
the encoder gets; the batches are then replayed through the prior's encoder in each mode, alternating, `--repeats`
times each:

- ``eager``: no C++ kernels (``EFEM_VIZ_FUSED=0``): `torch.topk` k-NN, the Python farthest-point loop.
- ``fused_topk``: the fused edge kernels with `torch.topk` k-NN (`geometry.knn.knn_indices`), the Python
  farthest-point loop and the first layer's products in memory (`F.linear` twice, then the fused activation): the
  encoder of 2026-12-04.
- ``fused_topk_order``: the same with the one-pass k-NN selection, every row with equal distances decided in
  torch's order (the k-NN selection before duplicate points were recognised).
- ``fused_gram``: the same as ``fused`` but for the k-NN's Gram matrix, formed whole for the batch before the
  selection (the encoder of 2026-12-06).
- ``fused``: as the product runs it (`fused.knn`: its Gram rows a slab at a time, its duplicate rows; `fused.fps`,
  the first layer in one pass, `fused.lin_act_mean`).

Reported per scene and mode: the median seconds, milliseconds per point set, the ratio to ``eager``, to
``fused_topk``, to ``fused_topk_order`` and to ``fused_gram`` (those of the modes run), and whether the outputs
(Θ_R, Θ_inv, δ, Θ_s) equal ``fused_topk_order``'s bit for bit (``eager`` differs by float rounding: its largest
difference is given).

Usage: python -m bench.encoder_kernel [--scenes real_tabletop_0 z_7000] [--repeats 3] [--threads 1] [--tag NAME]
    [--prior PRIOR] [--modes fused_gram fused]
(``--prior``: solve and replay with this prior instead of the scene's own, e.g. a candidate's weights; ``--modes``:
a subset of the modes, ``fused_topk_order`` always among them as the reference.)
Writes bench/results/encoder_kernel/latest.json (encoder_kernel_<TAG>.json with --tag).
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any

# first: the OpenMP wait policy, before torch
from bench.common import kernels_or_say, machine, replay_parser, result_path, write_result

MODES = ("eager", "fused_topk", "fused_topk_order", "fused_gram", "fused")
"""Replay modes, the reference of the bit-for-bit comparison second."""


def record_batches(name: str, prior_spec: str | None = None) -> tuple[Any, list[Any]]:
    """One solve of the scene (with `prior_spec`, else the scene's own prior); the prior and every batch of point
    sets its encoder was given."""
    from efem_viz.em.config import preset
    from efem_viz.em.solver import run_em
    from efem_viz.prior.model import load_prior
    from bench.speed import load

    scene, pname, prior_name = load(name)
    prior = load_prior(prior_spec or prior_name)
    batches: list[Any] = []
    enc = prior.encoder
    plain = enc.forward

    def recording(x: Any) -> Any:
        batches.append(x.detach().clone())
        return plain(x)

    enc.forward = recording
    try:
        run_em(scene, prior, preset(pname), seed=0)
    finally:
        del enc.forward  # the class's forward again
    return prior, batches


def _knn_whole_gram(query: Any, ref: Any, k: int, *, duplicates: bool = True) -> Any:
    """`fused.knn` with the batch's whole Gram matrix formed first; without `duplicates` every tie row is decided in
    torch's order (the selection before duplicate points were recognised)."""
    import torch

    with torch.no_grad(), torch.autocast(query.device.type, enabled=False):
        q, r = query.detach(), ref.detach()
        gram = q @ r.transpose(1, 2)
        return torch.ops.efem_vn.knn_select(gram, (q * q).sum(-1), (r * r).sum(-1), int(k), r if duplicates else None)


def _knn_topk_order(query: Any, ref: Any, k: int) -> Any:
    """`_knn_whole_gram` with every tie row in torch's order."""
    return _knn_whole_gram(query, ref, k, duplicates=False)


def _first_layer_in_memory(x: Any, w_lin: Any, w_dir: Any, slope: float) -> Any:
    """The first layer as it was: both products in memory, then the fused activation and mean."""
    import torch
    import torch.nn.functional as F

    y = F.linear(x, w_lin)
    return torch.ops.efem_vn.act_mean(y, F.linear(y, w_dir), float(slope))


def replay(prior: Any, batches: list[Any], mode: str) -> tuple[float, list[Any]]:
    """Seconds to encode every recorded batch in a `MODES` mode, and the outputs."""
    import torch

    from efem_viz.geometry.fps import farthest_point_sample
    from efem_viz.geometry.knn import knn_indices
    from efem_viz.prior import fused

    knn, fps, first = fused.knn, fused.fps, fused.lin_act_mean
    os.environ["EFEM_VIZ_FUSED"] = "0" if mode == "eager" else "1"
    if mode in ("fused_topk", "fused_topk_order"):
        fused.knn = knn_indices if mode == "fused_topk" else _knn_topk_order  # type: ignore[assignment]
        fused.fps, fused.lin_act_mean = farthest_point_sample, _first_layer_in_memory  # type: ignore[assignment]
    elif mode == "fused_gram":
        fused.knn = _knn_whole_gram  # type: ignore[assignment]
    try:
        out = []
        t0 = time.perf_counter()
        with torch.no_grad():
            for x in batches:
                o = prior.encoder(x)
                out.append(torch.cat([o.R.flatten(1), o.inv, o.delta, o.scale[:, None]], dim=1))
        seconds = time.perf_counter() - t0
    finally:
        fused.knn, fused.fps, fused.lin_act_mean = knn, fps, first  # type: ignore[assignment]
        os.environ.pop("EFEM_VIZ_FUSED", None)
    return seconds, out


def main() -> int:
    ap = replay_parser(__doc__)
    ap.add_argument("--prior", default=None, help="solve and replay with this prior (default: the scene's own)")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    a = ap.parse_args()
    modes = [m for m in MODES if m in a.modes or m == "fused_topk_order"]
    if not kernels_or_say(a.threads):
        return 1
    import torch

    rows: dict[str, Any] = {}
    for name in a.scenes:
        prior, batches = record_batches(name, a.prior)
        sets = sum(int(x.shape[0]) for x in batches)
        times: dict[str, list[float]] = {m: [] for m in modes}
        results: dict[str, list[Any]] = {}
        for _ in range(a.repeats):
            for m in modes:
                sec, results[m] = replay(prior, batches, m)
                times[m].append(sec)
        med = {m: statistics.median(times[m]) for m in modes}
        ref = results["fused_topk_order"]
        row: dict[str, Any] = {"batches": len(batches), "point_sets": sets,
                               "points_per_set": sorted({int(x.shape[1]) for x in batches}), "modes": {}}
        for m in modes:
            same = all(torch.equal(e, f) for e, f in zip(ref, results[m]))
            diff = max(float((e - f).abs().max()) for e, f in zip(ref, results[m]))
            ratios = {f"ratio_to_{short}": (med[m] / med[base] if base in med else None)
                      for short, base in (("eager", "eager"), ("topk", "fused_topk"),
                                          ("topk_order", "fused_topk_order"), ("gram", "fused_gram"))}
            row["modes"][m] = {"seconds": med[m], "ms_per_set": 1e3 * med[m] / sets, **ratios,
                               "bitwise_equal_to_topk_order": same, "max_abs_diff_to_topk_order": diff,
                               "times": times[m]}
        rows[name] = row
        print(f"{name:>16}: {len(batches)} encoder calls, {sets} point sets of {row['points_per_set']} points",
              flush=True)
        for m, r in row["modes"].items():
            ratios = ", ".join(f"to {short.replace('_', ' ')} {r['ratio_to_' + short]:.2f}"
                               for short in ("eager", "topk", "topk_order", "gram") if r["ratio_to_" + short])
            print(f"{'':>18}{m:>16}: {r['seconds']:.2f} s, {r['ms_per_set']:.2f} ms a set, ratio {ratios}; "
                  + ("outputs bit for bit those of topk order" if r["bitwise_equal_to_topk_order"]
                     else f"largest output difference {r['max_abs_diff_to_topk_order']:.1e}"), flush=True)
    write_result(result_path("encoder_kernel", a.tag),
                 {"machine": machine(a.threads), "repeats": a.repeats, "prior": a.prior, "scenes": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
