"""Normals: mesh vertex normals (incl. degenerate vertices) and open3d estimates oriented toward a sensor."""

from __future__ import annotations

import numpy as np

from efem_viz.geometry.normals import estimate_normals


def test_unreferenced_vertex_gets_a_unit_normal_instead_of_crashing() -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], float)
    nrm = estimate_normals(verts, faces=np.array([[0, 1, 2]]))
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(nrm[:3], [[0, 0, 1]] * 3, atol=1e-6)


def test_point_normals_face_the_sensor() -> None:
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (500, 2)), 0.001 * rng.standard_normal(500)]
    nrm = estimate_normals(pts, toward=np.array([0.0, 0.0, -2.0]))
    assert (nrm[:, 2] < -0.95).mean() > 0.98
    nrm_up = estimate_normals(pts)
    assert (nrm_up[:, 2] > 0.95).mean() > 0.98
