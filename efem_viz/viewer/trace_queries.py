"""What the viewer makes of a recorded run: the deaths as the panels list them, the timeline's phase marks, the
top-N proposals to draw, the drawn proposals' samples coloured by proposal (`proposal_samples`) and a stored
latent's decoded shape (`decode_shape`). Plain NumPy over an `efem_viz.em.EMTrace` (no viser, no drawing module:
the headless sessions use them, and so do the scene nodes).

The questions that are the trace's own are `EMTrace` methods: `alive_scores(step)` (a step's proposals and their
stationary scores), `sample_indices(pid, step)`, `is_dead_at(pid, step)`, `center_at(pid, step)`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.colors import instance_colors

if TYPE_CHECKING:
    from efem_viz.em.trace import EMTrace
    from efem_viz.prior.config import ShapePriorLike


@dataclass(frozen=True)
class PhaseMark:
    """A labelled step on the timeline (phase start or end-of-phase review)."""

    step: int
    label: str


def phase_marks(phase: np.ndarray) -> list[PhaseMark]:
    """Timeline marks from the per-step phase array.

    Args:
        phase: (T,) int phase (1 or 2, possibly with episodes repeating the pattern) of each EM step.

    Returns:
        A mark at step 0 ("P1"), at each phase change ("P<phase>") and a review mark ("R") at the last step of
        every phase run (the review runs after that step).
    """
    ph = np.asarray(phase).reshape(-1)
    marks: list[PhaseMark] = []
    if ph.size == 0:
        return marks
    marks.append(PhaseMark(0, f"P{int(ph[0])}"))
    for t in range(1, ph.size):
        if ph[t] != ph[t - 1]:
            marks.append(PhaseMark(t - 1, "R"))
            marks.append(PhaseMark(t, f"P{int(ph[t])}"))
    marks.append(PhaseMark(int(ph.size - 1), "R"))
    # Merge marks that fall on the same step: "R|P2".
    merged: dict[int, str] = {}
    for m in marks:
        merged[m.step] = f"{merged[m.step]}|{m.label}" if m.step in merged else m.label
    return [PhaseMark(s, lab) for s, lab in sorted(merged.items())]


def top_n(ids: np.ndarray, scores: np.ndarray, n: int) -> np.ndarray:
    """The `n` ids with the highest scores (ties broken by id), in descending score order.

    Args:
        ids: (K,) int proposal ids.
        scores: (K,) float scores (NaN counts as lowest).
        n: how many to keep (<= 0 keeps none).
    """
    ids_arr = np.asarray(ids).reshape(-1)
    sc = np.asarray(scores, dtype=np.float64).reshape(-1)
    if ids_arr.shape != sc.shape:
        raise ValueError(f"ids {ids_arr.shape} and scores {sc.shape} differ in shape")
    if n <= 0 or ids_arr.size == 0:
        return ids_arr[:0]
    sc = np.where(np.isfinite(sc), sc, -np.inf)
    order = np.lexsort((ids_arr, -sc))
    return ids_arr[order[:n]]


@dataclass(frozen=True)
class Death:
    """A terminated proposal: id, step, reason ("proposal too small", "duplicated or included", ...), partner."""

    pid: int
    step: int
    reason: str
    partner: int | None = None
    ratio: float | None = None


def deaths(trace: EMTrace) -> list[Death]:
    """Every terminated proposal with its step and reason (accepted survivors excluded), in order of death."""
    out: list[Death] = []
    for ev in trace.events():
        reason = str(ev.reason)
        if reason == "survive":
            continue
        partner, ratio = int(ev.partner), float(ev.ratio)
        out.append(
            Death(
                pid=int(ev.proposal_id),
                step=int(ev.step),
                reason=reason,
                partner=None if partner < 0 else partner,
                ratio=None if not np.isfinite(ratio) else ratio,
            )
        )
    return out


def proposal_anchors(trace: EMTrace, drawn: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The anchor points of some proposals (where their first crops are centred), each coloured by its proposal
    id as its samples are (`proposal_samples`).

    Returns:
        (D, 3) float32 points and (D, 3) uint8 colours.
    """
    ids = np.asarray(drawn, np.int64).reshape(-1)
    anchors = np.asarray(trace.prop_anchor, np.int64)[ids]
    return np.asarray(points, np.float32)[anchors], np.asarray(instance_colors(ids), np.uint8).reshape(-1, 3)


def proposal_samples(
    trace: EMTrace, step: int, drawn: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points sampled by some proposals at one step, each coloured by its proposal id.

    Args:
        trace: the run's `EMTrace`.
        step: EM step.
        drawn: (D,) int proposal ids to draw.
        points: (N, 3) float32 scene points, world frame.

    Returns:
        (S, 3) float32 points and (S, 3) uint8 colours (S = 0 when none of them sampled anything).
    """
    cols = instance_colors(drawn)
    pts_list, col_list = [], []
    for k, pid in enumerate(np.asarray(drawn).reshape(-1)):
        idx = trace.sample_indices(int(pid), int(step))
        if idx is None or idx.size == 0:
            continue
        idx = np.unique(idx)
        pts_list.append(np.asarray(points)[idx])
        col_list.append(np.repeat(cols[k : k + 1], idx.size, axis=0))
    if not pts_list:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    return np.concatenate(pts_list).astype(np.float32), np.concatenate(col_list).astype(np.uint8)


def decode_shape(
    prior: ShapePriorLike, latent: dict[str, np.ndarray], *, resolution: int, max_faces: int | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """World-frame mesh of a stored latent, or None when its SDF has no zero crossing on the grid.

    Args:
        prior: the run's shape prior.
        latent: `EMTrace.latent(pid, step)`.
        resolution: meshing grid (the run's `EMConfig.review.mesh_resolution`).
        max_faces: decimate to at most this many faces (`simplify_mesh`; None: the marching-cubes mesh).

    Returns:
        (V, 3) float32 vertices and (F, 3) int32 faces, or None.
    """
    from efem_viz.em.decoding import mesh_of_latent

    mesh = mesh_of_latent(prior, latent, resolution=int(resolution))
    if mesh is None or not len(getattr(mesh, "faces", ())):
        return None
    if max_faces is not None:
        from efem_viz.prior.meshing import simplify_mesh

        mesh = simplify_mesh(mesh, int(max_faces))
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
