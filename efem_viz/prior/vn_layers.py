"""Vector-neuron (VN) primitive layers (docs/design/efem-method.md §1.2).

Memory layout. The spec writes a VN feature as a matrix ``V`` of shape ``(C, 3)``. Here every VN tensor is
stored *channels last*, ``(..., 3, C)`` (the 3-D axis second to last), so that a VN-Linear is one dense GEMM
(``torch.nn.functional.linear``) over all points, edges and spatial components at once. The weights keep the
spec's ``(C_out, C_in)`` shape and names (``lin.weight``, ``act.lin_dir.weight``) so released checkpoints map
one to one.

All layers are bias-free and positively homogeneous: for a similarity ``g = (s, R, t)`` with ``s > 0`` and
``R ∈ SO(3)``, ``f(s R V) = s R f(V)`` in this layout (``V ↦ s V Rᵀ`` in the spec's row layout).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from efem_viz.prior.fused import leaky
from efem_viz.prior.vn_math import EPS


class VNLinear(nn.Module):
    """VN-Linear ``L_W(V) = W V``: mixes channels, never the 3-D axis.

    Args:
        c_in: Input channels.
        c_out: Output channels.
    """

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(c_out, c_in))
        bound = 1.0 / math.sqrt(c_in)
        nn.init.uniform_(self.weight, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Apply the layer.

        Args:
            x: ``(..., 3, C_in)`` VN features.

        Returns:
            ``(..., 3, C_out)``.
        """
        return F.linear(x, self.weight)


class VNLeakyReLU(nn.Module):
    """VN-LeakyReLU with a learned direction (negative slope ``alpha``).

    ``k = U V``; ``π_c = <v_c, k̂_c>``; ``out_c = v_c − (1 − α) min(π_c, 0) k̂_c``.

    Args:
        channels: Number of feature channels ``C``.
        shared: If True one direction serves all channels (``U ∈ R^{1×C}``), else per-channel
            (``U ∈ R^{C×C}``).
        negative_slope: ``α``.
    """

    def __init__(self, channels: int, *, shared: bool = False, negative_slope: float = 0.2) -> None:
        super().__init__()
        self.lin_dir = VNLinear(channels, 1 if shared else channels)
        self.negative_slope = float(negative_slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Apply the activation.

        Args:
            x: ``(..., 3, C)`` VN features.

        Returns:
            ``(..., 3, C)``.
        """
        return leaky(x, self.lin_dir(x), self.negative_slope)


class VNLinearLeakyReLU(nn.Module):
    """VNLA: a VN-Linear (``lin``) followed by a VN-LeakyReLU (``act``) on the output channels.

    Args:
        c_in: Input channels.
        c_out: Output channels.
        shared: Shared activation direction (``act.lin_dir.weight`` is ``(1, C_out)``).
        negative_slope: Leaky slope ``α``.
    """

    def __init__(self, c_in: int, c_out: int, *, shared: bool = False, negative_slope: float = 0.2) -> None:
        super().__init__()
        self.lin = VNLinear(c_in, c_out)
        self.act = VNLeakyReLU(c_out, shared=shared, negative_slope=negative_slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., 3, C_in) -> (..., 3, C_out)``."""
        return self.act(self.lin(x))


def channel_normalize(x: torch.Tensor) -> torch.Tensor:
    """ChNorm: ``V / ‖V‖_F`` over each ``3×C`` block (rotation-equivariant, scale-invariant).

    Args:
        x: ``(..., 3, C)``.

    Returns:
        ``(..., 3, C)`` with unit Frobenius norm per leading index (zero blocks stay zero).
    """
    n = x.flatten(-2).norm(dim=-1)[..., None, None]
    return x / n.clamp_min(EPS)


class VNResnetBlock(nn.Module):
    """VN residual block of the centre head (§1.2).

    ``h = fc0(X)`` (VNLA ``C_in→H``), ``y = lin1(h) + shortcut(X)``, ``out = act2(y)``.

    Args:
        c_in: Input channels.
        hidden: Hidden channels ``H``.
        c_out: Output channels.
        negative_slope: Leaky slope ``α``.
    """

    def __init__(self, c_in: int, hidden: int, c_out: int, *, negative_slope: float = 0.2) -> None:
        super().__init__()
        self.fc0 = VNLinearLeakyReLU(c_in, hidden, negative_slope=negative_slope)
        self.lin1 = VNLinear(hidden, c_out)
        self.shortcut: VNLinear | None = VNLinear(c_in, c_out) if c_in != c_out else None
        self.act2 = VNLeakyReLU(c_out, negative_slope=negative_slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., 3, C_in) -> (..., 3, C_out)``."""
        skip = self.shortcut(x) if self.shortcut is not None else x
        return self.act2(self.lin1(self.fc0(x)) + skip)
