"""Tests of efem_viz.geometry: transforms, Procrustes (points and VN latents), rotation-only ICP, boxes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from efem_viz.geometry.icp import icp_rotation
from efem_viz.geometry.obb import BOX_CORNER_SIGNS, BOX_EDGES, oriented_box
from efem_viz.geometry.procrustes import latent_procrustes, procrustes, rotation_from_cross_covariance
from efem_viz.geometry.transforms import (
    Sim3,
    apply_transform,
    compose_transforms,
    invert_transform,
    make_transform,
    project_to_so3,
    quat_wxyz_to_rotation,
    random_rotation,
    random_rotations,
    random_sim3,
    rotation_about_axis,
    rotation_angle_deg,
    rotation_to_quat_wxyz,
    xyz_tuple,
)

seeds = st.integers(min_value=0, max_value=2**31 - 1)


def _reflection() -> np.ndarray:
    return np.diag([1.0, 1.0, -1.0])


# ---------------------------------------------------------------------------------------------- transforms
def test_random_rotations_are_proper_and_seeded() -> None:
    Rs = random_rotations(50, seed=3)
    assert Rs.shape == (50, 3, 3)
    np.testing.assert_allclose(Rs @ np.swapaxes(Rs, 1, 2), np.broadcast_to(np.eye(3), Rs.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(Rs), 1.0, atol=1e-12)
    np.testing.assert_array_equal(Rs, random_rotations(50, seed=3))
    assert not np.allclose(Rs, random_rotations(50, seed=4))
    # Haar measure: the mean of uniformly random rotations is ~0
    assert np.abs(random_rotations(4000, seed=0).mean(axis=0)).max() < 0.05


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_quaternion_round_trip(seed: int) -> None:
    R = random_rotation(seed)
    q = rotation_to_quat_wxyz(R)
    assert q.shape == (4,) and q[0] >= 0
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_wxyz_to_rotation(q), R, atol=1e-10)


def test_quaternion_known_values_and_edge_angles() -> None:
    R = rotation_about_axis([0, 0, 1], np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    expected = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]
    np.testing.assert_allclose(rotation_to_quat_wxyz(R), expected, atol=1e-12)
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]):  # 180° turns: trace = −1 branch
        R = rotation_about_axis(axis, np.pi)
        np.testing.assert_allclose(quat_wxyz_to_rotation(rotation_to_quat_wxyz(R)), R, atol=1e-10)
    np.testing.assert_allclose(rotation_to_quat_wxyz(np.eye(3)), [1, 0, 0, 0])


def test_xyz_tuple() -> None:
    t = xyz_tuple(np.array([1, 2.5, -3], np.float32))
    assert t == (1.0, 2.5, -3.0) and all(type(c) is float for c in t)
    assert xyz_tuple([0, 0, 1]) == (0.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        xyz_tuple([1.0, 2.0])


def test_box_select_camera_uses_the_one_quaternion_convention() -> None:
    """The annotator's camera projection rotates with `quat_wxyz_to_rotation` (R_world_camera, OpenCV axes)."""
    from annotator.selection import project

    R = random_rotation(3)
    q = rotation_to_quat_wxyz(R)
    pos = np.array([0.1, -0.2, 0.3])
    pts_cam = np.array([[0.0, 0.0, 2.0], [0.5, -0.25, 1.0]])  # camera frame: +Z forward
    uv, depth = project(pts_cam @ R.T + pos, position=pos, wxyz=q, fov=np.pi / 2, aspect=2.0)
    np.testing.assert_allclose(depth, [2.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(uv, [[0.5, 0.5], [0.5 + 0.5 * 0.5 / 2.0, 0.5 - 0.5 * 0.25]], atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seeds, seeds)
def test_sim3_compose_inverse_and_matrix(seed_a: int, seed_b: int) -> None:
    a, b = random_sim3(seed_a), random_sim3(seed_b)
    pts = np.random.default_rng(seed_a ^ seed_b).normal(size=(20, 3))
    np.testing.assert_allclose(a.compose(b).apply(pts), a.apply(b.apply(pts)), atol=1e-9)
    np.testing.assert_allclose((a @ a.inverse()).apply(pts), pts, atol=1e-9)
    np.testing.assert_allclose(apply_transform(a.matrix(), pts), a.apply(pts), atol=1e-9)
    np.testing.assert_allclose(compose_transforms(a.matrix(), b.matrix()), (a @ b).matrix(), atol=1e-9)
    np.testing.assert_allclose(invert_transform(a.matrix()) @ a.matrix(), np.eye(4), atol=1e-9)
    back = Sim3.from_matrix(a.matrix())
    np.testing.assert_allclose(back.scale, a.scale, rtol=1e-12)
    np.testing.assert_allclose(back.R, a.R, atol=1e-12)


def test_transform_validation() -> None:
    with pytest.raises(ValueError, match="shape"):
        make_transform(np.eye(2))
    with pytest.raises(ValueError, match="scale"):
        Sim3(0.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        apply_transform(np.eye(4), np.zeros((3, 2)))


def test_project_to_so3_and_angle() -> None:
    R = random_rotation(1)
    noisy = R + 1e-3 * np.random.default_rng(0).normal(size=(3, 3))
    P = project_to_so3(noisy)
    np.testing.assert_allclose(np.linalg.det(P), 1.0, atol=1e-12)
    assert rotation_angle_deg(P, R) < 0.5
    assert np.linalg.det(project_to_so3(R @ _reflection())) > 0
    assert abs(rotation_angle_deg(rotation_about_axis([1, 2, 3], 0.7)) - np.degrees(0.7)) < 1e-9


# ---------------------------------------------------------------------------------------------- procrustes
@settings(max_examples=30, deadline=None)
@given(seeds)
def test_procrustes_recovers_similarity(seed: int) -> None:
    rng = np.random.default_rng(seed)
    g = random_sim3(rng)
    X = rng.normal(size=(30, 3))
    res = procrustes(X, g.apply(X), with_scale=True)
    np.testing.assert_allclose(res.R, g.R, atol=1e-8)
    np.testing.assert_allclose(res.scale, g.scale, rtol=1e-8)
    np.testing.assert_allclose(res.t, g.t, atol=1e-7)
    assert res.rmse < 1e-7


def test_weighted_procrustes_ignores_zero_weight_outliers() -> None:
    rng = np.random.default_rng(0)
    R = random_rotation(2)
    X = rng.normal(size=(40, 3))
    Y = X @ R.T + [1.0, 2.0, 3.0]
    Y[:5] += rng.normal(scale=5.0, size=(5, 3))  # gross outliers
    w = np.ones(40)
    w[:5] = 0.0
    assert rotation_angle_deg(procrustes(X, Y, weights=w).R, R) < 1e-6
    assert rotation_angle_deg(procrustes(X, Y).R, R) > 1.0  # unweighted is pulled away (control)
    with pytest.raises(ValueError, match="weights"):
        procrustes(X, Y, weights=np.zeros(40))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        procrustes(X, Y[:3])


def test_procrustes_proper_vs_orthogonal_on_reflected_data() -> None:
    rng = np.random.default_rng(1)
    X = rng.normal(size=(50, 3)) * [3.0, 2.0, 1.0]
    Y = X @ _reflection().T
    orth = procrustes(X, Y, proper=False)
    assert np.linalg.det(orth.R) < 0 and orth.rmse < 1e-9
    prop = procrustes(X, Y, proper=True)
    assert np.linalg.det(prop.R) > 0 and prop.rmse > 0.1


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_latent_procrustes_recovers_rotation(seed: int) -> None:
    """Spec §1.8.9: if Θ'_R = Θ_R Rᵀ exactly, the solver recovers R (both variants)."""
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    theta_canon = rng.normal(size=(64, 3))
    theta_obs = theta_canon @ R.T
    for proper in (False, True):
        np.testing.assert_allclose(latent_procrustes(theta_obs, theta_canon, proper=proper), R, atol=1e-8)
    batch = latent_procrustes(theta_obs, np.stack([theta_canon, theta_canon @ random_rotation(seed + 1).T]))
    assert batch.shape == (2, 3, 3)
    np.testing.assert_allclose(batch[0], R, atol=1e-8)


def test_latent_procrustes_reflection_and_det_fix() -> None:
    rng = np.random.default_rng(5)
    theta = np.linalg.qr(rng.normal(size=(32, 3)))[0] * [1.0, 2.0, 3.0]  # orthogonal columns: S is diagonal
    M = random_rotation(3) @ _reflection()
    R_raw = latent_procrustes(theta @ M.T, theta, proper=False)
    np.testing.assert_allclose(R_raw, M, atol=1e-8)
    R_fix = latent_procrustes(theta @ M.T, theta, proper=True)
    assert np.linalg.det(R_fix) == pytest.approx(1.0)
    # the det-fixed solution flips the weakest direction (smallest variance: canonical x here)
    np.testing.assert_allclose(R_fix[:, 1:], M[:, 1:], atol=1e-8)
    with pytest.raises(ValueError, match="theta_ref"):
        latent_procrustes(theta, theta[:5])


def test_rotation_from_cross_covariance_is_optimal() -> None:
    rng = np.random.default_rng(7)
    H = rng.normal(size=(3, 3))
    R = rotation_from_cross_covariance(H, proper=True)
    best = np.trace(R.T @ H)
    assert all(np.trace(Q.T @ H) <= best + 1e-9 for Q in random_rotations(500, seed=8))


# ---------------------------------------------------------------------------------------------- ICP
def _asymmetric_cloud(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    body = rng.normal(size=(n, 3)) * [0.5, 0.3, 0.15]
    bump = rng.normal(size=(n // 5, 3)) * 0.05 + [0.4, 0.2, 0.0]
    return np.concatenate([body, bump])


@pytest.mark.parametrize("angle_deg", [5.0, 15.0, 25.0])
def test_icp_converges_on_rotated_cloud(angle_deg: float) -> None:
    X = _asymmetric_cloud(1500, 0)
    R = rotation_about_axis([0.3, 1.0, 0.2], np.radians(angle_deg))
    Y = X @ R.T + [2.0, -1.0, 0.5]
    res = icp_rotation(X, Y, iters=30, proper=True, tol_deg=1e-4)
    assert rotation_angle_deg(res.R, R) < 0.5
    np.testing.assert_allclose(res.aligned.mean(axis=0), Y.mean(axis=0), atol=1e-9)
    assert np.abs(res.aligned - Y).max() < 0.05
    few = icp_rotation(X, Y, iters=3)
    assert few.iterations == 3 and rotation_angle_deg(few.R, R) < angle_deg  # 3 iterations already help


def test_icp_zero_iterations_and_validation() -> None:
    X = _asymmetric_cloud(200, 1)
    res = icp_rotation(X, X, iters=0)
    np.testing.assert_allclose(res.R, np.eye(3))
    assert res.mean_distance == pytest.approx(0.0)
    with pytest.raises(ValueError, match="source"):
        icp_rotation(np.zeros((0, 3)), X)


# ---------------------------------------------------------------------------------------------- OBB
def test_oriented_box_of_rotated_box_is_the_box() -> None:
    rng = np.random.default_rng(0)
    e = np.array([0.3, 0.2, 0.1])
    R = random_rotation(11)
    c_true = np.array([1.0, 2.0, 0.5])
    # points filling the box, with all 8 corners present (exact extremes)
    local = np.concatenate([rng.uniform(-1, 1, size=(500, 3)), BOX_CORNER_SIGNS]) * e
    world = c_true + local @ R.T
    theta_c = c_true + np.array([0.05, -0.02, 0.01])  # object centre != box centre: o must be used
    box = oriented_box(world, theta_c, R)
    np.testing.assert_allclose(box.center, c_true, atol=1e-12)
    np.testing.assert_allclose(box.half_extents, e, atol=1e-12)
    np.testing.assert_allclose(box.axes, R)
    np.testing.assert_allclose(box.corners, c_true + (BOX_CORNER_SIGNS * e) @ R.T, atol=1e-12)
    assert box.volume == pytest.approx(8 * np.prod(e))
    assert box.contains(world).all()
    outside = c_true + (np.array([[1.05, 0, 0], [0, -1.05, 0], [0, 0, 1.1]]) * e) @ R.T
    assert not box.contains(outside).any()
    # every edge joins corners that differ in exactly one sign and has the length of that side
    for i, j in box.edges:
        diff = BOX_CORNER_SIGNS[i] != BOX_CORNER_SIGNS[j]
        assert diff.sum() == 1
        assert np.linalg.norm(box.corners[i] - box.corners[j]) == pytest.approx(2 * e[diff][0])
    assert len({tuple(sorted(p)) for p in BOX_EDGES.tolist()}) == 12
    assert box.line_segments().shape == (12, 2, 3)


def test_oriented_box_validation() -> None:
    with pytest.raises(ValueError, match="non-empty"):
        oriented_box(np.zeros((0, 3)), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="orthonormal"):
        oriented_box(np.ones((4, 3)), np.zeros(3), 2 * np.eye(3))
    with pytest.raises(ValueError, match="center"):
        oriented_box(np.ones((4, 3)), np.zeros(2), np.eye(3))
