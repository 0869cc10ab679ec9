"""Output masks at another SDF threshold, re-derived from a saved run.

docs/design/efem-method.md §3.9.12 takes a point into an instance's output mask when |d| < τ_out (0.04 canonical units
for mugs). That value fits the authors' prior, whose decoded surfaces lie within a few millimetres of the
scan. A prior with blurrier surfaces (ours, trained on two CPU cores) leaves true object points outside
that band, so masks come out too small and AP at IoU ≥ 0.5 suffers while the objects are found. τ_out is
therefore a property of the prior: `efem-viz calibrate-masks` picks it on labelled *tuning* scenes (AP over
IoU 0.50:0.95 of the re-thresholded masks; every other output of the run is unchanged) and stores it in the
prior file's metadata, and `run_em` uses it whenever the config leaves `tau_out` unset. A prior without the
key (a converted release checkpoint) keeps the spec's 0.04. The calibration needs ground truth and AP, so it is
`efem_viz.eval.calibrate`; this module is the re-thresholding it builds on.

Re-thresholding decodes each accepted instance's final latent over its E-step neighbourhood (radius
r_err around Θ_c, the points available in its episode, at full resolution), exactly as the last review did,
so the mask at the run's own τ_out is the one the run produced.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.prior.config import MAX_TAU_OUT

if TYPE_CHECKING:
    from efem_viz.prior.config import PriorArg
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class InstanceDistances:
    """Decoded SDF of every accepted instance over its final neighbourhood.

    Attributes:
        idx: K arrays of scene-point indices (the neighbourhood of instance k).
        d: K arrays of canonical SDF values, aligned with `idx`.
        gamma: K arrays of normal angles (degrees; 180 where not computed), aligned with `idx`.
    """

    idx: list[np.ndarray]
    d: list[np.ndarray]
    gamma: list[np.ndarray]

    def masks(self, tau_out: float, gamma_out: float = 180.0) -> list[np.ndarray]:
        """Output masks (int32 scene indices) at |d| < tau_out (and γ < gamma_out when below 180°)."""
        out = []
        for idx, d, g in zip(self.idx, self.d, self.gamma, strict=True):
            keep = np.abs(d) < tau_out
            if gamma_out < 180.0:
                keep &= g < gamma_out
            out.append(idx[keep].astype(np.int32))
        return out


def instance_distances(result: "EMResult", scene: "Scene", prior: "PriorArg", *,
                       normals_within: float | None = None) -> InstanceDistances:
    """Decode the final latent of every accepted instance of `result` over its neighbourhood in `scene`.

    Args:
        result: a finished run (`run_em` or `EMResult.load`).
        scene: the scene it ran on (same number of points).
        prior: the prior it ran with, or the list of priors of a multi-prior run (in the run's order).
        normals_within: compute normal angles for entries with |d| ≤ this (None: only when the run's config
            gates masks by normals, then up to the largest accepted τ_out).

    Raises:
        ValueError: the scene does not match the result, or the priors do not match the run.
    """
    from efem_viz.em.decoding import PriorTable, decode_owned_rows
    from efem_viz.em.proposals import AvailableTree, Ragged

    if scene.num_points != result.num_points:
        raise ValueError(f"result {result.scene_name!r} was computed on {result.num_points} points but scene "
                         f"{scene.name!r} has {scene.num_points}")
    inst, trace, cfg = result.instances, result.trace, result.config
    if len(inst) == 0:
        return InstanceDistances([], [], [])
    if normals_within is None:
        normals_within = MAX_TAU_OUT if cfg.output.gamma_out < 180.0 else -1.0
    points = np.ascontiguousarray(scene.points, np.float32)
    normals = np.ascontiguousarray(scene.normals, np.float32)
    lats = [trace.latent(int(pid), trace.last_step(int(pid))) for pid in inst.ids]
    episodes = trace.prop_episode[np.asarray(inst.ids, np.int64)]
    balls: list[np.ndarray] = [np.zeros(0, np.int64)] * len(inst)
    for ep in np.unique(episodes):  # neighbourhoods among the points available in each instance's episode
        tree = AvailableTree(points, trace.available_mask(int(ep)), crop=cfg.proposals.crop)
        ks = np.flatnonzero(episodes == ep)
        nb = tree.query(np.stack([np.asarray(lats[k]["center"], np.float64) for k in ks]), cfg.proposals.radii()[1])
        for j, k in enumerate(ks):
            balls[k] = nb.idx[nb.row_slice(j)]
    rag = Ragged.from_lists(balls)
    lat_all = {key: np.stack([np.asarray(x[key]) for x in lats]) for key in lats[0]}
    table = PriorTable.of(prior)
    if len(table) != max(1, len(trace.prior_names)):
        raise ValueError(f"the run used {max(1, len(trace.prior_names))} prior(s), got {len(table)}")
    owner = np.array([trace.prior_index(int(pid)) for pid in inst.ids], np.int64)
    d, g = decode_owned_rows(table, owner, lat_all, rag, points, normals, chunk=cfg.compute.decode_chunk,
                             normals_within=normals_within)
    split = rag.offsets[1:-1]
    return InstanceDistances(list(np.split(rag.idx, split)), list(np.split(d, split)), list(np.split(g, split)))
