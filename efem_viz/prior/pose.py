"""Pose of a proposal: codebook retrieval, latent Procrustes and rotation-only ICP
(docs/design/efem-method.md §3.9, 2-7).

Steps for one latent Θ with centred surface samples `Q` (samples of its decoded mesh minus Θ_c, world scale):

1. retrieve `k_inv + k_so3 + k_joint` codebook rows (`Codebook.retrieve`, duplicates kept);
2. per neighbour n: latent Procrustes `R_n = U Vᵀ` of `H = Σ_c θ_c θ'_cᵀ`;
3. bring its canonical cloud over: `A_n = (Θ_s/Θ'_s,n) R_n (pcl_n − c_n)` (`c_n` = the stored full centre);
4. rotation-only ICP (`icp_iters` iterations, about the centroids), `R_n ← R' R_n`;
5. inlier ratio `r_n = (#{Q→A < τ} + #{A→Q < τ}) / (|Q| + |A|)` with distances in canonical units
   (× Θ'_s,n/Θ_s); select `n* = argmax r_n`.

Reflections (spec §8.5, our decision). Steps 2 and 4 use the release's *orthogonal* Procrustes (no
determinant fix), so `R_raw = R_{n*}` may be a reflection (det −1); it is returned as found, with
`score_db_sim = r_{n*}` (release parity; the EM orientation check reads `R_raw` like the release does). For
display and the OBB, `R` must be a proper rotation. Projecting a reflection matrix after the fact is
ill-posed (all singular values are 1, so "the nearest rotation" is arbitrary), so instead we **re-solve**
for the selected neighbour: latent Procrustes with the determinant fix (`U diag(1,1,det(UVᵀ)) Vᵀ`), then ICP
restricted to SO(3). That finds the best proper rotation aligning the same neighbour; when `R_raw` is
already proper, `R = R_raw`. With `proper_search=True` every neighbour is aligned with proper rotations from
the start (then `R_raw = R` always).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from efem_viz.geometry.icp import icp_rotation
from efem_viz.geometry.procrustes import latent_procrustes

if TYPE_CHECKING:
    from efem_viz.prior.codebook import Codebook

logger = logging.getLogger(__name__)

__all__ = ["PoseEstimate", "estimate_pose"]


@dataclass(frozen=True)
class PoseEstimate:
    """Result of `estimate_pose`."""

    R: np.ndarray
    """(3, 3) float64 proper rotation (det +1); columns = canonical x, y, z axes in the world frame."""
    R_raw: np.ndarray
    """(3, 3) float64 orthogonal matrix as found by the release's search (may be a reflection)."""
    scale_sel: float
    """Θ'_s of the selected codebook entry (the mean codebook scale when there were no samples)."""
    score_db_sim: float
    """Inlier ratio r_{n*} in [0, 1] (release parity: of the raw search)."""
    neighbour_ids: np.ndarray
    """(n,) int64 codebook rows retrieved (duplicates kept), in retrieval order."""
    scores: np.ndarray
    """(n,) float64 inlier ratio per retrieved neighbour."""
    selected: int
    """Codebook row n* (−1 when there were no samples)."""
    aligned_cloud: np.ndarray
    """(n_store, 3) float64 the selected entry's cloud aligned to the samples by `R` (same frame as the
    samples: world orientation and scale, centred like `surface_samples`)."""
    reflected: bool
    """True when `R_raw` was a reflection and `R` was re-solved."""

    @property
    def neighbours(self) -> np.ndarray:
        """Alias of `neighbour_ids` (docs/INTERFACES.md name)."""
        return self.neighbour_ids

    @property
    def up(self) -> np.ndarray:
        """(3,) canonical up axis (+Z column of `R`) in the world frame."""
        return self.R[:, 2]


def _align_neighbour(
    theta: np.ndarray,
    scale: float,
    cb: Codebook,
    n: int,
    Q: np.ndarray,
    Q_tree: Any,
    *,
    icp_iters: int,
    proper: bool,
    subset: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Latent Procrustes + ICP for codebook row n (on the cloud's `subset` rows, when given). Returns
    (R_n (3,3), aligned cloud (n_store or len(subset), 3))."""
    R0 = latent_procrustes(theta, cb.z_so3[n].astype(np.float64), proper=proper)
    cloud = cb.cloud(n) if subset is None else cb.pcl[n][subset].astype(np.float64)
    A = (scale / float(cb.scale[n])) * (cloud - cb.center[n].astype(np.float64)) @ R0.T
    res = icp_rotation(A, Q, iters=icp_iters, proper=proper, tree=Q_tree)
    return res.R @ R0, res.aligned


def _subset(n: int, k: int | None) -> np.ndarray | None:
    """Fixed random rows (seed 0, sorted) of an n-row sample set, or None when k keeps them all."""
    if k is None or k >= n:
        return None
    return np.sort(np.random.default_rng(0).choice(n, size=int(k), replace=False))


def _inlier_ratio(Q: np.ndarray, Q_tree: Any, A: np.ndarray, to_canonical: float, tau: float) -> float:
    from efem_viz._typeshims import cKDTree

    d_aq, _ = Q_tree.query(A - Q.mean(axis=0), k=1)
    d_qa, _ = cKDTree(A).query(Q, k=1)
    hits = np.count_nonzero(d_aq * to_canonical < tau) + np.count_nonzero(d_qa * to_canonical < tau)
    return hits / float(len(Q) + len(A))


def _pose_inputs(prior: Any, latent_i: Any, surface_samples: np.ndarray, normals: np.ndarray | None, *,
                 codebook: Codebook | None) -> tuple[Codebook, np.ndarray, np.ndarray, float]:
    """`estimate_pose`'s inputs, checked: the codebook (`codebook`, else the prior's), the (S, 3) float64 samples,
    and the latent's Θ_R (C, 3) and Θ_s.

    Raises:
        ValueError: no codebook, samples not (S, 3) or not finite, normals of another shape, Θ_s not > 0.
    """
    from efem_viz.prior.codebook import latent_to_numpy

    cb = codebook if codebook is not None else getattr(prior, "codebook", None)
    if cb is None:
        raise ValueError("estimate_pose needs a codebook: the prior has none (run `efem-viz build-codebook`)")
    Q = np.asarray(surface_samples, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[1] != 3:
        raise ValueError(f"surface_samples must have shape (S, 3), got {Q.shape}")
    if normals is not None and np.shape(normals) != Q.shape:
        raise ValueError(f"normals must have the shape of surface_samples {Q.shape}, got {np.shape(normals)}")
    if not np.isfinite(Q).all():
        raise ValueError("surface_samples contain non-finite values")
    theta, _, _, scale = latent_to_numpy(latent_i)
    if not scale > 0:
        raise ValueError(f"latent scale must be > 0, got {scale}")
    return cb, Q, theta, scale


def _no_surface_pose(cb: Codebook) -> PoseEstimate:
    """The pose of a proposal without surface samples (an empty mesh): identity, score 0, no neighbour, and the
    mean codebook scale (finite, so downstream unit conversions stay finite)."""
    eye = np.eye(3)
    return PoseEstimate(eye, eye.copy(), cb.mean_scale, 0.0, np.zeros(0, np.int64), np.zeros(0), -1,
                        np.zeros((0, 3)), False)


def _placed_cloud(cb: Codebook, n: int, R: np.ndarray, *, scale: float, centroid: np.ndarray) -> np.ndarray:
    """(n_store, 3) float64: codebook row `n`'s whole cloud at the proposal's scale, rotated by `R` and centred on
    `centroid` (the samples' centroid), as the search placed its subset."""
    full = (scale / float(cb.scale[n])) * (cb.cloud(n) - cb.center[n].astype(np.float64))
    A = full @ R.T
    return A - A.mean(axis=0) + centroid


def _score_neighbours(
    nbrs: np.ndarray,
    align: Callable[[int, bool], tuple[np.ndarray, np.ndarray]],
    *,
    proper: bool,
    Q: np.ndarray,
    Q_tree: Any,
    cb: Codebook,
    scale: float,
    tau_db: float,
) -> tuple[np.ndarray, dict[int, tuple[np.ndarray, np.ndarray, float]]]:
    """Align every retrieved neighbour once (`align(n, proper)`: steps 2-4) and score it (step 5).

    Returns:
        (n,) float64 inlier ratio per retrieved neighbour (duplicates share theirs), and per distinct codebook
        row its (R_n, aligned cloud, inlier ratio).
    """
    cache: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
    scores = np.zeros(len(nbrs))
    for j, n in enumerate(nbrs.tolist()):
        if n not in cache:
            R_n, A_n = align(n, proper)
            r_n = _inlier_ratio(Q, Q_tree, A_n, float(cb.scale[n]) / scale, tau_db)
            cache[n] = (R_n, A_n, r_n)
        scores[j] = cache[n][2]
    return scores, cache


def estimate_pose(
    prior: Any,
    latent_i: Any,
    surface_samples: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    codebook: Codebook | None = None,
    icp_iters: int = 3,
    tau_db: float = 0.04,
    k_inv: int = 10,
    k_so3: int = 3,
    k_joint: int = 3,
    proper_search: bool = False,
    search_points: int | None = None,
) -> PoseEstimate:
    """Pose of one proposal from the prior's codebook (spec §3.9 steps 3-7).

    Args:
        prior: the `ShapePrior` (only its `.codebook` is used, when `codebook` is None).
        latent_i: one `Latent` (Θ_R (1, C, 3) or (C, 3)), world frame.
        surface_samples: (S, 3) float, samples of the proposal's decoded surface minus Θ_c (world orientation
            and scale, centred at the object centre). All-zero/empty samples: identity pose, score 0.
        normals: (S, 3) face normals of the samples; accepted for interface compatibility, not used by the
            pose search (they matter for the coverage score only).
        codebook: overrides `prior.codebook`.
        icp_iters: rotation-only ICP iterations per neighbour.
        tau_db: inlier threshold in canonical units (0.04 mugs/kitchen, 0.05 chairs).
        k_inv: neighbours by Θ_inv.
        k_so3: neighbours by the projected Θ_R.
        k_joint: neighbours by both.
        proper_search: align every neighbour with proper rotations only (no reflections anywhere).
        search_points: align and score the neighbours on fixed random subsets of this many samples (of the
            proposal and of each codebook cloud) instead of all of them; the search's cost falls in proportion
            (k-d tree queries dominate) and the inlier ratios become estimates of the same fractions. None =
            every sample. `aligned_cloud` is always the whole selected cloud.

    Returns:
        PoseEstimate.

    Raises:
        ValueError: no codebook, or bad shapes.
    """
    from efem_viz._typeshims import cKDTree

    cb, Q, theta, scale = _pose_inputs(prior, latent_i, surface_samples, normals, codebook=codebook)
    if len(Q) == 0 or not np.any(Q):
        return _no_surface_pose(cb)
    if search_points is not None and search_points < 1:
        raise ValueError(f"search_points must be >= 1 or None, got {search_points}")
    nbrs = cb.retrieve(latent_i, k_inv=k_inv, k_so3=k_so3, k_joint=k_joint)
    Q_full = Q
    q_sub = _subset(len(Q), search_points)
    c_sub = _subset(cb.pcl.shape[1], search_points)
    if q_sub is not None:
        Q = Q[q_sub]
    Q_tree = cKDTree(Q - Q.mean(axis=0))

    def align(n: int, proper: bool) -> tuple[np.ndarray, np.ndarray]:
        return _align_neighbour(theta, scale, cb, n, Q, Q_tree, icp_iters=icp_iters, proper=proper, subset=c_sub)

    scores, cache = _score_neighbours(nbrs, align, proper=bool(proper_search), Q=Q, Q_tree=Q_tree, cb=cb,
                                      scale=scale, tau_db=tau_db)
    best = int(np.argmax(scores))
    n_star = int(nbrs[best])
    R_raw, A_raw, r_star = cache[n_star]
    reflected = bool(np.linalg.det(R_raw) < 0)
    R, A = align(n_star, True) if reflected else (R_raw, A_raw)
    if q_sub is not None or c_sub is not None:  # the whole selected cloud, placed as the search placed its subset
        A = _placed_cloud(cb, n_star, R, scale=scale, centroid=Q_full.mean(axis=0))
    return PoseEstimate(
        R=R,
        R_raw=R_raw,
        scale_sel=float(cb.scale[n_star]),
        score_db_sim=float(r_star),
        neighbour_ids=nbrs,
        scores=scores,
        selected=n_star,
        aligned_cloud=A,
        reflected=reflected,
    )
