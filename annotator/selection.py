"""Selection tools: picking, brush, region grow, fill and box select → vertex indices (pure numpy/scipy).

All positions are world frame, metres. `ScanGeometry` holds the scan's points, normals and optional faces and
builds its search structures lazily (kd-tree, adjacency graph, mesh ray caster); the tools take it and return
sorted unique int32 vertex indices. Nothing here knows about labels beyond an optional `labels` array, or about
viser: the app turns GUI events into these calls, and tests/benchmarks call them directly.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable, Literal

import numpy as np

from efem_viz.geometry.transforms import quat_wxyz_to_rotation

log = logging.getLogger(__name__)


class ScanGeometry:
    """Scan geometry with lazily built search structures (thread-safe construction).

    Args:
        points: (N, 3) float32 vertex positions, world frame, metres.
        normals: (N, 3) float32 unit normals.
        faces: (M, 3) int triangle indices, or None for a point cloud.
        knn: neighbours per point for the point-cloud graph (region grow / fill).
    """

    def __init__(
        self, points: np.ndarray, normals: np.ndarray, *, faces: np.ndarray | None = None, knn: int = 10
    ) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float32)
        nrm = np.ascontiguousarray(normals, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
            raise ValueError(f"points {pts.shape} and normals {nrm.shape} must both be (N, 3)")
        self.points = pts
        self.normals = nrm
        self.faces = None if faces is None or len(faces) == 0 else np.ascontiguousarray(faces, dtype=np.int32)
        self.knn = int(knn)
        self._lock = threading.RLock()  # re-entrant: adjacency() builds the tree under the same lock
        self._tree = None
        self._adj: tuple[np.ndarray, np.ndarray] | None = None
        self._raycaster = None
        self.building_raycaster = threading.Event()
        """Set while `warm_up` builds the open3d ray-casting scene."""
        self.warming = threading.Event()
        """Set while `warm_up` runs: until its ray caster is ready, picks use the vertices (never build it)."""
        self._spacing: float | None = None

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    @property
    def is_mesh(self) -> bool:
        return self.faces is not None

    # ------------------------------------------------------------------ lazy structures
    @property
    def tree(self):  # noqa: ANN201 - scipy type
        """scipy cKDTree over the points."""
        if self._tree is None:
            with self._lock:
                if self._tree is None:
                    from efem_viz._typeshims import cKDTree

                    self._tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)
        return self._tree

    @property
    def spacing(self) -> float:
        """Median nearest-neighbour distance (metres), from a sample of ≤ 2000 points."""
        if self._spacing is None:
            rng = np.random.default_rng(0)
            sample = self.points[rng.choice(self.n, size=min(2000, self.n), replace=False)]
            d, _ = self.tree.query(sample, k=2)
            self._spacing = float(max(np.median(d[:, 1]), 1e-6))
        return self._spacing

    @property
    def adjacency(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR graph (indptr (N+1,) int64, indices (E,) int32): mesh edges, or symmetric kNN for points."""
        if self._adj is None:
            with self._lock:
                if self._adj is None:
                    self._adj = self._build_adjacency()
        return self._adj

    def _build_adjacency(self) -> tuple[np.ndarray, np.ndarray]:
        from scipy import sparse

        n = self.n
        if self.faces is not None:
            f = self.faces
            a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
            b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
        else:
            k = min(self.knn + 1, n)
            d, nb = self.tree.query(self.points, k=k, workers=1)
            # Cut long edges (across gaps) at 4x the median spacing so that fills stop at holes.
            ok = d[:, 1:] <= 4.0 * self.spacing
            a = np.repeat(np.arange(n, dtype=np.int32), k - 1)[ok.ravel()]
            b = nb[:, 1:].astype(np.int32).ravel()[ok.ravel()]
        m = sparse.coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n)).tocsr()
        m = (m + m.T).tocsr()
        return m.indptr.astype(np.int64), m.indices.astype(np.int32)

    def raycaster(self):  # noqa: ANN201 - open3d type
        """open3d RaycastingScene over the mesh (meshes only)."""
        if self.faces is None:
            raise ValueError("ray casting against triangles needs a mesh; this scan is a point cloud")
        if self._raycaster is None:
            with self._lock:
                if self._raycaster is None:
                    import open3d as o3d

                    from efem_viz._typeshims import o3d_tensor

                    rc = o3d.t.geometry.RaycastingScene()
                    rc.add_triangles(
                        o3d_tensor(self.points), o3d_tensor(self.faces.astype(np.uint32))
                    )
                    self._raycaster = rc
        return self._raycaster

    @property
    def raycaster_ready(self) -> bool:
        """Whether the ray-casting scene is built (meshes)."""
        return self._raycaster is not None

    def warm_up_stages(self) -> list[str]:
        """What `warm_up` builds, in order (the names its progress reports)."""
        return ["search tree", "point spacing", "neighbour graph"] + (["ray caster"] if self.faces is not None
                                                                      else [])

    def warm_up(self, cancel: threading.Event | None = None,
                on_stage: Callable[[str, int, int], None] | None = None) -> None:
        """Build every structure now (call from a worker thread after opening a scan); stops between structures
        once `cancel` is set. While the ray-casting scene is being built, `building_raycaster` is set (open3d must
        not be torn down under it; the scipy structures can simply be abandoned at exit), and `pick` uses the
        vertices instead of waiting for it.

        Args:
            cancel: stop before the next structure when set.
            on_stage: called with (stage name, stages done, stages in all) before each structure and with
                ("", total, total) when every one is built.
        """
        stages = self.warm_up_stages()
        builds = [lambda: self.tree, lambda: self.spacing, lambda: self.adjacency, self._warm_raycaster]
        self.warming.set()
        try:
            for k, (name, build) in enumerate(zip(stages, builds)):
                if cancel is not None and cancel.is_set():
                    return
                if on_stage is not None:
                    on_stage(name, k, len(stages))
                build()
        finally:
            self.warming.clear()
        if on_stage is not None:
            on_stage("", len(stages), len(stages))

    def _warm_raycaster(self) -> None:
        self.building_raycaster.set()
        try:
            self.raycaster()
        finally:
            self.building_raycaster.clear()


# ---------------------------------------------------------------------------------------------- picking
PICK_CHUNK = 1_000_000
"""Points per piece of a pick by the points (point clouds; meshes while their ray caster is being built)."""

def pick(
    geom: ScanGeometry,
    origin: np.ndarray,
    direction: np.ndarray,
    *,
    tolerance: float | None = None,
) -> tuple[int, np.ndarray] | None:
    """The first surface point hit by a ray.

    Meshes: exact triangle ray cast, then the nearest vertex of the hit. Point clouds: among the points within
    `tolerance` of the ray (default 2x the median spacing), the one closest to the ray origin.

    Args:
        geom: the scan.
        origin: (3,) ray origin, world frame.
        direction: (3,) ray direction (need not be unit).

    Returns:
        (vertex index, hit position (3,) float32), or None when the ray misses.
    """
    o = np.asarray(origin, np.float64).reshape(3)
    dvec = np.asarray(direction, np.float64).reshape(3)
    nd = np.linalg.norm(dvec)
    if not np.isfinite(nd) or nd < 1e-12 or not np.isfinite(o).all():
        return None
    dvec = dvec / nd
    # while the warm-up builds the structures (opening a big scan), a mesh is picked by its vertices: a pick never
    # waits for the warm-up's lock nor builds the ray caster itself
    warming = geom.warming.is_set() or geom.building_raycaster.is_set()
    if geom.faces is not None and (geom.raycaster_ready or not warming):
        from efem_viz._typeshims import o3d_tensor

        rays = o3d_tensor(np.concatenate([o, dvec])[None].astype(np.float32))
        ans = geom.raycaster().cast_rays(rays)
        t = float(ans["t_hit"].numpy()[0])
        if not np.isfinite(t):
            return None
        hit = (o + t * dvec).astype(np.float32)
        prim = int(ans["primitive_ids"].numpy()[0])
        tri = geom.faces[prim]
        v = tri[np.argmin(np.linalg.norm(geom.points[tri] - hit, axis=1))]
        return int(v), hit
    tol = 2.0 * geom.spacing if tolerance is None else float(tolerance)
    best, best_t = -1, np.inf
    for start in range(0, geom.n, PICK_CHUNK):  # bounded memory on big scans (24 MB per chunk, not 24 B per point)
        rel = geom.points[start:start + PICK_CHUNK].astype(np.float64) - o
        t = rel @ dvec
        perp2 = np.einsum("ij,ij->i", rel, rel) - t * t
        cand = np.flatnonzero((t > 0) & (perp2 <= tol * tol))
        if len(cand):
            k = int(cand[np.argmin(t[cand])])
            if t[k] < best_t:  # strict: on a tie the lower index wins, as one argmin over all points would
                best, best_t = start + k, float(t[k])
    if best < 0:
        return None
    return best, geom.points[best].copy()


# ---------------------------------------------------------------------------------------------- brush
def _normal_filter(
    geom: ScanGeometry, idx: np.ndarray, normal: np.ndarray | None, max_normal_angle_deg: float | None
) -> np.ndarray:
    if normal is None or max_normal_angle_deg is None or max_normal_angle_deg >= 180:
        return idx
    nv = np.asarray(normal, np.float32).reshape(3)
    nv = nv / max(float(np.linalg.norm(nv)), 1e-12)
    cos = geom.normals[idx] @ nv
    return idx[cos >= np.cos(np.deg2rad(max_normal_angle_deg))]


def brush(
    geom: ScanGeometry,
    center: np.ndarray,
    radius: float,
    *,
    normal: np.ndarray | None = None,
    max_normal_angle_deg: float | None = None,
) -> np.ndarray:
    """Vertices within `radius` of `center`, optionally only those whose normal is within an angle of `normal`.

    Args:
        geom: the scan.
        center: (3,) brush centre on the surface, world frame.
        radius: metres (> 0).
        normal: (3,) reference normal (usually the normal at the hit vertex), or None.
        max_normal_angle_deg: keep vertices whose normal is within this angle of `normal`; None = no limit.

    Returns:
        (K,) int32 sorted vertex indices.
    """
    if not radius > 0:
        raise ValueError(f"brush radius must be > 0, got {radius}")
    idx = np.asarray(geom.tree.query_ball_point(np.asarray(center, np.float64), float(radius)), np.int64)
    idx = np.sort(idx).astype(np.int32)
    return _normal_filter(geom, idx, normal, max_normal_angle_deg)


def brush_segment(
    geom: ScanGeometry,
    a: np.ndarray,
    b: np.ndarray,
    radius: float,
    *,
    normal: np.ndarray | None = None,
    max_normal_angle_deg: float | None = None,
) -> np.ndarray:
    """Vertices within `radius` of the segment a→b (a continuous stroke between two drag samples).

    Segments longer than 4 radii are walked along the surface instead (samples snapped to the nearest scan
    point), so a fast stroke over a curved object does not cut through it.

    Args:
        geom: the scan.
        a: (3,) previous brush position. b: (3,) current brush position (world frame).
        radius: metres.
        normal, max_normal_angle_deg: as in `brush`.

    Returns:
        (K,) int32 sorted vertex indices.
    """
    a64 = np.asarray(a, np.float64).reshape(3)
    b64 = np.asarray(b, np.float64).reshape(3)
    seg = b64 - a64
    length = float(np.linalg.norm(seg))
    if length < 1e-9:
        return brush(geom, a64, radius, normal=normal, max_normal_angle_deg=max_normal_angle_deg)
    if length > 50 * radius:  # a jump (pointer left the surface): paint only the end
        return brush(geom, b64, radius, normal=normal, max_normal_angle_deg=max_normal_angle_deg)
    if length > 4 * radius:
        # A long chord may cut through the object: walk it in steps of radius/2, snap each sample to the
        # nearest scan point, and paint balls there (a polyline on the surface).
        k = int(np.ceil(length / (0.5 * radius))) + 1
        samples = a64 + np.linspace(0.0, 1.0, k)[:, None] * seg
        _, nn = geom.tree.query(samples)
        centres = geom.points[np.unique(nn)].astype(np.float64)
        lists = geom.tree.query_ball_point(centres, float(radius))
        idx = np.unique(np.concatenate([np.asarray(li, np.int64) for li in lists])).astype(np.int32)
        return _normal_filter(geom, idx, normal, max_normal_angle_deg)
    mid = 0.5 * (a64 + b64)
    cand = np.asarray(geom.tree.query_ball_point(mid, radius + 0.5 * length), np.int64)
    if len(cand) == 0:
        return np.zeros(0, np.int32)
    p = geom.points[cand].astype(np.float64)
    t = np.clip((p - a64) @ seg / (length * length), 0.0, 1.0)
    d = np.linalg.norm(p - (a64 + t[:, None] * seg), axis=1)
    idx = np.sort(cand[d <= radius]).astype(np.int32)
    return _normal_filter(geom, idx, normal, max_normal_angle_deg)


# ---------------------------------------------------------------------------------------------- graph fills
def _csr_neighbours(indptr: np.ndarray, indices: np.ndarray, frontier: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(source, neighbour) pairs of all edges leaving `frontier` (vectorised CSR gather)."""
    starts = indptr[frontier]
    lens = (indptr[frontier + 1] - starts).astype(np.int64)
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32)
    src = np.repeat(frontier, lens)
    offs = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(lens) - lens, lens)
    nb = indices[np.repeat(starts, lens) + offs]
    return src, nb


def region_grow(
    geom: ScanGeometry,
    seed: int,
    *,
    max_angle_deg: float = 25.0,
    max_distance: float | None = None,
    max_vertices: int | None = None,
    allowed: np.ndarray | None = None,
) -> np.ndarray:
    """Flood fill from `seed` over the mesh adjacency (or kNN graph) through smooth surface.

    An edge u→v is crossed when the normals of u and v differ by at most `max_angle_deg` (the fill stops at
    creases such as the mug/table contact) and v lies within `max_distance` of the seed.

    Args:
        geom: the scan.
        seed: start vertex.
        max_angle_deg: maximum normal change across one edge, degrees.
        max_distance: maximum Euclidean distance from the seed (metres), or None.
        max_vertices: stop once this many vertices are reached (breadth-first order), or None.
        allowed: (N,) bool mask of vertices the fill may enter (e.g. not locked), or None.

    Returns:
        (K,) int32 sorted vertex indices, including the seed.
    """
    n = geom.n
    if not 0 <= int(seed) < n:
        raise ValueError(f"seed vertex {seed} outside [0, {n})")
    if allowed is not None and allowed.shape != (n,):
        raise ValueError(f"allowed mask must have shape ({n},), got {allowed.shape}")
    indptr, indices = geom.adjacency
    cos_min = np.float32(np.cos(np.deg2rad(max_angle_deg)))
    p0 = geom.points[int(seed)]
    r2 = None if max_distance is None else float(max_distance) ** 2
    visited = np.zeros(n, bool)
    if allowed is not None and not allowed[seed]:
        return np.zeros(0, np.int32)
    visited[seed] = True
    frontier = np.array([seed], np.int32)
    count = 1
    while len(frontier):
        src, nb = _csr_neighbours(indptr, indices, frontier)
        keep = ~visited[nb]
        if allowed is not None:
            keep &= allowed[nb]
        src, nb = src[keep], nb[keep]
        if len(nb) == 0:
            break
        ok = np.einsum("ij,ij->i", geom.normals[src], geom.normals[nb]) >= cos_min
        if r2 is not None:
            dv = geom.points[nb] - p0
            ok &= np.einsum("ij,ij->i", dv, dv) <= r2
        nb = np.unique(nb[ok])
        if max_vertices is not None and count + len(nb) > max_vertices:
            nb = nb[: max(0, int(max_vertices) - count)]
        visited[nb] = True
        count += len(nb)
        frontier = nb
        if max_vertices is not None and count >= max_vertices:
            break
    return np.flatnonzero(visited).astype(np.int32)


def fill_same_label(geom: ScanGeometry, seed: int, labels: np.ndarray, *, max_angle_deg: float = 180.0) -> np.ndarray:
    """Bucket fill: the connected set of vertices that share the seed's current label.

    Args:
        geom: the scan.
        seed: start vertex.
        labels: (N,) int labels.
        max_angle_deg: optional normal-smoothness limit as in `region_grow` (180 = none).

    Returns:
        (K,) int32 sorted vertex indices.
    """
    lab = np.asarray(labels)
    if lab.shape != (geom.n,):
        raise ValueError(f"labels must have shape ({geom.n},), got {lab.shape}")
    return region_grow(geom, seed, max_angle_deg=max_angle_deg, allowed=lab == lab[int(seed)])


# ---------------------------------------------------------------------------------------------- box select
def project(
    points: np.ndarray, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points with a viser camera (OpenCV axes: +Z forward, +Y down; `fov` vertical, radians).

    Args:
        points: (N, 3) world frame.
        position: (3,) camera position, world frame.
        wxyz: (4,) camera orientation R_world_camera as a quaternion.
        fov: vertical field of view, radians.
        aspect: width / height.

    Returns:
        (uv (N, 2) float64 in [0, 1] screen coordinates (0,0) = top-left, depth (N,) float64 along +Z).
    """
    R = quat_wxyz_to_rotation(wxyz)
    pc = (np.asarray(points, np.float64) - np.asarray(position, np.float64)) @ R  # world → camera
    z = pc[:, 2]
    f = 0.5 / np.tan(0.5 * float(fov))  # focal length in units of the image height
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 0.5 + f * pc[:, 0] / (z * float(aspect))
        v = 0.5 + f * pc[:, 1] / z
    return np.stack([u, v], axis=1), z


Facing = Literal["visible", "front", "all"]
"""Which vertices a box or lasso takes: "visible" (facing the camera and not hidden behind other scan surface),
"front" (facing the camera, hidden or not) or "all" (through the object)."""

VISIBLE_CELL = 2.0
"""Visibility grid cell, in scan spacings at the depth of the nearest selected surface."""
VISIBLE_TOLERANCE = 2.0
"""Depth a visible vertex may always lie behind the nearest surface of its cell, in scan spacings; on top of it a
surface seen at a slant may recede by its own slope across the cell's width (capped at 4: 76°)."""


def visible_among(points: np.ndarray, normals: np.ndarray, *, position: np.ndarray, wxyz: np.ndarray,
                  spacing: float) -> np.ndarray:
    """Which of a set of points the camera sees: not behind another point of the set along the same ray.

    Whatever hides a point inside a screen outline projects inside the same outline, so testing a selection's
    candidates against each other is a full visibility test. The candidates are binned on a grid over the image
    plane whose cells are `VISIBLE_CELL` scan spacings wide at the nearest candidate's depth (so the nearest
    surface covers its cells without gaps); a point is visible when it lies within a tolerance of its cell's
    nearest depth (`VISIBLE_TOLERANCE`, plus its surface's slope across the cell). Points within about one cell of
    an occluding outline may be taken as hidden.

    Args:
        points: (K, 3) candidate points, world frame, in front of the camera.
        normals: (K, 3) their unit normals.
        position: (3,) camera position, world frame.
        wxyz: (4,) camera orientation R_world_camera.
        spacing: the scan's point spacing (m).

    Returns:
        (K,) bool, True for the points the camera sees.
    """
    if len(points) == 0:
        return np.zeros(0, bool)
    R = quat_wxyz_to_rotation(wxyz)
    view = np.asarray(points, np.float64) - np.asarray(position, np.float64)
    pc = view @ R
    z = np.maximum(pc[:, 2], 1e-9)
    z_near = max(float(np.percentile(z, 2)), 1e-6)
    cell = VISIBLE_CELL * float(spacing) / z_near  # tangent-plane units
    ij = np.floor(pc[:, :2] / z[:, None] / cell).astype(np.int64)
    _, key = np.unique(ij, axis=0, return_inverse=True)
    key = key.reshape(-1)
    nearest = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(nearest, key, z)
    cos = np.abs(np.einsum("ij,ij->i", view, np.asarray(normals, np.float64)))
    cos /= np.maximum(np.linalg.norm(view, axis=1), 1e-12)
    slope = np.minimum(np.sqrt(np.maximum(1.0 - cos**2, 0.0)) / np.maximum(cos, 1e-6), 4.0)
    tol = float(spacing) * (VISIBLE_TOLERANCE + VISIBLE_CELL * (z / z_near) * slope)
    return z <= nearest[key] + tol


def visible_by_rays(geom: ScanGeometry, idx: np.ndarray, *, position: np.ndarray) -> np.ndarray:
    """Which vertices of a mesh the camera sees, by casting a ray from the camera to each (exact at the mesh's
    resolution): hidden when the ray meets a triangle more than a quarter spacing before the vertex.

    Args:
        geom: a mesh scan (its ray caster is built if it is not yet).
        idx: (K,) vertex indices.
        position: (3,) camera position, world frame.

    Returns:
        (K,) bool.
    """
    from efem_viz._typeshims import o3d_tensor

    if len(idx) == 0:
        return np.zeros(0, bool)
    d = geom.points[idx].astype(np.float64) - np.asarray(position, np.float64)
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([np.broadcast_to(np.asarray(position, np.float64), d.shape),
                           d / np.maximum(dist, 1e-12)[:, None]], axis=1).astype(np.float32)
    t = geom.raycaster().cast_rays(o3d_tensor(rays))["t_hit"].numpy()
    return t >= dist - (0.25 * geom.spacing + 1e-4 * dist)


def _keep_facing(geom: ScanGeometry, keep: np.ndarray, facing: Facing, position: np.ndarray,
                 wxyz: np.ndarray, counts: dict[str, int] | None = None) -> np.ndarray:
    """The candidates `keep` that the `facing` rule takes (see `Facing`); `counts["hidden"]` gets the number of
    candidates facing the camera that "visible" left out as hidden."""
    if facing not in ("visible", "front", "all"):
        raise ValueError(f"facing must be 'visible', 'front' or 'all', got {facing!r}")
    if facing == "all" or not len(keep):
        return keep
    view = geom.points[keep].astype(np.float64) - np.asarray(position, np.float64)
    front = np.einsum("ij,ij->i", view, geom.normals[keep].astype(np.float64)) < 0
    if facing == "front":
        return keep[front]
    if geom.is_mesh:  # exact (waits for the warm-up's ray caster if it is still being built)
        seen = front & visible_by_rays(geom, keep, position=position)
    else:
        seen = front & visible_among(geom.points[keep], geom.normals[keep], position=position, wxyz=wxyz,
                                     spacing=geom.spacing)
    if counts is not None:
        counts["hidden"] = int(front.sum() - seen.sum())
    return keep[seen]


def box_select(
    geom: ScanGeometry,
    *,
    position: np.ndarray,
    wxyz: np.ndarray,
    fov: float,
    aspect: float,
    screen_min: tuple[float, float],
    screen_max: tuple[float, float],
    facing: Facing = "visible",
    counts: dict[str, int] | None = None,
) -> np.ndarray:
    """Vertices whose projection falls in a screen rectangle.

    Args:
        geom: the scan.
        position, wxyz, fov, aspect: the client camera (see `project`).
        screen_min, screen_max: rectangle corners in [0, 1] screen coordinates (OpenCV: (0,0) top-left).
        facing: which vertices inside it are taken (`Facing`): "visible" (default) what the camera sees,
            "front" everything facing the camera, hidden or not, "all" through the object.
        counts: if given, "hidden" is set to the number of vertices inside that face the camera but are hidden
            behind other surface (left out by "visible").

    Returns:
        (K,) int32 sorted vertex indices.
    """
    uv, z = project(geom.points, position=position, wxyz=wxyz, fov=fov, aspect=aspect)
    u0, v0 = min(screen_min[0], screen_max[0]), min(screen_min[1], screen_max[1])
    u1, v1 = max(screen_min[0], screen_max[0]), max(screen_min[1], screen_max[1])
    inside = (z > 1e-6) & (uv[:, 0] >= u0) & (uv[:, 0] <= u1) & (uv[:, 1] >= v0) & (uv[:, 1] <= v1)
    keep = _keep_facing(geom, np.flatnonzero(inside), facing, position, wxyz, counts)
    return np.sort(keep).astype(np.int32)


def points_in_polygon(uv: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd test of 2D points against a closed polygon (vectorised over points, looped over edges).

    Args:
        uv: (N, 2) points.
        polygon: (P, 2) vertices, P >= 3, in order (the last connects to the first).

    Returns:
        (N,) bool, True inside.
    """
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    if len(poly) < 3:
        raise ValueError(f"a lasso needs at least 3 points, got {len(poly)}")
    x, y = uv[:, 0], uv[:, 1]
    inside = np.zeros(len(uv), bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xc)
    return inside


def lasso_select(
    geom: ScanGeometry,
    *,
    position: np.ndarray,
    wxyz: np.ndarray,
    fov: float,
    aspect: float,
    polygon: np.ndarray,
    facing: Facing = "visible",
    counts: dict[str, int] | None = None,
) -> np.ndarray:
    """Vertices whose projection falls inside a screen polygon (lasso), like `box_select` with any outline.

    Args:
        geom: the scan.
        position, wxyz, fov, aspect: the client camera (see `project`).
        polygon: (P, 2) outline in [0, 1] screen coordinates (OpenCV: (0,0) top-left), P >= 3.
        facing: which vertices inside it are taken (`Facing`, as `box_select`).
        counts: as `box_select`.

    Returns:
        (K,) int32 sorted vertex indices.
    """
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    if not np.isfinite(poly).all():
        raise ValueError("lasso points must be finite")
    uv, z = project(geom.points, position=position, wxyz=wxyz, fov=fov, aspect=aspect)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    cand = np.flatnonzero((z > 1e-6) & np.all((uv >= lo) & (uv <= hi), axis=1))
    keep = _keep_facing(geom, cand[points_in_polygon(uv[cand], poly)], facing, position, wxyz, counts)
    return np.sort(keep).astype(np.int32)
