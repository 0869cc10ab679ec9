"""SIM(3) equivariance of the shape prior, layer by layer and end to end (docs/design/efem-method.md §1.8), in
float64."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from efem_viz.geometry.fps import farthest_point_sample
from efem_viz.geometry.knn import knn_indices
from efem_viz.prior.model import Latent, PriorConfig, ShapePrior
from efem_viz.prior.train import calibrate_scale_factor
from efem_viz.prior.vn_layers import (
    VNLinear,
    VNLinearLeakyReLU,
    VNLeakyReLU,
    VNResnetBlock,
    channel_normalize,
)

DT = torch.float64
SMALL = dict(widths=(8, 8, 16, 16, 32), down_blocks=(2, 4), down_factors=(2, 4), k=8, n_pcl=128,
             latent_dim=16, center_hidden=8, decoder_hidden=32, decoder_blocks=2)


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    """Uniform proper rotation (3, 3) float64."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DT))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_similarity(seed: int) -> tuple[float, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    s = float(0.3 + 2.7 * torch.rand(1, generator=gen, dtype=DT))
    return s, random_rotation(gen), torch.randn(3, generator=gen, dtype=DT) * 2.0


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).detach())


def vn_rotate(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Rotate channels-last VN features (..., 3, C) by R."""
    return torch.einsum("ij,...jc->...ic", R, v)


def mug_like(n: int, seed: int) -> torch.Tensor:
    """A handled cup-like cloud (n, 3) float64, z up, about unit size (asymmetric: poses are well defined)."""
    gen = torch.Generator().manual_seed(seed)
    n_body = n * 3 // 4
    th = torch.rand(n_body, generator=gen, dtype=DT) * 6.283
    z = torch.rand(n_body, generator=gen, dtype=DT) - 0.5
    body = torch.stack([0.35 * th.cos(), 0.35 * th.sin(), z], -1)
    ph = torch.rand(n - n_body, generator=gen, dtype=DT) * 3.1416 - 1.5708
    handle = torch.stack([0.35 + 0.18 * ph.cos(), 0.02 * torch.randn(n - n_body, generator=gen, dtype=DT),
                          0.22 * ph.sin()], -1)
    return torch.cat([body, handle]) + 0.005 * torch.randn(n, 3, generator=gen, dtype=DT)


@pytest.fixture(scope="module")
def prior() -> ShapePrior:
    torch.manual_seed(0)
    m = ShapePrior(PriorConfig(**SMALL)).double().eval().requires_grad_(False)
    calibrate_scale_factor(m, torch.stack([mug_like(128, i) for i in range(4)]))
    return m


@pytest.fixture(scope="module")
def prior_att() -> ShapePrior:
    torch.manual_seed(1)
    cfg = PriorConfig(**{**SMALL, "attention_blocks": (2, 3, 4), "att_head_dim": 8,
                         "center_times_sigma": True, "decoder_proj_gain": 4.0, "decoder_inv_gain": 16.0})
    m = ShapePrior(cfg).double().eval().requires_grad_(False)
    calibrate_scale_factor(m, torch.stack([mug_like(128, i) for i in range(4)]))
    return m


# ----------------------------------------------------------------------------------------------------- layers
@pytest.mark.parametrize("seed", range(3))
def test_vn_layers_equivariant(seed: int) -> None:
    torch.manual_seed(seed)
    s, R, _ = random_similarity(seed)
    v = torch.randn(5, 7, 3, 6, dtype=DT)
    layers = [VNLinear(6, 4), VNLeakyReLU(6), VNLeakyReLU(6, shared=True), VNLinearLeakyReLU(6, 5),
              VNLinearLeakyReLU(6, 5, shared=True), VNResnetBlock(6, 4, 3), VNResnetBlock(6, 4, 1)]
    for layer in layers:
        layer = layer.double()
        out = layer(v)
        assert rel_err(layer(s * vn_rotate(v, R)), s * vn_rotate(out, R)) < 1e-12, type(layer).__name__


def test_leaky_relu_really_is_nonlinear() -> None:
    """The activation changes features (else the equivariance test above would be trivial for it)."""
    torch.manual_seed(0)
    act = VNLeakyReLU(6).double()
    v = torch.randn(100, 3, 6, dtype=DT)
    out = act(v)
    assert (out - v).abs().max() > 1e-2
    # equivariant to rotations only: an anisotropic linear map of the 3-axis does not commute with it
    A = torch.diag(torch.tensor([2.0, 1.0, 0.5], dtype=DT))
    assert rel_err(act(vn_rotate(v, A)), vn_rotate(out, A)) > 1e-2


def test_channel_normalize() -> None:
    s, R, _ = random_similarity(5)
    v = torch.randn(4, 3, 9, dtype=DT)
    n = channel_normalize(v)
    assert rel_err(channel_normalize(s * vn_rotate(v, R)), vn_rotate(n, R)) < 1e-12
    assert torch.allclose(n.flatten(-2).norm(dim=-1), torch.ones(4, dtype=DT))
    assert torch.equal(channel_normalize(torch.zeros(2, 3, 4, dtype=DT)), torch.zeros(2, 3, 4, dtype=DT))


def test_knn_and_fps_indices_invariant() -> None:
    s, R, t = random_similarity(7)
    gen = torch.Generator().manual_seed(3)
    feat = torch.randn(2, 64, 3, 5, generator=gen, dtype=DT)
    idx = knn_indices(feat.flatten(2), feat.flatten(2), 8)
    idx_g = knn_indices((s * vn_rotate(feat, R)).flatten(2), (s * vn_rotate(feat, R)).flatten(2), 8)
    assert torch.equal(idx, idx_g)
    assert torch.equal(idx[..., 0], torch.arange(64).expand(2, 64))  # each point is its own nearest neighbour
    pts = torch.randn(2, 100, 3, generator=gen, dtype=DT)
    f = farthest_point_sample(pts, 25)
    assert torch.equal(f, farthest_point_sample(s * pts @ R.T + t, 25))
    assert torch.equal(f[:, 0], torch.zeros(2, dtype=torch.long))
    assert all(len(set(row.tolist())) == 25 for row in f)


def test_fps_matches_naive_loop() -> None:
    gen = torch.Generator().manual_seed(11)
    pts = torch.randn(1, 50, 3, generator=gen, dtype=DT)
    chosen = [0]
    for _ in range(9):
        d = torch.cdist(pts[0], pts[0][chosen]).min(dim=1).values
        chosen.append(int(d.argmax()))
    assert farthest_point_sample(pts, 10)[0].tolist() == chosen


def test_knn_matches_cdist() -> None:
    gen = torch.Generator().manual_seed(12)
    q, r = torch.randn(2, 30, 7, generator=gen, dtype=DT), torch.randn(2, 40, 7, generator=gen, dtype=DT)
    ref = torch.cdist(q, r).topk(5, dim=-1, largest=False).indices
    assert torch.equal(knn_indices(q, r, 5), ref)


def test_knn_keeps_float32_distances_under_bf16_autocast() -> None:
    """compute.matmul_dtype="bfloat16" runs the encoder under autocast; its k-NN graph must not change: the
    distance matrix stays float32 (in bf16 many of these neighbours would swap)."""
    gen = torch.Generator().manual_seed(13)
    q = torch.randn(3, 64, 48, generator=gen)  # encoder-like: 16 VN channels x 3
    r = q + 1e-3 * torch.randn(3, 64, 48, generator=gen)
    ref = torch.cdist(q.double(), r.double()).topk(8, dim=-1, largest=False).indices
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(knn_indices(q, r, 8), ref)
        assert torch.equal(knn_indices(q.bfloat16(), r.bfloat16(), 8),
                           knn_indices(q.bfloat16().float(), r.bfloat16().float(), 8))


# ---------------------------------------------------------------------------------------------------- encoder
def _check_encoder(model: ShapePrior, seed: int) -> None:
    s, R, t = random_similarity(seed)
    P = torch.stack([mug_like(128, 10 + seed), mug_like(128, 20 + seed)])
    lat = model.encode(P)
    lat_g = model.encode(s * P @ R.T + t)
    assert rel_err(lat_g.R, lat.R @ R.T) < 1e-9
    assert rel_err(lat_g.inv, lat.inv) < 1e-9
    assert rel_err(lat_g.scale, s * lat.scale) < 1e-9
    assert rel_err(lat_g.center, s * lat.center @ R.T + t) < 1e-9
    # outputs are not degenerate (so the checks above mean something)
    assert lat.inv.abs().max() > 1e-3 and lat.R.abs().max() > 1e-3
    assert float(lat.scale.min()) > 0


@pytest.mark.parametrize("seed", range(3))
def test_encoder_sim3_equivariant(prior: ShapePrior, seed: int) -> None:
    _check_encoder(prior, seed)


def test_encoder_with_attention_equivariant(prior_att: ShapePrior) -> None:
    """VN attention (softmax weights from ChNorm'd features) and a σ-scaled centre head stay equivariant."""
    _check_encoder(prior_att, 4)


def test_attention_changes_aggregation(prior: ShapePrior, prior_att: ShapePrior) -> None:
    assert {k for k in prior_att.state_dict() if k.startswith("encoder.Q_list.")}
    assert not {k for k in prior.state_dict() if k.startswith("encoder.Q_list.")}


def test_encoder_rejects_bad_shapes(prior: ShapePrior) -> None:
    with pytest.raises(ValueError, match="points must be"):
        prior.encode(torch.zeros(2, 10, 2, dtype=DT))


# ---------------------------------------------------------------------------------------------------- decoder
@pytest.mark.parametrize("seed", range(3))
def test_decoder_invariant_and_normals_rotate(prior: ShapePrior, seed: int) -> None:
    s, R, t = random_similarity(100 + seed)
    P = mug_like(128, seed)[None]
    lat = prior.encode(P)
    lat_g = prior.encode(s * P @ R.T + t)
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 300, 3, generator=gen, dtype=DT) - 0.5
    xg = s * x @ R.T + t
    f = prior.sdf(x, lat)
    assert f.std() > 1e-4
    assert rel_err(prior.sdf(xg, lat_g), f) < 1e-9
    # the decoder alone is invariant for a directly transformed latent as well
    lat_t = Latent(lat.R @ R.T, lat.inv, s * lat.center @ R.T + t, s * lat.scale)
    assert rel_err(prior.sdf(xg, lat_t), f) < 1e-12
    with torch.no_grad():
        f1, n1 = prior.sdf_and_normals(x, lat)
        f2, n2 = prior.sdf_and_normals(xg, lat_g)
    assert rel_err(f2, f1) < 1e-9
    assert rel_err(n2, n1 @ R.T) < 1e-7
    assert torch.allclose(n1.norm(dim=-1), torch.ones(300, dtype=DT))


def test_decoder_gains_are_a_reparameterisation(prior_att: ShapePrior) -> None:
    """φ gains == the same decoder with gain 1 and scaled fc_in columns; and invariance holds with gains."""
    plain = ShapePrior(PriorConfig(**{**dataclasses.asdict(prior_att.config), "decoder_proj_gain": 1.0,
                                      "decoder_inv_gain": 1.0})).double()
    plain.load_state_dict(prior_att.state_dict())
    L = prior_att.config.latent_dim
    with torch.no_grad():
        plain.decoder.fc_in.weight[:, :L] *= 4.0
        plain.decoder.fc_in.weight[:, -L:] *= 16.0
    lat = prior_att.encode(mug_like(128, 5)[None])
    x = torch.rand(1, 200, 3, generator=torch.Generator().manual_seed(1), dtype=DT) - 0.5
    assert rel_err(plain.sdf(x, lat), prior_att.sdf(x, lat)) < 1e-12
    s, R, t = random_similarity(42)
    lat_t = Latent(lat.R @ R.T, lat.inv, s * lat.center @ R.T + t, s * lat.scale)
    assert rel_err(prior_att.sdf(s * x @ R.T + t, lat_t), prior_att.sdf(x, lat)) < 1e-12


def test_normals_match_finite_differences(prior: ShapePrior) -> None:
    lat = prior.encode(mug_like(128, 3)[None])
    gen = torch.Generator().manual_seed(9)
    x = torch.rand(50, 3, generator=gen, dtype=DT) - 0.5
    _, n = prior.sdf_and_normals(x, lat)
    h = 1e-6
    grad = torch.stack([(prior.sdf(x + h * e, lat) - prior.sdf(x - h * e, lat)) / (2 * h)
                        for e in torch.eye(3, dtype=DT)], -1).detach()
    assert rel_err(n, grad / grad.norm(dim=-1, keepdim=True)) < 1e-5


def test_ragged_index_matches_batched(prior: ShapePrior) -> None:
    P = torch.stack([mug_like(128, i) for i in range(3)])
    lat = prior.encode(P)
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(3, 40, 3, generator=gen, dtype=DT) - 0.5
    batched = prior.sdf(x, lat)
    index = torch.arange(3).repeat_interleave(40)
    perm = torch.randperm(120, generator=gen)
    ragged = prior.sdf(x.reshape(-1, 3)[perm], lat, index[perm], chunk=17)
    assert rel_err(ragged, batched.reshape(-1)[perm]) < 1e-12
    single = prior.sdf(x[1], lat[1])
    assert rel_err(single, batched[1]) < 1e-12
    _, nr = prior.sdf_and_normals(x.reshape(-1, 3)[perm], lat, index[perm], chunk=50)
    _, nb = prior.sdf_and_normals(x, lat)
    assert rel_err(nr, nb.reshape(-1, 3)[perm]) < 1e-10
    with pytest.raises(ValueError, match="index"):
        prior.sdf(x[0], lat)
    with pytest.raises(ValueError, match="index values"):
        prior.sdf(x[0], lat, torch.full((40,), 3))


def test_latent_indexing(prior: ShapePrior) -> None:
    lat = prior.encode(torch.stack([mug_like(128, i) for i in range(3)]))
    assert len(lat) == 3 and lat[1].R.shape == (1, 16, 3) and lat[-1].scale.shape == (1,)
    assert torch.equal(lat[torch.tensor([2, 0])].center, lat.center[[2, 0]])
    assert torch.equal(Latent.cat([lat[0], lat[1:]]).inv, lat.inv)
    assert lat.numpy().R.shape == (3, 16, 3)
    with pytest.raises(IndexError):
        lat[3]


# ------------------------------------------------------------------------------------------- negative control
def test_anisotropic_stretch_changes_output(prior: ShapePrior) -> None:
    """A non-similarity (stretch) must change the invariant code and the decoded SDF by a lot."""
    P = mug_like(128, 1)[None]
    S = torch.diag(torch.tensor([1.6, 1.0, 0.6], dtype=DT))
    lat, lat_s = prior.encode(P), prior.encode(P @ S.T)
    assert rel_err(lat_s.inv, lat.inv) > 1e-2
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(1, 300, 3, generator=gen, dtype=DT) - 0.5
    assert rel_err(prior.sdf(x @ S.T, lat_s), prior.sdf(x, lat)) > 1e-2


# ----------------------------------------------------------------------------------------------------- refinement
def _np_latent(lat: Latent) -> dict:
    return {"R": lat.R.detach().numpy(), "inv": lat.inv.detach().numpy(), "center": lat.center.detach().numpy(),
            "scale": lat.scale.detach().numpy().reshape(-1)}


@pytest.mark.parametrize("seed", range(3))
def test_latent_refinement_is_sim3_equivariant(prior: ShapePrior, seed: int) -> None:
    """Refining Θ on samples, then transforming, equals refining on transformed samples (float64)."""
    import numpy as np

    from efem_viz.em.config import RefineSettings
    from efem_viz.em.refine import refine_latents

    s, R, t = random_similarity(300 + seed)
    P = torch.stack([mug_like(128, seed), mug_like(128, seed + 7) * 0.8])
    Pg = s * P @ R.T + t
    # encode a perturbed cloud (so the refinement has work to do) and transform that code exactly
    lat = prior.encode(P + 0.05 * torch.randn(P.shape, generator=torch.Generator().manual_seed(seed), dtype=DT))
    lat_g = Latent(lat.R @ R.T, lat.inv, s * lat.center @ R.T + t, s * lat.scale)
    st = RefineSettings(steps=6, lr=0.05, momentum=0.5)
    out, loss = refine_latents(prior, _np_latent(lat), P.numpy(), st)
    out_g, loss_g = refine_latents(prior, _np_latent(lat_g), Pg.numpy(), st)
    Rn = R.numpy()
    _, loss0 = refine_latents(prior, _np_latent(lat), P.numpy(), RefineSettings(steps=1, lr=1e-12))
    assert (loss < loss0).all(), "the refinement must lower the data term"
    assert np.abs(out["R"] - _np_latent(lat)["R"]).max() > 1e-4, "the code must move"
    assert np.allclose(out_g["R"], out["R"] @ Rn.T, atol=1e-9, rtol=0)
    assert np.allclose(out_g["inv"], out["inv"], atol=1e-9, rtol=0)
    assert np.allclose(out_g["center"], s * out["center"] @ Rn.T + t.numpy(), atol=1e-9, rtol=0)
    assert np.allclose(out_g["scale"], s * out["scale"], rtol=1e-10)
    assert np.allclose(loss_g, loss, atol=1e-10)


def test_latent_refinement_with_adam_would_not_be_equivariant(prior: ShapePrior) -> None:
    """Negative control: the same loss minimised with per-coordinate Adam steps breaks rotation equivariance, so
    the test above can tell an equivariant optimiser from one that is not."""
    s, R, t = random_similarity(400)
    P = mug_like(128, 1)[None]
    lat = prior.encode(P + 0.05)

    def adam(points: torch.Tensor, l0: Latent) -> torch.Tensor:
        Rp = l0.R.clone().requires_grad_(True)
        opt = torch.optim.Adam([Rp], lr=0.05)
        for _ in range(6):
            opt.zero_grad()
            m, b = prior.decoder.fold(Rp, l0.inv)
            q = (points - l0.center[:, None]) / l0.scale[:, None, None]
            prior.decoder.forward_batched(q, m, b).abs().mean().backward()
            opt.step()
        return Rp.detach()

    lat_g = Latent(lat.R @ R.T, lat.inv, s * lat.center @ R.T + t, s * lat.scale)
    a, b = adam(P, lat), adam(s * P @ R.T + t, lat_g)
    assert rel_err(b, a @ R.T) > 1e-4
