"""SIM(3)-equivariant point-cloud encoder: VN-DGCNN backbone + four latent heads (docs/design/efem-method.md §1.3-1.4).

Tensors are channels-last VN features ``(B, N, 3, C)`` (see ``vn_layers``). Parameter names follow §1.7
(``V_list.{b}.lin.weight``, ``global_conv_list.{j}``, ``Q_list.{b}``/``K_list.{b}``, ``conv_c``, ``fc_inv``,
``fc_center.{fc0,lin1,shortcut,act2}``) so the released checkpoints stay convertible.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Iterable, NamedTuple, cast

import torch
import torch.nn.functional as F
from torch import nn

from efem_viz.prior import fused
from efem_viz.prior.vn_math import EPS
from efem_viz.prior.vn_layers import (
    VNLinear,
    VNLinearLeakyReLU,
    VNResnetBlock,
    channel_normalize,
)

if TYPE_CHECKING:
    from efem_viz.prior.config import PriorConfig


class EncoderOutput(NamedTuple):
    """Raw encoder heads for a batch of centred clouds (channels-last; the model makes them a ``Latent``).

    Attributes:
        R: ``(B, 3, L)`` Θ_R (ChNorm of the pooled feature), rotation-carrying, scale-free.
        inv: ``(B, L)`` Θ_inv, invariant.
        delta: ``(B, 3)`` centre offset δ (Θ_c = x̄ + δ), in the frame of the centred input.
        scale: ``(B,)`` Θ_s.
    """

    R: torch.Tensor
    inv: torch.Tensor
    delta: torch.Tensor
    scale: torch.Tensor


def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Batched gather along dim 1: ``x (B, N, ...)``, ``idx (B, ...)`` -> ``(B, *idx.shape[1:], ...)``."""
    b = x.shape[0]
    ar = torch.arange(b, device=x.device).view(b, *([1] * (idx.ndim - 1)))
    return x[ar, idx]


class VNDGCNNEncoder(nn.Module):
    """VN-DGCNN encoder with optional VN attention and global-context fusion.

    Args:
        cfg: The prior configuration (widths, k, down-sampling, attention blocks, latent width, σ).
    """

    def __init__(self, cfg: PriorConfig) -> None:
        super().__init__()
        self.cfg = cfg
        slope = cfg.negative_slope
        widths = list(cfg.widths)
        self.V_list = nn.ModuleList()
        self.global_conv_list = nn.ModuleList()
        self.Q_list = nn.ModuleDict()
        self.K_list = nn.ModuleDict()
        c_prev = 1
        for b, c_b in enumerate(widths):
            c_edge = 3 if b == 0 else 2 * c_prev
            self.V_list.append(VNLinearLeakyReLU(c_edge, c_b, negative_slope=slope))
            if b in cfg.attention_blocks:
                if b == 0:
                    raise ValueError("attention is not supported in block 0")
                if c_b % cfg.att_head_dim != 0:
                    raise ValueError(f"block {b} width {c_b} is not a multiple of att_head_dim "
                                     f"{cfg.att_head_dim}")
                self.Q_list[str(b)] = VNLinearLeakyReLU(c_prev, c_b, negative_slope=slope)
                self.K_list[str(b)] = VNLinearLeakyReLU(c_edge, c_b, negative_slope=slope)
            if b >= cfg.global_from:
                self.global_conv_list.append(VNLinearLeakyReLU(2 * c_b, c_b, negative_slope=slope))
            c_prev = c_b
        lat = cfg.latent_dim
        self.conv_c = VNLinearLeakyReLU(widths[-1], lat, shared=True, negative_slope=slope)
        self.fc_inv = VNLinear(lat, lat)
        self.fc_center = VNResnetBlock(lat, cfg.center_hidden, 1, negative_slope=slope)
        self.down = dict(zip(cfg.down_blocks, cfg.down_factors))

    @staticmethod
    def _edge_terms(layer: VNLinearLeakyReLU, f_src: torch.Tensor, f_dst: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(a, c, U a, U c)`` of an edge layer: ``layer([f_j − f_i ; f_i]) = act(a[j] + c[i])`` with
        ``a = W1 f_src``, ``c = (W2 − W1) f_dst`` (exact, k× cheaper than per edge) and the activation's directions
        ``U a``, ``U c`` (``U x`` is linear), as `fused.attention` takes them.

        Args:
            layer: VNLA whose ``lin.weight`` is ``(C_out, 2 C_in)``.
            f_src: ``(B, Ns, 3, C_in)``.
            f_dst: ``(B, Nd, 3, C_in)``.
        """
        w = layer.lin.weight
        c_in = f_src.shape[-1]
        w1 = w[:, :c_in]
        a = F.linear(f_src, w1)
        c = F.linear(f_dst, w[:, c_in:] - w1)
        u = layer.act.lin_dir.weight
        return a, c, F.linear(a, u), F.linear(c, u)

    def forward(self, x: torch.Tensor) -> EncoderOutput:
        """Encode centred point clouds.

        Args:
            x: ``(B, N, 3)`` points already centred by their (possibly perturbed) centroid.

        Returns:
            ``EncoderOutput`` with Θ_R ``(B, 3, L)``, Θ_inv ``(B, L)``, δ ``(B, 3)``, Θ_s ``(B,)``.
        """
        cfg = self.cfg
        pos = x
        feat = x[..., None]  # (B, N, 3, 1)
        g_idx = 0
        # casts: nn.ModuleList/ModuleDict are not generic; __init__ fills them with VNLinearLeakyReLU only
        for b, layer in enumerate(cast("Iterable[VNLinearLeakyReLU]", self.V_list)):
            n_src = feat.shape[1]
            if b in self.down:
                n_dst = max(1, n_src // self.down[b])
                sel = fused.fps(pos, n_dst, start=0)
                f_dst = _gather(feat, sel)
                pos = _gather(pos, sel)
            else:
                f_dst = feat
            k = min(cfg.k, n_src)
            nbr = fused.knn(f_dst.flatten(2), feat.flatten(2), k)  # (B, Nd, k)
            if b == 0:
                xi = f_dst[..., 0]  # (B, Nd, 3)
                xj = _gather(feat[..., 0], nbr)  # (B, Nd, k, 3)
                xi_hat = xi / xi.norm(dim=-1, keepdim=True).clamp_min(EPS)
                xi_e = xi[:, :, None].expand_as(xj)
                cross = torch.cross(xi_hat[:, :, None].expand_as(xj), xj, dim=-1)
                edge = torch.stack([cross, xj - xi_e, xi_e], dim=-1)  # (B, Nd, k, 3, 3)
                out = fused.lin_act_mean(edge, layer.lin.weight, layer.act.lin_dir.weight,
                                         layer.act.negative_slope)
            elif str(b) in self.Q_list:
                k_layer = cast(VNLinearLeakyReLU, self.K_list[str(b)])
                q = channel_normalize(self.Q_list[str(b)](f_dst))  # (B, Nd, 3, C)
                out = fused.attention(self._edge_terms(layer, feat, f_dst), self._edge_terms(k_layer, feat, f_dst),
                                      q, nbr, layer.act.negative_slope, cfg.att_head_dim)
            else:
                w = layer.lin.weight
                c_in = feat.shape[-1]
                w1 = w[:, :c_in]
                out = fused.edge_mean(F.linear(feat, w1), F.linear(f_dst, w[:, c_in:] - w1), nbr,
                                      layer.act.lin_dir.weight, layer.act.negative_slope)
            if b >= cfg.global_from:
                glayer = cast(VNLinearLeakyReLU, self.global_conv_list[g_idx])
                g_idx += 1
                c = out.shape[-1]
                w = glayer.lin.weight
                g = out.mean(dim=1, keepdim=True)
                out = glayer.act(F.linear(out, w[:, :c]) + F.linear(g, w[:, c:]))
            feat = out
        pooled = self.conv_c(feat).mean(dim=1)  # (B, 3, L)
        R = channel_normalize(pooled)
        scale = cfg.scale_factor * pooled.norm(dim=-2).mean(dim=-1)
        inv_dir = channel_normalize(self.fc_inv(pooled))
        inv = (inv_dir * R).sum(dim=-2)
        delta = self.fc_center(pooled)[..., 0]  # (B, 3)
        if cfg.center_times_sigma:
            delta = delta * cfg.scale_factor
        return EncoderOutput(R=R, inv=inv, delta=delta, scale=scale)
