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
        keep &= np.linalg.norm(table_pts[:, :2] - c[:2], axis=1) > c[2] * 0.3
        p_k, n_k = sphere_samples(c, float(c[2]), spacing, rng)
        pts.append(p_k)
        nrm.append(n_k)
        inst.append(np.full(len(p_k), k + 1, np.int32))
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


def sphere_samples(center: np.ndarray, radius: float, spacing: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) and outward normals of a sphere resting on a table, as a scan sees it (the part below
    z = centre − 0.8 r, hidden by the table contact, is left out); about one point per `spacing`²."""
    n = int(4 * np.pi * radius * radius / spacing**2)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > -0.8]
    return np.asarray(center) + radius * v, v


def add_spheres(scene: Any, radii: Any, *, centers_xy: Any = None, spacing: float = 0.004, seed: int = 0,
                category: str = "sphere") -> Any:
    """A copy of a tabletop scene (table at z = 0, +Z up) with spheres resting on the table, labelled as new
    ground-truth instances: a scene with two kinds of object for multi-prior solves.

    Args:
        scene: a `Scene` (its `instance` labels, if any, are kept; the spheres get the next ids).
        radii: (S,) sphere radii (m).
        centers_xy: (S, 2) sphere centres on the table (m); None = free places found by a seeded random search
            (no scene point above the table within r + 1.5 cm, inside the table's extent).
        spacing: approximate point spacing on the spheres (m).
        seed: sampling seed.
        category: category name of the new instances.

    Returns:
        The new `Scene` (colours of the added points mid-grey).

    Raises:
        ValueError: mismatched centres and radii, a sphere that overlaps a point of the scene above the table, or
            no free place found.
    """
    from efem_viz.data.scene import Scene

    r = np.asarray(radii, np.float64).reshape(-1)
    rng = np.random.default_rng(seed)
    pts, nrm = np.asarray(scene.points, np.float64), np.asarray(scene.normals, np.float64)
    if centers_xy is None:
        xy = _free_places(pts, r, rng)
    else:
        xy = np.asarray(centers_xy, np.float64).reshape(-1, 2)
    if len(xy) != len(r) or not len(r) or (r <= 0).any():
        raise ValueError(f"need one positive radius per centre, got {len(xy)} centres and radii {r.tolist()}")
    inst = (np.asarray(scene.instance, np.int32) if scene.instance is not None
            else np.zeros(len(pts), np.int32))
    cats = dict(scene.categories or {})
    keep = np.ones(len(pts), bool)
    new_p, new_n, new_i = [], [], []
    next_id = int(inst.max()) + 1 if len(inst) else 1
    for k, (c_xy, rk) in enumerate(zip(xy, r)):
        c = np.r_[c_xy, rk]
        near = np.linalg.norm(pts - c, axis=1) < rk + 0.01
        if (near & (pts[:, 2] > 0.01)).any():
            raise ValueError(f"sphere {k} at {c_xy.tolist()} (r={rk}) overlaps an object of the scene")
        keep &= np.linalg.norm(pts[:, :2] - c_xy, axis=1) > rk * 0.3
        p_k, n_k = sphere_samples(c, float(rk), spacing, rng)
        new_p.append(p_k)
        new_n.append(n_k)
        new_i.append(np.full(len(p_k), next_id + k, np.int32))
        cats[next_id + k] = category
    colors = np.concatenate([np.asarray(scene.colors)[keep],
                             np.full((sum(len(p) for p in new_p), 3), 160, np.uint8)])
    return Scene.create(
        f"{scene.name}+spheres",
        np.concatenate([pts[keep], *new_p]).astype(np.float32),
        normals=np.concatenate([nrm[keep], *new_n]).astype(np.float32),
        colors=colors,
        instance=np.concatenate([inst[keep], *new_i]),
        categories=cats,
        provenance={**dict(scene.provenance or {}), "added_spheres": {"centers_xy": xy.tolist(),
                                                                     "radii": r.tolist(), "seed": seed}},
    )


def _free_places(pts: np.ndarray, radii: np.ndarray, rng: np.random.Generator, *, tries: int = 4000) -> np.ndarray:
    """(S, 2) table positions where spheres of these radii touch no raised point and no other new sphere."""
    from efem_viz._typeshims import cKDTree

    raised = pts[pts[:, 2] > 0.01]
    tree = cKDTree(raised[:, :2]) if len(raised) else None
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    out: list[np.ndarray] = []
    for rk in radii:
        for _ in range(tries):
            c = rng.uniform(lo + rk, hi - rk)
            clear = tree is None or not tree.query_ball_point(c, rk + 0.015)
            if clear and all(np.linalg.norm(c - o) > rk + ro + 0.02 for o, ro in zip(out, radii)):
                out.append(c)
                break
        else:
            raise ValueError(f"no free place on the table for a sphere of radius {rk} m")
    return np.asarray(out).reshape(-1, 2)
