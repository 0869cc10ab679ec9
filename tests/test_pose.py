"""Tests of the pose codebook (efem_viz.prior.codebook) and pose estimation (efem_viz.prior.pose).

They use a small randomly initialised ShapePrior: exact SO(3) equivariance of the encoder is all the pose
search needs to recover the rotation of a codebook entry's own (rotated, scaled, shifted) input.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from efem_viz.data.procedural import make_mug, sample_mug_params
from efem_viz.geometry.obb import oriented_box
from efem_viz.geometry.transforms import random_rotation, rotation_angle_deg
from efem_viz.prior.codebook import Codebook, project_so3_code
from efem_viz.prior.codebook_build import build_codebook
from efem_viz.prior.model import Latent, PriorConfig, ShapePrior
from efem_viz.prior.pose import estimate_pose

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def prior() -> ShapePrior:
    cfg = PriorConfig(widths=(8, 8, 16, 16, 32), down_blocks=(2, 4), down_factors=(2, 2), latent_dim=32,
                      center_hidden=16, decoder_hidden=32, decoder_blocks=1, n_pcl=256, k=8)
    torch.manual_seed(0)
    return ShapePrior(cfg, name="test").eval()


@pytest.fixture(scope="module")
def codebook(prior: ShapePrior) -> Codebook:
    seeds = [s for s in range(60) if sample_mug_params(s).handle != "none"][:6]  # handled: pose is unique
    return build_codebook(prior, [make_mug(s) for s in seeds], n_store=800, noise=0.01, seed=0)


def _encode(prior: ShapePrior, pts: np.ndarray) -> Latent:
    with torch.no_grad():
        return prior.encode(torch.as_tensor(pts, dtype=torch.float32)[None])


# ---------------------------------------------------------------------------------------------- codebook
def test_codebook_contents(codebook: Codebook, prior: ShapePrior) -> None:
    K, C = len(codebook), prior.config.latent_dim
    assert codebook.z_so3.shape == (K, C, 3) and codebook.z_inv.shape == (K, C)
    assert codebook.pcl.dtype == np.float16 and codebook.pcl.shape == (K, 800, 3)
    assert codebook.input_idx.shape == (K, prior.config.n_pcl)
    # stored clouds are in the normalised canonical frame: longest bbox side ≈ 1 (+ noise)
    ext = codebook.pcl.astype(np.float64).max(axis=1) - codebook.pcl.astype(np.float64).min(axis=1)
    np.testing.assert_allclose(ext.max(axis=1), 1.0, atol=0.08)
    # the stored latent is the encoding of the stored input
    lat = _encode(prior, codebook.encoder_input(2))
    np.testing.assert_allclose(lat.R.numpy()[0], codebook.z_so3[2], atol=1e-4)
    np.testing.assert_allclose(lat.scale.numpy(), codebook.scale[2:3], rtol=1e-4)
    assert codebook.mean_scale == pytest.approx(float(np.mean(codebook.scale)))
    # tied to the weights it was built from
    assert codebook.matches(prior)
    other = ShapePrior(prior.config)
    assert not codebook.matches(other)


def test_projection_is_rotation_invariant() -> None:
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(32, 3)) * [0.5, 1.0, 2.0]
    proj, E, ev = project_so3_code(theta)
    assert np.all(np.diff(ev) >= 0)
    np.testing.assert_allclose(theta @ E, proj, atol=1e-12)
    for seed in range(5):
        proj_r, _, ev_r = project_so3_code(theta @ random_rotation(seed).T)
        np.testing.assert_allclose(proj_r, proj, atol=1e-9)
        np.testing.assert_allclose(ev_r, ev, rtol=1e-9)


def test_codebook_save_load_round_trip(codebook: Codebook, tmp_path: Path) -> None:
    path = codebook.save(tmp_path / "cb.npz")
    loaded = Codebook.load(path)
    for f in dataclasses.fields(Codebook):
        if f.name.startswith("_"):
            continue
        a, b = getattr(codebook, f.name), getattr(loaded, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
            assert a.dtype == b.dtype, f.name
        else:
            assert a == b, f.name
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write leaves no temporary file
    entry = (codebook.z_so3[1], codebook.z_inv[1], codebook.center[1], codebook.scale[1])
    lat = Latent(*(torch.as_tensor(np.asarray(x)[None]) for x in entry))
    np.testing.assert_array_equal(loaded.retrieve(lat), codebook.retrieve(lat))


def test_codebook_load_errors(codebook: Codebook, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        Codebook.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(ValueError, match="schema_version"):
        Codebook.load(bad)
    old = tmp_path / "old.npz"
    np.savez(old, schema_version=np.array(999))
    with pytest.raises(ValueError, match="999"):
        Codebook.load(old)
    with pytest.raises(ValueError, match="z_inv"):
        dataclasses.replace(codebook, z_inv=codebook.z_inv[:, :3])


def test_retrieve_finds_entry_under_rotation(codebook: Codebook, prior: ShapePrior) -> None:
    R = random_rotation(4)
    lat = _encode(prior, 0.2 * codebook.encoder_input(3) @ R.T + [1.0, 2.0, 3.0])
    idx = codebook.retrieve(lat, k_inv=2, k_so3=2, k_joint=2)
    assert idx.shape == (6,)
    assert idx[0] == 3 and idx[2] == 3 and idx[4] == 3  # nearest in every feature space
    assert codebook.retrieve(lat, k_inv=100, k_so3=0, k_joint=0).shape == (len(codebook),)  # k clipped


# ---------------------------------------------------------------------------------------------- pose
@pytest.mark.parametrize("entry", [0, 4])
def test_pose_recovers_rotation_of_own_input(codebook: Codebook, prior: ShapePrior, entry: int) -> None:
    rng = np.random.default_rng(entry)
    R_true = random_rotation(rng)
    s, t = 0.12, rng.normal(size=3)
    lat = _encode(prior, s * codebook.encoder_input(entry) @ R_true.T + t)
    samples = s * codebook.cloud(entry) @ R_true.T + t - lat.center.numpy()[0]
    est = estimate_pose(prior, lat, samples, codebook=codebook)
    assert est.selected == entry
    assert entry in est.neighbour_ids.tolist()
    assert len(est.neighbour_ids) == len(est.scores) == min(10, len(codebook)) + 3 + 3
    assert np.linalg.det(est.R) == pytest.approx(1.0)
    assert rotation_angle_deg(est.R, R_true) < 2.0
    assert est.score_db_sim > 0.95
    assert est.scale_sel == pytest.approx(float(codebook.scale[entry]))
    # the aligned neighbour cloud lies on the samples
    assert np.abs(est.aligned_cloud - samples).max() < 0.02 * s
    # the canonical up column is the rotated +Z
    np.testing.assert_allclose(est.up, R_true[:, 2], atol=0.03)
    # an OBB with this pose has the extents of the canonical cloud (times s)
    box = oriented_box(samples + lat.center.numpy()[0], lat.center.numpy()[0], est.R)
    cloud = codebook.cloud(entry)
    np.testing.assert_allclose(box.half_extents, s * (cloud.max(0) - cloud.min(0)) / 2, rtol=0.05, atol=1e-3)


def test_pose_reflection_is_resolved_to_a_rotation(codebook: Codebook, prior: ShapePrior) -> None:
    """A mug is mirror symmetric (y → −y); fake a latent that the raw search maps with a reflection."""
    rng = np.random.default_rng(0)
    theta = np.linalg.qr(rng.normal(size=(prior.config.latent_dim, 3)))[0] * [2.0, 0.5, 1.0]  # y weakest
    K = len(codebook)
    cb = dataclasses.replace(codebook, z_so3=np.repeat(theta[None], K, 0).astype(np.float32),
                             proj=np.repeat(project_so3_code(theta)[0][None], K, 0).astype(np.float32))
    F = np.diag([1.0, -1.0, 1.0])
    R_true = random_rotation(7)
    lat = Latent(R=torch.as_tensor((theta @ (R_true @ F).T)[None]), inv=torch.as_tensor(cb.z_inv[1][None]),
                 center=torch.zeros(1, 3), scale=torch.as_tensor(cb.scale[1:2]))
    cloud = cb.cloud(1) - cb.center[1]
    samples = (cloud - cloud.mean(0)) @ R_true.T
    est = estimate_pose(prior, lat, samples, codebook=cb)
    assert np.linalg.det(est.R_raw) < 0 and est.reflected
    assert np.linalg.det(est.R) == pytest.approx(1.0)
    assert rotation_angle_deg(est.R, R_true) < 3.0
    proper = estimate_pose(prior, lat, samples, codebook=cb, proper_search=True)
    assert not proper.reflected and np.linalg.det(proper.R_raw) > 0


def test_pose_edge_cases(codebook: Codebook, prior: ShapePrior) -> None:
    lat = _encode(prior, codebook.encoder_input(0))
    est = estimate_pose(prior, lat, np.zeros((100, 3)), codebook=codebook)
    np.testing.assert_array_equal(est.R, np.eye(3))
    assert est.score_db_sim == 0.0 and est.selected == -1
    assert est.scale_sel == pytest.approx(codebook.mean_scale)
    with pytest.raises(ValueError, match="codebook"):
        estimate_pose(prior, lat, np.ones((10, 3)))  # the prior has no codebook attached
    with pytest.raises(ValueError, match=r"\(S, 3\)"):
        estimate_pose(prior, lat, np.ones((10, 2)), codebook=codebook)
    with pytest.raises(ValueError, match="normals"):
        estimate_pose(prior, lat, np.ones((10, 3)), np.ones((9, 3)), codebook=codebook)


def test_load_prior_refuses_a_codebook_of_other_weights(prior: ShapePrior, codebook: Codebook,
                                                         tmp_path) -> None:  # noqa: ANN001
    """A codebook built from other weights is not attached by load_prior (its poses would be meaningless)."""
    from efem_viz.prior.model import load_prior, save_prior

    save_prior(prior, tmp_path / "p.pt")
    codebook.save(tmp_path / "p_codebook.npz")
    assert load_prior(tmp_path / "p.pt").codebook is not None
    save_prior(ShapePrior(prior.config), tmp_path / "p.pt")  # other (random) weights, same file name
    assert load_prior(tmp_path / "p.pt").codebook is None


def test_pose_search_on_sample_subsets_finds_the_same_pose(codebook: Codebook, prior: ShapePrior) -> None:
    """`search_points` aligns and scores subsets: the same entry and rotation as the full search, the whole
    selected cloud returned, and a bad count refused."""
    rng = np.random.default_rng(3)
    R_true = random_rotation(rng)
    s, t = 0.1, rng.normal(size=3)
    lat = _encode(prior, s * codebook.encoder_input(4) @ R_true.T + t)
    samples = s * codebook.cloud(4) @ R_true.T + t - lat.center.numpy()[0]
    full = estimate_pose(prior, lat, samples, codebook=codebook)
    sub = estimate_pose(prior, lat, samples, codebook=codebook, search_points=300)
    assert sub.selected == full.selected == 4
    assert rotation_angle_deg(sub.R, full.R) < 2.0
    assert abs(sub.score_db_sim - full.score_db_sim) < 0.05
    assert sub.aligned_cloud.shape == full.aligned_cloud.shape
    assert np.abs(sub.aligned_cloud - samples).max() < 0.03 * s
    with pytest.raises(ValueError, match="search_points"):
        estimate_pose(prior, lat, samples, codebook=codebook, search_points=0)


def test_a_family_codebook_classes_its_entries_and_names_an_instance_by_majority(prior: ShapePrior,
                                                                                  tmp_path: Path) -> None:
    """(category, seed) pairs give each entry its category's class id; the classes survive a save and load;
    `category_of` takes the class with the largest total weight among the retrieved rows (ties: the first
    retrieved), ignores rows out of range, and falls back to the prior's name without classes or rows."""
    pairs = [("mug", 0), ("bowl", 0), ("bottle", 0), ("can", 0), ("mug", 1), ("bowl", 1)]
    cb = build_codebook(prior, pairs, n_store=200, noise=0.01, seed=0, classes=("mug", "bowl", "bottle", "can"))
    np.testing.assert_array_equal(cb.class_id, [0, 1, 2, 3, 0, 1])
    np.testing.assert_array_equal(cb.ids, [0, 0, 0, 0, 1, 1])
    loaded = Codebook.load(cb.save(tmp_path / "kitchen_codebook.npz"))
    assert loaded.classes == ["mug", "bowl", "bottle", "can"]
    np.testing.assert_array_equal(loaded.class_id, cb.class_id)
    assert cb.category_of([1, 5, 0], "kitchen") == "bowl"          # two bowls, one mug
    assert cb.category_of([2, 0, 4, 2], "kitchen") == "bottle"     # tie 2:2, the bottle retrieved first
    assert cb.category_of([3, 99, -1], "kitchen") == "can"         # out of range ignored
    assert cb.category_of([], "kitchen") == "kitchen"
    assert cb.category_of([99], "kitchen") == "kitchen"
    # weighted by how well each entry aligned: one well-aligned can outvotes two poorly aligned bowls
    assert cb.category_of([1, 5, 3], "kitchen", weights=[0.2, 0.3, 0.9]) == "can"
    assert cb.category_of([1, 5, 3], "kitchen", weights=[0.5, 0.5, 0.9]) == "bowl"
    with pytest.raises(ValueError, match="weights"):
        cb.category_of([1, 5], "kitchen", weights=[1.0])
    inferred = build_codebook(prior, pairs[:3], n_store=50, noise=0.01, seed=0)
    assert inferred.classes == ["mug", "bowl", "bottle"]
    single = build_codebook(prior, [0, 1], n_store=50, noise=0.01, seed=0)  # seeds of one category: no classes
    assert single.classes == [] and single.category_of([0, 1], "mug") == "mug"
    with pytest.raises(ValueError, match="not among the classes"):
        build_codebook(prior, [("chair", 0)], n_store=50, classes=("mug",))
