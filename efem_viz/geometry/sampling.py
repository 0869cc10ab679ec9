"""Area-uniform sampling of a triangle mesh surface: the one home of surface sampling in efem-viz.

The solver's reviews (completed-shape samples Q), pose retrieval, codebook building and the checkpoint
converter all draw their samples here, so an empty mesh is handled one way everywhere (see `empty`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np

if TYPE_CHECKING:
    import trimesh


class MeshArrays(NamedTuple):
    """A triangle mesh as two arrays, for code that must run without trimesh (`sample_surface` takes either).

    Attributes:
        vertices: (V, 3) float vertex positions.
        faces: (F, 3) int triangle vertex indices.
    """

    vertices: np.ndarray
    faces: np.ndarray


class SurfaceSamples(NamedTuple):
    """Samples on a mesh surface, in the mesh's frame.

    Attributes:
        points: (n, 3) float64 sample positions.
        normals: (n, 3) float64 unit normals of the faces the samples lie on.
        face_index: (n,) int64 face of each sample; −1 for the samples of an empty mesh.
    """

    points: np.ndarray
    normals: np.ndarray
    face_index: np.ndarray


def sample_surface(
    mesh: "trimesh.Trimesh | MeshArrays",
    n: int,
    *,
    seed: int | np.random.Generator = 0,
    empty: Literal["zeros", "raise"] = "zeros",
) -> SurfaceSamples:
    """`n` area-uniform samples on a mesh (faces drawn by area, then uniform barycentric coordinates).

    Draws `rng.choice(faces, p=area)` and then `rng.random((n, 2))` from one generator, so a given seed always
    gives the same samples.

    Args:
        mesh: triangle mesh (any frame): a trimesh, or `MeshArrays` (the same samples for the same arrays).
        n: number of samples (>= 0).
        seed: integer seed or a Generator (advanced in place).
        empty: what a mesh without faces or with zero total area gives: "zeros" = n samples at the origin with
            zero normals and face index −1 (the release's convention: pose retrieval then returns an identity
            pose with score 0), "raise" = ValueError.

    Returns:
        `SurfaceSamples` (points, normals, face_index).

    Raises:
        ValueError: n < 0, or an empty mesh with empty="raise".
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if empty not in ("zeros", "raise"):
        raise ValueError(f"empty must be 'zeros' or 'raise', got {empty!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if isinstance(mesh, MeshArrays):
        tris = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces, np.int64)].reshape(-1, 3, 3)
        cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        norm = np.linalg.norm(cross, axis=1)
        area = norm / 2.0
        face_normals = np.where(norm[:, None] > 0, cross / np.maximum(norm, 1e-300)[:, None], 0.0)
    else:
        tris = np.asarray(mesh.triangles, dtype=np.float64) if len(mesh.faces) else np.zeros((0, 3, 3))
        area = np.asarray(mesh.area_faces, dtype=np.float64) if len(mesh.faces) else np.zeros(0)
        face_normals = np.asarray(mesh.face_normals, dtype=np.float64) if len(mesh.faces) else np.zeros((0, 3))
    if len(area) == 0 or not area.sum() > 0:
        if empty == "raise":
            raise ValueError(f"cannot sample the surface of an empty mesh ({len(mesh.faces)} faces, zero area)")
        return SurfaceSamples(np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, -1, np.int64))
    face = rng.choice(len(area), size=n, p=area / area.sum())
    u = rng.random((n, 2))
    flip = u.sum(axis=1) > 1.0
    u[flip] = 1.0 - u[flip]
    tri = tris[face]
    pts = tri[:, 0] + u[:, :1] * (tri[:, 1] - tri[:, 0]) + u[:, 1:] * (tri[:, 2] - tri[:, 0])
    normals = face_normals[face]
    return SurfaceSamples(pts, normals, np.asarray(face, np.int64))
