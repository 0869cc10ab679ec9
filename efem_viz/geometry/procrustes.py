"""Procrustes / Kabsch / Umeyama alignment, for point sets and for vector-neuron latent codes.

Two flavours everywhere:

* `proper=False` — the best *orthogonal* map (may be a reflection, det = −1). This is what the EFEM release
  uses for its codebook pose search (docs/design/efem-method.md §3.9 steps 4 and 6).
* `proper=True` — the best *proper rotation* (Kabsch with the determinant fix: the sign of the smallest
  singular direction is flipped when `det(U Vᵀ) < 0`).

Pure NumPy; no torch.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = [
    "ProcrustesResult",
    "latent_procrustes",
    "procrustes",
    "rotation_from_cross_covariance",
]


def rotation_from_cross_covariance(H: np.ndarray, *, proper: bool = True) -> np.ndarray:
    """Maximise `tr(Rᵀ H)` over orthogonal (or proper-rotation) `R`.

    With `H = Σ_i w_i y_i x_iᵀ` (target times source), the result is the `R` that best maps the source
    vectors `x_i` onto the target vectors `y_i` (`y ≈ R x`).

    Args:
        H: (..., 3, 3) cross-covariance.
        proper: enforce det(R) = +1.

    Returns:
        (..., 3, 3) float64.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape[-2:] != (3, 3):
        raise ValueError(f"H must have shape (..., 3, 3), got {H.shape}")
    U, _, Vt = np.linalg.svd(H)
    if not proper:
        return U @ Vt
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


class ProcrustesResult(NamedTuple):
    """`target ≈ scale · R source + t` (rows: `target ≈ scale · source @ R.T + t`)."""

    R: np.ndarray
    """(3, 3) float64."""
    t: np.ndarray
    """(3,) float64."""
    scale: float
    """1.0 unless `with_scale=True`."""
    rmse: float
    """Weighted root-mean-square residual after alignment."""


def procrustes(
    source: np.ndarray,
    target: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    proper: bool = True,
    with_scale: bool = False,
) -> ProcrustesResult:
    """Weighted Kabsch (rigid) or Umeyama (similarity) alignment of corresponding points.

    Minimises `Σ_i w_i ‖s R x_i + t − y_i‖²`.

    Args:
        source: (N, 3) float, points `x_i`.
        target: (N, 3) float, corresponding points `y_i`.
        weights: (N,) non-negative weights (default all 1); must not all be zero.
        proper: restrict `R` to SO(3) (otherwise O(3), reflections allowed).
        with_scale: also solve for a positive scale `s` (Umeyama); otherwise s = 1.

    Returns:
        ProcrustesResult.

    Raises:
        ValueError: on mismatched shapes, fewer than 1 point or all-zero weights.
    """
    X = np.asarray(source, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or Y.shape != X.shape:
        raise ValueError(f"source and target must both be (N, 3); got {X.shape} and {Y.shape}")
    if len(X) == 0:
        raise ValueError("procrustes needs at least one point")
    w = np.ones(len(X)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (len(X),):
        raise ValueError(f"weights must have shape ({len(X)},), got {np.asarray(weights).shape}")
    if np.any(w < 0) or not w.sum() > 0:
        raise ValueError("weights must be non-negative and not all zero")
    w = w / w.sum()
    mx = w @ X
    my = w @ Y
    Xc = X - mx
    Yc = Y - my
    H = (Yc * w[:, None]).T @ Xc
    R = rotation_from_cross_covariance(H, proper=proper)
    if with_scale:
        var_x = float(w @ np.sum(Xc * Xc, axis=1))
        s = float(np.trace(R.T @ H) / var_x) if var_x > 0 else 1.0
        s = s if s > 0 else 1.0
    else:
        s = 1.0
    t = my - s * R @ mx
    resid = Y - (s * X @ R.T + t)
    rmse = float(np.sqrt(w @ np.sum(resid * resid, axis=1)))
    return ProcrustesResult(R, t, s, rmse)


def latent_procrustes(
    theta_obs: np.ndarray,
    theta_ref: np.ndarray,
    *,
    proper: bool = False,
) -> np.ndarray:
    """Rotation that maps reference VN codes onto observed ones (docs/design/efem-method.md §3.9 step 4).

    With observed channel vectors `θ_c` (rows of `theta_obs`, world frame) and reference vectors `θ'_c`
    (rows of `theta_ref`, canonical frame): `H = Σ_c θ_c θ'_cᵀ`, SVD `H = U Σ Vᵀ`, `R = U Vᵀ`. If
    `Θ_obs = Θ_ref Rᵀ` exactly (the VN transformation rule), this returns `R`. `proper=False` reproduces the
    release (may return a reflection); `proper=True` applies the determinant fix.

    Args:
        theta_obs: (C, 3) float, observed Θ_R.
        theta_ref: (C, 3) or (K, C, 3) float, reference code(s).
        proper: enforce det = +1.

    Returns:
        (3, 3) or (K, 3, 3) float64; columns are the reference (canonical) axes in the observed frame.
    """
    A = np.asarray(theta_obs, dtype=np.float64)
    B = np.asarray(theta_ref, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f"theta_obs must have shape (C, 3), got {A.shape}")
    if B.shape[-2:] != A.shape or B.ndim not in (2, 3):
        raise ValueError(f"theta_ref must have shape {A.shape} or (K, *{A.shape}), got {B.shape}")
    H = np.einsum("ci,...cj->...ij", A, B)
    return rotation_from_cross_covariance(H, proper=proper)
