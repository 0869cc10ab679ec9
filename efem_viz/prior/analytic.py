"""An analytic sphere "prior" and a sphere tabletop scene: EM tests without trained weights.

`SpherePrior` implements the `ShapePrior` interface the solver uses (`encode`, `sdf`, `sdf_and_normals`,
`config.n_pcl`, `codebook`, `name`) with a closed form: the encoder is an algebraic least-squares sphere fit,
the decoder the sphere's SDF. It is exactly SIM(3)-equivariant, deterministic and fast, so the EM machinery
(sampling, eliminations, reviews, trace replay) can be tested on scenes whose answer is known.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class SpherePriorConfig:
    n_pcl: int = 256
    """Points per encoded set."""
    latent_dim: int = 4
    """Width of the (unused, zero) Θ_R / Θ_inv codes."""


def _torch() -> Any:
    import torch

    return torch


def make_sphere_prior(n_pcl: int = 256) -> Any:
    """A `SpherePrior` (torch.nn.Module) with `n_pcl` points per encoded set.

    Canonical shape: the sphere of radius 0.5 (diameter 1, the canonical object size); Θ_s = 2 r (world),
    Θ_c = the fitted centre; the SDF is `‖x − Θ_c‖/Θ_s − 0.5` (canonical units, negative inside).
    """
    torch = _torch()
    from efem_viz.prior.model import Latent

    class SpherePrior(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.config = SpherePriorConfig(n_pcl=n_pcl)
            self.name = "sphere"
            self.codebook = None
            self.metadata: dict[str, Any] = {}
            self._p = torch.nn.Parameter(torch.zeros(1), requires_grad=False)

        @property
        def n_pcl(self) -> int:
            return int(self.config.n_pcl)

        @property
        def category(self) -> Any:
            from efem_viz.prior.config import category_settings

            return category_settings(self.name, self.metadata)

        def encode(self, points: Any) -> Any:
            if points.ndim == 2:
                points = points[None]
            x = points.to(self._p)
            b, m, _ = x.shape
            mean = x.mean(1, keepdim=True)
            xc = x - mean
            a = torch.cat([2 * xc, torch.ones(b, m, 1, dtype=x.dtype, device=x.device)], dim=2).double()
            rhs = (xc * xc).sum(-1, keepdim=True).double()
            ata = a.transpose(1, 2) @ a + 1e-9 * torch.eye(4, dtype=a.dtype, device=a.device)
            sol = torch.linalg.solve(ata, a.transpose(1, 2) @ rhs)[..., 0]
            c = sol[:, :3]
            r2 = (sol[:, 3] + (c * c).sum(-1)).clamp_min(1e-8)
            r = r2.sqrt().to(x.dtype)
            center = mean[:, 0] + c.to(x.dtype)
            L = self.config.latent_dim
            return Latent(R=x.new_zeros(b, L, 3), inv=x.new_zeros(b, L), center=center, scale=2 * r)

        def _prep(self, x: Any, latent: Any, index: Any) -> tuple[Any, Any]:
            center = latent.center.to(self._p)
            scale = latent.scale.to(self._p).reshape(-1)
            x = x.to(self._p)
            if x.ndim == 3:
                return x - center[:, None, :], scale[:, None]
            if index is None:
                return x - center[0], scale[0].expand(x.shape[0])
            index = index.to(x.device)
            return x - center[index], scale[index]

        def sdf(self, x: Any, latent: Any, index: Any = None, *, chunk: int = 65536) -> Any:
            v, s = self._prep(x, latent, index)
            return v.norm(dim=-1) / s - 0.5

        def sdf_and_normals(
            self, x: Any, latent: Any, index: Any = None, *, chunk: int = 65536
        ) -> tuple[Any, Any]:
            v, s = self._prep(x, latent, index)
            nrm = v.norm(dim=-1, keepdim=True)
            return (nrm[..., 0] / s - 0.5), v / nrm.clamp_min(1e-12)

    return SpherePrior().eval()


def make_sphere_scene(
    *,
    seed: int = 0,
    radii: tuple[float, ...] = (0.05, 0.045, 0.055),
    table: float = 0.5,
    spacing: float = 0.005,
    name: str = "spheres",
) -> Any:
    """A tabletop point cloud with resting spheres (ground truth instance ids 1..K, table = 0).

    Args:
        seed: placement and sampling seed.
        radii: sphere radii (m).
        table: table side length (m), centred at the origin, z = 0.
        spacing: approximate point spacing (m).
        name: scene name.

    Returns:
        `efem_viz.data.scene.Scene` with points, outward normals and `instance`.
    """
    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(seed)
    n_side = int(table / spacing)
    g = (np.arange(n_side) + 0.5) * spacing - table / 2
    xx, yy = np.meshgrid(g, g, indexing="ij")
    table_pts = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    centers: list[np.ndarray] = []
    for r in radii:
        for _ in range(1000):
            c = np.r_[rng.uniform(-table / 2 + 0.08, table / 2 - 0.08, 2), r]
            if all(np.linalg.norm(c[:2] - o[:2]) > r + o[2] + 0.04 for o in centers):
                centers.append(c)
                break
        else:
            raise ValueError("could not place the spheres without overlap; use a larger table")
    pts = [table_pts]
    nrm = [np.tile([0.0, 0.0, 1.0], (len(table_pts), 1))]
    inst = [np.zeros(len(table_pts), np.int32)]
    keep = np.ones(len(table_pts), bool)
    for k, c in enumerate(centers):
        r = c[2]
        keep &= np.linalg.norm(table_pts[:, :2] - c[:2], axis=1) > r * 0.3
        n = int(4 * np.pi * r * r / spacing**2)
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v = v[v[:, 2] > -0.8]
        pts.append(c + r * v)
        nrm.append(v)
        inst.append(np.full(len(v), k + 1, np.int32))
    pts[0], nrm[0], inst[0] = pts[0][keep], nrm[0][keep], inst[0][keep]
    return Scene.create(
        name,
        np.concatenate(pts).astype(np.float32),
        normals=np.concatenate(nrm).astype(np.float32),
        instance=np.concatenate(inst),
        categories={k + 1: "sphere" for k in range(len(centers))},
        provenance={"generator": "efem_viz.prior.analytic.make_sphere_scene", "seed": seed,
                    "radii": list(radii)},
    )
