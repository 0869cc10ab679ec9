"""Invariant implicit SDF decoder (efem-method.md §1.5).

``q = (x − Θ_c)/Θ_s``; ``φ = [Θ_R q ; ‖q‖ ; Θ_inv]``; ``h_0 = A_in φ + a_in``; pre-activation residual
ReLU blocks; ``sdf = w_outᵀ ReLU(h) + b_out``. Parameter names follow §1.7 (``fc_in``,
``block{i}.fc_0/fc_1``, ``fc_out``).

Implementation note: ``A_in φ`` is evaluated as ``(A_proj Θ_R) q + a_q ‖q‖ + (A_inv Θ_inv + a_in)``, i.e.
the projection onto the ``L`` rows of Θ_R is folded into the first layer once per latent. That is the same
function (same parameters, same gradients) but costs 4 instead of ``2L+1`` multiply-adds per query and
hidden unit.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ResnetBlockFC(nn.Module):
    """Pre-activation residual block ``h + fc_1(ReLU(fc_0(ReLU(h))))`` with ``fc_1`` zero-initialised.

    Args:
        width: Hidden width.
    """

    def __init__(self, width: int) -> None:
        super().__init__()
        self.fc_0 = nn.Linear(width, width)
        self.fc_1 = nn.Linear(width, width)
        nn.init.zeros_(self.fc_1.weight)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """``(..., W) -> (..., W)``."""
        return h + self.fc_1(F.relu(self.fc_0(F.relu(h))))


class SDFDecoder(nn.Module):
    """Inner-product SDF decoder.

    Args:
        latent_dim: ``L`` (rows of Θ_R and length of Θ_inv).
        hidden: MLP width.
        n_blocks: Number of residual blocks.
        use_qnorm: Include ``‖q‖`` in φ (the released models do).
        proj_gain: Constant multiplier of the projections ``Θ_R q`` in φ.
        inv_gain: Constant multiplier of Θ_inv in φ.
    """

    def __init__(self, latent_dim: int, hidden: int, n_blocks: int, *, use_qnorm: bool = True,
                 proj_gain: float = 1.0, inv_gain: float = 1.0) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.use_qnorm = use_qnorm
        self.proj_gain = float(proj_gain)
        self.inv_gain = float(inv_gain)
        self.n_blocks = n_blocks
        self.fc_in = nn.Linear(2 * latent_dim + (1 if use_qnorm else 0), hidden)
        for i in range(n_blocks):
            self.add_module(f"block{i}", ResnetBlockFC(hidden))
        self.fc_out = nn.Linear(hidden, 1)

    def fold(self, R: torch.Tensor, inv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fold a batch of latents into per-latent first-layer weights.

        Args:
            R: ``(B, L, 3)`` Θ_R (row layout).
            inv: ``(B, L)`` Θ_inv.

        Returns:
            ``M (B, H, 3)`` and ``bias (B, H)`` so that ``h_0 = M q + a_q ‖q‖ + bias``.
        """
        L = self.latent_dim
        w = self.fc_in.weight
        m = torch.matmul(w[:, :L], R)  # (B, H, 3)
        if self.proj_gain != 1.0:
            m = m * self.proj_gain
        bias = F.linear(inv * self.inv_gain if self.inv_gain != 1.0 else inv, w[:, -L:], self.fc_in.bias)
        return m, bias

    def _mlp(self, h: torch.Tensor) -> torch.Tensor:
        if torch.is_autocast_enabled(h.device.type):
            # keep the residual stream in the autocast dtype: mixed fp32 + bf16 adds cost more than the
            # matrix products they sit between (bench/decoder_bf16.py)
            h = h.to(torch.get_autocast_dtype(h.device.type))
        for i in range(self.n_blocks):
            h = getattr(self, f"block{i}")(h)
        return self.fc_out(F.relu(h))[..., 0]

    def _qfeat(self, q: torch.Tensor) -> torch.Tensor | None:
        if not self.use_qnorm:
            return None
        return (q * q).sum(-1, keepdim=True).clamp_min(1e-24).sqrt() * self.fc_in.weight[:, self.latent_dim]

    def forward_batched(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """SDF of canonical queries with one latent per batch row.

        Args:
            q: ``(B, Q, 3)`` queries already mapped by ``(x − Θ_c)/Θ_s``.
            m: ``(B, H, 3)`` from ``fold``.
            bias: ``(B, H)`` from ``fold``.

        Returns:
            ``(B, Q)`` canonical SDF.
        """
        h = torch.matmul(q, m.transpose(1, 2)) + bias[:, None, :]
        qf = self._qfeat(q)
        if qf is not None:
            h = h + qf
        return self._mlp(h)

    def forward_ragged(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """SDF of canonical queries that each carry their own (already gathered) folded latent.

        Args:
            q: ``(Q, 3)``.
            m: ``(Q, H, 3)``.
            bias: ``(Q, H)``.

        Returns:
            ``(Q,)`` canonical SDF.
        """
        h = (m * q[:, None, :]).sum(-1) + bias
        qf = self._qfeat(q)
        if qf is not None:
            h = h + qf
        return self._mlp(h)
