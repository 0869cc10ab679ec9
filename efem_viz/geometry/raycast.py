"""Mesh queries in plain torch: signed distance and ray casting, on any device.

The training data of a shape prior needs, per object, the signed distance of ~32k query points and a dozen
ray-cast depth views. open3d's `RaycastingScene` does this on the CPU; these functions do the same with
brute-force tensor operations (every query against every triangle, in chunks), so that a machine without open3d
(a GPU box with only torch) prepares the data itself, at GPU speed. Sizes that suit a procedural object (a few
thousand triangles) are the intended use; the cost is O(queries x triangles).

- `signed_distance`: unsigned distance to the nearest triangle, negative inside; inside/outside by the
  generalised winding number (Jacobson et al. 2013), so the mesh must be closed (watertight), as open3d's needs.
- `cast_rays`: first hit distance along each ray (Möller-Trumbore) and the hit triangle's unit normal.
- `pinhole_rays`: the rays of a square pinhole camera looking at a point, +Z up, in the pixel order of open3d's
  `create_rays_pinhole` (row-major; directions of unit length along the optical axis).
"""

from __future__ import annotations

import math

import torch

__all__ = ["signed_distance", "cast_rays", "pinhole_rays", "winding_number"]


def _check_mesh(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"faces must be (F, 3) with F >= 1, got {tuple(faces.shape)}")
    if int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]:
        raise ValueError(f"face indices span [{int(faces.min())}, {int(faces.max())}], "
                         f"but there are {vertices.shape[0]} vertices")


def _chunk_rows(n_rows: int, n_faces: int, budget: int) -> int:
    return max(1, min(n_rows, budget // max(n_faces, 1)))


def _segment_distance_sq(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distance from points (P, 1, 3) to segments a-b (1, F, 3) -> (P, F)."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-30)
    t = t.clamp(0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return (d * d).sum(-1)


def _unsigned_distance_chunk(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor,
                             n: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """Distance from points (P, 3) to the nearest of the triangles (F, 3 each) -> (P,)."""
    pp = p[:, None, :]
    ap = pp - a  # (P, F, 3)
    h = (ap * n).sum(-1)  # signed height over the plane (n is unit; zero for degenerate faces)
    q = pp - h[..., None] * n  # projection on the plane
    # inside the triangle when the projection lies left of all three edges (same side as the normal)
    s0 = (torch.linalg.cross(b - a, q - a) * n).sum(-1)
    s1 = (torch.linalg.cross(c - b, q - b) * n).sum(-1)
    s2 = (torch.linalg.cross(a - c, q - c) * n).sum(-1)
    inside = (s0 >= 0) & (s1 >= 0) & (s2 >= 0) & ok
    d_edge = torch.minimum(torch.minimum(_segment_distance_sq(pp, a, b), _segment_distance_sq(pp, b, c)),
                           _segment_distance_sq(pp, c, a))
    d_sq = torch.where(inside, h * h, d_edge)
    return d_sq.min(dim=1).values.sqrt()


def winding_number(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, *,
                   budget: int = 1 << 24) -> torch.Tensor:
    """Generalised winding number of a closed mesh at each point (1 inside, 0 outside, ~0.5 on the surface).

    Args:
        vertices: (V, 3) float mesh vertices.
        faces: (F, 3) long triangle indices (outward orientation: counter-clockwise seen from outside).
        points: (P, 3) query points, same frame and dtype as the vertices.
        budget: how many point-triangle pairs one chunk may hold (memory: ~100 bytes a pair).

    Returns:
        (P,) winding numbers, dtype of the points.
    """
    _check_mesh(vertices, faces)
    tri = vertices[faces.long()]
    out = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    step = _chunk_rows(points.shape[0], faces.shape[0], budget)
    for i in range(0, points.shape[0], step):
        p = points[i:i + step, None, :]
        a, b, c = tri[None, :, 0] - p, tri[None, :, 1] - p, tri[None, :, 2] - p
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
        out[i:i + step] = torch.atan2(det, den).sum(dim=1) / (2.0 * math.pi)  # Σ Ω / 4π, Ω = 2 atan2(...)
    return out


def signed_distance(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, *,
                    budget: int = 1 << 24) -> torch.Tensor:
    """Signed distance from each point to a closed triangle mesh (negative inside).

    Args:
        vertices: (V, 3) float mesh vertices.
        faces: (F, 3) long triangle indices of a watertight mesh.
        points: (P, 3) query points, same frame, dtype and device as the vertices.
        budget: how many point-triangle pairs one chunk may hold.

    Returns:
        (P,) signed distances.

    Raises:
        ValueError: On malformed shapes or out-of-range face indices.
    """
    _check_mesh(vertices, faces)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (P, 3), got {tuple(points.shape)}")
    tri = vertices[faces.long()]
    a, b, c = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    cr = torch.linalg.cross(b - a, c - a)
    area2 = cr.norm(dim=-1, keepdim=True)
    ok = area2[..., 0] > 1e-20
    n = torch.where(ok[..., None], cr / area2.clamp_min(1e-30), torch.zeros_like(cr))
    dist = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    step = _chunk_rows(points.shape[0], faces.shape[0], budget // 4)
    for i in range(0, points.shape[0], step):
        dist[i:i + step] = _unsigned_distance_chunk(points[i:i + step], a, b, c, n, ok)
    inside = winding_number(vertices, faces, points, budget=budget) > 0.5
    return torch.where(inside, -dist, dist)


def cast_rays(vertices: torch.Tensor, faces: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, *,
              budget: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    """First intersection of each ray with the mesh (Möller-Trumbore against every triangle).

    Args:
        vertices: (V, 3) float mesh vertices.
        faces: (F, 3) long triangle indices.
        origins: (R, 3) ray origins.
        directions: (R, 3) ray directions (any length; ``t`` is in units of the direction's length).
        budget: how many ray-triangle pairs one chunk may hold.

    Returns:
        ``(t_hit, normals)``: (R,) distance parameter of the first hit (``inf`` for a miss) and (R, 3) the unit
        normal of the hit triangle (zeros for a miss).
    """
    _check_mesh(vertices, faces)
    if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins and directions must both be (R, 3), got {tuple(origins.shape)} and "
                         f"{tuple(directions.shape)}")
    tri = vertices[faces.long()]
    v0, e1, e2 = tri[None, :, 0], tri[None, :, 1] - tri[None, :, 0], tri[None, :, 2] - tri[None, :, 0]
    fn = torch.linalg.cross(e1[0], e2[0])
    fn = fn / fn.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    t_hit = torch.full((origins.shape[0],), math.inf, dtype=origins.dtype, device=origins.device)
    face_hit = torch.full((origins.shape[0],), -1, dtype=torch.long, device=origins.device)
    step = _chunk_rows(origins.shape[0], faces.shape[0], budget // 4)
    eps = 1e-12
    for i in range(0, origins.shape[0], step):
        o, d = origins[i:i + step, None, :], directions[i:i + step, None, :]
        pv = torch.linalg.cross(d, e2)
        det = (e1 * pv).sum(-1)
        good = det.abs() > eps
        inv = 1.0 / torch.where(good, det, torch.ones_like(det))
        tv = o - v0
        u = (tv * pv).sum(-1) * inv
        qv = torch.linalg.cross(tv, e1)
        v = (d * qv).sum(-1) * inv
        t = (e2 * qv).sum(-1) * inv
        hit = good & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = torch.where(hit, t, torch.full_like(t, math.inf))
        best, idx = t.min(dim=1)
        t_hit[i:i + step] = best
        face_hit[i:i + step] = torch.where(torch.isfinite(best), idx, torch.full_like(idx, -1))
    normals = torch.where((face_hit >= 0)[:, None], fn[face_hit.clamp_min(0)], torch.zeros_like(origins))
    return t_hit, normals


def pinhole_rays(eye: torch.Tensor, *, center: torch.Tensor | None = None, fov_deg: float, resolution: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of a square pinhole camera at ``eye`` looking at ``center`` (default the origin), +Z up.

    Args:
        eye: (3,) camera centre.
        center: (3,) the point the optical axis passes through (default the origin).
        fov_deg: field of view (both axes), degrees.
        resolution: image width = height, pixels.

    Returns:
        ``(origins, directions)``, each (resolution², 3), row-major pixels in open3d's order; directions have
        unit length along the optical axis (so ``t`` is depth).

    Raises:
        ValueError: If the camera looks straight up or down (the +Z up vector is then undefined).
    """
    center = torch.zeros_like(eye) if center is None else center
    fwd = center - eye
    fwd = fwd / fwd.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype, device=eye.device)
    right = torch.linalg.cross(up, fwd)  # open3d's pixel order: both image axes as its create_rays_pinhole
    if float(right.norm()) < 1e-9:
        raise ValueError("the camera looks along +-Z: no image 'up' direction")
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    half = math.tan(math.radians(fov_deg) / 2.0)
    px = (torch.arange(resolution, dtype=eye.dtype, device=eye.device) + 0.5) / resolution * 2.0 - 1.0
    yy, xx = torch.meshgrid(px * half, px * half, indexing="ij")
    dirs = fwd + xx.reshape(-1, 1) * right + yy.reshape(-1, 1) * down
    return eye.expand(dirs.shape[0], 3).contiguous(), dirs
