"""The proposal pool's sparse bookkeeping: neighbourhoods and M-step sampling (eliminations: em/rules.py).

Everything here is plain NumPy/SciPy and works on *ragged rows*: proposal r owns the scene-point indices
`idx[offsets[r]:offsets[r+1]]` (its crop or E-step neighbourhood) with one value per entry (weights, SDF).
Weights outside a row are zero by definition, so cost scales with the neighbourhood sizes, never with P × N.
Rows are always in increasing proposal-id order. References: docs/design/efem-method.md §3.3 and §3.4.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

logger = logging.getLogger(__name__)

@dataclass(frozen=True)
class Ragged:
    """Per-proposal sets of scene-point indices, stored flat.

    Attributes:
        idx: (K,) int64 scene-point indices, row after row.
        offsets: (P + 1,) int64; row r is `idx[offsets[r]:offsets[r + 1]]`.
    """

    idx: np.ndarray
    offsets: np.ndarray

    @property
    def num_rows(self) -> int:
        return int(len(self.offsets) - 1)

    @property
    def lengths(self) -> np.ndarray:
        """(P,) int64 number of entries per row."""
        return np.diff(self.offsets)

    @property
    def row(self) -> np.ndarray:
        """(K,) int64 row of every entry."""
        return np.repeat(np.arange(self.num_rows, dtype=np.int64), self.lengths)

    def row_slice(self, r: int) -> slice:
        return slice(int(self.offsets[r]), int(self.offsets[r + 1]))

    @classmethod
    def from_lists(cls, rows: Sequence[Sequence[int] | np.ndarray]) -> "Ragged":
        """Build from one index sequence per row."""
        lens = np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows))
        offsets = np.zeros(len(rows) + 1, np.int64)
        np.cumsum(lens, out=offsets[1:])
        if len(rows) and isinstance(rows[0], np.ndarray):
            parts = [np.asarray(r, np.int64) for r in rows]
            idx = np.concatenate(parts) if lens.sum() else np.zeros(0, np.int64)
        else:
            idx = np.fromiter(itertools.chain.from_iterable(rows), dtype=np.int64, count=int(lens.sum()))
        return cls(idx=idx, offsets=offsets)

    def take_rows(self, rows: np.ndarray) -> tuple["Ragged", np.ndarray]:
        """Keep some rows (in the given order).

        Returns:
            (the new Ragged, (K',) int64 positions of the kept entries in the old flat arrays) so that
            per-entry values can be carried over with `values[positions]`.
        """
        rows = np.asarray(rows, np.int64)
        lens = self.lengths[rows]
        offsets = np.zeros(len(rows) + 1, np.int64)
        np.cumsum(lens, out=offsets[1:])
        starts = self.offsets[:-1][rows]
        pos = np.repeat(starts - offsets[:-1], lens) + np.arange(int(offsets[-1]), dtype=np.int64)
        return Ragged(idx=self.idx[pos], offsets=offsets), pos


def neighbourhoods(
    points: np.ndarray,
    available: np.ndarray,
    centers: np.ndarray,
    radius: float,
    *,
    crop: str = "sphere",
    tree: object | None = None,
) -> Ragged:
    """Available scene points within `radius` of each centre (ball, or vertical cylinder for crop="cylinder").

    Args:
        points: (N, 3) float32 scene points, world frame.
        available: (N,) bool, points not yet assigned to an accepted object.
        centers: (P, 3) float centres, world frame.
        radius: metres.
        crop: "sphere" (3-D distance) or "cylinder" (distance in the x-y plane, +Z up).
        tree: optional prebuilt `AvailableTree` for these points/availability (speeds up repeated calls).

    Returns:
        Ragged rows of scene-point indices, each sorted increasingly.
    """
    t = tree if isinstance(tree, AvailableTree) else AvailableTree(points, available, crop=crop)
    return t.query(centers, radius)


class AvailableTree:
    """A KD-tree over the available points (3-D, or x-y for cylinder crops) that answers ball queries."""

    def __init__(self, points: np.ndarray, available: np.ndarray, *, crop: str = "sphere") -> None:
        from efem_viz._typeshims import cKDTree

        if crop not in ("sphere", "cylinder"):
            raise ValueError(f"crop must be 'sphere' or 'cylinder', got {crop!r}")
        self.crop = crop
        self.avail_idx = np.flatnonzero(np.asarray(available, bool)).astype(np.int64)
        dims = 3 if crop == "sphere" else 2
        pts = np.asarray(points, np.float64)[self.avail_idx, :dims]
        self.tree = cKDTree(pts) if len(self.avail_idx) else None
        self.dims = dims

    def query(self, centers: np.ndarray, radius: float) -> Ragged:
        centers = np.asarray(centers, np.float64).reshape(-1, 3)
        if self.tree is None or len(centers) == 0:
            return Ragged(np.zeros(0, np.int64), np.zeros(len(centers) + 1, np.int64))
        finite = np.isfinite(centers).all(axis=1)
        if finite.all():
            res = list(self.tree.query_ball_point(centers[:, : self.dims], r=float(radius),
                                                  return_sorted=True))
        else:  # a degenerate latent (NaN centre) owns no points
            res = [[] for _ in range(len(centers))]
            if finite.any():
                got = self.tree.query_ball_point(centers[finite, : self.dims], r=float(radius),
                                                 return_sorted=True)
                for i, lst in zip(np.flatnonzero(finite), got):
                    res[i] = lst
        rag = Ragged.from_lists(res)
        return Ragged(idx=self.avail_idx[rag.idx], offsets=rag.offsets)


def init_crops(
    points: np.ndarray,
    available: np.ndarray,
    n: int,
    r_init: float,
    rng: np.random.Generator,
    *,
    crop: str = "sphere",
    tree: AvailableTree | None = None,
    anchor_mask: np.ndarray | None = None,
    spread: bool = False,
) -> tuple[np.ndarray, Ragged]:
    """Draw `n` anchors with replacement among the available points and crop around them (§3.3).

    Args:
        points: (N, 3) float32 scene points, world frame.
        available: (N,) bool.
        n: number of proposals.
        r_init: crop radius (m).
        rng: NumPy generator (anchors are its first draw).
        crop: "sphere" or "cylinder".
        tree: optional prebuilt AvailableTree for (points, available, crop).
        anchor_mask: optional (N,) bool: anchors are drawn only among available points where it is True (the
            crops still take every available point).
        spread: anchors spread over space instead (`spread_anchors`: one random point per occupied grid cell).

    Returns:
        anchors (n,) int64 scene indices, and the crops as Ragged rows (initial weights are 1 on every entry).

    Raises:
        ValueError: no available point (within `anchor_mask`) to anchor on, or a mask of the wrong shape.
    """
    avail = np.asarray(available, bool)
    if anchor_mask is not None:
        anchor_mask = np.asarray(anchor_mask, bool)
        if anchor_mask.shape != avail.shape:
            raise ValueError(f"anchor_mask has shape {anchor_mask.shape}, expected {avail.shape}")
        avail = avail & anchor_mask
    avail_idx = np.flatnonzero(avail)
    if len(avail_idx) == 0:
        raise ValueError("no available points to draw proposal anchors from")
    if spread:
        anchors = avail_idx[spread_anchors(np.asarray(points)[avail_idx], int(n), rng)].astype(np.int64)
    else:
        anchors = avail_idx[rng.integers(0, len(avail_idx), size=int(n))].astype(np.int64)
    t = tree if tree is not None else AvailableTree(points, available, crop=crop)
    return anchors, t.query(np.asarray(points)[anchors], r_init)


def spread_anchors(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` anchor rows of `points` spread over space: the finest cubic grid with at most `n` occupied cells
    (found by bisection on the cell size), one random point per cell, the rest drawn uniformly (with replacement);
    shuffled, so any block of them is spread too.

    Random draws put anchors where the points are dense (a near object, a large table); these put about the same
    number in every region the scan covers.

    Returns:
        (n,) int64 row indices into `points`.
    """
    pts = np.asarray(points, np.float64)
    m = len(pts)
    if m == 0 or n <= 0:
        return np.zeros(0, np.int64)
    lo = pts.min(axis=0)
    ext = float((pts.max(axis=0) - lo).max())
    order = rng.permutation(m)  # a random member of each cell: the first of the cell in this order

    def cells(h: float) -> np.ndarray:
        q = np.floor((pts[order] - lo) / h).astype(np.int64)
        span = q.max(axis=0) + 1
        return (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]

    h_lo, h_hi = max(ext, 1e-9) * 1e-4, max(ext, 1e-9) * 2.0  # many cells / one cell
    for _ in range(20):
        h = float(np.sqrt(h_lo * h_hi))
        if len(np.unique(cells(h))) > n:
            h_lo = h
        else:
            h_hi = h
    _, first = np.unique(cells(h_hi), return_index=True)
    picked = order[first]
    if len(picked) < n:
        picked = np.concatenate([picked, rng.integers(0, m, size=n - len(picked))])
    return rng.permutation(picked[:n]).astype(np.int64)


def _categorical_rows(
    rag: Ragged,
    w: np.ndarray,
    m: int,
    rng: np.random.Generator,
    fallback: np.ndarray,
) -> np.ndarray:
    """M i.i.d. draws per row from the categorical ∝ w over the row's entries.

    Rows with zero mass draw uniformly from `fallback` (the whole-scene safety rule of §3.4).
    Returns (P, m) int64 scene indices.
    """
    p = rag.num_rows
    out = np.empty((p, m), np.int64)
    if p == 0:
        return out
    row = rag.row
    w64 = np.asarray(w, np.float64)
    tot = np.bincount(row, weights=w64, minlength=p)
    ok = tot > 0
    # Normalise every row to mass 1 before the global cumsum: no cancellation between rows.
    wn = np.where(ok[row], w64 / np.where(tot > 0, tot, 1.0)[row], 0.0)
    cs = np.cumsum(wn)
    start, end = rag.offsets[:-1], rag.offsets[1:]
    u = rng.random((p, m))
    if ok.any():
        base = np.where(start > 0, cs[np.maximum(start - 1, 0)], 0.0)
        rows_ok = np.flatnonzero(ok)
        target = base[rows_ok, None] + u[rows_ok]
        pos = np.searchsorted(cs, target, side="right")
        pos = np.clip(pos, start[rows_ok, None], end[rows_ok, None] - 1)
        # zero-weight entries are only hit through rounding at a row's end: step to a positive one
        bad = wn[pos] <= 0
        if bad.any():
            for r_local, j in zip(*np.nonzero(bad)):
                r = rows_ok[r_local]
                sl = rag.row_slice(int(r))
                nz = np.flatnonzero(wn[sl] > 0)
                k = min(int(np.searchsorted(nz, pos[r_local, j] - sl.start)), len(nz) - 1)
                pos[r_local, j] = sl.start + nz[k]
        out[rows_ok] = rag.idx[pos]
    if (~ok).any():
        if len(fallback) == 0:
            raise ValueError("a proposal has no weight and there are no available points to fall back on")
        n_bad = int((~ok).sum())
        logger.debug("%d proposals with all-zero weights sample the whole scene", n_bad)
        out[~ok] = fallback[np.minimum((u[~ok] * len(fallback)).astype(np.int64), len(fallback) - 1)]
    return out


def sample_independent(
    rag: Ragged,
    w: np.ndarray,
    m: int,
    omega: float,
    rng: np.random.Generator,
    *,
    fallback: np.ndarray,
    replace: bool = True,
) -> np.ndarray:
    """Phase-1 M-step sampling (§3.4): Bernoulli(w/(w+ω)) masks, then M categorical draws ∝ w·b per row.

    Args:
        rag: the rows' supports (entries outside have weight 0).
        w: (K,) float weights per entry in [0, 1].
        m: samples per row (with replacement).
        omega: background weight ω.
        rng: NumPy generator.
        fallback: (F,) int scene indices drawn uniformly for rows without weight (available points).
        replace: False = draws without replacement where a row has enough weighted entries
            (`EMConfig.steps.m_step_replace`).

    Returns:
        (P, m) int64 scene indices.
    """
    w = np.asarray(w, np.float64)
    keep = rng.random(len(w)) < w / (w + omega)
    out = _categorical_rows(rag, w * keep, m, rng, fallback)
    if not replace:
        _without_replacement(rag, w * keep, out, rng)
    return out


def _without_replacement(rag: Ragged, w: np.ndarray, out: np.ndarray, rng: np.random.Generator) -> None:
    """Redraw each row of ``out`` without replacement ∝ ``w`` (Efraimidis-Spirakis keys u^(1/w)).

    A row with fewer positive-weight entries than its draws keeps all of them once and its remaining draws
    from ``out`` (the categorical draws with replacement). Rows without weight keep their fallback draws.
    """
    m = out.shape[1]
    for r in range(rag.num_rows):
        sl = rag.row_slice(r)
        wr = w[sl]
        pos = np.flatnonzero(wr > 0)
        if len(pos) == 0:
            continue
        keys = np.log(rng.random(len(pos))) / wr[pos]
        if len(pos) >= m:
            top = pos[np.argpartition(-keys, m - 1)[:m]]
            out[r] = rag.idx[sl][top]
        else:
            out[r, :len(pos)] = rag.idx[sl][pos]


def sample_joint(
    rag: Ragged,
    w: np.ndarray,
    scores: np.ndarray,
    m: int,
    omega: float,
    rng: np.random.Generator,
    *,
    fallback: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Phase-2 M-step sampling (§3.4).

    Every scene point draws one owner among {background: ω} ∪ {i: w_ij·S_i}; each proposal then samples M
    points ∝ w over the points it claimed.

    Args:
        rag: the rows' supports.
        w: (K,) float weights per entry.
        scores: (P,) float competition weights S_i (the previous step's stationary scores).
        m: samples per row.
        omega: background weight ω.
        rng: NumPy generator.
        fallback: (F,) int scene indices for rows without any weight.

    Returns:
        ((P, m) int64 scene indices, (K,) bool claimed flag per entry).
    """
    p = rag.num_rows
    w = np.asarray(w, np.float64)
    k = len(w)
    claimed = np.zeros(k, bool)
    row = rag.row
    if k:
        vals = w * np.asarray(scores, np.float64)[row]
        order = np.argsort(rag.idx, kind="stable")
        pts = rag.idx[order]
        v = vals[order]
        gstart = np.flatnonzero(np.r_[True, pts[1:] != pts[:-1]])
        gend = np.r_[gstart[1:], len(pts)]
        gsum = np.add.reduceat(v, gstart)
        total = gsum + omega
        gid = np.repeat(np.arange(len(gstart)), gend - gstart)
        vn = v / total[gid]
        cs = np.cumsum(vn)
        base = np.where(gstart > 0, cs[np.maximum(gstart - 1, 0)], 0.0)
        u = rng.random(len(gstart))
        pos = np.searchsorted(cs, base + u, side="right")
        hit = (pos < gend) & (u < gsum / total)
        pos = np.minimum(pos, gend - 1)
        hit &= vn[pos] > 0
        claimed[order[pos[hit]]] = True
        # points labelled background: every entry of a group without a hit
        bg_entry = np.zeros(k, bool)
        bg_entry[order] = ~np.repeat(hit, gend - gstart)
    else:
        bg_entry = np.zeros(0, bool)
    has = np.bincount(row[claimed], minlength=p) > 0 if k else np.zeros(p, bool)
    empty_rows = np.flatnonzero(~has)
    for r in empty_rows:
        sl = rag.row_slice(int(r))
        if sl.stop == sl.start:
            continue
        cand = np.flatnonzero(bg_entry[sl] & (w[sl] > 0))
        if len(cand) == 0:
            cand = np.flatnonzero(w[sl] > 0)
        if len(cand) == 0:
            continue
        best = sl.start + cand[np.argmax(w[sl][cand])]
        claimed[best] = True
    if len(empty_rows):
        logger.warning("joint M-step: %d proposals claimed no point; each gets its best background point",
                       len(empty_rows))
    return _categorical_rows(rag, w * claimed, m, rng, fallback), claimed


def lookup(rag: Ragged, rows: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Flat entry positions of (row, scene index) pairs, -1 where the point is not in that row.

    Args:
        rag: ragged rows, each sorted increasingly.
        rows: (...) int row per query.
        idx: (...) int scene index per query (same shape).

    Returns:
        (...) int64 positions into rag.idx, or -1.
    """
    rows = np.asarray(rows, np.int64)
    idx = np.asarray(idx, np.int64)
    if len(rag.idx) == 0:
        return np.full(idx.shape, -1, np.int64)
    n = int(max(rag.idx.max(), idx.max() if idx.size else 0)) + 1
    keys = rag.row * n + rag.idx  # sorted because rows are contiguous and each row is sorted
    q = rows * n + idx
    pos = np.searchsorted(keys, q)
    pos_c = np.minimum(pos, len(keys) - 1)
    found = keys[pos_c] == q
    return np.where(found, pos_c, -1)
