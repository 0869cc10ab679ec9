"""The EFEM solver: proposals → EM steps (independent, then joint) → reviews → accepted instances.

Reference: docs/design/efem-method.md §3 (efem-viz is +Z up). One prior or several: with several priors (one per
category) every prior starts `n_init` proposals per episode and all of them share one pool, so the joint
phase's competition for points, the duplicate and the inclusion rules act across categories; each proposal is
encoded, decoded, meshed and reviewed with its own prior and its category's settings (sizes, up range, τ_out).
Batched over proposals: one decoder pass per step over the
error balls of all live proposals at once (rows of similar size padded into batches, see `decode_rows`),
encoder calls in chunks of `cfg.compute.encode_batch` proposals, eliminations on sparse P×N sets. A dead proposal
costs nothing after its death. Randomness: one NumPy Generator seeded from `seed` draws anchors, Bernoulli masks and all
categorical draws (on the CPU), so a run is reproducible on any device; the network itself is deterministic.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from efem_viz.em.config import CATEGORY_LOOK_ALIKE, EMConfig, resolve_for_prior
from efem_viz.em.decoding import (
    LatentArrays,
    PriorTable,
    decode_owned_rows,
    encode_rows,
    matmul_precision,
    mesh_of_latent,
    prior_device,
)
from efem_viz.em.estep import energy_weights, normals_threshold, schedule, stationary_score
from efem_viz.em.look_alike import LookAlikeModel, load_model, review_features
from efem_viz.em.replay import TraceReplay
from efem_viz.em.proposals import AvailableTree, Ragged, init_crops, sample_independent, sample_joint
from efem_viz.em.rules import (
    REASON_SURVIVE,
    REVIEW_RULES,
    STEP_RULES,
    ReviewRecord,
    ReviewRule,
    StepContext,
    StepRule,
    apply_step_rules,
    capped_confidence,
    explained_decay,
    first_failed_review,
    reason_names,
    size_passes,
    up_passes,
)
from efem_viz.em.trace import TraceRecorder
from efem_viz.geometry.normals import planar_share

if TYPE_CHECKING:
    import trimesh

    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult
    from efem_viz.geometry.camera import Camera, FreeSpace
    from efem_viz.prior.config import ShapePriorLike

logger = logging.getLogger(__name__)

STAGES: tuple[str, ...] = (
    "m_step", "encode", "neighbourhood", "decode", "score", "eliminate", "review_mesh", "review_pose",
    "review_coverage", "accept",
)


PROGRESSIVE_EVERY_S = 1.0
"""Seconds between two shown states of a running EFEM in the viewer's Run and the annotator's EFEM run (the first
step is always shown, the finished result replaces the last)."""


BELOW_SUPPORT_M = 0.1
BELOW_SUPPORT_SHARE = 0.1
"""A scan with more than this share of its points over `BELOW_SUPPORT_M` below z = 0 does not stand on a support
plane at z = 0 (a room scan with its origin at the sensor): `proposals.min_point_height` is not applied to it."""


def eligible_points(points: np.ndarray, min_height: float | None, name: str = "scene") -> np.ndarray:
    """Which points may join a proposal: those at least ``min_height`` above the support plane at z = 0
    (`ProposalSettings.min_point_height`; None: all). A scan whose support plane is not at z = 0 (`BELOW_SUPPORT_*`)
    keeps every point, with a warning: cutting at z = 0 there would remove whole objects, not a floor."""
    every = np.ones(len(points), bool)
    if min_height is None or not len(points):
        return every
    z = np.asarray(points[:, 2], np.float64)
    below = float(np.mean(z < -BELOW_SUPPORT_M))
    if below > BELOW_SUPPORT_SHARE:
        logger.warning("%s: %.0f %% of its points lie more than %g cm below z = 0, so z = 0 is not its support plane; "
                       "the points low above it are not kept out (min_point_height). Bring the scan in with "
                       "`efem-viz import-scan` to put its floor at z = 0.", name, 100 * below, 100 * BELOW_SUPPORT_M)
        return every
    return z >= float(min_height)


class EMCancelled(RuntimeError):
    """Raised by `run_em` when its `cancel` event is set."""


@dataclass(frozen=True)
class StepInfo:
    """Progress report passed to `on_step` after every EM step."""

    step: int
    """Global step index (0-based, over all episodes); −1 for the first report of a run, when its first proposals
    are drawn and no step is done yet (`partial()` then holds their anchors and no step)."""
    num_steps: int
    """Planned number of steps (episodes × (t1 + t2)); a run may end earlier when every proposal died."""
    phase: int
    """1 = independent, 2 = joint."""
    active: int
    """Live proposals after this step's eliminations (and review)."""
    elapsed_s: float
    """Seconds since `run_em` started."""
    episode: int = 0
    """Episode of this step."""
    @property
    def time_left_s(self) -> float | None:
        """Seconds left by the mean step time so far (an upper estimate: later steps hold fewer proposals); None
        after the last step."""
        done = self.step + 1
        if done <= 0 or done >= self.num_steps:
            return None
        return self.elapsed_s / done * (self.num_steps - done)

    def status(self) -> str:
        """The progress words every front end shows after its own "step k of N": the phase, the proposals alive,
        the seconds so far and the time left, e.g. "phase 1 · 178 proposals alive · 12 s · about 30 s left"."""
        left = self.time_left_s
        return (f"phase {self.phase} · {self.active} proposals alive · {self.elapsed_s:.0f} s"
                + ("" if left is None else f" · about {left:.0f} s left"))

    partial: "Callable[[], EMResult] | None" = field(default=None, repr=False, compare=False)
    """The run so far as an `EMResult` (its trace up to this step, the instances accepted so far), built when
    called, in the solver's thread (a viewer shows runs as they go; the batch never calls it)."""


def confidence(stationary: float, coverage: float, *, cap: float = 0.4, seen_through: float = float("nan"),
               pose: float = float("nan"), pose_weight: float = 0.0, pose_ref: float = 0.6) -> float:
    """Final confidence of an accepted proposal: s_stat · min(coverage, cap) / cap (docs/design/efem-method.md §3.10),
    times (1 − seen-through fraction) when the free-space check measured one (`EMConfig.free_space.margin`), times
    min(1, pose score / `pose_ref`)^`pose_weight` when the codebook gave a pose score
    (`EMConfig.confidence.pose_weight`)."""
    conf = float(capped_confidence(float(stationary), float(coverage), cap))
    st = float(seen_through)
    if math.isfinite(st):
        conf *= 1.0 - min(max(st, 0.0), 1.0)
    if pose_weight > 0 and math.isfinite(float(pose)):
        conf *= min(max(float(pose), 0.0) / pose_ref, 1.0) ** pose_weight
    return conf


def working_set(points: np.ndarray, voxel: float | None) -> np.ndarray:
    """Indices of the points EM iterates on: one point per `voxel`-sized cell (the first in index order), or
    every point when `voxel` is None/0. Sorted increasingly.

    Args:
        points: (N, 3) float32 world points.
        voxel: cell size (m) or None.

    Returns:
        (N_w,) int64 indices into `points`.
    """
    n = len(points)
    if not voxel:
        return np.arange(n, dtype=np.int64)
    keys = np.floor(np.asarray(points, np.float64) / float(voxel)).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, first = np.unique(flat, return_index=True)
    return np.sort(first).astype(np.int64)


# ---------------------------------------------------------------------------------------------- pool state
@dataclass
class ProposalPool:
    """Live proposals of an episode, rows in increasing id order."""

    ids: np.ndarray  # (P,) int64
    rag: Ragged  # supports of the current weights
    w: np.ndarray  # (K,) float32 weights (W_out of the last step; crop mask at t = 0)
    owner: np.ndarray  # (P,) int64 prior of each row
    d: np.ndarray | None = None  # (K,) last E-step SDF over rag
    gamma: np.ndarray | None = None  # (K,) last E-step normal angles
    latent: LatentArrays | None = None
    stationary: np.ndarray | None = None  # (P,)
    inliers: np.ndarray | None = None  # (P,)
    scale_max: np.ndarray | None = None  # (P,) largest Θ_s so far (EMConfig.elimination.trust_scale)
    coverage: np.ndarray | None = None  # (P,) coverage of the last review (elimination.inclusion_by = "confidence")
    small_streak: np.ndarray | None = None  # (P,) steps in a row under the "too small" threshold (min_size_patience)
    recent: np.ndarray | None = None  # (P, m) the last m stationary scores, newest last, NaN before (score_memory)

    @property
    def size(self) -> int:
        return int(len(self.ids))

    def keep(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, np.int64)
        self.rag, pos = self.rag.take_rows(rows)
        self.ids = self.ids[rows]
        self.owner = self.owner[rows]
        self.w = self.w[pos]
        if self.d is not None:
            self.d = self.d[pos]
        if self.gamma is not None:
            self.gamma = self.gamma[pos]
        if self.latent is not None:
            self.latent = {k: v[rows] for k, v in self.latent.items()}
        if self.stationary is not None:
            self.stationary = self.stationary[rows]
        if self.inliers is not None:
            self.inliers = self.inliers[rows]
        if self.scale_max is not None:
            self.scale_max = self.scale_max[rows]
        if self.coverage is not None:
            self.coverage = self.coverage[rows]
        if self.small_streak is not None:
            self.small_streak = self.small_streak[rows]
        if self.recent is not None:
            self.recent = self.recent[rows]

    def remember(self, stationary: np.ndarray, memory: int) -> np.ndarray | None:
        """Add this step's stationary scores to the rows' last `memory` (`EliminationSettings.score_memory`) and
        return each row's best of them; None for a memory of 1 (this step's scores are the ones compared)."""
        if memory <= 1:
            return None
        fresh = np.full((self.size, memory), np.nan)
        if self.recent is not None:
            keep = min(memory - 1, self.recent.shape[1])
            if keep:
                fresh[:, -1 - keep:-1] = self.recent[:, -keep:]
        fresh[:, -1] = stationary
        self.recent = fresh
        return np.nanmax(fresh, axis=1)


class _Timer:
    def __init__(self) -> None:
        self.t: dict[str, float] = {k: 0.0 for k in STAGES}

    def add(self, key: str, t0: float) -> float:
        now = time.perf_counter()
        self.t[key] = self.t.get(key, 0.0) + now - t0
        return now


# ---------------------------------------------------------------------------------------------- main entry
def run_em(
    scene: "Scene",
    prior: "ShapePriorLike | None" = None,
    cfg: EMConfig | None = None,
    *,
    priors: "Sequence[ShapePriorLike] | None" = None,
    seed: int = 0,
    device: str = "cpu",
    on_step: Callable[[StepInfo], None] | None = None,
    cancel: threading.Event | None = None,
    anchor_candidates: np.ndarray | None = None,
    step_rules: Sequence[StepRule] = STEP_RULES,
    review_rules: Sequence[ReviewRule] = REVIEW_RULES,
) -> "EMResult":
    """Segment a scene with EFEM (docs/design/efem-method.md §3) and record the full trace.

    Args:
        scene: the scan (points (N,3) float32 world metres, +Z up, unit normals).
        prior: a shape prior (`ShapePriorLike`: `ShapePrior`, the analytic sphere prior, ...). It is moved to
            `device` if needed. Give `prior` or `priors`, not both.
        cfg: solver config (default `preset("synthetic")`). Fields left None (τ_out, size ranges, up range) are
            taken from each prior's category settings for `cfg.domain`.
        priors: several priors, one per category: a joint solve (see the module docstring). Their category
            names must differ; instances carry the category of the prior that found them.
        seed: seeds the NumPy generator of every random draw.
        device: "cpu" or "cuda" (or a torch device string).
        on_step: called with a `StepInfo` after every step.
        cancel: when set, the run stops at the next check and raises `EMCancelled`.
        anchor_candidates: optional (K,) int scene point indices: the first episode draws its proposal anchors
            only among these (with replacement; on a thinned working set, among the kept points nearest to
            them), e.g. the points around a click for click-to-segment. Crops, E-steps and later episodes still
            use the whole scene. None = every point (the method as specified).
        step_rules: the per-step elimination rules, in order (default the method's, `rules.STEP_RULES`).
        review_rules: the review checks, in order (default `rules.REVIEW_RULES`).

    Returns:
        EMResult with trace, instances, config (resolved for the prior; with several priors the shared config,
        τ_out the largest of theirs, and the per-prior settings in `categories`) and `timings`: wall seconds
        per stage (`STAGES`), `total` (wall), `total_cpu` (process CPU time, all threads), and the counts
        `decoder_queries`, `normal_queries` (the gradient subset) and `encoded_sets`.

    Raises:
        ValueError: bad config, a scene without points, a prior without the needed methods, or both / neither of
            `prior` and `priors`.
        EMCancelled: `cancel` was set.
    """
    from efem_viz.em.config import preset
    from efem_viz.prior.config import prior_category

    plist = _solve_priors(prior, priors)
    cats = [prior_category(pr) for pr in plist]
    names = [c.name for c in cats]
    if len(set(names)) != len(names):
        raise ValueError(f"the priors of one solve need distinct category names, got {names}")
    base = cfg if cfg is not None else preset("synthetic")
    cfgs = [resolve_for_prior(base, pr) for pr in plist]
    if getattr(scene, "faces", None) is None and base.review.max_planar is None:
        # a category's planar check reads a mesh's surface normals; a point cloud's estimated normals gather in a
        # few directions (true fits on merged-points kitchen piles held 0.41-0.53): not checked, only recorded
        cfgs = [c.replace(review={"max_planar": None}) for c in cfgs]
    # a joint solve shares one crop and neighbourhood: the widest of its priors' (a narrower one only costs time);
    # and one ranking: the weakest explained-share decay of its priors'
    run_cfg = cfgs[0] if len(plist) == 1 else base.replace(
        output={"tau_out": max(c.output.out_tau for c in cfgs)},
        confidence={"explained_decay": min(c.confidence.explained_decay or 0.0 for c in cfgs)},
        proposals={"r_init": max(c.proposals.radii()[0] for c in cfgs),
                   "r_err": max(c.proposals.radii()[1] for c in cfgs)})
    points, normals = _scene_arrays(scene)
    if anchor_candidates is not None:
        anchor_candidates = _checked_anchor_candidates(anchor_candidates, len(points))
    was_training = []
    for pr in plist:
        _move_prior(pr, device)
        was_training.append(getattr(pr, "training", False))
        if hasattr(pr, "eval"):
            pr.eval()
    try:
        cameras, warnings = _capture_cameras(scene) if run_cfg.free_space.margin is not None else ([], [])
        solver = Solver(scene.name, points, normals, PriorTable.of(plist), run_cfg, cfgs, seed=seed,
                         on_step=on_step, cancel=cancel, anchor_candidates=anchor_candidates,
                         step_rules=step_rules, review_rules=review_rules, cameras=cameras)
        solver.partial_result = lambda: _result_of(solver, scene, plist, run_cfg, cats, cfgs, seed, warnings)
        solver.run()
    finally:
        for pr, was in zip(plist, was_training):
            if was and hasattr(pr, "train"):
                pr.train(True)
    result = _result_of(solver, scene, plist, run_cfg, cats, cfgs, seed, warnings)
    logger.info(
        "%s: %d instances, %d steps, %.1f s (%s)",
        scene.name, len(result.instances), result.trace.num_steps, result.timings["total"],
        ", ".join(f"{k} {v:.1f}" for k, v in result.timings.items() if k in STAGES and v > 0.05),
    )
    return result


def _result_of(solver: Solver, scene: "Scene", plist: list[Any], run_cfg: EMConfig, cats: list[Any],
                    cfgs: list[EMConfig], seed: int, warnings: list[str]) -> "EMResult":
    """The run so far as an `EMResult` (the finished run's too): the trace of the steps done, the instances
    accepted so far, the timings and counts."""
    from efem_viz.em.results import EMResult, Instances

    timings = dict(solver.timer.t) | {
        "total": time.perf_counter() - solver.t_start, "total_cpu": time.process_time() - solver.cpu_start,
        "decoder_queries": float(solver.n_queries), "encoded_sets": float(solver.n_encoded),
        "normal_queries": float(solver.stats["normal_queries"])}
    trace = solver.rec.finish(timings)
    categories = tuple(c.replace(tau_out=k.output.out_tau) for c, k in zip(cats, cfgs))
    return EMResult(trace=trace, instances=Instances.from_rows(list(solver.accepted)), config=run_cfg,
                    timings=timings, scene_name=scene.name, num_points=len(solver.full_points), seed=int(seed),
                    categories=categories, warnings=tuple(warnings),
                    replay=TraceReplay(trace, scene, plist[0] if len(plist) == 1 else plist))


def _solve_priors(prior: ShapePriorLike | None, priors: Sequence[ShapePriorLike] | None) -> list[ShapePriorLike]:
    """The priors of a solve: `prior` alone or the list `priors` (exactly one of them given), each with the
    methods the solver calls.

    Raises:
        ValueError: both or neither given, an empty list, a prior without `encode`, `sdf_and_normals` or `sdf`.
    """
    if (prior is None) == (priors is None):
        raise ValueError("give run_em one prior (prior=...) or a list of priors (priors=[...]), not both")
    plist = [prior] if prior is not None else list(priors or [])
    if not plist:
        raise ValueError("priors must not be empty")
    for pr in plist:
        for meth in ("encode", "sdf_and_normals", "sdf"):
            if not callable(getattr(pr, meth, None)):
                raise ValueError(f"prior {type(pr).__name__} has no {meth}() method")
    return plist


def _scene_arrays(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's (N, 3) float32 points and normals, contiguous, checked.

    Raises:
        ValueError: no points, not (N, 3), or normals of another shape.
    """
    points = np.ascontiguousarray(scene.points, np.float32)
    normals = np.ascontiguousarray(scene.normals, np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"scene points must be a non-empty (N, 3) array, got {points.shape}")
    if normals.shape != points.shape:
        raise ValueError(f"scene normals {normals.shape} do not match points {points.shape}")
    return points, normals


def _checked_anchor_candidates(anchor_candidates: np.ndarray, n_points: int) -> np.ndarray:
    """`run_em`'s `anchor_candidates` as an array, checked: a non-empty (K,) integer array of point indices.

    Raises:
        ValueError: another shape or dtype, or an index outside [0, n_points).
    """
    anchor_candidates = np.asarray(anchor_candidates)
    if anchor_candidates.ndim != 1 or len(anchor_candidates) == 0 or anchor_candidates.dtype.kind not in "iu":
        raise ValueError(f"anchor_candidates must be a non-empty (K,) integer array, got "
                         f"{anchor_candidates.dtype} {anchor_candidates.shape}")
    if anchor_candidates.min() < 0 or anchor_candidates.max() >= n_points:
        raise ValueError(f"anchor_candidates must index the scene's {n_points} points, got range "
                         f"[{anchor_candidates.min()}, {anchor_candidates.max()}]")
    return anchor_candidates


def _capture_cameras(scene: Scene) -> tuple[list[Camera], list[str]]:
    """Every camera recorded in the scene's provenance (a frame's capture camera, a fused scan's cameras:
    `Camera.parse_all`), for the free-space check, and the run's warning when recorded ones are unusable (never
    silently off: the CLI log, the result and the viewer say it)."""
    from efem_viz.geometry.camera import Camera

    warnings: list[str] = []
    cameras, problems = Camera.parse_all(getattr(scene, "provenance", None))
    if problems and not cameras:
        what = "the recorded capture camera is" if len(problems) == 1 else "the recorded cameras are"
        warnings.append(f"{what} unusable ({problems[0]}{'; ...' if len(problems) > 1 else ''}): the free-space "
                        "check is off for this run")
    elif problems:
        warnings.append(f"{len(problems)} of the recorded cameras unusable ({problems[0]}"
                        f"{'; ...' if len(problems) > 1 else ''}): the free-space check uses the other "
                        f"{len(cameras)}")
    for w in warnings:
        logger.warning("%s: %s", scene.name, w)
    return cameras, warnings


def _move_prior(prior: Any, device: str) -> None:
    import torch

    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available")
    cur = prior_device(prior)
    if hasattr(prior, "to") and torch.device(cur).type != dev.type:
        prior.to(dev)


class Solver:
    def __init__(
        self,
        name: str,
        points: np.ndarray,
        normals: np.ndarray,
        table: PriorTable,
        cfg: EMConfig,
        cfgs: list[EMConfig],
        *,
        seed: int,
        on_step: Callable[[StepInfo], None] | None,
        cancel: threading.Event | None,
        anchor_candidates: np.ndarray | None = None,
        step_rules: Sequence[StepRule] = STEP_RULES,
        review_rules: Sequence[ReviewRule] = REVIEW_RULES,
        cameras: Sequence[Camera] = (),
    ) -> None:
        self.name = name
        self.full_points = points
        self.full_normals = normals
        self.n_full = len(points)
        self.work_idx = working_set(points, cfg.compute.work_voxel)
        self.identity = len(self.work_idx) == self.n_full
        self.points = points[self.work_idx] if not self.identity else points
        self.normals = normals[self.work_idx] if not self.identity else normals
        self.n = len(self.points)
        self.anchor_mask: np.ndarray | None = None
        if anchor_candidates is not None:
            self.anchor_mask = self._anchor_mask(points, anchor_candidates)
        # min_size is defined at the scene's resolution; on a thinned working set it scales with the density
        self.min_size = max(1, int(round(cfg.elimination.min_size * self.n / self.n_full)))
        self.table = table
        self.cfg = cfg  # shared settings (with several priors: τ_out = the largest, used for decode bounds)
        self.cfgs = cfgs  # per prior: the category's sizes, up range and τ_out filled in
        self.patience = np.array([c.elimination.min_size_patience or 1 for c in cfgs], np.int64)
        """Per prior: steps in a row its proposals may be too small before they die."""
        self.step_rules = tuple(step_rules)
        self.review_rules = tuple(review_rules)
        self.rng = np.random.default_rng(seed)
        self.seed = int(seed)
        self.on_step = on_step
        self.cancel = cancel
        self.m = int(cfg.compute.n_pcl or max(_n_pcl(p) for p in table.priors))
        self._spacing: np.ndarray | None = None
        prior_names = tuple(c.name for c in (_category(p) for p in table.priors))
        self.rec = TraceRecorder(cfg, self.n_full, work_idx=self.work_idx, work_min_size=self.min_size,
                                 reasons=reason_names(self.step_rules, self.review_rules),
                                 prior_names=prior_names)
        self.categories = prior_names
        self.pose_votes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        """Proposal id -> the codebook rows its last review's pose search retrieved and how well each aligned
        (`_pose`; a family prior's class, `_category`)."""
        self.timer = _Timer()
        self.t_start = time.perf_counter()
        self.cpu_start = time.process_time()
        self.n_queries = 0
        self.n_encoded = 0
        self.stats: dict[str, float] = {"normal_queries": 0.0}
        self.free_space: FreeSpace | None = None
        """What the recorded cameras saw empty (`EMConfig.free_space.margin`); None: no check."""
        if len(cameras) and cfg.free_space.margin is not None:
            from efem_viz.geometry.camera import FreeSpace

            self.free_space = FreeSpace.of_points(list(cameras), points, lateral=cfg.free_space.lateral,
                                                  edge=cfg.free_space.edge)
        self.planned_steps = cfg.proposals.num_episodes * cfg.steps.per_episode
        self.accepted: list[dict[str, Any]] = []
        """The instances' rows accepted so far (the end of each episode adds its survivors)."""
        self.partial_result: Callable[[], EMResult] | None = None
        """Builds the run so far as an `EMResult` (`StepInfo.partial`); set by `run_em`."""
        self.ref_scales = [float(cb.mean_scale) if (cb := getattr(p, "codebook", None)) is not None else 1.0
                           for p in table.priors]
        if not self.identity and cfg.compute.work_voxel:  # a thinned working set implies work_voxel > 0
            logger.info("%s: EM on a %.1f mm working set of %d of %d points (min_size %d -> %d)", name,
                        cfg.compute.work_voxel * 1000, self.n, self.n_full, cfg.elimination.min_size, self.min_size)

    @property
    def spacing(self) -> np.ndarray | None:
        """Nearest-neighbour spacing of the working set (computed once, only for `cfg.elimination.min_size_spacing`)."""
        if self.cfg.elimination.min_size_spacing is None:
            return None
        if self._spacing is None:
            from efem_viz.geometry.knn import point_spacing

            self._spacing = point_spacing(self.points)
        return self._spacing

    def _anchor_mask(self, points: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """(n,) bool over the working set: the candidates, or (thinned set) the kept point nearest to each."""
        if self.identity:
            mask = np.zeros(self.n, bool)
            mask[candidates] = True
            return mask
        from efem_viz._typeshims import cKDTree

        _, near = cKDTree(self.points).query(points[candidates])
        mask = np.zeros(self.n, bool)
        mask[np.asarray(near, np.int64)] = True
        return mask

    def _episode_anchor_mask(self, ep: int, available: np.ndarray) -> np.ndarray | None:
        """Where episode `ep` may anchor its proposals (None: every available point): the first episode's anchor
        candidates, and only points at least `proposals.anchor_min_height` above z = 0 while any available one
        is (else that restriction is dropped)."""
        mask = self.anchor_mask if ep == 0 else None
        h = self.cfg.proposals.anchor_min_height
        if h is None:
            return mask
        high = self.points[:, 2] >= h
        if mask is not None:
            high &= mask
        return high if np.any(high & available) else mask

    def _check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise EMCancelled(f"EM on {self.name!r} cancelled after {self.rec.num_steps} steps")

    # ------------------------------------------------------------------ episodes
    def run(self) -> list[dict[str, Any]]:
        cfg = self.cfg
        k_priors = len(self.table)
        assigned = np.zeros(self.n_full, bool)  # full resolution
        accepted = self.accepted
        look_alike = _look_alike_models(self.cfgs)
        eligible = eligible_points(self.full_points, cfg.proposals.min_point_height, self.name)
        for ep, n_init in enumerate(cfg.proposals.n_init):
            self._check_cancel()
            available_full = ~assigned & eligible
            available = available_full[self.work_idx]
            n_avail = int(available.sum())
            if n_avail <= self.min_size:
                logger.info("episode %d skipped: %d available points <= min_size %d", ep, n_avail,
                            self.min_size)
                break
            tree = AvailableTree(self.points, available, crop=cfg.proposals.crop)
            full_tree = tree if self.identity else None
            # every prior gets n_init proposals; anchors are iid, so prior k takes the k-th block of draws
            anchors, crops = init_crops(self.points, available, n_init * k_priors, cfg.proposals.radii()[0], self.rng,
                                        crop=cfg.proposals.crop, tree=tree,
                                        anchor_mask=self._episode_anchor_mask(ep, available),
                                        spread=cfg.proposals.anchors == "spread")
            owner = np.repeat(np.arange(k_priors, dtype=np.int64), n_init)[: len(anchors)]
            ids = self.rec.birth(ep, self.work_idx[anchors], *cfg.proposals.radii(), owner=owner)
            self.rec.start_episode(np.flatnonzero(assigned), len(ids))
            pool = ProposalPool(ids=ids, rag=crops, w=np.ones(len(crops.idx), np.float32), owner=owner)
            if ep == 0 and self.on_step is not None:  # the proposals are drawn: a front end can show them already
                self.on_step(StepInfo(-1, self.planned_steps, 1, pool.size, time.perf_counter() - self.t_start, ep,
                                      partial=self.partial_result))
            last_review: dict[int, ReviewRecord] = {}
            for t in range(cfg.steps.per_episode):
                if pool.size == 0:
                    break
                self._check_cancel()
                phase = 1 if t < cfg.steps.t1 else 2
                step = self._em_step(pool, tree, ep, t, phase)
                self._eliminate(pool, step, t, phase)
                if (phase == 1 and t == cfg.steps.t1 - 1) or (phase == 2 and t == cfg.steps.per_episode - 1):
                    if full_tree is None:
                        full_tree = AvailableTree(self.full_points, available_full, crop=cfg.proposals.crop)
                    last_review = self._review(pool, full_tree, step, phase)  # float32 (matmul_dtype: E-steps)
                elapsed = time.perf_counter() - self.t_start
                self.rec.end_step(pool.size, elapsed)
                if self.on_step is not None:
                    self.on_step(StepInfo(step, self.planned_steps, phase, pool.size, elapsed, ep,
                                          partial=self.partial_result))
            if pool.size == 0:
                continue
            t0 = time.perf_counter()
            final_step = self.rec.num_steps - 1
            # every live proposal has been through an E-step (stationary, latent) and the last review
            assert pool.stationary is not None and pool.latent is not None
            revs = [last_review[int(pid)] for pid in pool.ids]
            confs = np.empty(pool.size)
            for r, rev in enumerate(revs):
                s_stat = float(pool.stationary[r])
                conf = confidence(s_stat, float(rev.coverage), cap=cfg.confidence.cov_cap,
                                  seen_through=rev.seen_through,
                                  pose=float(rev.db_sim), pose_weight=cfg.confidence.pose_weight,
                                  pose_ref=cfg.confidence.pose_ref)
                model = look_alike[rev.prior]
                if model is not None and self.categories[rev.prior] == model.category:
                    conf = model.confidence(conf, review_features(
                        stationary=s_stat, coverage=float(rev.coverage), pose=float(rev.db_sim),
                        radius=float(rev.radii[0]), half_height=float(rev.radii[1]), up_angle=float(rev.up_angle),
                        seen_through=float(rev.seen_through), mask_size=len(rev.mask)))
                confs[r] = conf
            if cfg.confidence.explained_decay:  # a solve's config has its priors' value (`run_em`)
                confs = explained_decay(confs, [rev.mask for rev in revs], self.n_full, cfg.confidence.explained_decay)
            for r, (pid, rev) in enumerate(zip(pool.ids, revs)):
                conf = float(confs[r])
                self.rec.death(int(pid), final_step, REASON_SURVIVE, -1, conf)
                accepted.append({**rev._asdict(), "confidence": conf, "stationary": float(pool.stationary[r]),
                                 "center": pool.latent["center"][r], "scale": float(pool.latent["scale"][r]),
                                 "category": self._category(rev, self.table.latent_of(
                                     int(pool.owner[r]), {key: v[r] for key, v in pool.latent.items()}))})
                assigned[rev.mask] = True
            self.timer.add("accept", t0)
        return accepted

    # ------------------------------------------------------------------ one EM step
    def _em_step(self, pool: ProposalPool, tree: AvailableTree, ep: int, t: int, phase: int) -> int:
        cfg = self.cfg
        fallback = tree.avail_idx
        t0 = time.perf_counter()
        if phase == 1 or pool.stationary is None:
            samples = sample_independent(pool.rag, pool.w, self.m, cfg.steps.omega, self.rng, fallback=fallback,
                                         replace=cfg.steps.m_step_replace)
        else:
            samples, _ = sample_joint(pool.rag, pool.w, pool.stationary, self.m, cfg.steps.omega, self.rng,
                                      fallback=fallback)
        t0 = self.timer.add("m_step", t0)
        with matmul_precision(cfg.compute.encoder_dtype or cfg.compute.matmul_dtype,
                              self.table.priors[0]):  # EM steps only
            latent = encode_rows(self.table, pool.owner, self.points[samples], batch=cfg.compute.encode_batch)
            self.n_encoded += len(samples)
            review_step = t in (cfg.steps.t1 - 1, cfg.steps.per_episode - 1)
            if cfg.refine.steps > 0 and pool.size <= cfg.refine.max_pool and (cfg.refine.at == "every_step"
                                                                              or review_step):
                latent = self._refine(latent, self.points[samples], pool.owner)
        if cfg.elimination.trust_scale is not None:
            latent = _trust_scale(latent, pool, cfg.elimination.trust_scale)
        t0 = self.timer.add("encode", t0)
        rag = tree.query(latent["center"], cfg.proposals.radii()[1])
        t0 = self.timer.add("neighbourhood", t0)
        sched = schedule(cfg, t)
        with matmul_precision(cfg.compute.matmul_dtype, self.table.priors[0]):
            d, gamma = decode_owned_rows(self.table, pool.owner, latent, rag, self.points, self.normals,
                                         chunk=cfg.compute.decode_chunk,
                                         normals_within=normals_threshold(cfg, sched[1]), stats=self.stats)
        self.n_queries += len(rag.idx)
        t0 = self.timer.add("decode", t0)
        w, inlier = energy_weights(d, gamma, sched, out_value=cfg.steps.out_value)
        inliers = np.bincount(rag.row[inlier], minlength=pool.size).astype(np.int32)
        stationary = stationary_score(rag, samples, d, gamma, tau=cfg.confidence.stat_tau,
                                      gamma_max=cfg.confidence.stat_gamma)
        pool.rag, pool.w, pool.d, pool.gamma = rag, w, d, gamma
        pool.latent, pool.stationary, pool.inliers = latent, stationary, inliers
        self.timer.add("score", t0)
        return self.rec.step(phase=phase, episode=ep, local=t, sched=sched, ids=pool.ids, latent=latent,
                             stationary=stationary, inliers=inliers, samples=self.work_idx[samples])

    def _refine(self, latent: LatentArrays, pts: np.ndarray, owner: np.ndarray) -> LatentArrays:
        """Test-time latent refinement (`EMConfig.refine`) of every row with its own prior."""
        from efem_viz.em.refine import refine_latents

        cfg = self.cfg
        settings = cfg.refine
        if len(self.table) == 1:
            return refine_latents(self.table.priors[0], latent, pts, settings)[0]
        out = {k: v.copy() for k, v in latent.items()}
        for k, prior in enumerate(self.table.priors):
            rows = np.flatnonzero(owner == k)
            if not len(rows):
                continue
            width = self.table.widths[k]
            lat_k = self.table.latent_of(k, {key: v[rows] for key, v in latent.items()})
            ref, _ = refine_latents(prior, lat_k, pts[rows], settings)
            out["R"][rows, :width], out["inv"][rows, :width] = ref["R"], ref["inv"]
            out["center"][rows], out["scale"][rows] = ref["center"], ref["scale"]
        return out

    # ------------------------------------------------------------------ eliminations (§3.8)
    def _eliminate(self, pool: ProposalPool, step: int, local: int, phase: int) -> None:
        t0 = time.perf_counter()
        assert pool.inliers is not None and pool.d is not None and pool.stationary is not None
        ctx = StepContext(phase=phase, step=step, local_step=local, cfg=self.cfg, inliers=pool.inliers,
                          stationary=pool.stationary, d=pool.d,
                          rag=pool.rag, n_points=self.n, min_size=self.min_size, owner=pool.owner,
                          tau_d=schedule(self.cfg, local)[1], spacing=self.spacing, coverage=pool.coverage,
                          small_streak=pool.small_streak, patience=self.patience[pool.owner],
                          recent_best=pool.remember(pool.stationary, self.cfg.elimination.score_memory))
        kills = apply_step_rules(ctx, self.step_rules)
        before = pool.small_streak if pool.small_streak is not None else np.zeros(pool.size, np.int64)
        pool.small_streak = np.where(ctx.small, before + 1, 0)
        for k in kills:
            partner = int(pool.ids[k.partner]) if k.partner >= 0 else -1
            self.rec.death(int(pool.ids[k.row]), step, k.reason, partner, k.ratio)
        if kills:
            pool.keep(np.flatnonzero(ctx.active))
        self.timer.add("eliminate", t0)

    # ------------------------------------------------------------------ review (§3.9)
    def _review(
        self, pool: ProposalPool, full_tree: AvailableTree, step: int, phase: int
    ) -> dict[int, ReviewRecord]:
        """§3.9 at the end of a phase: every live proposal's completed shape, pose, box, coverage, size and up
        checks and tentative mask (a `ReviewRecord` each); the review rules kill the failures."""
        cfg = self.cfg
        assert pool.latent is not None and pool.d is not None and pool.gamma is not None
        records: dict[int, ReviewRecord] = {}
        keep = np.ones(pool.size, bool)
        t0 = time.perf_counter()
        if self.identity and cfg.compute.matmul_dtype == "float32":
            full_rag, d_full, g_full = pool.rag, pool.d, pool.gamma
        else:  # masks and coverage at the scene's full resolution, in float32
            full_rag = full_tree.query(pool.latent["center"], cfg.proposals.radii()[1])
            d_full, g_full = decode_owned_rows(
                self.table, pool.owner, pool.latent, full_rag, self.full_points, self.full_normals,
                chunk=cfg.compute.decode_chunk,
                normals_within=cfg.output.out_tau if cfg.output.gamma_out < 180.0 else -1.0)
            self.n_queries += len(full_rag.idx)
        self.timer.add("review_coverage", t0)
        for r in range(pool.size):
            self._check_cancel()
            pid = int(pool.ids[r])
            k = int(pool.owner[r])
            cfg_k = self.cfgs[k]
            lat = self.table.latent_of(k, {key: v[r] for key, v in pool.latent.items()})
            t0 = time.perf_counter()
            mesh, Q, fnorm, center, scale = self._completed_shape(k, lat, pid)
            t0 = self.timer.add("review_mesh", t0)
            R, R_raw, s_sel, db_sim, nbrs = self._pose(k, lat, Q, fnorm, pid)
            t0 = self.timer.add("review_pose", t0)
            from efem_viz.geometry.obb import oriented_box

            obb = oriented_box(Q + center, center, R)
            sl = full_rag.row_slice(r)
            ball = full_rag.idx[sl]
            cov = self._coverage(ball, Q, center, fnorm, s_sel / scale)
            radii, scale_pass, up_angle, pose_pass = _size_and_up(Q, R, R_raw, cfg_k)
            st = float("nan")
            if self.free_space is not None and cfg.free_space.margin is not None and np.any(Q):
                st = self.free_space.seen_through(Q + center, cfg.free_space.margin,
                                                  per_depth2=cfg.free_space.range_growth)[0]
            m_ok = np.abs(d_full[sl]) < cfg_k.output.out_tau
            if cfg.output.gamma_out < 180.0:
                m_ok &= g_full[sl] < cfg.output.gamma_out
            mask = ball[m_ok]
            rec = ReviewRecord(
                step=step, phase=phase, proposal_id=pid, R=R, R_raw=R_raw, scale_sel=s_sel, db_sim=db_sim,
                coverage=cov, radii=radii, scale_pass=scale_pass, up_angle=up_angle, pose_pass=pose_pass,
                obb_center=obb.center, obb_axes=obb.axes, obb_half_extents=obb.half_extents,
                mask=mask.astype(np.int32),
                mesh_vertices=(np.asarray(mesh.vertices) - center).astype(np.float32),
                mesh_faces=np.asarray(mesh.faces, np.int32), neighbours=np.asarray(nbrs, np.int32), prior=k,
                seen_through=st, planar=planar_share(self.full_normals[mask]),
            )
            self.rec.review(rec)
            records[pid] = rec
            failed = first_failed_review(rec, cfg_k, self.review_rules)
            if failed is not None:
                keep[r] = False
                self.rec.death(pid, step, failed[0], -1, failed[1])
            self.timer.add("review_coverage", t0)
        pool.coverage = np.array([records[int(pid)].coverage for pid in pool.ids], np.float64)
        if not keep.all():
            pool.keep(np.flatnonzero(keep))
        return records

    def _completed_shape(self, k: int, lat: LatentArrays, pid: int
                         ) -> tuple["trimesh.Trimesh", np.ndarray, np.ndarray, np.ndarray, float]:
        """Prior k's mesh of a latent and `cfg.review.n_store` surface samples Q (relative to Θ_c) with their normals;
        returns (mesh, Q, normals, Θ_c, Θ_s). A degenerate latent (non-finite, Θ_s ≤ 0) has an empty mesh and
        all-zero samples (it fails the size check)."""
        from efem_viz.geometry.sampling import sample_surface

        cfg = self.cfg
        center = lat["center"].astype(np.float64)
        scale = float(lat["scale"])
        if np.isfinite(center).all() and np.isfinite(scale) and scale > 0:
            mesh = mesh_of_latent(self.table.priors[k], lat, resolution=cfg.review.mesh_resolution)
        else:
            import trimesh

            mesh = trimesh.Trimesh()
            center = np.nan_to_num(center)
            scale = 1.0
        if len(mesh.faces) and np.isfinite(np.asarray(mesh.vertices)).all():
            surf = sample_surface(mesh, cfg.review.n_store, seed=self.seed * 1_000_003 + pid)
            return mesh, surf.points - center, surf.normals, center, scale
        return mesh, np.zeros((cfg.review.n_store, 3)), np.zeros((cfg.review.n_store, 3)), center, scale

    def _coverage(self, ball: np.ndarray, Q: np.ndarray, center: np.ndarray, normals: np.ndarray,
                  to_canonical: float) -> float:
        """Fraction of completed-shape samples (Q + Θ_c, world) explained by an observed point of the ball:
        nearest distance (canonical units: × `to_canonical`) ≤ cov_tau and normal angle ≤ cov_gamma. 0 for an
        empty ball or a shape without samples."""
        cfg = self.cfg
        if not len(ball) or not np.any(Q):
            return 0.0
        from efem_viz._typeshims import cKDTree

        dist, j = cKDTree(self.full_points[ball]).query(Q + center)
        dist_c = dist * to_canonical
        cosang = np.clip((normals * self.full_normals[ball][j]).sum(1), -1.0, 1.0)
        ang = np.degrees(np.arccos(cosang))
        return float(np.mean((dist_c <= cfg.confidence.cov_tau) & (ang <= cfg.confidence.cov_gamma)))

    def _category(self, rev: ReviewRecord, lat: LatentArrays) -> str:
        """An accepted instance's category: its prior's name, or for a family prior (kitchen) the class its final
        latent `lat` and its completed shape's size say (the prior's member head, `member_head_of`), else the class
        its last pose search's codebook entries vote for, each by how well it aligned (`Codebook.category_of`)."""
        from efem_viz.prior.member_head import member_head_of

        name = self.categories[rev.prior]
        prior = self.table.priors[rev.prior]
        head = member_head_of(prior)
        if head is not None:
            return head.classify(np.asarray(lat["inv"]), radii=np.asarray(rev.radii, np.float64))
        cb = getattr(prior, "codebook", None)
        if cb is None:
            return name
        rows, scores = self.pose_votes.get(rev.proposal_id, (rev.neighbours, None))
        return cb.category_of(rows, name, weights=scores)

    def _pose(
        self, k: int, lat: LatentArrays, Q: np.ndarray, fnorm: np.ndarray, pid: int = -1
    ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
        """(R, R_raw, s_sel, db_sim, neighbour ids) from prior k's codebook, or identity without one; the
        rows it retrieved and their alignment scores are kept as `pose_votes[pid]` (a family prior's class)."""
        prior = self.table.priors[k]
        cb = getattr(prior, "codebook", None)
        if cb is None or not self.cfg.review.pose_retrieval:
            eye = np.eye(3)
            return eye, eye.copy(), self.ref_scales[k], float("nan"), np.zeros(0, np.int32)
        from efem_viz.em.decoding import latent_from_numpy
        from efem_viz.prior.pose import estimate_pose

        one = {key: np.asarray(v)[None] if key != "scale" else np.asarray(v).reshape(1) for key, v in lat.items()}
        est = estimate_pose(prior, latent_from_numpy(prior, one), Q, fnorm, search_points=self.cfg.review.pose_points)
        s_sel = (float(est.scale_sel) if np.isfinite(est.scale_sel) and est.scale_sel > 0
                 else self.ref_scales[k])
        R = np.asarray(est.R, np.float64)
        if cb.classes:  # a family prior's: what names the instance (`_category`)
            self.pose_votes[pid] = (np.asarray(est.neighbour_ids), np.asarray(est.scores, np.float64))
        return R, np.asarray(est.R_raw, np.float64), s_sel, float(est.score_db_sim), np.asarray(est.neighbour_ids)


def _look_alike_models(cfgs: Sequence[EMConfig]) -> list[LookAlikeModel | None]:
    """The look-alike model of each prior's (resolved) config, or None; each file read once."""
    names = [c.confidence.look_alike for c in cfgs]
    models = {n: load_model(n) for n in set(names) if n is not None and n != CATEGORY_LOOK_ALIKE}
    return [models.get(n) if n is not None else None for n in names]


def _trust_scale(latent: LatentArrays, pool: ProposalPool, trust: float) -> LatentArrays:
    """Θ_s ≥ (1 − trust) × the row's largest Θ_s so far (Θ_R is scale-free, so only Θ_s changes)."""
    s = np.asarray(latent["scale"], np.float32)
    if pool.scale_max is not None and len(pool.scale_max) == len(s):
        s = np.maximum(s, (1.0 - trust) * pool.scale_max).astype(np.float32)
        pool.scale_max = np.maximum(pool.scale_max, s)
    else:
        pool.scale_max = s.copy()
    return {**latent, "scale": s}


def _size_and_up(Q: np.ndarray, R: np.ndarray, R_raw: np.ndarray, cfg: EMConfig
                 ) -> tuple[np.ndarray, bool, float, bool]:
    """§3.9 measures of a completed shape and the rules' verdicts on them: (radii = (horizontal radius,
    half-height) in its canonical frame, `rules.size_passes`, angle of the canonical up axis to world +Z,
    `rules.up_passes`)."""
    Qt = Q @ R
    radii = np.array([np.linalg.norm(Qt[:, :2], axis=1).max(), np.abs(Qt[:, 2]).max()])
    up_angle = float(np.degrees(np.arccos(np.clip(R_raw[:, 2] @ np.array([0.0, 0.0, 1.0]), -1.0, 1.0))))
    # the verdicts are the rules' (em/rules.py); the record keeps them for the trace and the viewer
    return radii, size_passes(radii, cfg), up_angle, up_passes(up_angle, cfg)


def _n_pcl(prior: Any) -> int:
    """Points per encoded set of a prior (`n_pcl`, else its config's, else 512)."""
    n = getattr(prior, "n_pcl", None)
    if n is None:
        n = getattr(getattr(prior, "config", None), "n_pcl", 512)
    return int(n)


def _category(prior: Any) -> Any:
    from efem_viz.prior.config import prior_category

    return prior_category(prior)
