"""Nearest neighbours: brute-force k-NN (batched, torch, any feature dimension) and point spacing (KD-tree)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


def knn_indices(query: torch.Tensor, ref: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the ``k`` nearest ``ref`` rows of every ``query`` row (Euclidean, ascending distance).

    Args:
        query: ``(B, Nq, D)`` float.
        ref: ``(B, Nr, D)`` float, same dtype/device.
        k: Neighbours per query, ``1 <= k <= Nr``.

    Returns:
        ``(B, Nq, k)`` int64 indices into ``Nr``. No gradient flows through the selection.

    Raises:
        ValueError: On mismatched shapes or a bad ``k``.
    """
    import torch

    if query.ndim != 3 or ref.ndim != 3 or query.shape[0] != ref.shape[0] or query.shape[2] != ref.shape[2]:
        raise ValueError(f"query (B,Nq,D) and ref (B,Nr,D) must agree, "
                         f"got {tuple(query.shape)} / {tuple(ref.shape)}")
    if not 1 <= k <= ref.shape[1]:
        raise ValueError(f"k must be in [1, {ref.shape[1]}], got {k}")
    # float32 distances even inside a bf16 autocast region (EMConfig.compute.matmul_dtype): bf16 keeps 8 bits of
    # mantissa, too few to order neighbours in feature space
    with torch.no_grad(), torch.autocast(query.device.type, enabled=False):
        q = query.detach().float() if query.dtype in (torch.bfloat16, torch.float16) else query.detach()
        r = ref.detach().to(q.dtype)
        d2 = (q * q).sum(-1, keepdim=True) - 2.0 * q @ r.transpose(1, 2) + (r * r).sum(-1)[:, None, :]
        return d2.topk(k, dim=-1, largest=False).indices


def point_spacing(points: np.ndarray) -> np.ndarray:
    """(N,) distance of every point to its nearest other point (m)."""
    from efem_viz._typeshims import cKDTree

    pts = np.asarray(points, np.float64)
    if len(pts) < 2:
        return np.zeros(len(pts))
    dist, _ = cKDTree(pts).query(pts, k=2)
    return np.asarray(dist[:, 1], np.float64)
