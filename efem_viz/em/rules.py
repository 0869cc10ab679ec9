"""Elimination rules of the EFEM solver (docs/design/efem-method.md §3.8 and §3.9), registered in one place.

Two kinds of rule:
- `StepRule`: runs after every EM step on the live proposals of the pool (too small, duplicate, inclusion);
  it sees a `StepContext` and returns `Kill`s. Rules run in list order; a kill takes effect for the rules
  after it.
- `ReviewRule`: runs on each proposal's `ReviewRecord` at the end of each phase (scale check, pose check);
  the first rule that fails kills the proposal.

`run_em(..., step_rules=..., review_rules=...)` takes other lists (see examples/add_elimination_rule.py). Each
rule's `reason` is the name a death is recorded under; a trace saves the table of reason names it used
(`reason_names`), so its int8 codes stay readable whatever rules a later build registers. Traces written
before the table existed decode with `LEGACY_REASONS`.
"""

from __future__ import annotations

import math

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from efem_viz.em.proposals import Ragged

if TYPE_CHECKING:
    import scipy.sparse as sp

    from efem_viz.em.config import EMConfig, InclusionMode

REASON_TOO_SMALL = "proposal too small"
REASON_DUPLICATE = "duplicated"
REASON_INCLUDED = "included"
REASON_INCLUDES_BETTER = "includes a better fit"
"""An includer that scores lower than the fit it includes (`EMConfig.elimination.inclusion` = "swap")."""
REASON_SCALE = "scale-fail"
REASON_POSE = "pose-fail"
REASON_SEEN_THROUGH = "seen-through"
REASON_PLANAR = "planar"
"""A fit whose mask's normals three directions hold (`EMConfig.review.max_planar`): the edge or corner of a box."""
REASON_SURVIVE = "survive"
LEGACY_REASONS: tuple[str, ...] = ("proposal too small", "duplicated or included", "scale-fail", "pose-fail",
                                   "survive")
"""The reason codes of traces saved before the name table (inclusions were recorded as duplicates)."""


def set_matrix(rag: Ragged, mask: np.ndarray, n_points: int) -> sp.csr_matrix:
    """(P, N) scipy.sparse CSR boolean matrix of the entries where `mask` holds (e.g. |d| < δ_dup)."""
    import scipy.sparse as sp

    mask = np.asarray(mask, bool)
    row = rag.row[mask]
    col = rag.idx[mask]
    data = np.ones(len(row), np.float32)
    return sp.csr_matrix((data, (row, col)), shape=(rag.num_rows, int(n_points)))


def overlap_counts(sets: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise intersection sizes of sparse sets.

    Args:
        sets: (P, N) scipy.sparse matrix with 0/1 entries.

    Returns:
        inter (P, P) float64 |B_i ∩ B_k| and sizes (P,) float64 |B_i|.
    """
    gram = (sets @ sets.T).toarray().astype(np.float64)
    sizes = np.asarray(sets.sum(axis=1)).ravel().astype(np.float64)
    return gram, sizes


@dataclass(frozen=True)
class Kill:
    """One elimination: row `row` dies because of `partner` (row index, or -1) with overlap `ratio`."""

    row: int
    reason: str
    partner: int = -1
    ratio: float = float("nan")


def find_too_small(inlier_counts: np.ndarray, min_size: "int | float | np.ndarray") -> list[Kill]:
    """§3.8a: rows with fewer than `min_size` inliers (`min_size` one number, or one per row)."""
    counts = np.asarray(inlier_counts)
    return [Kill(int(r), REASON_TOO_SMALL, -1, float(counts[r]))
            for r in np.flatnonzero(counts < np.asarray(min_size))]


def size_counts(cfg: "EMConfig", inliers: np.ndarray, d: np.ndarray, rag: Ragged, min_size: int,
                tau_d: float, *, spacing: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What the "too small" rule compares, per row: (counts, thresholds).

    ``cfg.elimination.min_size_on`` picks the count (inliers, or the SDF-band support |d| ≤ ``tau_d``);
    ``cfg.elimination.min_size_spacing`` makes the threshold density-relative: ``min_size`` × (reference spacing /
    median nearest-neighbour spacing of the row's band points)², so it asks for the same surface area at any
    density.

    Args:
        cfg: Solver config.
        inliers: (P,) inlier counts.
        d: (K,) canonical SDF over ``rag``.
        rag: The rows' neighbourhoods.
        min_size: The absolute threshold (on the working set).
        tau_d: This step's SDF truncation τ_D.
        spacing: (N,) nearest-neighbour spacing of every point (needed with ``min_size_spacing``).

    Returns:
        (P,) float counts and (P,) float thresholds.
    """
    p = rag.num_rows
    band = np.abs(np.asarray(d)) <= tau_d
    if cfg.elimination.min_size_on == "band":
        counts = np.bincount(rag.row[band], minlength=p).astype(np.float64)
    else:
        counts = np.asarray(inliers, np.float64)
    thr = np.full(p, float(min_size))
    if cfg.elimination.min_size_spacing is not None:
        if spacing is None:
            raise ValueError("min_size_spacing needs the points' spacing")
        for r in range(p):
            sl = rag.row_slice(r)
            sp_r = spacing[rag.idx[sl][band[sl]]]
            if len(sp_r):
                ratio = cfg.elimination.min_size_spacing / max(float(np.median(sp_r)), 1e-6)
                thr[r] = float(min_size) * ratio * ratio
    return counts, thr



def find_duplicates(
    sets: sp.csr_matrix,
    scores: np.ndarray,
    iou_threshold: float,
    *,
    active: np.ndarray | None = None,
) -> list[Kill]:
    """§3.8b duplicate removal over sparse sets, rows visited in order (= increasing proposal id).

    For each still-active row i, the group is {k active : IoU(B_i, B_k) ≥ θ} (i included when B_i is not
    empty); if it has more than one member, only the member with the highest score survives (argmax within the group,
    ties to the lowest row), the others die with that winner as partner.

    Args:
        sets: (P, N) sparse 0/1 matrix of the sets B_i.
        scores: (P,) stationary scores.
        iou_threshold: θ_iou.
        active: (P,) bool rows that take part (default all).

    Returns:
        The kills in the order they happen; `ratio` is IoU(killed, winner).
    """
    inter, sizes = overlap_counts(sets)
    p = len(sizes)
    alive = np.ones(p, bool) if active is None else np.asarray(active, bool).copy()
    union = sizes[:, None] + sizes[None, :] - inter
    iou = inter / (union + 1e-6)
    scores = np.asarray(scores, np.float64)
    kills: list[Kill] = []
    for i in range(p):
        if not alive[i]:
            continue
        group = np.flatnonzero(alive & (iou[i] >= iou_threshold))
        if len(group) <= 1:
            continue
        winner = int(group[np.argmax(scores[group])])
        for k in group:
            if k != winner:
                alive[k] = False
                kills.append(Kill(int(k), REASON_DUPLICATE, winner, float(iou[k, winner])))
    return kills


def capped_confidence(stationary: np.ndarray | float, coverage: np.ndarray | float, cap: float) -> np.ndarray:
    """The paper's confidence (docs/design/efem-method.md §3.10): stationary score · min(coverage, cap) / cap,
    elementwise."""
    if not cap > 0:
        raise ValueError(f"coverage cap must be > 0, got {cap}")
    return np.asarray(stationary, np.float64) * np.minimum(np.asarray(coverage, np.float64), cap) / cap


def explained_decay(confidences: np.ndarray, masks: Sequence[np.ndarray], n_points: int, power: float
                    ) -> np.ndarray:
    """Confidences lowered by how much of each mask fits ranked above it already explain.

    Greedy, highest first: a fit's confidence is multiplied by (1 − e)^`power`, where e is the share of its mask's
    points inside the union of the masks taken before it. The next taken is the fit with the highest lowered
    confidence. A fit over two objects that two better fits already hold, or a partial copy of a found object,
    falls below the fits of objects nobody else holds; a fit no other overlaps keeps its confidence. Nothing is
    removed (masks may still overlap, as the method lets them): only the order, and what a confidence threshold
    shows, change. (The solver calls it per episode: a later episode's masks hold only points no earlier instance
    took.)

    Args:
        confidences: (K,) confidences, >= 0.
        masks: K integer index arrays into the scene's `n_points` points.
        n_points: the scene's point count.
        power: the exponent (0: confidences unchanged).

    Returns:
        (K,) float64 lowered confidences.

    Raises:
        ValueError: lengths differ, a negative or non-finite confidence or power, or a mask that is not integer
            indices into the scene.
    """
    conf = np.asarray(confidences, np.float64).reshape(-1)
    if len(conf) != len(masks):
        raise ValueError(f"{len(masks)} masks but {len(conf)} confidences")
    if not (math.isfinite(power) and power >= 0):
        raise ValueError(f"power must be finite and >= 0, got {power}")
    if not (np.isfinite(conf).all() and (conf >= 0).all()):
        raise ValueError("confidences must be finite and >= 0")
    out = conf.copy()
    if power == 0 or not len(conf):
        return out
    import scipy.sparse as sp

    idx = []
    for m in masks:
        a = np.asarray(m).reshape(-1)
        if len(a) and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"masks must be integer point indices, got dtype {a.dtype}")
        a = np.unique(a.astype(np.int64))
        if len(a) and (int(a[0]) < 0 or int(a[-1]) >= n_points):
            raise ValueError(f"a mask indexes outside the scene's {n_points} points")
        idx.append(a)
    sizes = np.array([len(m) for m in idx], np.float64)
    # (N, K) incidence: the fits each point belongs to; `held` counts each fit's points already taken
    incidence = sp.csr_matrix((np.ones(int(sizes.sum()), np.float64),
                               (np.concatenate(idx), np.repeat(np.arange(len(idx)), sizes.astype(np.int64)))),
                              shape=(int(n_points), len(idx)))
    taken = np.zeros(int(n_points), bool)
    held = np.zeros(len(idx))
    left = np.ones(len(conf), bool)
    for _ in range(len(conf)):
        share = np.divide(held, sizes, out=np.zeros_like(held), where=sizes > 0)
        lowered = conf * (1.0 - np.clip(share, 0.0, 1.0)) ** power
        j = int(np.flatnonzero(left)[np.argmax(lowered[left])])  # ties: the earlier row
        out[j] = lowered[j]
        left[j] = False
        new = idx[j][~taken[idx[j]]]
        if len(new):
            taken[new] = True
            held += np.asarray(incidence[new].sum(axis=0)).reshape(-1)
    return out


def find_inclusions(
    sets: sp.csr_matrix,
    threshold: float,
    *,
    active: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    mode: "InclusionMode" = "paper",
) -> list[Kill]:
    """§3.8c pairwise inclusion: row i dies if |B_i ∩ B_k| / |B_i| > θ for a single other active k.

    Rows are visited in order and a kill takes effect immediately (later rows no longer see it).

    Args:
        sets: (P, N) sparse sets.
        threshold: θ_incl.
        active: rows still alive.
        scores: (P,) the rows' scores (modes other than "paper"): stationary scores or confidences
            (`EMConfig.elimination.inclusion_by`).
        mode: "paper" (§3.8c: the included row dies), "score" (it dies only when its includer scores at least as
            high; else both stay) or "swap" (as "score", but an includer that scores lower than the row it
            includes dies instead: a fit wider than its object swallowing a better fit of that object).

    Returns:
        The kills; `partner` is the k of the largest overlap and `ratio` that overlap (a swapped kill: reason
        `REASON_INCLUDES_BETTER`, partner the row it included, ratio that row's overlap with it).
    """
    from efem_viz.em.config import INCLUSION_MODES

    if mode not in INCLUSION_MODES:
        raise ValueError(f"inclusion mode must be one of {', '.join(INCLUSION_MODES)}, got {mode!r}")
    if mode != "paper" and scores is None:
        raise ValueError(f"inclusion mode {mode!r} needs the rows' scores")
    inter, sizes = overlap_counts(sets)
    p = len(sizes)
    score = np.zeros(p) if scores is None else np.asarray(scores, np.float64)
    alive = np.ones(p, bool) if active is None else np.asarray(active, bool).copy()
    kills: list[Kill] = []
    for i in range(p):
        if not alive[i]:
            continue
        ratio = inter[i] / (sizes[i] + 1e-6)
        ratio = np.where(alive, ratio, -1.0)
        ratio[i] = -1.0
        k = int(np.argmax(ratio)) if p > 1 else -1
        if k >= 0 and ratio[k] > threshold:
            if mode == "paper" or score[k] >= score[i]:
                alive[i] = False
                kills.append(Kill(i, REASON_INCLUDED, k, float(ratio[k])))
            elif mode == "swap":
                alive[k] = False
                kills.append(Kill(k, REASON_INCLUDES_BETTER, i, float(ratio[k])))
    return kills


# ---------------------------------------------------------------------------------------------- step rules
@dataclass
class StepContext:
    """What a step rule sees: the pool after an E-step (rows in increasing proposal id).

    Attributes:
        phase: 1 = independent, 2 = joint.
        step: global step index (over all episodes).
        local_step: step within the episode (0 .. t1 + t2 − 1; phase 2 starts at `cfg.steps.t1`).
        cfg: solver config.
        inliers: (P,) int inlier counts.
        stationary: (P,) float stationary scores.
        d: (K,) canonical SDF over `rag`.
        rag: the rows' E-step neighbourhoods (working-set indices).
        n_points: size of the working set.
        min_size: the "too small" threshold on the working set.
        owner: (P,) int prior of each row (index into the solve's priors).
        tau_d: this step's SDF truncation τ_D (for `cfg.elimination.min_size_on` = "band").
        spacing: (N,) nearest-neighbour spacing of the working set (for `cfg.elimination.min_size_spacing`), or None.
        active: (P,) bool rows still alive; the runner clears the rows each rule kills.
        coverage: (P,) coverage of each row's last review (in phase 2 its phase-1 review; for
            `cfg.elimination.inclusion_by` = "confidence"), or None before any review.
        small_streak: (P,) steps in a row each row was under the "too small" threshold before this one (for
            `cfg.elimination.min_size_patience`), or None (none yet).
        patience: (P,) each row's `min_size_patience` (its prior's resolved config), or None: `cfg`'s for all.
        small: (P,) bool rows under the threshold at this step, set by the "too small" rule (the runner carries
            the streak on from it).
        recent_best: (P,) each row's best stationary score over its last `cfg.elimination.score_memory` steps,
            this one included, or None: this step's (`pair_scores`).
    """

    phase: int
    step: int
    local_step: int
    cfg: "EMConfig"
    inliers: np.ndarray
    stationary: np.ndarray
    d: np.ndarray
    rag: Ragged
    n_points: int
    min_size: int
    owner: np.ndarray
    active: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    tau_d: float = float("inf")
    spacing: np.ndarray | None = None
    coverage: np.ndarray | None = None
    small_streak: np.ndarray | None = None
    patience: np.ndarray | None = None
    small: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    recent_best: np.ndarray | None = None

    @property
    def pair_scores(self) -> np.ndarray:
        """The stationary scores the pair rules compare (`EliminationSettings.score_memory`)."""
        return self.stationary if self.recent_best is None else self.recent_best

    def __post_init__(self) -> None:
        if len(self.active) != len(self.inliers):
            self.active = np.ones(len(self.inliers), bool)
        if len(self.small) != len(self.inliers):
            self.small = np.zeros(len(self.inliers), bool)

    @cached_property
    def sets(self) -> "sp.csr_matrix":
        """(P, N) sparse sets {j : |d_ij| < δ_dup} of every row (built once per step, on first use)."""
        return set_matrix(self.rag, np.abs(self.d) < self.cfg.elimination.dup_sdf, self.n_points)


@dataclass(frozen=True)
class StepRule:
    """A per-step elimination rule.

    Attributes:
        reason: the name its deaths are recorded under.
        find: the rule: StepContext → kills (rows of the context; must only kill active rows).
        phases: the phases it runs in.
        needs_pair: run only while more than one row is active (pairwise rules).
        also: other reasons its kills may carry (a rule that can kill either row of a pair).
    """

    reason: str
    find: Callable[[StepContext], list[Kill]]
    phases: tuple[int, ...] = (1, 2)
    needs_pair: bool = False
    also: tuple[str, ...] = ()


def _too_small(ctx: StepContext) -> list[Kill]:
    counts, thr = size_counts(ctx.cfg, ctx.inliers, ctx.d, ctx.rag, ctx.min_size, ctx.tau_d, spacing=ctx.spacing)
    kills = find_too_small(counts, thr)
    ctx.small[[k.row for k in kills]] = True
    patience = (ctx.patience if ctx.patience is not None
                else np.full(len(counts), ctx.cfg.elimination.min_size_patience or 1, np.int64))
    if np.any(patience > 1):  # under the threshold for `patience` steps in a row, this one included
        before = ctx.small_streak if ctx.small_streak is not None else np.zeros(len(counts), np.int64)
        kills = [k for k in kills if int(before[k.row]) + 1 >= int(patience[k.row])]
    return kills


def _duplicates(ctx: StepContext) -> list[Kill]:
    thr = ctx.cfg.elimination.dup_iou if ctx.phase == 1 else ctx.cfg.elimination.joint_dup_iou
    if ctx.cfg.elimination.early_dup_iou is not None and ctx.local_step < ctx.cfg.elimination.early_dup_steps:
        thr = ctx.cfg.elimination.early_dup_iou
    return find_duplicates(ctx.sets, ctx.pair_scores, thr, active=ctx.active)


def _inclusions(ctx: StepContext) -> list[Kill]:
    scores = ctx.pair_scores
    if ctx.cfg.elimination.inclusion != "paper" and ctx.cfg.elimination.inclusion_by == "confidence":
        if ctx.coverage is None:
            raise ValueError("inclusion_by 'confidence' needs the rows' review coverage (StepContext.coverage)")
        scores = capped_confidence(scores, ctx.coverage, ctx.cfg.confidence.cov_cap)
    return find_inclusions(ctx.sets, ctx.cfg.elimination.joint_incl, active=ctx.active, scores=scores,
                           mode=ctx.cfg.elimination.inclusion)


STEP_RULES: tuple[StepRule, ...] = (
    StepRule(REASON_TOO_SMALL, _too_small),
    StepRule(REASON_DUPLICATE, _duplicates, needs_pair=True),
    StepRule(REASON_INCLUDED, _inclusions, phases=(2,), needs_pair=True, also=(REASON_INCLUDES_BETTER,)),
)
"""The method's per-step rules (§3.8a-c), in the order they run."""


def apply_step_rules(ctx: StepContext, rules: Sequence[StepRule] = STEP_RULES) -> list[Kill]:
    """Run the rules of `ctx.phase` in order; returns every kill (`ctx.active` updated in place)."""
    kills: list[Kill] = []
    for rule in rules:
        if ctx.phase not in rule.phases or (rule.needs_pair and ctx.active.sum() <= 1):
            continue
        found = rule.find(ctx)
        for k in found:
            if not ctx.active[k.row]:
                raise ValueError(f"rule {rule.reason!r} killed row {k.row}, which was already dead")
            if k.reason != rule.reason and k.reason not in rule.also:
                k = Kill(k.row, rule.reason, k.partner, k.ratio)
            ctx.active[k.row] = False
            kills.append(k)
    return kills


# ---------------------------------------------------------------------------------------------- review rules
class ReviewRecord(NamedTuple):
    """One proposal's review at the end of a phase (§3.9); what the trace stores per review.

    Arrays are in the world frame; the mesh is relative to Θ_c (`mesh_vertices` + Θ_c = world) when it comes
    from the solver; `EMTrace.review_record` returns it in world coordinates.
    """

    step: int
    """Global step of the review."""
    phase: int
    """Phase it ends (1 or 2)."""
    proposal_id: int
    R: np.ndarray
    """(3, 3) pose used for the box: columns = canonical axes in the world frame."""
    R_raw: np.ndarray
    """(3, 3) pose from retrieval before the up-axis snap."""
    scale_sel: float
    """Codebook scale of the retrieved neighbours."""
    db_sim: float
    """Codebook similarity (NaN without a codebook)."""
    coverage: float
    """Fraction of completed-shape samples explained by observed points."""
    radii: np.ndarray
    """(2,) horizontal radius and half-height of the completed shape (m)."""
    scale_pass: bool
    up_angle: float
    """Angle between the canonical up axis and world +Z (degrees)."""
    pose_pass: bool
    obb_center: np.ndarray
    obb_axes: np.ndarray
    obb_half_extents: np.ndarray
    mask: np.ndarray
    """(n,) int32 scene indices of the tentative output mask."""
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    neighbours: np.ndarray
    """Codebook ids of the retrieved neighbours."""
    prior: int = 0
    """Index of the proposal's prior in the solve."""
    seen_through: float = float("nan")
    """Fraction of the completed shape's surface the capture camera saw through (NaN: not checked)."""
    planar: float = float("nan")
    """Share of its mask's normals that three directions hold (`geometry.normals.planar_share`; NaN: older
    traces, an empty mask)."""


@dataclass(frozen=True)
class ReviewColumn:
    """How one `ReviewRecord` field is kept in a trace (`REVIEW_COLUMNS`): the `EMTrace` array `trace`, one row
    per review of `shape` and `dtype`; a ragged field (`offsets`: the offsets array's name) as flat values plus
    offsets. An `optional` one is stored only when its check ran (`measured(config)`): older traces and runs
    without the check lack it, and their records hold NaN. `scores`: the names the trace replay's review scores
    (`em.replay.ProposalView.scores`, the viewer's inspector) give it, one per element of its row."""

    field: str
    trace: str
    shape: tuple[int, ...] = ()
    dtype: Any = np.float32
    offsets: str | None = None
    measured: "Callable[[EMConfig], bool] | None" = None
    scores: tuple[str, ...] = ()

    @property
    def optional(self) -> bool:
        return self.measured is not None


REVIEW_COLUMNS: tuple[ReviewColumn, ...] = (
    ReviewColumn("step", "rev_step", dtype=np.int32),
    ReviewColumn("phase", "rev_phase", dtype=np.int8),
    ReviewColumn("proposal_id", "rev_id", dtype=np.int32),
    ReviewColumn("R", "rev_R", (3, 3)),
    ReviewColumn("R_raw", "rev_R_raw", (3, 3)),
    ReviewColumn("scale_sel", "rev_scale_sel"),
    ReviewColumn("db_sim", "rev_db_sim", scores=("db_sim",)),
    ReviewColumn("coverage", "rev_coverage", scores=("coverage",)),
    ReviewColumn("radii", "rev_radii", (2,), scores=("radius_horizontal", "half_height")),
    ReviewColumn("scale_pass", "rev_scale_pass", dtype=bool, scores=("scale_pass",)),
    ReviewColumn("up_angle", "rev_up_angle", scores=("up_angle",)),
    ReviewColumn("pose_pass", "rev_pose_pass", dtype=bool, scores=("pose_pass",)),
    ReviewColumn("obb_center", "rev_obb_center", (3,)),
    ReviewColumn("obb_axes", "rev_obb_axes", (3, 3)),
    ReviewColumn("obb_half_extents", "rev_obb_half", (3,)),
    ReviewColumn("mask", "rev_mask", dtype=np.int32, offsets="rev_mask_offsets"),
    ReviewColumn("mesh_vertices", "rev_mesh_vertices", (3,), np.float16, offsets="rev_mesh_vertex_offsets"),
    ReviewColumn("mesh_faces", "rev_mesh_faces", (3,), np.int32, offsets="rev_mesh_face_offsets"),
    ReviewColumn("neighbours", "rev_neighbours", dtype=np.int32, offsets="rev_neighbour_offsets"),
    ReviewColumn("seen_through", "rev_seen_through", measured=lambda cfg: cfg.free_space.margin is not None,
                 scores=("seen_through",)),
    ReviewColumn("planar", "rev_planar", measured=lambda cfg: True, scores=("planar",)),
)
"""Every measure a review records, declared once: the trace's arrays, the recorder, `EMTrace.review_record`,
saving and loading, and the replay's scores are derived from this table (`ReviewRecord.prior` is not a column:
it comes from the trace's per-proposal prior table). A new measure is a `ReviewRecord` field, a row here and
its `EMTrace` array (tests check that the three agree)."""


@dataclass(frozen=True)
class ReviewRule:
    """A review check: `check(record, cfg)` → (passed, ratio recorded with the death)."""

    reason: str
    check: Callable[[ReviewRecord, EMConfig | None], tuple[bool, float]]


def size_passes(radii: np.ndarray, cfg: EMConfig) -> bool:
    """§3.9 size verdict: the completed shape's (horizontal radius, half-height) within the config's resolved
    ranges (`scale_horizontal`, `scale_height`, metres)."""
    h_rng, v_rng = cfg.review.scale_horizontal, cfg.review.scale_height
    if h_rng is None or v_rng is None:
        raise ValueError("size ranges unresolved: resolve the config for its prior first (resolve_for_prior)")
    return bool(h_rng[0] <= float(radii[0]) <= h_rng[1] and v_rng[0] <= float(radii[1]) <= v_rng[1])


def up_passes(up_angle: float, cfg: EMConfig) -> bool:
    """§3.9 up verdict: the angle between the canonical up axis and world +Z within the config's `up_range`."""
    rng = cfg.review.up_range
    if rng is None:
        raise ValueError("up range unresolved: resolve the config for its prior first (resolve_for_prior)")
    return bool(rng[0] <= float(up_angle) <= rng[1])


def _resolved(cfg: EMConfig | None, *names: str) -> bool:
    """Whether the config's review settings ``names`` are filled (by `resolve_for_prior`)."""
    return cfg is not None and all(getattr(cfg.review, n) is not None for n in names)


def _scale_check(rec: ReviewRecord, cfg: EMConfig | None) -> tuple[bool, float]:
    # the rule decides from the record's measures; a record read back without its config keeps its stored verdict
    ok = (size_passes(rec.radii, cfg) if cfg is not None and _resolved(cfg, "scale_horizontal", "scale_height")
          else bool(rec.scale_pass))
    return ok, float(np.max(rec.radii))


def _pose_check(rec: ReviewRecord, cfg: EMConfig | None) -> tuple[bool, float]:
    ok = up_passes(rec.up_angle, cfg) if cfg is not None and _resolved(cfg, "up_range") else bool(rec.pose_pass)
    return ok, float(rec.up_angle)


def _seen_through_check(rec: ReviewRecord, cfg: EMConfig | None) -> tuple[bool, float]:
    st = float(rec.seen_through)
    limit = 1.0
    if cfg is not None and not (cfg.free_space.final and int(rec.phase) == 1 and cfg.steps.t2 > 0):
        limit = cfg.free_space.max_seen_through  # with free_space.final the independent phase's review only measures
    return bool(not math.isfinite(st) or st <= limit), st


def _planar_check(rec: ReviewRecord, cfg: EMConfig | None) -> tuple[bool, float]:
    share = float(rec.planar)
    limit = cfg.review.max_planar if cfg is not None else None
    return bool(limit is None or not math.isfinite(share) or share <= limit), share


REVIEW_RULES: tuple[ReviewRule, ...] = (
    ReviewRule(REASON_SCALE, _scale_check),
    ReviewRule(REASON_POSE, _pose_check),
    ReviewRule(REASON_SEEN_THROUGH, _seen_through_check),
    ReviewRule(REASON_PLANAR, _planar_check),
)
"""The review checks: the method's (§3.9: the completed shape's size, then its up axis), then the free-space
check of single-view frames (`EMConfig.free_space.margin`; passes when it was not measured), then the planar
check of categories that ask for it (`EMConfig.review.max_planar`: a fit on a box's edge or corner)."""


def first_failed_review(rec: ReviewRecord, cfg: EMConfig | None, rules: Sequence[ReviewRule] = REVIEW_RULES
                        ) -> tuple[str, float] | None:
    """(reason, ratio) of the first review rule the record fails, or None when it passes them all."""
    for rule in rules:
        ok, ratio = rule.check(rec, cfg)
        if not ok:
            return rule.reason, ratio
    return None


def reason_names(step_rules: Sequence[StepRule] = STEP_RULES,
                 review_rules: Sequence[ReviewRule] = REVIEW_RULES) -> tuple[str, ...]:
    """The reason-name table of a run with these rules (its int8 death codes index it; "survive" last)."""
    names: list[str] = []
    every = [reason for r in step_rules for reason in (r.reason, *r.also)] + [r.reason for r in review_rules]
    for reason in every:
        if reason == REASON_SURVIVE:
            raise ValueError(f"a rule cannot be named {REASON_SURVIVE!r}")
        if reason not in names:
            names.append(reason)
    names.append(REASON_SURVIVE)
    if len(names) > 127:
        raise ValueError(f"too many distinct rule reasons ({len(names)}): the trace stores int8 codes")
    return tuple(names)
