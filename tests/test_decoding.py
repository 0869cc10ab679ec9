"""The E-step's decoder glue (`efem_viz.em.decoding`): the one-pass SDF + band-normals decode against autograd."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from efem_viz.em.decoding import decode_rows
from efem_viz.em.proposals import Ragged
from efem_viz.prior.model import Latent, PriorConfig, ShapePrior


def _prior(dtype: torch.dtype, seed: int = 0) -> ShapePrior:
    torch.manual_seed(seed)
    cfg = PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16, center_hidden=8,
                      n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=3)
    prior = ShapePrior(cfg).to(dtype)
    with torch.no_grad():  # fc_1 starts at zero: give every block a part in the answer
        for p in prior.decoder.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return prior.eval()


def _latent(prior: ShapePrior, b: int, seed: int) -> Latent:
    g = torch.Generator().manual_seed(seed)
    dt = prior.dtype
    return Latent(R=torch.randn(b, 16, 3, generator=g, dtype=dt), inv=torch.randn(b, 16, generator=g, dtype=dt),
                  center=0.1 * torch.randn(b, 3, generator=g, dtype=dt),
                  scale=0.5 + torch.rand(b, generator=g, dtype=dt))


@pytest.mark.parametrize("seed", [0, 1])
def test_one_pass_band_normals_equal_autograd_in_float64(seed: int) -> None:
    """`sdf_and_band_normals` (one forward, a hand-made backward on the band rows) gives autograd's SDF and
    normals inside the band, zeros outside it, and the band exactly where |sdf| <= within."""
    prior = _prior(torch.float64, seed)
    lat = _latent(prior, 4, seed)
    x = torch.randn(4, 300, 3, generator=torch.Generator().manual_seed(seed + 9), dtype=torch.float64)
    sdf_ref = prior.sdf(x, lat).detach()
    within = float(sdf_ref.abs().median())  # about half of the queries in the band
    sdf, normals, band = prior.sdf_and_band_normals(x, lat, within=within)
    assert torch.equal(band, sdf_ref.abs() <= within) and 0.3 < band.double().mean() < 0.7
    assert torch.allclose(sdf, sdf_ref, rtol=0, atol=1e-12)
    _, n_ref = prior.sdf_and_normals(x, lat)
    assert torch.allclose(normals[band], n_ref[band], rtol=0, atol=1e-10)
    assert torch.count_nonzero(normals[~band]) == 0


def test_decode_rows_one_pass_gives_the_two_pass_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    """decode_rows with `normals_within` on a `ShapePrior` with the one pass switched on, and on a prior without
    the one-pass method (SDF pass, then autograd on the band, the default): the same SDF bit for bit, the same
    band, angles to float rounding."""
    monkeypatch.setenv("EFEM_VIZ_ONE_PASS", "1")
    prior = _prior(torch.float32, 3)
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=0.2, size=(500, 3)).astype(np.float32)
    nrm = rng.normal(size=(500, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rows = [rng.choice(500, size=n, replace=False) for n in (40, 120, 7, 300, 1)]
    rag = Ragged(np.concatenate(rows).astype(np.int64),
                 np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64))
    lat = _latent(prior, len(rows), 5)

    class TwoPass:  # the same prior, seen without `sdf_and_band_normals`
        def __init__(self, p: ShapePrior) -> None:
            self.p = p

        def __getattr__(self, name: str) -> object:
            if name == "sdf_and_band_normals":
                raise AttributeError(name)
            return getattr(self.p, name)

    d_all, _ = decode_rows(prior, lat, rag, pts, nrm)
    within = float(np.median(np.abs(d_all)))
    one, two = {}, {}
    d1, g1 = decode_rows(prior, lat, rag, pts, nrm, normals_within=within, chunk=200, stats=one)
    monkeypatch.setenv("EFEM_VIZ_ONE_PASS", "0")
    d2, g2 = decode_rows(prior, lat, rag, pts, nrm, normals_within=within, chunk=200)
    d0, g0 = decode_rows(TwoPass(prior), lat, rag, pts, nrm, normals_within=within, chunk=200, stats=two)
    assert np.array_equal(d1, d0) and np.array_equal(d2, d0) and np.array_equal(g2, g0)  # off: the two-pass
    assert np.array_equal(g1 < 180.0, g0 < 180.0) and np.array_equal(g0 < 180.0, np.abs(d0) <= within)
    assert np.abs(g1 - g0).max() < 0.05
    assert one["normal_queries"] == two["normal_queries"] == np.count_nonzero(np.abs(d0) <= within)
