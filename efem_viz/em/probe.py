"""One proposal through the EM loop, with the solver's own code: the stability probe of real-scan work.

`track_proposal` starts one proposal from a given crop (an oracle crop: exactly one object's points; or an
anchor ball of radius ``r_init`` around a point, as real proposals start) and runs it through phase 1 of the
solver (`Solver._em_step`: M-step, encode, E-step in the r_err ball, annealing) for ``steps`` steps, then the
phase-end review (completed shape, pose, output mask). No other proposal competes and nothing is eliminated;
instead every step records what the elimination rule would see (inliers, SDF-band support, the size rule
`min_size_count` chooses) and how much of a labelled object the fit explains. ``bench/em_stability.py`` runs it
over single-view renders and real frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.em.config import EMConfig, resolve_for_prior
from efem_viz.em.decoding import PriorTable
from efem_viz.em.estep import schedule
from efem_viz.em.proposals import AvailableTree, Ragged, init_crops
from efem_viz.em.rules import size_counts

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.prior.config import ShapePriorLike


@dataclass
class ProposalTrack:
    """What happened to one proposal, step by step (index 0 = the first EM step)."""

    inliers: list[int] = field(default_factory=list)
    """Inlier count of the solver (|d| ≤ τ_D and normal angle ≤ τ_N) over the r_err ball."""
    band: list[int] = field(default_factory=list)
    """SDF-band support (|d| ≤ τ_D, normals ignored)."""
    size_count: list[int] = field(default_factory=list)
    """The count the "too small" rule compares with `min_size` under the config (`min_size_count`)."""
    min_size: list[float] = field(default_factory=list)
    """The threshold that count is compared with at each step (density-relative when configured)."""
    explained: list[float] = field(default_factory=list)
    """Fraction of the object's points that are inliers (0 without an object mask)."""
    explained_band: list[float] = field(default_factory=list)
    """Fraction of the object's points in the SDF band."""
    scale: list[float] = field(default_factory=list)
    """Θ_s after each encode."""
    center: list[np.ndarray] = field(default_factory=list)
    """Θ_c after each encode (world, m)."""
    output_iou: float = 0.0
    """IoU of the phase-end output mask (|d| < τ_out) with the object (0 without an object mask)."""
    output_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """Scene indices of the phase-end output mask."""

    @property
    def alive(self) -> bool:
        """The proposal passed the size rule at every step."""
        return all(c >= m for c, m in zip(self.size_count, self.min_size))


def oracle_crop(object_mask: np.ndarray) -> Ragged:
    """One crop holding exactly the object's points (weights 1)."""
    return Ragged.from_lists([np.flatnonzero(np.asarray(object_mask, bool))])


def track_proposal(scene: "Scene", prior: "ShapePriorLike", cfg: EMConfig, *, object_mask: np.ndarray | None,
                   start: str | int = "oracle", steps: int | None = None, seed: int = 0) -> ProposalTrack:
    """Run one proposal through phase 1 of the solver and review it.

    Args:
        scene: The scan.
        prior: Shape prior.
        cfg: Solver config (resolved for the prior here).
        object_mask: (N,) bool, the labelled object the proposal should explain (None: no object metrics).
        start: ``"oracle"`` (exactly ``object_mask``), or a scene point index: an anchor ball of
            ``cfg.proposals.r_init``.
        steps: Phase-1 steps (default ``cfg.steps.t1``).
        seed: Seed of the solver's generator.

    Returns:
        The `ProposalTrack`.
    """
    from efem_viz.em.solver import ProposalPool, Solver

    cfg = resolve_for_prior(cfg, prior)
    n_steps = int(steps if steps is not None else cfg.steps.t1)
    cfg = cfg.replace(steps={"t1": n_steps, "t2": 0})
    points = np.ascontiguousarray(scene.points, np.float32)
    normals = np.ascontiguousarray(scene.normals, np.float32)
    obj = None if object_mask is None else np.asarray(object_mask, bool)
    if hasattr(prior, "eval"):
        prior.eval()
    solver = Solver(scene.name, points, normals, PriorTable.of([prior]), cfg, [cfg], seed=seed, on_step=None,
                     cancel=None)
    available = np.ones(len(points), bool)
    tree = AvailableTree(points, available, crop=cfg.proposals.crop)
    if start == "oracle":
        if obj is None:
            raise ValueError("an oracle start needs object_mask")
        rag = oracle_crop(obj)
    else:
        anchor = np.zeros(len(points), bool)
        anchor[int(start)] = True
        _, rag = init_crops(points, available, 1, cfg.proposals.radii()[0], solver.rng, crop=cfg.proposals.crop,
                            tree=tree, anchor_mask=anchor)
    ids = solver.rec.birth(0, np.array([0], np.int64), *cfg.proposals.radii(), owner=np.zeros(1, np.int64))
    solver.rec.start_episode(np.zeros(0, np.int64), len(ids))
    pool = ProposalPool(ids=ids, rag=rag, w=np.ones(len(rag.idx), np.float32), owner=np.zeros(1, np.int64))
    track = ProposalTrack()
    n_obj = max(1, int(obj.sum())) if obj is not None else 1
    step = 0
    for t in range(n_steps):
        step = solver._em_step(pool, tree, 0, t, 1)
        assert pool.d is not None and pool.gamma is not None and pool.latent is not None
        assert pool.inliers is not None
        sched = schedule(cfg, t)
        idx = pool.rag.idx
        band = np.abs(pool.d) <= sched[1]
        inl = band & (pool.gamma <= sched[3])
        track.inliers.append(int(pool.inliers[0]))
        track.band.append(int(band.sum()))
        counts, thresholds = size_counts(cfg, pool.inliers, pool.d, pool.rag, solver.min_size, sched[1],
                                         spacing=solver.spacing)
        track.size_count.append(int(counts[0]))
        track.min_size.append(float(thresholds[0]))
        if obj is not None:
            track.explained.append(float(obj[idx[inl]].sum() / n_obj))
            track.explained_band.append(float(obj[idx[band]].sum() / n_obj))
        track.scale.append(float(pool.latent["scale"][0]))
        track.center.append(np.asarray(pool.latent["center"][0], np.float64).copy())
        solver.rec.end_step(pool.size, 0.0)
    records = solver._review(pool, tree, step, 1) if pool.size else {}
    rec = records.get(int(ids[0]))
    if rec is not None:
        mask = np.asarray(rec.mask, np.int64)
        track.output_mask = mask
        if obj is not None:
            pred = np.zeros(len(points), bool)
            pred[mask] = True
            track.output_iou = float((pred & obj).sum() / max(1, (pred | obj).sum()))
    return track
