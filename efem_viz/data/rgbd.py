"""Real RGB-D frames to scenes: back-project, find the table, rotate it to z = 0 with +Z up, crop, downsample.

Frames: the camera follows OpenCV (+X right, +Y down, +Z forward). The output world frame has the support plane
(table) at z = 0 with its normal +Z, objects at z > 0, the origin at the centre of the visible table and +X along
the camera's +X projected onto the table.
"""

from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.scene import Scene, SceneError
from efem_viz.terminal import one_line

log = logging.getLogger(__name__)

REAL_TABLETOP_LICENSE = "MIT, UOIS example images, (c) 2019 Chris Xie"
"""Licence line of the frames in `shared/data/real_tabletop` (the UOIS project's example images), which the bundled
real sample scenes carry. An import records it only when asked to (`licence=`): a user's frame is theirs."""
MAX_FRAME_SPAN_M = 1000.0
"""A frame whose back-projected points span more than this (metres) has absurd intrinsics and is refused."""


MAX_FRAME_PIXELS = 4096 * 4096
"""Largest RGB-D frame read (depth sensors top out near 4K)."""


def load_rgbd_npz(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a frame `.npz` with `rgb` (H, W, 3) uint8, `depth_mm` (H, W) uint16 (0 = no reading), `K` (3, 3).

    A float `depth` array in metres is accepted instead of `depth_mm`.

    Args:
        path: the `.npz` file.

    Returns:
        `(rgb (H, W, 3) uint8 or None, depth_m (H, W) float32 metres with 0 = invalid, K (3, 3) float64)`.

    Raises:
        SceneError: missing file or arrays, a corrupt archive (an array header that disagrees with its member's
            bytes is refused before numpy allocates), wrong shapes or dtypes.
    """
    from efem_viz.data.npz_guard import check_npz_headers
    from efem_viz.data.scene import DEFAULT_MAX_POINTS

    p = Path(path)
    if not p.is_file():
        raise SceneError(f"{p} is a directory, not an RGB-D frame" if p.is_dir() else f"{p}: no such file")
    shapes = check_npz_headers(p, DEFAULT_MAX_POINTS)  # the scene reader's header check: names the file
    for k in ("depth_mm", "depth", "rgb"):  # before anything is inflated (a 130 KB file, 8000² pixels)
        shape = shapes.get(k)
        if shape is not None and len(shape) >= 2 and shape[0] * shape[1] > MAX_FRAME_PIXELS:
            raise SceneError(f"{p}: {k!r} is {shape[1]}x{shape[0]} pixels, more than the {MAX_FRAME_PIXELS:,} "
                             "a depth sensor gives (4096x4096)")
    try:
        with np.load(p, allow_pickle=False) as d:
            data = {k: np.array(d[k]) for k in d.keys()}
    except MemoryError:
        raise
    except Exception as exc:
        raise SceneError(f"{p}: could not read the RGB-D .npz ({one_line(exc, limit=300)})") from exc
    if "K" not in data:
        raise SceneError(f"{p}: RGB-D .npz needs an intrinsics array 'K' (has {sorted(data)})")
    key = "depth_mm" if "depth_mm" in data else "depth" if "depth" in data else None
    if key is None:
        raise SceneError(f"{p}: RGB-D .npz needs 'depth_mm' (uint16 mm) or 'depth' (float m) (has {sorted(data)})")
    for k in (key, "K", "rgb"):
        if k in data and data[k].dtype.kind not in ("biu" if k == "rgb" else "biuf"):
            raise SceneError(f"{p}: RGB-D array {k!r} must be numeric, got dtype {data[k].dtype}")
    depth_m = data.pop(key).astype(np.float32)  # one float copy at a time
    if key == "depth_mm":
        depth_m /= 1000.0
    rgb = data.get("rgb")
    K = np.asarray(data["K"], dtype=np.float64)
    _check_inputs(depth_m, K, rgb, where=str(p))
    return rgb, depth_m, K  # type: ignore[return-value]


def _check_inputs(depth_m: np.ndarray, K: np.ndarray, rgb: np.ndarray | None, *, where: str) -> None:
    if depth_m.ndim != 2:
        raise SceneError(f"{where}: depth must be (H, W), got {depth_m.shape}")
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        shown = K.tolist() if K.size <= 9 else f"shape {K.shape}"
        raise SceneError(f"{where}: K must be a (3, 3) pinhole matrix with fx, fy > 0, got {shown}")
    if rgb is not None and (rgb.ndim != 3 or rgb.shape[:2] != depth_m.shape or rgb.shape[2] not in (3, 4)):
        raise SceneError(f"{where}: rgb of shape {rgb.shape} does not match depth {depth_m.shape}")


def backproject(depth_m: np.ndarray, K: np.ndarray, *, max_depth: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Back-project valid depth pixels to camera-frame points (OpenCV camera).

    Args:
        depth_m: (H, W) float, metres; 0, negative, NaN or > max_depth = invalid.
        K: (3, 3) intrinsics.
        max_depth: drop readings beyond this (metres).

    Returns:
        `(points_cam (N, 3) float64, pixel_index (N,) int64 into the flattened image)`.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    H, W = d.shape
    valid = np.isfinite(d) & (d > 0) & (d <= max_depth)
    idx = np.flatnonzero(valid)
    v, u = np.divmod(idx, W)
    z = d.reshape(-1)[idx]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pts = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    return pts, idx


@dataclass(frozen=True)
class PlaneFit:
    """The support plane found in a frame (camera frame)."""

    normal: np.ndarray
    """(3,) unit normal, pointing toward the camera side (up)."""
    offset: float
    """d in n·x + d = 0."""
    inliers: np.ndarray
    """(K,) indices (into the plane-fitting cloud) of the table's connected inlier region."""
    residual_rms: float
    """RMS point-to-plane distance of those inliers, metres."""


def ransac_plane(
    points: np.ndarray,
    *,
    rng: np.random.Generator,
    distance: float = 0.01,
    iterations: int = 1000,
    score_points: int = 4000,
) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic (seeded) RANSAC plane fit, vectorised in NumPy, refined by least squares on the inliers.

    (open3d's `segment_plane` runs its hypotheses in parallel threads and is not reproducible even when seeded.)

    Args:
        points: (N, 3) float.
        rng: random generator.
        distance: inlier distance.
        iterations: plane hypotheses.
        score_points: hypotheses are scored on this many random points (all if fewer).

    Returns:
        `(model (4,) [a, b, c, d] with unit normal, inlier indices (K,) int64)`.
    """
    n = len(points)
    tri = points[rng.integers(0, n, size=(iterations, 3))]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(nrm, axis=1)
    ok = length > 1e-12
    nrm = nrm[ok] / length[ok, None]
    d = -np.einsum("ij,ij->i", nrm, tri[ok, 0])
    sub = points[rng.choice(n, size=min(n, score_points), replace=False)]
    counts = (np.abs(sub @ nrm.T + d) < distance).sum(axis=0)
    best = int(np.argmax(counts))
    normal, off = nrm[best], float(d[best])
    inl = np.flatnonzero(np.abs(points @ normal + off) < distance)
    for _ in range(2):  # least-squares refinement
        if len(inl) < 3:
            break
        c = points[inl].mean(axis=0)
        normal = np.linalg.svd(points[inl] - c, full_matrices=False)[2][2]
        off = float(-normal @ c)
        inl = np.flatnonzero(np.abs(points @ normal + off) < distance)
    return np.array([*normal, off]), inl.astype(np.int64)


def find_support_plane(
    points_cam: np.ndarray,
    *,
    seed: int = 0,
    distance: float = 0.01,
    max_planes: int = 4,
    cluster_eps: float = 0.03,
) -> PlaneFit:
    """Find the table plane: RANSAC planes (seeded, `ransac_plane`), keep those facing the camera with normal toward
    image-up, take each one's largest connected region, prefer the plane nearest the camera among the large ones (a
    table above a floor), refit by least squares.

    Args:
        points_cam: (N, 3) float, camera frame, already thinned (e.g. a 1 cm voxel grid).
        seed: RANSAC seed.
        distance: RANSAC inlier distance, metres.
        max_planes: planes to extract one after another.
        cluster_eps: DBSCAN radius for the connected region, metres.

    Raises:
        SceneError: no plane facing the camera was found.
    """
    import open3d as o3d

    rng = np.random.default_rng(seed)
    pts = np.asarray(points_cam, dtype=np.float64)
    remaining = np.arange(len(pts))
    cands: list[dict[str, Any]] = []
    for _ in range(max_planes):
        if len(remaining) < 500:
            break
        model, inl = ransac_plane(pts[remaining], rng=rng, distance=distance)
        if len(inl) < 300:
            break
        idx = remaining[inl]
        remaining = np.delete(remaining, inl)
        n = np.asarray(model[:3], dtype=np.float64)
        dd = float(model[3]) / np.linalg.norm(n)
        n = n / np.linalg.norm(n)
        if dd < 0:  # orient toward the camera (origin): n·0 + d > 0
            n, dd = -n, -dd
        sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx]))
        labels = np.asarray(sub.cluster_dbscan(eps=cluster_eps, min_points=5))
        if (labels >= 0).any():
            best = np.bincount(labels[labels >= 0]).argmax()
            idx = idx[labels == best]
        centroid = pts[idx].mean(axis=0)
        view = -centroid / np.linalg.norm(centroid)
        cands.append(
            dict(
                idx=idx,
                normal=n,
                offset=dd,
                facing=float(n @ view),
                upness=float(-n[1]),
                size=len(idx),
            )
        )
    facing = [c for c in cands if c["facing"] > 0.25]
    upright = [c for c in facing if c["upness"] > 0.3]
    pool = upright or facing
    if not pool:
        raise SceneError("no support plane facing the camera was found in the depth image")
    biggest = max(c["size"] for c in pool)
    large = [c for c in pool if c["size"] >= 0.25 * biggest]
    chosen = min(large, key=lambda c: c["offset"])  # nearest to the camera: a table rather than the floor below it
    for c in pool:
        log.debug("plane n=%s d=%.3f size=%d facing=%.2f up=%.2f", c["normal"], c["offset"], c["size"],
                  c["facing"], c["upness"])
    # least-squares refit on the connected region
    q = pts[chosen["idx"]]
    c0 = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - c0, full_matrices=False)
    n = vt[2]
    if n @ (-c0) < 0:
        n = -n
    d = float(-n @ c0)
    res = (q - c0) @ n
    return PlaneFit(normal=n, offset=d, inliers=chosen["idx"], residual_rms=float(np.sqrt(np.mean(res**2))))


def table_frame(normal: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation taking camera coordinates to the table frame: `p_table = R @ (p_cam - origin)`.

    Args:
        normal: (3,) unit table normal (camera frame), pointing toward the camera.
        origin: (3,) a point on the table (camera frame), becomes the world origin.

    Returns:
        `(R (3, 3) proper rotation, t (3,))` with `p_table = R @ p_cam + t`.
    """
    z = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z  # camera +X projected onto the table
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 0.0, 1.0]) - z[2] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ np.asarray(origin, dtype=np.float64)


def _inside_hull(hull_xy: np.ndarray, q: np.ndarray, margin: float) -> np.ndarray:
    """Which (Q, 2) points lie inside the convex polygon `hull_xy` (counter-clockwise) grown by `margin`."""
    a = hull_xy
    b = np.roll(hull_xy, -1, axis=0)
    e = b - a
    nrm = np.stack([e[:, 1], -e[:, 0]], axis=1)  # outward normal for a CCW polygon
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    inside = np.ones(len(q), dtype=bool)
    for k in range(len(a)):  # one half-plane per edge keeps memory at O(Q)
        inside &= (q - a[k]) @ nrm[k] <= margin
    return inside


def _crop_above_table(points_cam: np.ndarray, colors: np.ndarray, table_pts: np.ndarray, R: np.ndarray,
                      t: np.ndarray, *, below: float, max_height: float, margin: float,
                      voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The frame's points over the table, in the table frame, voxel-downsampled (`import_rgbd`).

    Args:
        points_cam: (N, 3) float64 points, camera frame.
        colors: (N, 3) float64 colours in [0, 1].
        table_pts: (T, 3) float64 support-plane inliers, camera frame (their convex hull is the table outline).
        R, t: camera frame → table frame (`table_frame`).
        below, max_height: the height band kept, metres under and over the table.
        margin: the outline grown by this much, metres.
        voxel: voxel size, metres (colours averaged per voxel).

    Returns:
        (M, 3) float64 points in the table frame and (M, 3) uint8 colours.
    """
    import open3d as o3d
    from scipy.spatial import ConvexHull

    table_xy = (table_pts @ R.T + t)[:, :2]
    hull = ConvexHull(table_xy)
    hull_xy = table_xy[hull.vertices]  # scipy returns 2-D hull vertices counter-clockwise

    dense = points_cam @ R.T + t
    keep = (dense[:, 2] > -below) & (dense[:, 2] < max_height)
    keep[keep] = _inside_hull(hull_xy, dense[keep, :2], margin)
    crop = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dense[keep]))
    crop.colors = o3d.utility.Vector3dVector(colors[keep])
    down = crop.voxel_down_sample(voxel)
    pts = np.asarray(down.points)
    cols = np.clip(np.round(np.asarray(down.colors) * 255.0), 0, 255).astype(np.uint8)
    return pts, cols


def _rgbd_provenance(K: np.ndarray, depth_shape: tuple[int, ...], plane: PlaneFit, table_pts: np.ndarray,
                     R: np.ndarray, t: np.ndarray) -> dict[str, Any]:
    """What an imported frame records about its capture: the intrinsics and image size, the support plane (camera
    frame) and its residual, the camera pose in the table frame (`T_world_camera`, 4x4)."""
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3] = R
    T_world_cam[:3, 3] = t
    res_world = (table_pts @ R.T + t)[:, 2]
    return {
        "source": "rgbd",
        "frame": "table: z = 0 at the support plane, +Z up, origin at the visible table's centre",
        "K": np.round(K, 4).tolist(),
        "image_size": [int(depth_shape[1]), int(depth_shape[0])],
        "plane_camera": [float(v) for v in (*plane.normal, plane.offset)],
        "plane_residual_rms_m": round(float(np.sqrt(np.mean(res_world**2))), 5),
        "T_world_camera": np.round(T_world_cam, 6).tolist(),
    }


def import_rgbd(
    depth_m: np.ndarray,
    K: np.ndarray,
    rgb: np.ndarray | None = None,
    *,
    name: str,
    voxel: float = 0.004,
    max_depth: float = 2.5,
    max_height: float = 0.4,
    below: float = 0.015,
    margin: float = 0.02,
    seed: int = 0,
    licence: str | None = None,
    provenance: dict[str, Any] | None = None,
) -> Scene:
    """Turn one RGB-D frame into a tabletop `Scene` (table at z = 0, +Z up, objects above).

    Steps: back-project valid depth (OpenCV camera), find the support plane (RANSAC, the plane facing the
    camera and nearest to it among the large ones, refit by least squares on its connected region), rotate so the
    table normal is +Z with the table at z = 0, keep points over the table's convex hull (grown by `margin`) from
    `below` under the table to `max_height` above it, voxel-downsample (colours averaged), estimate normals and
    orient them toward the camera.

    Args:
        depth_m: (H, W) float, metres; 0/NaN = no reading.
        K: (3, 3) pinhole intrinsics.
        rgb: (H, W, 3) uint8 colours registered to the depth, or None (grey).
        name: scene name.
        voxel: voxel size of the output, metres.
        max_depth: drop readings farther than this, metres.
        max_height: keep points up to this height above the table, metres.
        below: keep points down to this depth under the table (sensor noise), metres.
        margin: grow the table outline by this much, metres.
        seed: RANSAC seed.
        licence: the frame's licence, recorded as `provenance["licence"]` (e.g. `REAL_TABLETOP_LICENSE` for the
            UOIS frames); None records none (the frame's owner knows its terms).
        provenance: extra provenance entries (e.g. the source file).

    Returns:
        The Scene; `provenance` holds the intrinsics, the plane (camera frame), the camera pose in the scene
        frame (`T_world_camera`, 4x4), the plane residual and the licence when one was given.

    Raises:
        SceneError: bad shapes, too few valid depth readings, no plane found.
    """
    import open3d as o3d

    t0 = time.perf_counter()
    depth_m = np.asarray(depth_m, dtype=np.float32)
    K = np.asarray(K, dtype=np.float64)
    if rgb is not None:
        rgb = np.asarray(rgb)
    _check_inputs(depth_m, K, rgb, where=name)
    with np.errstate(over="ignore", invalid="ignore"):
        pts_cam, pix = backproject(depth_m, K, max_depth=max_depth)
    if len(pts_cam) < 1000:
        raise SceneError(f"{name}: only {len(pts_cam)} valid depth readings within {max_depth} m")
    span = float(np.ptp(pts_cam, axis=0).max())
    if not span < MAX_FRAME_SPAN_M:  # NaN/Inf too: Open3D's voxel grid fails on such clouds with a RuntimeError
        raise SceneError(f"{name}: the depth image and K = {np.round(K, 3).tolist()} put the points {span:.3g} m "
                         f"apart (more than {MAX_FRAME_SPAN_M:g} m): not a camera's intrinsics")
    colors = (
        rgb.reshape(-1, rgb.shape[2])[pix, :3].astype(np.float64) / 255.0
        if rgb is not None
        else np.full((len(pts_cam), 3), 180 / 255.0)
    )
    full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts_cam))
    full.colors = o3d.utility.Vector3dVector(colors)
    coarse = np.asarray(full.voxel_down_sample(0.01).points)
    plane = find_support_plane(coarse, seed=seed)
    table_pts = coarse[plane.inliers]
    centre = table_pts.mean(axis=0)
    centre = centre - (centre @ plane.normal + plane.offset) * plane.normal  # projected onto the plane
    R, t = table_frame(plane.normal, centre)
    pts, cols = _crop_above_table(np.asarray(full.points), colors, table_pts, R, t, below=below,
                                  max_height=max_height, margin=margin, voxel=voxel)
    cam_world = t  # the camera centre (origin of the camera frame) in the table frame: R @ 0 + t
    from efem_viz.geometry.normals import estimate_normals

    normals = estimate_normals(pts, toward=cam_world, knn=20)
    prov = _rgbd_provenance(K, depth_m.shape, plane, table_pts, R, t)
    prov.update(voxel_m=voxel, max_depth_m=max_depth, max_height_m=max_height, seed=seed)
    if licence is not None:
        prov["licence"] = str(licence)
    prov.update(provenance or {})
    scene = Scene.create(name, pts, normals=normals, colors=cols, provenance=prov)
    log.info(
        "%s: %d valid depth pixels -> %d points (voxel %.3f m), plane rms %.4f m, %.2f s",
        name, len(pts_cam), scene.num_points, voxel, prov["plane_residual_rms_m"], time.perf_counter() - t0,
    )
    return scene


def import_rgbd_file(
    path: str | os.PathLike[str],
    *,
    name: str | None = None,
    voxel: float = 0.004,
    max_depth: float = 2.5,
    seed: int = 0,
    licence: str | None = None,
) -> Scene:
    """`load_rgbd_npz` + `import_rgbd`, recording the source file (and the licence, when given) in the provenance.

    Raises:
        SceneError: what either raises, the message naming the file.
    """
    p = Path(path)
    rgb, depth_m, K = load_rgbd_npz(p)
    try:
        return import_rgbd(
            depth_m, K, rgb, name=name or p.stem, voxel=voxel, max_depth=max_depth, seed=seed, licence=licence,
            provenance={"source_file": p.name},
        )
    except SceneError as exc:  # the import names the scene; the caller needs the file
        msg = str(exc)
        raise SceneError(msg if str(p) in msg else f"{p}: {msg}") from exc
    except RuntimeError as exc:  # Open3D's errors: coloured, over several lines
        text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).split())[:300]
        raise SceneError(f"{p}: could not import the RGB-D frame ({text})") from exc


def read_depth_image(path: Path) -> np.ndarray:
    """Depth in metres from a `.npy` (float metres, or integer millimetres) or a 16-bit `.png` (millimetres).

    Returns:
        (H, W) float32 metres, 0 = no reading.

    Raises:
        SceneError: missing file, unknown suffix, not a 2-D image.
    """
    p = Path(path)
    if not p.is_file():
        raise SceneError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        d = np.load(p, allow_pickle=False)
        d = d.astype(np.float32) / 1000.0 if np.issubdtype(d.dtype, np.integer) else d.astype(np.float32)
    elif suffix == ".png":
        from PIL import Image

        with Image.open(p) as im:
            arr = np.asarray(im)
        if arr.dtype not in (np.uint16, np.int32, np.uint32) and not (arr.dtype == np.int64):
            raise SceneError(f"{p}: a depth PNG must be 16-bit millimetres, got {arr.dtype} (mode {im.mode})")
        d = arr.astype(np.float32) / 1000.0
    else:
        raise SceneError(f"{p}: depth must be .npy (metres) or 16-bit .png (millimetres), got {suffix!r}")
    if d.ndim != 2:
        raise SceneError(f"{p}: depth must be a 2-D image, got shape {d.shape}")
    return np.where(np.isfinite(d), d, 0.0).astype(np.float32)


def read_rgb_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 colours from an image file."""
    from PIL import Image

    p = Path(path)
    if not p.is_file():
        raise SceneError(f"{p}: no such file")
    with Image.open(p) as im:
        return np.asarray(im.convert("RGB"))
