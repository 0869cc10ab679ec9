"""Farthest-point sampling (batched, torch), deterministic start index."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch


def farthest_point_sample(points: torch.Tensor, n_samples: int, *, start: int = 0) -> torch.Tensor:
    """Greedy farthest-point sampling starting from a fixed index.

    The result depends only on pairwise distances, so it is invariant to similarity transforms of the input
    (up to exact ties), but not to a permutation of the input order.

    Args:
        points: ``(B, N, D)`` float positions (any frame; D is usually 3).
        n_samples: Number of points to keep, ``1 <= n_samples <= N``.
        start: Index of the first sample (the spec uses 0).

    Returns:
        ``(B, n_samples)`` int64 indices into ``N``; the first column equals ``start``.

    Raises:
        ValueError: On a bad shape or sample count.
    """
    import torch

    if points.ndim != 3:
        raise ValueError(f"points must be (B, N, D), got {tuple(points.shape)}")
    b, n, _ = points.shape
    if not 1 <= n_samples <= n:
        raise ValueError(f"n_samples must be in [1, {n}], got {n_samples}")
    if not 0 <= start < n:
        raise ValueError(f"start must be in [0, {n}), got {start}")
    with torch.no_grad():
        comps = [c.contiguous() for c in points.detach().unbind(-1)]  # D x (B, N): contiguous slices are fast
        idx = torch.empty(b, n_samples, dtype=torch.long, device=points.device)
        dist = torch.full((b, n), float("inf"), dtype=points.dtype, device=points.device)
        cur = torch.full((b, 1), start, dtype=torch.long, device=points.device)
        for i in range(n_samples):
            idx[:, i] = cur[:, 0]
            d = None
            for c in comps:
                diff = c - c.gather(1, cur)
                d = diff * diff if d is None else d + diff * diff
            if d is None:
                raise ValueError("points must have at least one coordinate (D >= 1), got D = 0")
            dist = torch.minimum(dist, d)
            cur = dist.argmax(dim=1, keepdim=True)
    return idx
