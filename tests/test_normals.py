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


def test_coincident_points_are_estimated_on_the_distinct_positions() -> None:
    """a k-d tree cannot split coincident points, so N copies of one point made every k-NN query
    scan all N (quadratic: 2M copies ran for 200 s+). Duplicates now share the normal of their position."""
    import subprocess
    import sys
    from pathlib import Path

    rng = np.random.default_rng(0)
    g = np.linspace(-0.1, 0.1, 60)
    xx, yy = np.meshgrid(g, g)
    plane = np.stack([xx.ravel(), yy.ravel(), 0.01 * xx.ravel()], 1)
    pts = np.vstack([plane, np.repeat(plane[:5], 500, axis=0)])[rng.permutation(len(plane) + 2500)]
    nrm = estimate_normals(pts)
    expect = np.array([-0.01, 0.0, 1.0]) / np.linalg.norm([-0.01, 0.0, 1.0])
    assert np.abs(np.abs(nrm @ expect) - 1).max() < 1e-6  # every copy gets its position's plane normal
    # 300k copies of one point: seconds, not the quadratic scan (the timeout is a hang guard, 10x the expected)
    root = Path(__file__).resolve().parents[1]
    code = ("import numpy as np, sys; sys.path.insert(0, %r); from efem_viz.geometry.normals import estimate_normals;"
            " n = estimate_normals(np.zeros((300000, 3)));"
            " assert np.allclose(np.linalg.norm(n, axis=1), 1)" % str(root))
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_planar_share_tells_box_faces_from_a_curved_surface() -> None:
    """`planar_share`: the normals of a box corner (three faces) are all held by three directions; a cylinder's
    side seen from around spreads them, three 30-degree cones hold about a quarter; a flat patch alone is all
    one direction. The measure ignores normal length and is the same on a repeat."""
    from efem_viz.geometry.normals import planar_share

    rng = np.random.default_rng(1)
    faces = np.repeat(np.eye(3), [300, 250, 200], axis=0) + rng.normal(0, 0.02, (750, 3))
    assert planar_share(faces) == 1.0
    assert planar_share(faces * rng.uniform(0.1, 5.0, (750, 1))) == 1.0
    a = rng.uniform(0, 2 * np.pi, 2000)
    side = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
    share = planar_share(side)
    assert 0.2 < share < 0.35 and planar_share(side) == share  # 3 x 30 of 360 degrees, and sampling
    # a can: its side and its top; the top is one direction among three
    can = np.concatenate([side[:1200], np.tile([0.0, 0.0, 1.0], (300, 1))])
    assert 0.3 < planar_share(can) < 0.5
    assert planar_share(np.tile([0.0, 0.0, 1.0], (40, 1))) == 1.0
    assert np.isnan(planar_share(np.zeros((0, 3))))
    assert planar_share(np.zeros((10, 3))) == 0.0  # no direction at all
