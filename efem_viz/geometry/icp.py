"""Rotation-only ICP with a scipy cKDTree (docs/design/efem-method.md §3.9 step 6).

Both clouds are centred on their own centroids once; each iteration matches every source point to its
nearest target point, solves the orthogonal Procrustes problem on the matches and rotates the source.
Pure NumPy/SciPy; no torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from efem_viz.geometry.procrustes import rotation_from_cross_covariance

if TYPE_CHECKING:
    from efem_viz._typeshims import cKDTree

__all__ = ["IcpResult", "icp_rotation"]


class IcpResult(NamedTuple):
    """Outcome of `icp_rotation`."""

    R: np.ndarray
    """(3, 3) float64: accumulated rotation (applied about the source centroid), `R_total = R'_k ⋯ R'_1`."""
    aligned: np.ndarray
    """(N, 3) float64: the source, centred, rotated by `R`, then shifted onto the target centroid."""
    mean_distance: float
    """Mean nearest-neighbour distance source→target of the last iteration's matches (measured before
    that iteration's update, so it costs no extra tree query; with `iters=0`, of the unrotated source)."""
    iterations: int
    """Iterations actually run (stops early when the update rotation is below `tol_deg`)."""


def icp_rotation(
    source: np.ndarray,
    target: np.ndarray,
    *,
    iters: int = 3,
    proper: bool = True,
    tree: cKDTree | None = None,
    tol_deg: float = 0.0,
) -> IcpResult:
    """Rotation-only ICP about the clouds' centroids.

    Args:
        source: (N, 3) float, the cloud that moves.
        target: (M, 3) float, the fixed cloud.
        iters: number of iterations (>= 0).
        proper: restrict each update to SO(3); `False` reproduces the release (reflections possible).
        tree: a prebuilt `scipy.spatial.cKDTree` over the *centred* target (`target − target.mean(0)`),
            to share it across many sources; built here when None.
        tol_deg: stop early when an update rotates by less than this many degrees (0 = always run `iters`).

    Returns:
        IcpResult.
    """
    from efem_viz._typeshims import cKDTree

    X = np.asarray(source, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) == 0:
        raise ValueError(f"source must be a non-empty (N, 3) array, got {X.shape}")
    if Y.ndim != 2 or Y.shape[1] != 3 or len(Y) == 0:
        raise ValueError(f"target must be a non-empty (M, 3) array, got {Y.shape}")
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    my = Y.mean(axis=0)
    Yc = Y - my
    Xc = X - X.mean(axis=0)
    kd = cKDTree(Yc) if tree is None else tree
    R_total = np.eye(3)
    mean_d = float("nan")
    done = 0
    for _ in range(iters):
        dist, idx = kd.query(Xc, k=1)
        mean_d = float(np.mean(dist))
        H = Yc[idx].T @ Xc
        R_step = rotation_from_cross_covariance(H, proper=proper)
        Xc = Xc @ R_step.T
        R_total = R_step @ R_total
        done += 1
        if tol_deg > 0:
            cos = np.clip((np.trace(R_step) - 1.0) / 2.0, -1.0, 1.0)
            if np.degrees(np.arccos(cos)) < tol_deg:
                break
    if done == 0:
        dist, _ = kd.query(Xc, k=1)
        mean_d = float(np.mean(dist))
    return IcpResult(R_total, Xc + my, mean_d, done)
