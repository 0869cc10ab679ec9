"""Invariant implicit SDF decoder (docs/design/efem-method.md §1.5).

``q = (x − Θ_c)/Θ_s``; ``φ = [Θ_R q ; ‖q‖ ; Θ_inv]``; ``h_0 = A_in φ + a_in``; pre-activation residual
ReLU blocks; ``sdf = w_outᵀ ReLU(h) + b_out``. Parameter names follow §1.7 (``fc_in``,
``block{i}.fc_0/fc_1``, ``fc_out``).

Implementation note: ``A_in φ`` is evaluated as ``(A_proj Θ_R) q + a_q ‖q‖ + (A_inv Θ_inv + a_in)``, i.e.
the projection onto the ``L`` rows of Θ_R is folded into the first layer once per latent. That is the same
function (same parameters, same gradients) but costs 4 instead of ``2L+1`` multiply-adds per query and
hidden unit.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import nn

from efem_viz.prior import fused


TILE_ROWS = 1024
"""Rows per tile of the decoder's eager inference passes on a CPU (where `fused.decoder_band` does not serve them:
bf16 autocast, no compiler): at width 128 every activation of a tile (512 KB) stays in the core's cache between
the matrix products."""


def _qnorm(q: torch.Tensor) -> torch.Tensor:
    """``‖q‖`` of each query, ``(..., 1)`` (kept off zero so that its gradient stays finite)."""
    return (q * q).sum(-1, keepdim=True).clamp_min(1e-24).sqrt()


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
            ``M (B, H, 3)`` and ``bias (B, H)`` so that ``h_0 = M q + a_q ‖q‖ + bias``, in the weights' precision
            under an autocast too (one small product per latent; the fused bf16 pass takes float32 first-layer
            weights).
        """
        L = self.latent_dim
        w = self.fc_in.weight
        with torch.autocast(R.device.type, enabled=False):
            R, inv = R.to(w.dtype), inv.to(w.dtype)
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
        rows = h.reshape(-1, h.shape[-1])
        if (torch.is_grad_enabled() and h.requires_grad) or h.device.type != "cpu" or len(rows) <= 2 * TILE_ROWS:
            return self._mlp_rows(h)
        # on a CPU, tiles of rows whose activations stay in cache: the same products, 25-30 % less time
        parts = [self._mlp_rows(rows[s:s + TILE_ROWS]) for s in range(0, len(rows), TILE_ROWS)]
        return torch.cat(parts).reshape(h.shape[:-1])

    def _mlp_rows(self, h: torch.Tensor) -> torch.Tensor:
        for i in range(self.n_blocks):
            h = getattr(self, f"block{i}")(h)
        return self.fc_out(F.relu(h))[..., 0]

    def _qfeat(self, q: torch.Tensor) -> torch.Tensor | None:
        if not self.use_qnorm:
            return None
        return _qnorm(q) * self.fc_in.weight[:, self.latent_dim]

    def _augmented(self, q: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``[q, ‖q‖]`` and ``[M, a_q]`` (``(B, Q, 4)``, ``(B, H, 4)``), so that ``M q + a_q ‖q‖`` is one batched
        product; ``(q, M)`` without the ‖q‖ feature."""
        if not self.use_qnorm:
            return q, m
        a_q = self.fc_in.weight[:, self.latent_dim].to(m.dtype)
        return torch.cat([q, _qnorm(q)], -1), torch.cat([m, a_q.expand(m.shape[0], -1)[..., None]], -1)

    def forward_batched(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """SDF of canonical queries with one latent per batch row.

        Args:
            q: ``(B, Q, 3)`` queries already mapped by ``(x − Θ_c)/Θ_s``.
            m: ``(B, H, 3)`` from ``fold``.
            bias: ``(B, H)`` from ``fold``.

        Returns:
            ``(B, Q)`` canonical SDF.
        """
        out = self._fused(q, m, bias, -1.0)
        if out is not None:
            return out[0]
        return self._mlp(self._first_layer(q, m, bias))

    def _fused(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor, within: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """`fused.decoder_band` of these queries (None where it does not serve them: not a float32 CPU inference
        call, autograd or an autocast other than the CPU's bf16 on, no kernels, ``EFEM_VIZ_FUSED_DECODER=0``, too
        few queries for a tile to pay). Under a CPU bf16 autocast its products take bf16 operands, as the eager
        tiles' do (their results float32)."""
        if (q.device.type != "cpu" or q.shape[0] * q.shape[1] < 64 or os.environ.get("EFEM_VIZ_FUSED_DECODER") == "0"
                or not fused.usable(q, m, bias, autocast_ok=fused.autocast_bf16())):
            return None
        blocks = [getattr(self, f"block{i}") for i in range(self.n_blocks)]
        params = [(b.fc_0.weight, b.fc_0.bias, b.fc_1.weight, b.fc_1.bias) for b in blocks]
        a_q = (self.fc_in.weight[:, self.latent_dim] if self.use_qnorm else self.fc_in.weight.new_zeros(m.shape[1]))
        mt = torch.cat([m.transpose(1, 2), a_q.expand(m.shape[0], 1, -1), bias[:, None, :]], 1)
        return fused.decoder_band(q.contiguous(), mt, params, self.fc_out.weight[0], float(self.fc_out.bias[0]),
                                  within, self.use_qnorm)

    def _first_layer(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """``h_0 = M q + a_q ‖q‖ + bias`` for batched queries ``(B, Q, 3)`` -> ``(B, Q, H)``: one batched product
        of ``[q, ‖q‖, 1]`` and ``[M, a_q, bias]``, which writes the (B, Q, H) activations once (separate adds of
        the bias and the ‖q‖ feature were a quarter of an E-step's decode)."""
        q4, m4 = self._augmented(q, m)
        ones = torch.ones(q4.shape[:-1] + (1,), dtype=q4.dtype, device=q4.device)
        return torch.bmm(torch.cat([q4, ones], -1), torch.cat([m4, bias[..., None].to(m4.dtype)], -1).transpose(1, 2))

    def sdf_and_band_grad(self, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor, *, within: float
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDF of every query and its gradient in ``q`` for the queries with ``|sdf| <= within``, in one pass.

        One forward over every query keeps its ReLU masks; the input gradient is then back-propagated by hand
        through those masks for the band rows only (the same products autograd would form, without a second
        forward or autograd's bookkeeping). Outside the band the gradient is zero. Call under ``no_grad``.

        Args:
            q: ``(B, Q, 3)`` canonical queries.
            m: ``(B, H, 3)`` from ``fold``.
            bias: ``(B, H)`` from ``fold``.
            within: the band half-width (canonical SDF units).

        Returns:
            ``sdf (B, Q)``, ``dq (B, Q, 3)`` (∂sdf/∂q; zeros outside the band) and ``band (B, Q)`` bool.
        """
        out = self._fused(q, m, bias, within)
        if out is not None:
            return out
        h = self._first_layer(q, m, bias)
        if torch.is_autocast_enabled(h.device.type):
            h = h.to(torch.get_autocast_dtype(h.device.type))
        b, n, width = h.shape
        rows = h.reshape(-1, width)
        sdf = torch.empty(len(rows), dtype=q.dtype, device=q.device)
        band_rows: list[torch.Tensor] = []
        band_grads: list[torch.Tensor] = []
        tile = TILE_ROWS if q.device.type == "cpu" else max(len(rows), 1)
        for s in range(0, len(rows), tile):  # tiles whose activations stay in cache through the backward
            sdf_t, sel, g = self._band_grad_tile(rows[s:s + tile], within)
            sdf[s:s + tile] = sdf_t.to(q.dtype)
            if len(sel):
                band_rows.append(s + sel)
                band_grads.append(g.to(q.dtype))
        band = torch.zeros(len(rows), dtype=torch.bool, device=q.device)
        dq = torch.zeros(len(rows), 3, dtype=q.dtype, device=q.device)
        if band_rows:  # ∂sdf/∂q = ∂sdf/∂h0 · [M, a_q] · ∂[q, ‖q‖]/∂q, for the band rows only, latent by latent
            idx, grad = torch.cat(band_rows), torch.cat(band_grads)
            band[idx] = True
            q4, m4 = self._augmented(q.reshape(-1, 3)[idx], m)
            d4 = torch.empty(len(idx), m4.shape[-1], dtype=q.dtype, device=q.device)
            counts = torch.bincount(torch.div(idx, n, rounding_mode="floor"), minlength=b).tolist()
            start = 0
            for k, c in enumerate(counts):  # band rows are in row order: each latent's rows are contiguous
                if c:
                    d4[start:start + c] = torch.matmul(grad[start:start + c], m4[k])
                start += c
            d = d4[:, :3]
            if self.use_qnorm:
                d = d + d4[:, 3:] * q4[:, :3] / q4[:, 3:]
            dq[idx] = d
        return sdf.reshape(b, n), dq.reshape(b, n, 3), band.reshape(b, n)

    def _band_grad_tile(self, hf: torch.Tensor, within: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One tile of `sdf_and_band_grad`: the SDF of rows ``hf`` (first-layer outputs), the band rows and
        ∂sdf/∂h0 of those rows, back-propagated by hand through the ReLU masks (where autograd's relu backward
        uses ``x > 0``)."""
        stream: list[torch.Tensor] = []  # pre-activations kept for the band rows' backward (no copies made)
        for i in range(self.n_blocks):
            blk = getattr(self, f"block{i}")
            u = blk.fc_0(F.relu(hf))
            stream += [hf, u]
            hf = hf + blk.fc_1(F.relu(u))
        sdf = self.fc_out(F.relu(hf))[:, 0]
        sel = torch.nonzero(sdf.abs() <= within)[:, 0]
        width = hf.shape[-1]
        if len(sel) == 0:
            return sdf, sel, hf.new_zeros(0, width)
        relu_grad = torch.ops.aten.threshold_backward  # grad where x > 0 else 0: ReLU's own backward, vectorised
        g = relu_grad(self.fc_out.weight[0].to(hf.dtype).expand(len(sel), width), hf.index_select(0, sel), 0.0)
        for i in reversed(range(self.n_blocks)):
            blk = getattr(self, f"block{i}")
            h_i, u_i = stream[2 * i], stream[2 * i + 1]
            t = relu_grad(torch.matmul(g, blk.fc_1.weight.to(g.dtype)), u_i.index_select(0, sel), 0.0)
            g = g + relu_grad(torch.matmul(t, blk.fc_0.weight.to(g.dtype)), h_i.index_select(0, sel), 0.0)
        return sdf, sel, g

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
