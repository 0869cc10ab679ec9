"""Surface normals: from mesh faces, or estimated from points with open3d and oriented consistently."""

from __future__ import annotations

import numpy as np


def estimate_normals(
    points: np.ndarray,
    *,
    faces: np.ndarray | None = None,
    toward: np.ndarray | None = None,
    knn: int = 20,
) -> np.ndarray:
    """Unit normals for a point set or mesh.

    With `faces`, area-weighted vertex normals of the mesh (outward for a consistently wound mesh).
    Without, open3d PCA normals over `knn` neighbours, oriented toward the sensor position `toward`
    when given, otherwise consistently by tangent-plane propagation and then flipped so that most point
    away from the centroid (outward for closed scans) or up (+Z) for flat scenes.

    Args:
        points: (N, 3) float, world frame.
        faces: (M, 3) int or None.
        toward: (3,) sensor position, or None.
        knn: neighbours for PCA normals.

    Returns:
        (N, 3) float32 unit normals.
    """
    pts = np.asarray(points, dtype=np.float64)
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
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(knn, n)))
    if toward is not None:
        pcd.orient_normals_towards_camera_location(np.asarray(toward, dtype=np.float64))
        nrm = np.asarray(pcd.normals)
    else:
        try:
            pcd.orient_normals_consistent_tangent_plane(min(10, n - 1))
        except RuntimeError:
            pass
        nrm = np.asarray(pcd.normals)
        centre = pts.mean(axis=0)
        outward = np.einsum("ij,ij->i", nrm, pts - centre)
        extent = pts.max(axis=0) - pts.min(axis=0)
        flat = extent[2] < 0.25 * max(extent[0], extent[1], 1e-9)
        score = nrm[:, 2].sum() if flat else outward.sum()
        if score < 0:
            nrm = -nrm
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return nrm.astype(np.float32)
