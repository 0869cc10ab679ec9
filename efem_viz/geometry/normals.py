"""Surface normals: from mesh faces, or estimated from points (chunked kNN + batched PCA) and oriented consistently.

Point-cloud normals are PCA normals over a fixed number of nearest neighbours (the eigenvector of the smallest
eigenvalue of each neighbourhood's 3x3 covariance), computed in chunks so that memory stays bounded: one
`scipy.spatial.cKDTree` query and one batched `np.linalg.eigh` per chunk of `chunk` points. Orientation follows
the rule open3d's `orient_normals_consistent_tangent_plane` implements (Hoppe et al. 1992), then the global flip
this module has always applied:

1. toward a sensor position when one is given (each normal flipped to face it);
2. otherwise propagated along a minimum spanning tree of the kNN graph weighted by `1 - |n_i . n_j|` (so signs
   travel across flat regions first), then each connected piece of that graph is flipped so that most of its
   normals point away from its centroid (outward for closed scans) or up (+Z) when it is flat (z extent under a
   quarter of the larger horizontal extent). For a connected cloud this is the rule as it always was; separate
   pieces (objects not touching the table, say) used to share one sign chosen for the whole cloud, which left
   some objects' normals pointing inward.

Step 2 is vectorised: the MST and its breadth-first tree come from `scipy.sparse.csgraph`, and the sign of each
point relative to its piece's root is the parity of sign changes along its tree path, found by pointer jumping
(O(N log depth) array operations instead of a Python walk).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import numpy as np

log = logging.getLogger(__name__)

NormalsProgress = Callable[[str, int, int], None]
"""Progress callback `(stage, done, total)`: stage "pca" counts points done, stage "orient" counts steps (of 3)."""

DEFAULT_CHUNK = 32_768
"""Points per kNN/PCA chunk: about 16 MB of float64 neighbourhoods at k = 20."""
_ORIENT_KNN = 10
"""Neighbours per point in the orientation graph (open3d's `orient_normals_consistent_tangent_plane(10)`)."""
_MIN_PIECE = 50
"""Connected pieces with fewer points are oriented by the whole cloud's centroid and flatness."""


def estimate_normals(
    points: np.ndarray,
    *,
    faces: np.ndarray | None = None,
    toward: np.ndarray | None = None,
    knn: int = 20,
    chunk: int = DEFAULT_CHUNK,
    on_progress: NormalsProgress | None = None,
) -> np.ndarray:
    """Unit normals for a point set or mesh.

    With `faces`, area-weighted vertex normals of the mesh (outward for a consistently wound mesh; a vertex no
    face uses gets +Z). Without, PCA normals over `knn` nearest neighbours (the point itself included, as in
    open3d), oriented toward the sensor position `toward` when given, otherwise consistently by tangent-plane
    propagation and then flipped, per connected piece, so that most point away from the piece's centroid
    (outward for closed scans) or up (+Z) for a flat piece (z extent under a quarter of the larger horizontal
    extent); see the module docstring.

    Time and memory grow about linearly with N: some 20 s and under 0.8 GB for 2M points on one core
    (docs/BENCHMARKS.md).

    Args:
        points: (N, 3) float, world frame.
        faces: (M, 3) int indices into `points`, or None for a point cloud.
        toward: (3,) float sensor position, world frame, or None.
        knn: neighbours per PCA neighbourhood (clipped to N).
        chunk: points per kNN/PCA chunk (bounds the working memory).
        on_progress: called after each chunk with ("pca", points done, N) and during orientation with
            ("orient", step, 3); library code otherwise only logs.

    Returns:
        (N, 3) float32 unit normals.

    Raises:
        ValueError: `points` is not (N, 3), or holds NaN/Inf; `knn` or `chunk` < 1.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if knn < 1 or chunk < 1:
        raise ValueError(f"knn and chunk must be >= 1, got knn={knn}, chunk={chunk}")
    n = len(pts)
    if faces is not None and len(faces) > 0:
        import trimesh

        mesh = trimesh.Trimesh(vertices=pts, faces=np.asarray(faces), process=False)
        nrm = np.array(mesh.vertex_normals, dtype=np.float64)  # copy: trimesh caches are read-only
        bad = ~np.isfinite(nrm).all(axis=1) | (np.linalg.norm(nrm, axis=1) < 1e-9)
        if bad.any():
            nrm[bad] = 0.0
            nrm[bad, 2] = 1.0
        return nrm.astype(np.float32)
    if n < 3:
        out = np.zeros((n, 3), np.float32)
        out[:, 2] = 1.0
        return out
    if not np.isfinite(pts).all():
        raise ValueError(f"points contain NaN or Inf ({int((~np.isfinite(pts)).any(axis=1).sum())} of {n} rows)")
    k_orient = min(_ORIENT_KNN, n - 1) if toward is None else 0
    nrm, nbrs = pca_normals(pts, knn=knn, chunk=chunk, keep_neighbours=k_orient + 1 if k_orient else 0,
                            on_progress=on_progress)
    if toward is not None:
        to_sensor = np.asarray(toward, dtype=np.float64).reshape(3) - pts
        flip = np.einsum("ij,ij->i", nrm, to_sensor) < 0
        nrm[flip] *= -1.0
    else:
        assert nbrs is not None
        nrm = orient_normals(pts, nrm, nbrs, on_progress=on_progress)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return nrm.astype(np.float32)


def pca_normals(
    points: np.ndarray,
    *,
    knn: int = 20,
    chunk: int = DEFAULT_CHUNK,
    keep_neighbours: int = 0,
    on_progress: NormalsProgress | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Unoriented PCA normals over `knn` nearest neighbours, chunk by chunk.

    Args:
        points: (N, 3) float64, finite, N >= 1.
        knn: neighbours per neighbourhood, the point itself included (clipped to N).
        chunk: points per kNN query and batched `eigh`.
        keep_neighbours: also return the first this many neighbour indices of each point (0: none).
        on_progress: called with ("pca", points done, N) after each chunk.

    Returns:
        (normals, neighbours): (N, 3) float64 unit normals with arbitrary sign, and (N, keep_neighbours)
        int32 neighbour indices nearest first (None when `keep_neighbours` is 0).
    """
    from efem_viz._typeshims import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    k = max(1, min(knn, n))
    keep = min(keep_neighbours, k)
    # query in a space-filling-curve order: neighbouring queries then touch the same tree nodes and rows of
    # `pts` (about 2x faster on 2M points than file order); results are scattered back to the input order
    order = _morton_order(pts)
    sorted_pts = pts[order]
    if n > 1 and _longest_run_of_equal_rows(sorted_pts) > MAX_COINCIDENT:
        return _pca_normals_deduplicated(pts, knn=knn, chunk=chunk, keep_neighbours=keep_neighbours,
                                         on_progress=on_progress)
    tree = cKDTree(sorted_pts, leafsize=16, balanced_tree=False, compact_nodes=False)
    nrm = np.empty((n, 3), np.float64)
    nbrs = np.empty((n, keep), np.int32) if keep else None
    step = max(1, n // 10)
    next_log = step
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        _, idx = tree.query(sorted_pts[s:e], k=k, workers=1)
        idx = np.asarray(idx).reshape(e - s, k)
        nb = sorted_pts[idx]  # (C, k, 3)
        nb -= nb.mean(axis=1, keepdims=True)
        cov = np.matmul(nb.transpose(0, 2, 1), nb)  # (C, 3, 3)
        _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues: column 0 is the normal direction
        rows = order[s:e]
        nrm[rows] = vecs[:, :, 0]
        if nbrs is not None:
            nbrs[rows] = order[idx[:, :keep]]
        if on_progress is not None:
            on_progress("pca", e, n)
        if e >= next_log or e == n:
            log.log(logging.INFO if n >= 200_000 else logging.DEBUG, "normals: PCA %s / %s points", f"{e:,}",
                    f"{n:,}")
            next_log = e + step
    return nrm, nbrs


MAX_COINCIDENT = 64
"""More copies of one point than this and the normals are computed on the distinct points (a k-d tree
cannot split coincident points, so 2M copies of one point made every k-NN query scan all of them: 200 s+)."""


def _longest_run_of_equal_rows(sorted_pts: np.ndarray) -> int:
    """Longest run of identical consecutive rows (coincident points are adjacent in Morton order)."""
    same = np.all(sorted_pts[1:] == sorted_pts[:-1], axis=1)
    if not same.any():
        return 1
    edges = np.flatnonzero(np.diff(np.concatenate([[0], same.astype(np.int8), [0]])))
    return int((edges[1::2] - edges[::2]).max()) + 1


def _pca_normals_deduplicated(pts: np.ndarray, *, knn: int, chunk: int, keep_neighbours: int,
                              on_progress: NormalsProgress | None) -> tuple[np.ndarray, np.ndarray | None]:
    """`pca_normals` over the distinct points, copied to every duplicate; neighbour indices point at the first
    copy of each neighbour. Coincident copies carry no shape, so the neighbourhoods lose nothing."""
    uniq, first, inv = np.unique(pts, axis=0, return_index=True, return_inverse=True)
    inv = np.asarray(inv).reshape(-1)
    log.info("normals: %s points hold %s distinct positions; estimating on those", f"{len(pts):,}", f"{len(uniq):,}")
    if len(uniq) < 3:  # no plane through fewer than 3 distinct points: +Z, as for a flat patch seen from above
        nrm = np.tile(np.array([0.0, 0.0, 1.0]), (len(pts), 1))
        keep = min(keep_neighbours, max(1, min(knn, len(uniq))))
        nbrs = first[np.zeros((len(pts), keep), np.int64)].astype(np.int32) if keep else None
        if on_progress is not None:
            on_progress("pca", len(pts), len(pts))
        return nrm, nbrs
    nrm_u, nbrs_u = pca_normals(uniq, knn=knn, chunk=chunk, keep_neighbours=keep_neighbours, on_progress=None)
    if on_progress is not None:
        on_progress("pca", len(pts), len(pts))
    nbrs = first[nbrs_u[inv]].astype(np.int32) if nbrs_u is not None else None
    return nrm_u[inv], nbrs


def _morton_order(pts: np.ndarray, *, bits: int = 10) -> np.ndarray:
    """Permutation sorting (N, 3) points along a Z-order curve on a 2^bits grid over their bounding cube."""
    lo = pts.min(axis=0)
    span = float((pts.max(axis=0) - lo).max()) or 1.0
    q = np.minimum(((pts - lo) * ((1 << bits) / span)).astype(np.int64), (1 << bits) - 1)
    code = np.zeros(len(pts), np.int64)
    for b in range(bits):
        for a in range(3):
            code |= ((q[:, a] >> b) & 1) << (3 * b + a)
    return np.argsort(code, kind="stable")


def orient_normals(
    points: np.ndarray,
    normals: np.ndarray,
    neighbours: np.ndarray,
    *,
    on_progress: NormalsProgress | None = None,
) -> np.ndarray:
    """Orient normals consistently: MST propagation over the kNN graph, then a flip per connected piece.

    Args:
        points: (N, 3) float64, world frame.
        normals: (N, 3) float64 unit normals with arbitrary signs.
        neighbours: (N, K) int neighbour indices of each point (self entries are ignored).
        on_progress: called with ("orient", step, 3) after the graph, the tree and the flips.

    Returns:
        (N, 3) float64 normals: `normals` with some rows negated.
    """
    pts = np.asarray(points, dtype=np.float64)
    nrm = np.array(normals, dtype=np.float64)
    n = len(pts)
    mst = _spanning_forest(nrm, neighbours)
    if on_progress is not None:
        on_progress("orient", 1, 3)
    parent, is_root, labels, n_comp = _tree_parents(mst, n)
    del mst
    if on_progress is not None:
        on_progress("orient", 2, 3)
    _flip_along_trees(nrm, parent, is_root)
    _flip_pieces(pts, nrm, labels, n_comp)
    if on_progress is not None:
        on_progress("orient", 3, 3)
    log.log(logging.INFO if n >= 200_000 else logging.DEBUG, "normals: oriented %s points in %d piece(s)",
            f"{n:,}", n_comp)
    return nrm


def _spanning_forest(nrm: np.ndarray, neighbours: np.ndarray) -> Any:
    """The minimum spanning forest of the kNN graph weighted by 1 − |cos| between normals (Hoppe: signs travel
    along flat stretches first), as a scipy sparse matrix (`orient_normals`).

    Args:
        nrm: (N, 3) float64 unit normals.
        neighbours: (N, K) int neighbour indices (self entries give no edge).
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    n = len(nrm)
    kk = neighbours.shape[1]
    cols = np.ascontiguousarray(neighbours, dtype=np.int32).reshape(-1)
    # 1 - |cos| (Hoppe): signs travel along flat stretches first; + eps because scipy drops explicit zeros.
    # Self entries (the point is its own nearest neighbour) get weight 0, i.e. no edge.
    w = np.empty((n, kk), np.float64)
    for j in range(kk):  # column by column: no (N * K, 3) temporaries
        nb = neighbours[:, j]
        w[:, j] = 1.0 - np.abs(np.einsum("ij,ij->i", nrm, nrm[nb])) + 1e-6
        w[nb == np.arange(n), j] = 0.0
    w = w.reshape(-1)
    graph = csr_matrix((w, cols, np.arange(0, n * kk + 1, kk, dtype=np.int64)), shape=(n, n))
    del w, cols
    return minimum_spanning_tree(graph, overwrite=True)


def _tree_parents(mst: Any, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Root every tree of the spanning forest at its first point and find each point's parent (one BFS from a
    virtual root joined to every tree's root).

    Returns:
        (parent (N,) int64, a root its own parent; is_root (N,) bool; labels (N,) the connected piece of each
        point; the number of pieces).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    n_comp, labels = connected_components(mst, directed=False)
    # one virtual root (node n) joined to the first point of every piece: a single BFS roots all the trees
    _, roots = np.unique(labels, return_index=True)
    mst = mst.tocoo()
    tree = coo_matrix(
        (np.concatenate([mst.data, np.ones(len(roots))]),
         (np.concatenate([mst.row, np.full(len(roots), n)]), np.concatenate([mst.col, roots]))),
        shape=(n + 1, n + 1),
    ).tocsr()
    del mst
    _, pred = breadth_first_order(tree, n, directed=False, return_predecessors=True)
    del tree
    parent = pred[:n].astype(np.int64)
    is_root = parent == n
    parent[is_root] = np.flatnonzero(is_root)
    return parent, is_root, labels, int(n_comp)


def _flip_along_trees(nrm: np.ndarray, parent: np.ndarray, is_root: np.ndarray) -> None:
    """Negate (in place) the normals whose path to their tree's root changes sign an odd number of times, so
    that every normal agrees with its parent: the parity by pointer jumping (ceil(log2(depth)) rounds)."""
    parity = np.einsum("ij,ij->i", nrm, nrm[parent]) < 0
    parity[is_root] = False
    anc = parent
    while True:
        nxt = anc[anc]
        parity ^= parity[anc]
        if np.array_equal(nxt, anc):
            break
        anc = nxt
    nrm[parity] *= -1.0


def _flip_pieces(pts: np.ndarray, nrm: np.ndarray, labels: np.ndarray, n_comp: int) -> None:
    """The global sign rule, applied (in place) to each connected piece on its own: most normals away from the
    piece's centroid, or +Z when the piece is flat; pieces too small to judge (stray points) use the whole
    cloud's centroid and flatness. A single connected cloud gets exactly the rule as it was."""
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels, minlength=n_comp)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sorted_pts = pts[order]
    centre = np.add.reduceat(sorted_pts, starts, axis=0) / counts[:, None]
    extent = np.maximum.reduceat(sorted_pts, starts, axis=0) - np.minimum.reduceat(sorted_pts, starts, axis=0)
    del sorted_pts, order
    small = counts < _MIN_PIECE
    centre[small] = pts.mean(axis=0)
    extent[small] = pts.max(axis=0) - pts.min(axis=0)
    flat = extent[:, 2] < 0.25 * np.maximum(np.maximum(extent[:, 0], extent[:, 1]), 1e-9)
    outward = np.einsum("ij,ij->i", nrm, pts - centre[labels])
    per_point = np.where(flat[labels], nrm[:, 2], outward)
    score = np.bincount(labels, weights=per_point, minlength=n_comp)
    nrm[score[labels] < 0] *= -1.0


def planar_share(normals: np.ndarray, *, directions: int = 3, within_deg: float = 15.0,
                 max_samples: int = 600) -> float:
    """The share of a surface's normals that `directions` directions hold, each every normal within `within_deg`
    of it: near 1 for the faces of a box (two or three faces meet at an edge or corner), far less for a curved
    surface seen from around (a cylinder's side spreads its normals over a circle).

    Greedy: each direction is the normal with the most others within the angle, and takes those out. Signed
    angles (a face and its opposite are two directions). At most `max_samples` normals take part, a fixed
    subsample (seed 0) of larger sets, so the measure is cheap and repeatable.

    Args:
        normals: (N, 3) normals (any length; zero rows count as no direction).
        directions: directions to take.
        within_deg: the angle around each.
        max_samples: normals used at most.

    Returns:
        The share in [0, 1]; NaN for an empty set.
    """
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    if len(n) == 0:
        return float("nan")
    if len(n) > max_samples:
        n = n[np.random.default_rng(0).choice(len(n), max_samples, replace=False)]
    length = np.linalg.norm(n, axis=1)
    unit = n / np.maximum(length, 1e-12)[:, None]
    near = (unit @ unit.T) >= np.cos(np.radians(within_deg))
    near &= (length > 0)[:, None] & (length > 0)[None, :]
    left = length > 0
    taken = 0
    for _ in range(directions):
        if not left.any():
            break
        counts = near[:, left].sum(axis=1) * left
        members = near[int(np.argmax(counts))] & left
        taken += int(members.sum())
        left &= ~members
    return taken / len(n)
