"""Tests of efem_viz.prior.meshing: analytic SDFs, coarse-to-fine vs dense, decimation, and `extract_mesh`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from efem_viz.prior.meshing import MeshStats, extract_mesh, mesh_from_sdf_fn, sdf_grid
from efem_viz.prior.model import Latent, PriorConfig, ShapePrior

torch.set_num_threads(1)


def sphere_sdf(radius: float, center: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    c = np.asarray(center, dtype=np.float64)
    return lambda p: np.linalg.norm(p - c, axis=1) - radius


def box_sdf(half: tuple[float, float, float]):
    h = np.asarray(half, dtype=np.float64)

    def fn(p: np.ndarray) -> np.ndarray:
        q = np.abs(p) - h
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)

    return fn


def thin_plate_sdf(thickness: float):
    """A horizontal slab of the given thickness, clipped to a disc: thinner than a coarse cell."""

    def fn(p: np.ndarray) -> np.ndarray:
        slab = np.abs(p[:, 2] - 0.113) - thickness / 2  # between the z-planes of an 8³ grid
        disc = np.linalg.norm(p[:, :2], axis=1) - 0.5
        return np.maximum(slab, disc)

    return fn


def test_sphere_radius_volume_watertight() -> None:
    r = 0.4
    mesh = mesh_from_sdf_fn(sphere_sdf(r, (0.05, -0.03, 0.02)), resolution=64, coarse=16, max_faces=None)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward winding
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * r**3, rel=0.01)
    radii = np.linalg.norm(mesh.vertices - [0.05, -0.03, 0.02], axis=1)
    assert np.abs(radii - r).max() < 0.01
    # outward normals: they point away from the centre
    c = mesh.triangles_center - [0.05, -0.03, 0.02]
    assert (np.sum(mesh.face_normals * c, axis=1) > 0).all()


def test_box_volume() -> None:
    half = (0.3, 0.2, 0.1)
    mesh = mesh_from_sdf_fn(box_sdf(half), resolution=64, coarse=32, max_faces=None)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(8 * np.prod(half), rel=0.03)
    np.testing.assert_allclose(mesh.bounds[1], half, atol=0.02)


def test_coarse_to_fine_equals_dense() -> None:
    fn = sphere_sdf(0.37)
    dense = sdf_grid(fn, resolution=64, coarse=None)
    stats = MeshStats()
    grid = sdf_grid(fn, resolution=64, coarse=16, stats=stats)
    assert stats.queries < 0.25 * stats.dense_queries
    assert stats.levels == 2 and len(stats.active_cells) == 2
    # identical near the surface (exactly evaluated), same sign everywhere
    near = np.abs(dense) < 0.05
    np.testing.assert_allclose(grid[near], dense[near], atol=1e-6)
    assert (np.sign(grid) == np.sign(dense)).all()
    m_dense = mesh_from_sdf_fn(fn, resolution=64, coarse=None, max_faces=None)
    m_fine = mesh_from_sdf_fn(fn, resolution=64, coarse=16, max_faces=None)
    np.testing.assert_allclose(m_fine.vertices, m_dense.vertices, atol=1e-6)


def test_lipschitz_refinement_keeps_thin_parts() -> None:
    """A slab thinner than a coarse cell is missed by the pure sign rule but kept by the |sdf| rule."""
    fn = thin_plate_sdf(0.03)
    dense = mesh_from_sdf_fn(fn, resolution=64, coarse=None, max_faces=None)
    assert dense.is_watertight and dense.area > 0.5
    fine = mesh_from_sdf_fn(fn, resolution=64, coarse=8, lipschitz=1.0, max_faces=None)
    assert fine.area == pytest.approx(dense.area, rel=1e-6)
    sign_only = mesh_from_sdf_fn(fn, resolution=64, coarse=8, lipschitz=0.0, max_faces=None)
    assert len(sign_only.faces) == 0 or sign_only.area < 0.5 * dense.area  # control: the rule matters


def test_decimation_and_padding() -> None:
    mesh = mesh_from_sdf_fn(sphere_sdf(0.5), resolution=64, coarse=32, max_faces=800)
    assert 0 < len(mesh.faces) <= 800
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.5**3, rel=0.03)
    # a shape that sticks out of the cube is closed by the padding
    clipped = mesh_from_sdf_fn(sphere_sdf(0.7), half_extent=0.5, resolution=32, coarse=8, max_faces=None)
    assert clipped.is_watertight
    np.testing.assert_allclose(clipped.bounds, [[-0.5] * 3, [0.5] * 3], atol=0.02)


def test_stats_are_per_call_and_thread_safe() -> None:
    from concurrent.futures import ThreadPoolExecutor

    def run(radius: float) -> tuple[int, MeshStats]:
        st = MeshStats()
        mesh = mesh_from_sdf_fn(sphere_sdf(radius), resolution=32, coarse=8, max_faces=None, stats=st)
        return len(mesh.faces), st

    radii = [0.2, 0.45, 0.3, 0.6]
    with ThreadPoolExecutor(2) as pool:
        out = list(pool.map(run, radii))
    assert [st.faces for _, st in out] == [n for n, _ in out]
    assert len({n for n, _ in out}) == len(radii)  # different spheres: each call kept its own counters
    assert all(st.dense_queries == 33**3 and st.t_mc > 0 for _, st in out)


def test_empty_and_invalid() -> None:
    st = MeshStats(faces=7)
    empty = mesh_from_sdf_fn(lambda p: np.ones(len(p)), resolution=16, coarse=8, stats=st)
    assert len(empty.faces) == 0 and len(empty.vertices) == 0
    assert st.faces == 0 and st.queries > 0 and st.t_mc == 0.0
    with pytest.raises(ValueError, match="power of two"):
        sdf_grid(sphere_sdf(0.3), resolution=48, coarse=32)
    with pytest.raises(ValueError, match="non-finite"):
        mesh_from_sdf_fn(lambda p: np.full(len(p), np.nan), resolution=8, coarse=None)
    with pytest.raises(ValueError, match="returned"):
        mesh_from_sdf_fn(lambda p: np.zeros(3), resolution=8, coarse=None)


# ------------------------------------------------------------------------------------------ extract_mesh
def _sphere_prior(radius: float) -> ShapePrior:
    """A small ShapePrior whose decoder computes exactly `‖q‖ − radius` (q = (x − Θ_c)/Θ_s)."""
    cfg = PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                      center_hidden=8, n_pcl=64, k=8, decoder_hidden=16, decoder_blocks=1)
    torch.manual_seed(0)
    prior = ShapePrior(cfg).eval()
    dec = prior.decoder
    with torch.no_grad():
        for p in dec.parameters():
            p.zero_()
        dec.fc_in.weight[0, cfg.latent_dim] = 1.0  # the ‖q‖ input → hidden unit 0
        dec.fc_out.weight[0, 0] = 1.0
        dec.fc_out.bias[0] = -radius
    return prior


def test_extract_mesh_world_mapping() -> None:
    prior = _sphere_prior(0.3)
    C = prior.config.latent_dim
    g = torch.Generator().manual_seed(1)
    lat = Latent(R=torch.randn(1, C, 3, generator=g), inv=torch.randn(1, C, generator=g),
                 center=torch.tensor([[0.5, -0.2, 1.0]]), scale=torch.tensor([0.25]))
    ref = extract_mesh(prior, lat, resolution=32, coarse=8, world=False, max_faces=None, reference_scale=1.5)
    assert ref.is_watertight
    np.testing.assert_allclose(np.linalg.norm(ref.vertices, axis=1), 0.3 * 1.5, atol=0.01)
    world = extract_mesh(prior, lat, resolution=32, coarse=8, world=True, max_faces=None, reference_scale=1.5)
    np.testing.assert_allclose(world.vertices, ref.vertices * (0.25 / 1.5) + [0.5, -0.2, 1.0], atol=1e-9)
    # unbatched latent and the codebook-free default reference scale (1.0)
    unb = Latent(lat.R[0], lat.inv[0], lat.center[0], lat.scale[0])
    stats = MeshStats()
    m = extract_mesh(prior, unb, resolution=32, coarse=8, world=True, max_faces=None, stats=stats)
    np.testing.assert_allclose(np.linalg.norm(m.vertices - [0.5, -0.2, 1.0], axis=1), 0.3 * 0.25, atol=0.005)
    assert 0 < stats.queries < stats.dense_queries == 33**3
    assert stats.faces == len(m.faces) and stats.t_eval > 0
    with pytest.raises(ValueError, match="single latent"):
        extract_mesh(prior, Latent.cat([lat, lat]))
