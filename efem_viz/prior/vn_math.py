"""The vector-neuron activation's math, in one place: `vn_layers` builds its layers on it and `fused` checks its
kernels against it (and routes training through them), so neither imports the other for it.

Layout as in `vn_layers`: VN features ``(..., 3, C)``, channels last.
"""

from __future__ import annotations

import torch

EPS = 1e-12
"""Smallest direction norm the activation divides by (its square clamps ``|d|^2``)."""


def vn_leaky_relu(x: torch.Tensor, d: torch.Tensor, negative_slope: float) -> torch.Tensor:
    """VN-LeakyReLU of ``x (..., 3, C)`` along directions ``d (..., 3, C or 1)`` (the one copy of the math; the
    fused kernels of `prior.fused` compute the same).

    ``proj_c k̂_c = <v_c, k_c> k_c / ‖k_c‖²``; the three components are handled as separate contiguous slices
    because reductions over the short strided 3-axis are very slow on CPU.
    """
    dx, dy, dz = d.unbind(-2)
    xx, xy, xz = x.unbind(-2)
    dot = xx * dx + xy * dy + xz * dz
    dn2 = dx * dx + dy * dy + dz * dz
    coef = dot.clamp_max(0.0) / dn2.clamp_min(EPS * EPS) * (1.0 - negative_slope)
    return x - coef.unsqueeze(-2) * d
