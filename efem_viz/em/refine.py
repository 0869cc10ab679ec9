"""Test-time latent refinement: fit each proposal's latent to its M-step samples through the decoder.

The encoder sees M points and answers in one pass; on real partial scans its code often explains only part of the
object. Refinement starts from the encoder's code Θ⁰ and takes a few gradient steps on

    L(Θ) = mean_i min(|SDF(x_i; Θ)|, τ) + λ (‖Θ_R − Θ⁰_R‖² + ‖Θ_inv − Θ⁰_inv‖²) / L + λ_c ‖δ_c‖² + λ_s δ_s²

over the proposal's samples x_i (canonical-unit SDF, truncated at τ so that stray samples do not pull), with the
pose parametrised relative to the encoder's: Θ_c = Θ⁰_c + Θ⁰_s δ_c, Θ_s = Θ⁰_s exp(δ_s).

SIM(3) equivariance is kept exactly (up to rounding): the loss is invariant under a joint similarity transform of
the points and the code, δ_c and δ_s live in the encoder's normalised frame (so translation and scale drop out),
and plain gradient descent with heavy-ball momentum maps equivariant gradients to equivariant updates (per-tensor
step sizes only; no per-coordinate adaptivity such as Adam, which would break rotation equivariance).
tests/test_equivariance.py checks it in float64.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from efem_viz.em.config import RefineSettings

if TYPE_CHECKING:
    from efem_viz.prior.model import ShapePrior


def refine_latents(
    prior: "ShapePrior",
    latent: dict[str, np.ndarray],
    samples: np.ndarray,
    settings: RefineSettings,
    *,
    batch: int = 64,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Refine P latents on their (P, M, 3) samples; returns the refined latents and the per-proposal final loss.

    Args:
        prior: the shape prior (decoder and `fold`).
        latent: numpy latent arrays "R" (P, L, 3), "inv" (P, L), "center" (P, 3), "scale" (P,), world frame.
        samples: (P, M, 3) the points each proposal's encoder saw, world frame.
        settings: step count, step size, truncation and regularisation.
        batch: proposals per decoder call.

    Returns:
        (refined latent arrays in the input dtype, (P,) data-term loss after refinement).

    Raises:
        ValueError: inconsistent shapes.
    """
    import torch

    P = len(latent["center"])
    if samples.ndim != 3 or samples.shape[0] != P or samples.shape[2] != 3:
        raise ValueError(f"samples must be ({P}, M, 3), got {samples.shape}")
    if settings.steps <= 0 or P == 0:
        return dict(latent), np.zeros(P, np.float32)
    dev = next(prior.parameters()).device
    dt = next(prior.parameters()).dtype
    out = {k: np.array(v, copy=True) for k, v in latent.items()}
    losses = np.zeros(P, np.float32)
    for s in range(0, P, batch):
        sl = slice(s, s + batch)
        R0 = torch.as_tensor(latent["R"][sl], device=dev, dtype=dt)
        inv0 = torch.as_tensor(latent["inv"][sl], device=dev, dtype=dt)
        c0 = torch.as_tensor(latent["center"][sl], device=dev, dtype=dt)
        s0 = torch.as_tensor(latent["scale"][sl], device=dev, dtype=dt).reshape(-1)
        x = torch.as_tensor(samples[sl], device=dev, dtype=dt)
        y = (x - c0[:, None, :]) / s0[:, None, None]  # the encoder's normalised frame
        params = [R0.clone().requires_grad_(True), inv0.clone().requires_grad_(True),
                  torch.zeros_like(c0, requires_grad=True), torch.zeros_like(s0, requires_grad=True)]
        vel = [torch.zeros_like(p) for p in params]
        n_ch = max(1, R0.shape[1])
        for _ in range(settings.steps):
            R, inv, dc, ds = params
            m, bias = prior.decoder.fold(R, inv)
            q = (y - dc[:, None, :]) * torch.exp(-ds)[:, None, None]
            d = prior.decoder.forward_batched(q, m, bias)
            data = torch.clamp(d.abs(), max=settings.tau).mean(dim=1)
            reg = settings.reg * (((R - R0) ** 2).sum(dim=(1, 2)) + ((inv - inv0) ** 2).sum(dim=1)) / n_ch
            reg = reg + settings.reg_pose * ((dc**2).sum(dim=1) + ds**2)
            loss = (data + reg).sum()
            grads = torch.autograd.grad(loss, params)
            with torch.no_grad():
                for p, g, v in zip(params, grads, vel):
                    v.mul_(settings.momentum).add_(g)
                    p.sub_(settings.lr * v)
        with torch.no_grad():
            R, inv, dc, ds = params
            m, bias = prior.decoder.fold(R, inv)
            q = (y - dc[:, None, :]) * torch.exp(-ds)[:, None, None]
            d = prior.decoder.forward_batched(q, m, bias)
            losses[sl] = torch.clamp(d.abs(), max=settings.tau).mean(dim=1).float().cpu().numpy()
            out["R"][sl] = R.cpu().numpy().astype(latent["R"].dtype)
            out["inv"][sl] = inv.cpu().numpy().astype(latent["inv"].dtype)
            out["center"][sl] = (c0 + s0[:, None] * dc).cpu().numpy().astype(latent["center"].dtype)
            out["scale"][sl] = (s0 * torch.exp(ds)).cpu().numpy().astype(latent["scale"].dtype)
    return out, losses
