"""Tests of efem_viz.geometry.sampling.sample_surface: the one surface sampler (on-surface, outward normals,
seeded, area-uniform, one empty-mesh policy per caller)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from efem_viz.geometry.sampling import SurfaceSamples, sample_surface


def _empty_meshes() -> list[trimesh.Trimesh]:
    no_faces = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)  # zero area
    return [no_faces, flat]


def test_samples_lie_on_the_surface_with_outward_normals() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    s = sample_surface(mesh, 2000, seed=1)
    assert isinstance(s, SurfaceSamples)
    assert s.points.shape == s.normals.shape == (2000, 3) and s.face_index.shape == (2000,)
    assert s.points.dtype == s.normals.dtype == np.float64 and s.face_index.dtype == np.int64
    # on the triangle it names: zero distance to the face's plane, barycentric coordinates in [0, 1]
    tri = mesh.triangles[s.face_index]
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.points - tri[:, 0], mesh.face_normals[s.face_index]), 0,
                               atol=1e-12)
    bary = trimesh.triangles.points_to_barycentric(tri, s.points)
    assert (bary > -1e-9).all() and (bary < 1 + 1e-9).all()
    _, dist, _ = trimesh.proximity.closest_point(mesh, s.points)
    assert dist.max() < 1e-9
    # unit normals pointing away from the centre of the convex sphere
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-9)
    assert (np.einsum("ij,ij->i", s.points, s.normals) > 0.9 * 0.4).all()


def test_same_seed_same_samples_and_generators_advance() -> None:
    mesh = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    a, b = sample_surface(mesh, 100, seed=3), sample_surface(mesh, 100, seed=3)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.points, sample_surface(mesh, 100, seed=4).points)
    rng = np.random.default_rng(3)
    first, second = sample_surface(mesh, 100, seed=rng), sample_surface(mesh, 100, seed=rng)
    np.testing.assert_array_equal(first.points, a.points)  # an int seed is default_rng(seed)
    assert not np.array_equal(first.points, second.points)  # the Generator was advanced in place


def test_faces_are_drawn_by_area() -> None:
    # a box 1 × 1 × 4: the four long sides hold 16 of its 18 units of area
    mesh = trimesh.creation.box(extents=(1.0, 1.0, 4.0))
    s = sample_surface(mesh, 20000, seed=0)
    on_caps = np.abs(np.abs(s.points[:, 2]) - 2.0) < 1e-9
    assert on_caps.mean() == pytest.approx(2.0 / 18.0, abs=0.01)


@pytest.mark.parametrize("mesh", _empty_meshes(), ids=["no_faces", "zero_area"])
def test_empty_mesh_policy(mesh: trimesh.Trimesh) -> None:
    z = sample_surface(mesh, 7, seed=0)  # default "zeros": the release's convention (identity pose later)
    assert z.points.shape == z.normals.shape == (7, 3)
    assert not z.points.any() and not z.normals.any() and (z.face_index == -1).all()
    with pytest.raises(ValueError, match="empty mesh"):
        sample_surface(mesh, 7, seed=0, empty="raise")


def test_invalid_arguments() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=1)
    assert sample_surface(mesh, 0, seed=0).points.shape == (0, 3)
    with pytest.raises(ValueError, match="n must be"):
        sample_surface(mesh, -1)
    with pytest.raises(ValueError, match="empty must be"):
        sample_surface(mesh, 3, empty="nan")  # type: ignore[arg-type]
