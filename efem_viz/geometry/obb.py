"""Oriented bounding boxes from surface samples and a pose (docs/design/efem-method.md §3.9 step 8, the corrected form).

Given centred samples `Q = samples − Θ_c` and the pose `R` (columns = canonical x, y, z axes in the world
frame), the coordinates along the canonical axes are `Q̃ = Q R` (row form). Then `e = (max Q̃ − min Q̃)/2`,
`o = (max Q̃ + min Q̃)/2`, and the box has world centre `Θ_c + R o`, axes the columns of `R` and half-extents
`e`. (The release drops `o` from the corners; we keep it — this changes visuals only.)
Pure NumPy; no torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BOX_CORNER_SIGNS", "BOX_EDGES", "OBB", "oriented_box"]

BOX_CORNER_SIGNS: np.ndarray = np.array(
    [
        [+1, +1, +1],
        [-1, +1, +1],
        [+1, -1, +1],
        [+1, +1, -1],
        [-1, -1, +1],
        [+1, -1, -1],
        [-1, +1, -1],
        [-1, -1, -1],
    ],
    dtype=np.float64,
)
"""(8, 3) corner sign patterns in the release's order (+++, −++, +−+, ++−, −−+, +−−, −+−, −−−)."""

BOX_EDGES: np.ndarray = np.array(
    [[0, 1], [0, 2], [2, 4], [1, 4], [3, 6], [3, 5], [5, 7], [6, 7], [0, 3], [1, 6], [4, 7], [2, 5]],
    dtype=np.int32,
)
"""(12, 2) corner index pairs of the box edges, in the release's order."""


@dataclass(frozen=True)
class OBB:
    """An oriented box in the world frame."""

    center: np.ndarray
    """(3,) float64 world centre."""
    axes: np.ndarray
    """(3, 3) float64; column j is the box's j-th axis (canonical x, y, z) in the world frame."""
    half_extents: np.ndarray
    """(3,) float64 half side lengths along the columns of `axes` (world units)."""
    corners: np.ndarray
    """(8, 3) float64 world corners, `center + axes @ (signs * half_extents)` in `BOX_CORNER_SIGNS` order."""
    edges: np.ndarray
    """(12, 2) int32 corner index pairs (`BOX_EDGES`)."""

    @property
    def volume(self) -> float:
        """Box volume `8 e_x e_y e_z` (world units cubed)."""
        return float(8.0 * np.prod(self.half_extents))

    def local(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points to box-local coordinates along `axes` (origin at `center`)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        return (pts - self.center) @ self.axes

    def contains(self, points: np.ndarray, *, tol: float = 1e-9) -> np.ndarray:
        """Which points lie inside the box (inclusive, with absolute tolerance `tol`).

        Args:
            points: (N, 3) float, world frame.
            tol: slack added to each half-extent.

        Returns:
            (N,) bool.
        """
        return np.all(np.abs(self.local(points)) <= self.half_extents + tol, axis=1)

    def line_segments(self) -> np.ndarray:
        """(12, 2, 3) float64 endpoints of the edges (ready for a line-segment renderer)."""
        return self.corners[self.edges]


def _box(center: np.ndarray, axes: np.ndarray, half_extents: np.ndarray) -> OBB:
    corners = center + (BOX_CORNER_SIGNS * half_extents) @ axes.T
    return OBB(
        center=center,
        axes=axes,
        half_extents=half_extents,
        corners=corners,
        edges=BOX_EDGES.copy(),
    )


def oriented_box(samples_world: np.ndarray, center: np.ndarray, R: np.ndarray) -> OBB:
    """Tight box of `samples_world` along the axes of `R`.

    Args:
        samples_world: (S, 3) float, surface samples in the world frame (S >= 1).
        center: (3,) float, the object centre `Θ_c` (world); only used as the origin of the projection, the
            box centre is the true mid-point `Θ_c + R o`.
        R: (3, 3) orthonormal matrix (a proper rotation for display); columns = canonical axes in world.

    Returns:
        OBB.

    Raises:
        ValueError: on bad shapes, no samples, non-finite values or a non-orthonormal `R`.
    """
    Q = np.asarray(samples_world, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64).reshape(-1)
    Rm = np.asarray(R, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[1] != 3 or len(Q) == 0:
        raise ValueError(f"samples_world must be a non-empty (S, 3) array, got {Q.shape}")
    if c.shape != (3,):
        raise ValueError(f"center must have shape (3,), got {np.asarray(center).shape}")
    if Rm.shape != (3, 3):
        raise ValueError(f"R must have shape (3, 3), got {Rm.shape}")
    if not (np.isfinite(Q).all() and np.isfinite(c).all() and np.isfinite(Rm).all()):
        raise ValueError("oriented_box got non-finite input")
    if not np.allclose(Rm.T @ Rm, np.eye(3), atol=1e-4):
        raise ValueError(f"R must be orthonormal; RᵀR =\n{Rm.T @ Rm}")
    Qt = (Q - c) @ Rm
    hi = Qt.max(axis=0)
    lo = Qt.min(axis=0)
    e = (hi - lo) / 2.0
    o = (hi + lo) / 2.0
    return _box(c + Rm @ o, Rm.copy(), e)
