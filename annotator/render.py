"""Spatial chunks and label colours for drawing big scans with partial updates (pure numpy).

viser cannot update part of an array, so the scan is split into spatial chunks (a kd split into boxes of at most
`max_chunk` points); each chunk is one point-cloud node, and an edit resends the colours of the chunks it touched
only (3 bytes per point of those chunks).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from annotator.labels import InstanceInfo


@dataclass(frozen=True)
class Chunks:
    """A partition of the scan vertices into spatially compact chunks."""

    order: np.ndarray
    """(N,) int32: vertex ids grouped by chunk (chunk c = order[offsets[c]:offsets[c+1]])."""
    offsets: np.ndarray
    """(C+1,) int64 chunk boundaries in `order`."""
    chunk_of: np.ndarray
    """(N,) int32 chunk of each vertex (-1: a vertex that is not drawn, see `lifted`)."""

    @property
    def count(self) -> int:
        return int(len(self.offsets) - 1)

    def members(self, c: int) -> np.ndarray:
        """(n_c,) int32 vertex ids of chunk c."""
        return self.order[self.offsets[c] : self.offsets[c + 1]]

    def touched(self, idx: np.ndarray) -> np.ndarray:
        """Sorted chunk ids that contain any of the vertices `idx`."""
        if len(idx) == 0:
            return np.zeros(0, np.int32)
        c = np.unique(self.chunk_of[idx])
        return c[c >= 0] if len(c) and c[0] < 0 else c

    def lifted(self, ids: np.ndarray, n: int) -> Chunks:
        """These chunks, built over the points `ids` of an `n`-vertex scan, in that scan's vertex ids; the other
        vertices belong to no chunk (chunk -1).

        Args:
            ids: (D,) int vertex ids, in the order of the points the chunks were built on.
            n: vertex count of the scan.
        """
        ids = np.asarray(ids, np.int32)
        chunk_of = np.full(n, -1, np.int32)
        chunk_of[ids] = self.chunk_of
        return Chunks(order=ids[self.order], offsets=self.offsets, chunk_of=chunk_of)


def build_chunks(points: np.ndarray, *, max_chunk: int = 32768) -> Chunks:
    """Split points into chunks of at most `max_chunk` by recursive median splits along the longest axis.

    Args:
        points: (N, 3) float, world frame.
        max_chunk: maximum points per chunk.

    Returns:
        `Chunks`.
    """
    pts = np.asarray(points)
    n = len(pts)
    if max_chunk < 1:
        raise ValueError(f"max_chunk must be >= 1, got {max_chunk}")
    stack = [np.arange(n, dtype=np.int32)]
    done: list[np.ndarray] = []
    while stack:
        ids = stack.pop()
        if len(ids) <= max_chunk:
            done.append(ids)
            continue
        p = pts[ids]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        half = len(ids) // 2
        part = np.argpartition(p[:, axis], half)
        stack.append(ids[part[half:]])
        stack.append(ids[part[:half]])
    order = np.concatenate(done) if done else np.zeros(0, np.int32)
    offsets = np.concatenate([[0], np.cumsum([len(d) for d in done])]).astype(np.int64)
    chunk_of = np.empty(n, np.int32)
    for c, d in enumerate(done):
        chunk_of[d] = c
    return Chunks(order=order.astype(np.int32), offsets=offsets, chunk_of=chunk_of)


def color_lut(instances: Mapping[int, InstanceInfo], top: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour lookup tables indexed by label.

    Args:
        instances: instance table.
        top: highest label value that may occur.

    Returns:
        (lut (top+1, 3) uint8 instance colours, show (top+1,) bool: draw the label colour, i.e. the id is > 0,
        known and visible). Unreviewed EFEM pre-labels get a pale version of their colour (`PRELABEL_PALE`), so
        that what nobody has checked yet stands apart from accepted and hand-made instances.
    """
    size = max(int(top), max(instances, default=0)) + 1
    lut = np.zeros((size, 3), np.uint8)
    show = np.zeros(size, bool)
    for k, info in instances.items():
        col = np.asarray(info.color, np.float32)
        lut[k] = np.round(col + PRELABEL_PALE * (255.0 - col)) if info.unreviewed else col
        show[k] = info.visible
    return lut, show


PRELABEL_PALE = 0.55
"""Unreviewed pre-labels are drawn in their colour blended this far toward white."""
UNLABELLED_DIM = 0.8
"""The labels-only view draws unlabelled vertices in their grey shade blended this far toward light grey."""
SEARCH_COLOR = (255, 170, 0)
"""A running EFEM's live proposals: the points they sampled at the newest step are tinted this colour."""
SEARCH_ALPHA = 0.5
"""Weight of `SEARCH_COLOR` over the scan colour."""


def compose_colors(
    base: np.ndarray,
    labels: np.ndarray,
    lut: np.ndarray,
    show: np.ndarray,
    *,
    alpha: float = 0.7,
    highlight: np.ndarray | None = None,
    dim_unlabelled: bool = False,
    overlay: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Display colours: label colour blended over the scan colour where labelled and visible.

    Args:
        base: (K, 3) uint8 scan colours of the vertices to draw.
        labels: (K,) int labels of the same vertices.
        lut, show: from `color_lut`.
        alpha: label colour weight in [0, 1].
        highlight: (K,) bool vertices drawn bright white-ish (preview of a proposal), or None.
        dim_unlabelled: the labels-only view: vertices drawn without a label colour become a faint grey
            (`UNLABELLED_DIM`), so what is labelled stands out.
        overlay: a running EFEM's progress (`annotator.parts.assist.RunOverlay`): ((K,) uint16 codes of the same
            vertices — 0 nothing, 1 sampled by a live proposal (`SEARCH_COLOR` at `SEARCH_ALPHA`), k + 2 the k-th
            accepted instance (its colour made pale as a pre-label's, at `alpha`) — and (A, 3) uint8 colours of
            the accepted instances), drawn over unlabelled vertices only; None: none.

    Returns:
        (K, 3) uint8.
    """
    lab = np.minimum(labels, len(lut) - 1)
    m = show[lab] & (labels > 0) & (labels < len(lut))
    out = base.copy()
    if dim_unlabelled and (~m).any():
        lum = base[~m].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
        grey = np.round(lum * (1 - UNLABELLED_DIM) + 235.0 * UNLABELLED_DIM).astype(np.uint8)
        out[~m] = grey[:, None]
    if m.any():
        a = np.float32(alpha)
        out[m] = (a * lut[lab[m]].astype(np.float32) + (1 - a) * base[m].astype(np.float32)).astype(np.uint8)
    if overlay is not None:
        codes, accepted = overlay
        o = (codes > 0) & (labels <= 0)
        if o.any():
            pale = np.asarray(accepted, np.float32).reshape(-1, 3)
            pale = np.round(pale + PRELABEL_PALE * (255.0 - pale))
            palette = np.concatenate([np.zeros((1, 3), np.float32), np.asarray([SEARCH_COLOR], np.float32), pale])
            c = np.minimum(codes[o], len(palette) - 1)
            w = np.where(c == 1, SEARCH_ALPHA, alpha).astype(np.float32)[:, None]
            out[o] = (w * palette[c] + (1 - w) * out[o].astype(np.float32)).astype(np.uint8)
    if highlight is not None and highlight.any():
        out[highlight] = (0.5 * out[highlight].astype(np.float32) + 127.0).astype(np.uint8)
    return out


def splat_proxy(
    points: np.ndarray, normals: np.ndarray, *, size: float, max_splats: int = 150_000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A light triangle-splat surface for a point cloud (one small triangle per sampled point).

    Point clouds receive no drag events in viser; this proxy mesh (drawn fully transparent) does. It only has
    to catch where a drag starts: later positions are ray-cast against the points themselves.

    Args:
        points: (N, 3) float, world frame.
        normals: (N, 3) unit normals.
        size: splat circumradius, metres (about 2-3x the point spacing).
        max_splats: at most this many splats (a random subset beyond).
        seed: subset seed.

    Returns:
        (vertices (3S, 3) float32, faces (S, 3) int32).
    """
    pts = np.asarray(points, np.float32)
    nrm = np.asarray(normals, np.float32)
    n = len(pts)
    if n > max_splats:
        pick = np.sort(np.random.default_rng(seed).choice(n, size=max_splats, replace=False))
        pts, nrm = pts[pick], nrm[pick]
    ref = np.where(np.abs(nrm[:, 2:3]) < 0.9, np.array([[0, 0, 1]], np.float32), np.array([[1, 0, 0]], np.float32))
    t1 = np.cross(nrm, ref)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = np.cross(nrm, t1)
    c = pts - 0.3 * size * nrm  # slightly behind the points so it never hides them
    s = np.float32(size)
    v0 = c + s * t1
    v1 = c + s * (-0.5 * t1 + 0.8660254 * t2)
    v2 = c + s * (-0.5 * t1 - 0.8660254 * t2)
    verts = np.stack([v0, v1, v2], axis=1).reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    return verts, faces


CURSOR_SEGMENTS = 48
"""Segments of the brush cursor's ring."""
CURSOR_LIFT = 0.2
"""The brush cursor's ring floats this many radii above the surface along its normal (a ring in the tangent plane
of a curved surface would otherwise sink into it)."""


def ring_segments(center: np.ndarray, normal: np.ndarray, radius: float, *, n: int = CURSOR_SEGMENTS) -> np.ndarray:
    """A circle of `radius` around `center` in the plane perpendicular to `normal`, lifted `CURSOR_LIFT` radii along
    it: the brush cursor.

    Args:
        center: (3,) float, the brush position on the surface, world frame.
        normal: (3,) float, the surface normal there (any length; a zero normal draws the ring flat, around +Z).
        radius: ring radius, metres (> 0).
        n: number of segments (>= 3).

    Returns:
        (n, 2, 3) float32 line segments, world frame.

    Raises:
        ValueError: a non-positive or non-finite radius, fewer than 3 segments, or non-finite / wrongly shaped
            center or normal.
    """
    c = np.asarray(center, np.float64).reshape(-1)
    nrm = np.asarray(normal, np.float64).reshape(-1)
    if c.shape != (3,) or nrm.shape != (3,) or not (np.isfinite(c).all() and np.isfinite(nrm).all()):
        raise ValueError(f"center and normal must be 3 finite numbers each, got {c} and {nrm}")
    if not (np.isfinite(radius) and radius > 0) or n < 3:
        raise ValueError(f"need a positive radius and at least 3 segments, got {radius} and {n}")
    length = float(np.linalg.norm(nrm))
    nrm = nrm / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    ref = np.array([0.0, 0.0, 1.0]) if abs(nrm[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t1 = np.cross(nrm, ref)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(nrm, t1)
    ang = np.linspace(0.0, 2.0 * np.pi, n + 1)
    pts = c + CURSOR_LIFT * radius * nrm + radius * (np.cos(ang)[:, None] * t1 + np.sin(ang)[:, None] * t2)
    return np.stack([pts[:-1], pts[1:]], axis=1).astype(np.float32)

