"""Procedural object meshes: a parametric mug family plus simple tabletop distractors.

Every generator is deterministic in its integer seed (`np.random.default_rng(seed)`) and returns a watertight
`trimesh.Trimesh` in metres in the *canonical object frame*: +Z up, centred at the axis-aligned bounding-box
centre. Mugs have their handle (if any) on the +X side.

Mugs are built as
  * a body of revolution (closed (r, z) profile with outer wall, rounded rim, inner wall and a thick bottom,
    revolved about +Z; a real open cup, hollow inside),
  * a handle: an (optionally flattened) tube swept along a planar curve in the XZ half-plane x > 0, whose ends
    are sunk into the wall and clipped by a slightly grown copy of the cavity so they never poke into the cup,
  * a boolean union of both with manifold3d, which makes the result a single watertight solid.

The seed ranges of the train / val / test splits are disjoint (see `split_seeds`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np
import trimesh

from efem_viz.data.chairs import chair_with_parts
from efem_viz.data.solid import finish_solid

logger = logging.getLogger(__name__)

Profile = Literal["straight", "tapered", "barrel", "flared"]
HandleShape = Literal["none", "round", "d", "square", "ear"]
Split = Literal["train", "val", "test"]

PROFILES: tuple[Profile, ...] = ("straight", "tapered", "barrel", "flared")
HANDLE_SHAPES: tuple[HandleShape, ...] = ("none", "round", "d", "square", "ear")

_SPLIT_RANGES: dict[str, range] = {
    "train": range(0, 100_000),
    "val": range(100_000, 101_000),
    "test": range(200_000, 201_000),
}


# ====================================================================================== profile helpers
def _arc(center: tuple[float, float], radius: float, a0: float, a1: float, n: int) -> np.ndarray:
    """(n, 2) points on a circular arc from angle a0 to a1 (radians), endpoints included."""
    a = np.linspace(a0, a1, n)
    return np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)


def _inner_radius(r_out: Callable[[np.ndarray], np.ndarray], z: np.ndarray, wall: float) -> np.ndarray:
    """Inner-wall radius at heights z for a wall of perpendicular thickness `wall` (horizontal offset)."""
    dz = 1e-4
    slope = (r_out(z + dz) - r_out(z - dz)) / (2 * dz)
    return r_out(z) - wall * np.sqrt(1.0 + slope**2)


def _hollow_profile(
    r_out: Callable[[np.ndarray], np.ndarray],
    *,
    height: float,
    wall: float,
    bottom: float,
    foot_radius: float,
    inner_fillet: float,
    n_wall: int = 12,
) -> np.ndarray:
    """Closed (r, z) polyline of an open cup: axis, foot, outer wall, rounded rim, inner wall, floor, axis.

    Returns:
        (P, 2) float64, first and last point on the axis (r = 0); revolving it gives a positive-volume solid.
    """
    z_rim = height - wall / 2.0
    pts: list[np.ndarray] = [np.array([[0.0, 0.0]])]
    # outer foot fillet (quarter circle) then the outer wall
    r0 = float(r_out(np.array([foot_radius]))[0])
    pts.append(_arc((r0 - foot_radius, foot_radius), foot_radius, -np.pi / 2, 0.0, 4))
    z_o = np.linspace(foot_radius, z_rim, n_wall)[1:]
    pts.append(np.stack([r_out(z_o), z_o], axis=1))
    # rounded rim: half circle over the top of the wall
    r_o_top = float(r_out(np.array([z_rim]))[0])
    r_i_top = float(_inner_radius(r_out, np.array([z_rim]), wall)[0])
    rim_c = ((r_o_top + r_i_top) / 2.0, z_rim)
    rim_r = (r_o_top - r_i_top) / 2.0
    pts.append(_arc(rim_c, rim_r, 0.0, np.pi, 7)[1:-1])
    # inner wall down to the inner fillet, then the cavity floor
    z_i = np.linspace(z_rim, bottom + inner_fillet, n_wall)
    pts.append(np.stack([_inner_radius(r_out, z_i, wall), z_i], axis=1))
    r_f = float(_inner_radius(r_out, np.array([bottom + inner_fillet]), wall)[0])
    pts.append(_arc((r_f - inner_fillet, bottom + inner_fillet), inner_fillet, 0.0, -np.pi / 2, 5)[1:])
    pts.append(np.array([[0.0, bottom]]))
    prof = np.concatenate(pts, axis=0)
    if (prof[1:-1, 0] <= 0).any():
        raise ValueError(f"degenerate profile: non-positive radius in {prof[:, 0].min():.4f}")
    return prof


def _revolve(profile: np.ndarray, sections: int) -> trimesh.Trimesh:
    """Revolve a closed (r, z) profile (ends on the axis) about +Z into a watertight mesh."""
    mesh = trimesh.creation.revolve(profile, sections=sections)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


# ====================================================================================== mugs
@dataclass(frozen=True)
class MugParams:
    """Parameters of one procedural mug (all lengths in metres, canonical frame, handle on +X)."""

    profile: Profile
    """Body shape: straight cylinder, tapered (narrower foot), barrel (bulging) or flared (opening top)."""
    radius: float
    """Largest outer radius of the body, 0.03-0.06."""
    height: float
    """Body height, 0.06-0.13."""
    shape_k: float
    """Profile strength: taper / bulge / flare as a fraction of `radius`."""
    wall: float
    """Wall thickness, 0.003-0.008."""
    bottom: float
    """Bottom thickness (cavity floor height), 0.004-0.015."""
    foot_radius: float
    """Fillet radius of the outer foot edge."""
    inner_fillet: float
    """Fillet radius where the inner wall meets the cavity floor."""
    handle: HandleShape
    """Handle shape; "none" for a handle-less cup."""
    handle_span: float = 0.0
    """Vertical distance between the two attachment points (centre line)."""
    handle_center: float = 0.0
    """Height of the middle of the handle above the foot."""
    handle_reach: float = 0.0
    """How far the handle centre line reaches out from the body."""
    handle_radius: float = 0.0
    """Tube half-thickness in the bending plane (XZ)."""
    handle_aspect: float = 1.0
    """Tube half-width across (Y) divided by `handle_radius` (>= 1: flat handles)."""
    handle_skew: float = 0.0
    """Ear handles: how much fuller the top half is than the bottom half."""
    sections: int = 40
    """Angular resolution of the revolved body."""

    def outer_radius(self, z: np.ndarray) -> np.ndarray:
        """Outer radius (metres) at heights z (metres above the foot), shape (K,) -> (K,)."""
        t = np.clip(np.asarray(z, dtype=np.float64) / self.height, 0.0, 1.0)
        r, k = self.radius, self.shape_k
        if self.profile == "straight":
            return np.full_like(t, r)
        if self.profile == "tapered":
            return r * (1.0 - k * (1.0 - t))
        if self.profile == "barrel":
            return r * (1.0 - k * (2.0 * t - 1.0) ** 2)
        if self.profile == "flared":
            return r * (1.0 - k * (1.0 - t) ** 2)
        raise ValueError(f"unknown mug profile {self.profile!r}; expected one of {PROFILES}")


def _handle_curve(p: MugParams, n: int = 36) -> np.ndarray:
    """(n, 2) centre line (u outward from the body surface, v vertical offset from the handle centre)."""
    th = np.linspace(0.0, np.pi, n)
    s, c = np.sin(th), np.cos(th)
    half = p.handle_span / 2.0
    if p.handle == "round":
        u, v = p.handle_reach * s, half * c
    elif p.handle in ("d", "square"):
        e = 2.0 / (3.0 if p.handle == "d" else 5.0)
        u = p.handle_reach * np.abs(s) ** e
        v = half * np.sign(c) * np.abs(c) ** e
        if p.handle == "d":  # D: flatter top going straight out, rounder bottom
            u = u * (1.0 + 0.12 * c) / 1.12
    elif p.handle == "ear":
        u = p.handle_reach * s * (1.0 + p.handle_skew * c) / (1.0 + p.handle_skew)
        v = half * c + 0.15 * half * s**2
    else:
        raise ValueError(f"mug handle {p.handle!r} has no curve")
    return np.stack([u, v], axis=1)


def _min_curvature_radius(curve: np.ndarray) -> float:
    """Smallest radius of curvature of a planar polyline (N, 2) (circumradius of consecutive triples)."""
    a, b, c = curve[:-2], curve[1:-1], curve[2:]
    ab = np.linalg.norm(b - a, axis=1)
    bc = np.linalg.norm(c - b, axis=1)
    ca = np.linalg.norm(a - c, axis=1)
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore"):
        rad = ab * bc * ca / np.maximum(2.0 * cross, 1e-300)
    return float(rad.min())


def _handle_path_xz(p: MugParams) -> np.ndarray:
    """(K, 2) handle centre line in the XZ plane (x radial, z above the foot), both ends sunk in the wall."""
    uv = _handle_curve(p)
    z = p.handle_center + uv[:, 1]
    z_top, z_bot = z[0], z[-1]
    r_top, r_bot = p.outer_radius(np.array([z_top]))[0], p.outer_radius(np.array([z_bot]))[0]
    # body surface under the handle: linear between the attachments, never inside the real surface
    w = (z_top - z) / max(z_top - z_bot, 1e-9)
    x_base = np.maximum((1 - w) * r_top + w * r_bot, p.outer_radius(z))
    x = x_base + uv[:, 0]
    # extend both ends horizontally into the wall (clipped later by the grown cavity)
    deep_top = float(_inner_radius(p.outer_radius, np.array([z_top]), p.wall)[0]) - p.wall
    deep_bot = float(_inner_radius(p.outer_radius, np.array([z_bot]), p.wall)[0]) - p.wall
    head = np.array([[deep_top, z_top], [(deep_top + x[0]) / 2, z_top]])
    tail = np.array([[(deep_bot + x[-1]) / 2, z_bot], [deep_bot, z_bot]])
    return np.concatenate([head, np.stack([x, z], axis=1), tail], axis=0)


def _sweep_tube(path_xz: np.ndarray, *, radius: float, aspect: float, ring: int = 12) -> trimesh.Trimesh:
    """Sweep an ellipse (half-axes `radius` in-plane, `radius * aspect` along Y) along a planar path.

    Args:
        path_xz: (K, 2) centre line in the XZ plane.
        radius: half-axis of the cross-section in the bending (XZ) plane.
        aspect: Y half-axis / `radius`.
        ring: vertices per cross-section.

    Returns:
        Closed (capped) tube mesh with outward normals.
    """
    k = path_xz.shape[0]
    p3 = np.stack([path_xz[:, 0], np.zeros(k), path_xz[:, 1]], axis=1)
    verts = _tube_rings(path_xz, radius=radius, aspect=aspect, ring=ring).reshape(-1, 3)
    faces = []
    for i in range(k - 1):
        for j in range(ring):
            a0, a1 = i * ring + j, i * ring + (j + 1) % ring
            b0, b1 = a0 + ring, a1 + ring
            faces.append([a0, b0, a1])
            faces.append([a1, b0, b1])
    c0, c1 = len(verts), len(verts) + 1
    verts = np.concatenate([verts, p3[:1], p3[-1:]], axis=0)
    for j in range(ring):
        faces.append([c0, j, (j + 1) % ring])
        last = (k - 1) * ring
        faces.append([c1, last + (j + 1) % ring, last + j])
    mesh = trimesh.Trimesh(vertices=verts, faces=np.asarray(faces, np.int64), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _handle_ok(p: MugParams) -> bool:
    """True when the handle tube can be swept without self-intersection and stays clear of rim and foot."""
    uv = _handle_curve(p)
    if _min_curvature_radius(uv) < 1.3 * p.handle_radius:
        return False
    top = p.handle_center + p.handle_span / 2 + p.handle_radius * max(p.handle_aspect, 1.0)
    bot = p.handle_center - p.handle_span / 2 - p.handle_radius * max(p.handle_aspect, 1.0)
    # the gap inside the handle must be open (finger room)
    inner_gap = p.handle_reach - 2 * p.handle_radius
    return top <= p.height - p.wall - 0.004 and bot >= 0.08 * p.height and inner_gap >= 0.006


def sample_mug_params(seed: int) -> MugParams:
    """Draw the parameters of mug `seed` (deterministic).

    About 15% of the mugs have no handle; the rest use round, D-shaped, square or ear handles.

    Args:
        seed: any non-negative integer (see `split_seeds` for the split ranges).

    Returns:
        A frozen `MugParams`.
    """
    rng = np.random.default_rng([int(seed), 0x4D7547])
    profile: Profile = PROFILES[int(rng.choice(4, p=[0.35, 0.3, 0.15, 0.2]))]
    for _ in range(100):
        radius = float(rng.uniform(0.03, 0.06))
        height = float(rng.uniform(0.06, 0.13))
        if 0.5 <= height / (2 * radius) <= 1.9:
            break
    shape_k = {
        "straight": 0.0,
        "tapered": float(rng.uniform(0.08, 0.3)),
        "barrel": float(rng.uniform(0.05, 0.14)),
        "flared": float(rng.uniform(0.12, 0.3)),
    }[profile]
    wall = float(rng.uniform(0.003, 0.008))
    bottom = float(rng.uniform(max(0.004, wall), 0.015))
    foot_radius = float(rng.uniform(0.001, 0.004))
    r_min_inner = radius * (1 - shape_k) - wall * 1.2
    inner_fillet = float(min(rng.uniform(0.003, 0.012), 0.4 * r_min_inner, 0.4 * height))
    base = dict(
        profile=profile,
        radius=radius,
        height=height,
        shape_k=shape_k,
        wall=wall,
        bottom=bottom,
        foot_radius=foot_radius,
        inner_fillet=inner_fillet,
    )
    if rng.uniform() < 0.15:
        return MugParams(handle="none", **base)  # type: ignore[arg-type]
    handle: HandleShape = HANDLE_SHAPES[1 + int(rng.integers(4))]
    cand: MugParams | None = None
    for attempt in range(200):
        relax = 1.0 - 0.3 * min(attempt / 100, 1.0)  # thinner handles when nothing fits
        hr = float(rng.uniform(0.003, 0.007) * relax)
        span = float(rng.uniform(0.45, 0.8) * height)
        reach = float(rng.uniform(0.35, 0.75) * span)
        reach = float(np.clip(reach, 2 * hr + 0.008, 0.045))
        free = height - span
        center = float(height / 2 + rng.uniform(-0.25, 0.25) * free)
        cand = MugParams(
            handle=handle,
            handle_span=span,
            handle_center=center,
            handle_reach=reach,
            handle_radius=hr,
            handle_aspect=float(rng.uniform(1.0, 1.8)),
            handle_skew=float(rng.uniform(0.2, 0.6)) if handle == "ear" else 0.0,
            **base,  # type: ignore[arg-type]
        )
        if _handle_ok(cand):
            return cand
    # give up on this handle shape: a round, thin, centred handle always fits
    assert cand is not None
    fallback = dataclasses.replace(
        cand,
        handle="round",
        handle_span=0.5 * height,
        handle_center=0.5 * height,
        handle_reach=0.5 * 0.5 * height,
        handle_radius=0.003,
        handle_aspect=1.0,
        handle_skew=0.0,
    )
    if not _handle_ok(fallback):
        fallback = dataclasses.replace(fallback, handle="none")
    return fallback


def _mug_body(p: MugParams) -> trimesh.Trimesh:
    prof = _hollow_profile(
        p.outer_radius,
        height=p.height,
        wall=p.wall,
        bottom=p.bottom,
        foot_radius=p.foot_radius,
        inner_fillet=p.inner_fillet,
    )
    return _revolve(prof, p.sections)


def _grown_cavity(p: MugParams, grow: float) -> trimesh.Trimesh:
    """Solid of revolution: the cavity grown by `grow` (metres) into the wall, reaching above the rim."""
    z = np.linspace(p.bottom - grow, p.height + 0.02, 16)
    r = _inner_radius(p.outer_radius, np.minimum(z, p.height), p.wall) + grow
    prof = np.concatenate([[[0.0, z[0]]], np.stack([r, z], axis=1), [[0.0, z[-1]]]], axis=0)
    return _revolve(prof, p.sections)


def _wall_parts(
    r_out: Callable[[np.ndarray], np.ndarray],
    *,
    z0: float,
    z1: float,
    wall: float,
    sectors: int = 12,
    bands: int = 3,
    inset: float = 0.0005,
) -> list[np.ndarray]:
    """Convex pieces (angular sector x height band) covering a revolved wall between heights z0 and z1.

    The wall ends in the rounded rim of `_hollow_profile` (centre at z1 - wall / 2): the top band stops there
    and adds the rim's top points. Each piece is the point set of outer and inner wall samples at three
    angles of its sector; its convex hull lies inside the wall up to the chord sagitta (towards the cavity).

    Returns:
        A list of (K, 3) float64 point sets.
    """
    parts: list[np.ndarray] = []
    z_top = z1 - wall / 2.0
    z_edges = np.linspace(z0, z_top, bands + 1)
    for b in range(bands):
        z = np.linspace(z_edges[b], z_edges[b + 1], 4)
        # inset from both wall surfaces: the mesh is a polygonal approximation of the curved profile
        ro, ri = r_out(z) - inset, _inner_radius(r_out, z, wall) + inset
        rings = [(ro, z), (ri, z)]
        if b == bands - 1:
            rings.append((np.array([(ro[-1] + ri[-1]) / 2.0]), np.array([z1])))
        for s in range(sectors):
            a = np.linspace(2 * np.pi * s / sectors, 2 * np.pi * (s + 1) / sectors, 3)
            ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
            pts = [
                np.stack([r[None, :] * ca, r[None, :] * sa, np.broadcast_to(zz, (3, len(zz)))], -1)
                .reshape(-1, 3)
                for r, zz in rings
            ]
            parts.append(np.concatenate(pts, axis=0))
    return parts


def _disk_part(
    r_out: Callable[[np.ndarray], np.ndarray], *, z0: float, z1: float, foot_radius: float = 0.0, n: int = 24
) -> np.ndarray:
    """(2n, 3) points of a convex disk (solid base) between heights z0 and z1, inset by the foot fillet."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    out = []
    for z, inset in ((z0, foot_radius), (z1, 0.0)):
        r = float(r_out(np.array([z]))[0]) - inset
        out.append(np.stack([r * np.cos(a), r * np.sin(a), np.full(n, z)], axis=1))
    return np.concatenate(out, axis=0)


def _build_mug(p: MugParams) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """Mesh and convex collision pieces of a mug, both in the frame with the foot centre at the origin."""
    body = _mug_body(p)
    parts = _wall_parts(p.outer_radius, z0=max(p.bottom * 0.5, p.foot_radius), z1=p.height, wall=p.wall)
    parts.append(_disk_part(p.outer_radius, z0=0.0, z1=p.bottom, foot_radius=p.foot_radius))
    if p.handle == "none":
        return body, parts
    path = _handle_path_xz(p)
    tube = _sweep_tube(path, radius=p.handle_radius, aspect=p.handle_aspect)
    cavity = _grown_cavity(p, grow=0.3 * p.wall)
    handle = trimesh.boolean.difference([tube, cavity], engine="manifold")
    mesh = trimesh.boolean.union([body, handle], engine="manifold")
    # handle pieces: hulls of consecutive tube rings along the visible part of the centre line
    curve = path[2:-2]
    rings = _tube_rings(curve, radius=p.handle_radius, aspect=p.handle_aspect)
    step = 4
    for i in range(0, len(curve) - 1, step):
        parts.append(rings[i : min(i + step, len(curve) - 1) + 1].reshape(-1, 3))
    return mesh, parts


def _tube_rings(path_xz: np.ndarray, *, radius: float, aspect: float, ring: int = 12) -> np.ndarray:
    """(K, ring, 3) cross-section vertices of the tube swept along `path_xz` (see `_sweep_tube`)."""
    k = path_xz.shape[0]
    p3 = np.stack([path_xz[:, 0], np.zeros(k), path_xz[:, 1]], axis=1)
    tang = np.gradient(p3, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    y = np.array([0.0, 1.0, 0.0])
    nrm = np.cross(tang, y)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    a = np.linspace(0.0, 2 * np.pi, ring, endpoint=False)
    offs = (radius * np.cos(a))[None, :, None] * nrm[:, None, :] + (radius * aspect * np.sin(a))[
        None, :, None
    ] * y[None, None, :]
    return p3[:, None, :] + offs


def make_mug(seed: int, params: MugParams | None = None) -> trimesh.Trimesh:
    """Build procedural mug `seed` (or the mug described by `params`).

    Args:
        seed: mug seed (used only when `params` is None).
        params: explicit parameters, e.g. from `sample_mug_params` with a field replaced.

    Returns:
        Watertight mesh (about 3-4k faces), metres, canonical frame (+Z up, bbox centre at the origin,
        handle towards +X).

    Raises:
        RuntimeError: if the boolean union does not give a watertight solid (should not happen).
    """
    return make_mug_with_parts(seed, params)[0]


def make_mug_with_parts(
    seed: int, params: MugParams | None = None
) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """`make_mug` plus a convex decomposition for physics: list of (K, 3) point sets, canonical frame."""
    p = sample_mug_params(seed) if params is None else params
    mesh, parts = _build_mug(p)
    return finish_solid(mesh, parts, f"mug {seed} ({p.profile}, handle {p.handle})")


def handle_hole(mesh: trimesh.Trimesh, *, grid: int = 48) -> tuple[np.ndarray, float] | None:
    """The opening of a mug's handle: the point of the handle plane (y = 0, canonical frame, handle on +X)
    farthest from the surface among those enclosed by the handle and the body, where a line along Y passes
    freely (what a peg through the handle needs).

    Args:
        mesh: a canonical mug mesh (`make_mug`).
        grid: candidate points per side of the handle region.

    Returns:
        (centre (3,), clearance): the hole's centre and its distance to the nearest surface (metres), or None
        when the mug has no handle opening.
    """
    import open3d as o3d

    from efem_viz._typeshims import o3d_tensor

    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    # the handle region: the +X part beyond the body's axis, over the whole height
    xs = np.linspace(0.0, hi[0], grid)
    zs = np.linspace(lo[2], hi[2], grid)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    cand = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1).astype(np.float32)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d_tensor(np.asarray(v, np.float32)), o3d_tensor(np.asarray(mesh.faces, np.uint32)))
    dist = rc.compute_distance(o3d_tensor(cand)).numpy()
    inside = rc.compute_occupancy(o3d_tensor(cand)).numpy() > 0
    reach = float(np.linalg.norm(hi - lo))

    def hits(direction: tuple[float, float, float]) -> np.ndarray:
        rays = np.concatenate([cand, np.broadcast_to(np.asarray(direction, np.float32), cand.shape)], axis=1)
        return rc.cast_rays(o3d_tensor(np.ascontiguousarray(rays)))["t_hit"].numpy() < reach

    enclosed = hits((1, 0, 0)) & hits((-1, 0, 0)) & hits((0, 0, 1)) & hits((0, 0, -1))
    through = ~hits((0, 1, 0)) & ~hits((0, -1, 0))
    ok = enclosed & through & ~inside
    if not ok.any():
        return None
    best = int(np.argmax(np.where(ok, dist, -1.0)))
    return cand[best].astype(np.float64), float(dist[best])


# ====================================================================================== distractors
def _hull_parts(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    return [np.asarray(mesh.vertices, np.float64).copy()]


def box_with_parts(seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """A box (cereal / tea box) with sides 3-15 cm; convex (one collision piece)."""
    rng = np.random.default_rng([int(seed), 0x426F78])
    ext = np.array([rng.uniform(0.04, 0.15), rng.uniform(0.03, 0.09), rng.uniform(0.03, 0.15)])
    mesh = trimesh.creation.box(extents=ext)
    return finish_solid(mesh, _hull_parts(mesh), f"box {seed}")


def can_with_parts(seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """A closed cylinder (can / jar), radius 2.5-4.5 cm, height 6-15 cm; convex."""
    rng = np.random.default_rng([int(seed), 0x43616E])
    r, h = rng.uniform(0.025, 0.045), rng.uniform(0.06, 0.15)
    bevel = min(0.003, r / 5)
    prof = np.array(
        [[0.0, 0.0], [r - bevel, 0.0], [r, bevel], [r, h - bevel], [r - bevel, h], [0.0, h]], dtype=np.float64
    )
    mesh = _revolve(prof, 40)
    return finish_solid(mesh, _hull_parts(mesh), f"can {seed}")


def bowl_with_parts(seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """An open bowl, rim radius 6-10 cm, height 4-8 cm, curved wall; wall decomposed into sectors."""
    rng = np.random.default_rng([int(seed), 0x426F776C])
    rim, h = rng.uniform(0.06, 0.10), rng.uniform(0.04, 0.08)
    foot = rng.uniform(0.35, 0.55) * rim
    expo = rng.uniform(0.5, 0.8)
    wall = rng.uniform(0.003, 0.006)

    def r_out(z: np.ndarray) -> np.ndarray:
        # t**expo has an infinite slope at t = 0: start the curve slightly above the foot
        t = np.clip(np.asarray(z, np.float64) / h, 0.01, 1.0)
        return foot + (rim - foot) * t**expo

    bottom = wall * 1.5
    prof = _hollow_profile(
        r_out, height=h, wall=wall, bottom=bottom, foot_radius=0.002, inner_fillet=0.004, n_wall=22
    )
    mesh = _revolve(prof, 40)
    parts = _wall_parts(r_out, z0=max(bottom * 0.5, 0.002), z1=h, wall=wall, sectors=16, bands=4)
    parts.append(_disk_part(r_out, z0=0.0, z1=bottom, foot_radius=0.002))
    return finish_solid(mesh, parts, f"bowl {seed}")


def bottle_with_parts(seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """A closed bottle: cylinder body, rounded shoulder, neck; radius 3-4.5 cm, height 15-26 cm."""
    rng = np.random.default_rng([int(seed), 0x426F74])
    r, h = rng.uniform(0.03, 0.045), rng.uniform(0.15, 0.26)
    neck_r = rng.uniform(0.011, 0.016)
    body_h = rng.uniform(0.5, 0.65) * h
    shoulder_h = rng.uniform(0.12, 0.22) * h
    t = np.linspace(0.0, 1.0, 10)
    shoulder = np.stack(
        [neck_r + (r - neck_r) * np.cos(t * np.pi / 2), body_h + shoulder_h * np.sin(t * np.pi / 2)], axis=1
    )
    prof = np.concatenate(
        [
            [[0.0, 0.0], [r - 0.003, 0.0], [r, 0.003]],
            shoulder,
            [[neck_r, h - 0.002], [neck_r - 0.002, h], [0.0, h]],
        ]
    )
    mesh = _revolve(prof, 40)
    body = prof[prof[:, 1] <= body_h + shoulder_h + 1e-9]
    neck = prof[prof[:, 1] >= body_h + shoulder_h - 1e-9]
    a = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    parts = [
        np.concatenate([np.stack([rr * np.cos(a), rr * np.sin(a), np.full(24, zz)], 1) for rr, zz in q])
        for q in (body, neck)
    ]
    return finish_solid(mesh, parts, f"bottle {seed}")


def cabinet_with_parts(seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """A furniture-sized block (a cabinet, chest of drawers or low table), 40-100 cm wide, 30-60 cm deep and
    35-90 cm high; convex (one collision piece). The distractors of chair scenes."""
    rng = np.random.default_rng([int(seed), 0x436162696E6574])
    ext = np.array([rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.6), rng.uniform(0.35, 0.9)])
    mesh = trimesh.creation.box(extents=ext)
    return finish_solid(mesh, _hull_parts(mesh), f"cabinet {seed}")


def make_box(seed: int) -> trimesh.Trimesh:
    """A box with sides 3-15 cm, canonical frame, watertight."""
    return box_with_parts(seed)[0]


def make_can(seed: int) -> trimesh.Trimesh:
    """A closed cylinder, radius 2.5-4.5 cm, height 6-15 cm, canonical frame, watertight."""
    return can_with_parts(seed)[0]


def make_bowl(seed: int) -> trimesh.Trimesh:
    """An open bowl, rim radius 6-10 cm, height 4-8 cm, canonical frame, watertight."""
    return bowl_with_parts(seed)[0]


def make_bottle(seed: int) -> trimesh.Trimesh:
    """A closed bottle, 15-26 cm tall, canonical frame, watertight."""
    return bottle_with_parts(seed)[0]


# ====================================================================================== registry
@dataclass(frozen=True)
class CategorySpec:
    """A procedural object category."""

    name: str
    """Category name (also the label name in scenes)."""
    build: Callable[[int], tuple[trimesh.Trimesh, list[np.ndarray]]]
    """seed -> (watertight mesh, convex collision pieces as (K, 3) point sets), canonical frame, metres."""
    size_range: tuple[float, float]
    """Approximate (min, max) longest bounding-box side, metres."""
    target: bool = False
    """True for the categories that scenes label as objects (ground truth); False for distractors."""
    description: str = ""

    def generator(self, seed: int) -> trimesh.Trimesh:
        """seed -> watertight mesh in the canonical frame (metres)."""
        return self.build(int(seed))[0]


CATEGORIES: dict[str, CategorySpec] = {
    "mug": CategorySpec(
        "mug", make_mug_with_parts, (0.06, 0.20), target=True, description="cups and mugs, ~85% with a handle"
    ),
    "box": CategorySpec("box", box_with_parts, (0.04, 0.15), description="rectangular boxes"),
    "can": CategorySpec("can", can_with_parts, (0.06, 0.15), description="closed cylinders (cans, jars)"),
    "bowl": CategorySpec("bowl", bowl_with_parts, (0.12, 0.20), description="open bowls"),
    "bottle": CategorySpec("bottle", bottle_with_parts, (0.15, 0.26), description="closed bottles"),
    "cabinet": CategorySpec("cabinet", cabinet_with_parts, (0.40, 1.00),
                            description="furniture-sized blocks (cabinets, low tables): chair scenes' distractors"),
    "chair": CategorySpec("chair", chair_with_parts, (0.40, 1.10), target=True,
                          description="four-legged chairs, stools, sled, cantilever and swivel chairs; solid, "
                                      "slatted and curved backs; with and without arms (efem_viz.data.chairs)"),
}


def make_shape(category: str, seed: int) -> trimesh.Trimesh:
    """Generate object `seed` of a registered category.

    Args:
        category: a key of `CATEGORIES` ("mug", "box", "can", "bowl", "bottle", "cabinet", "chair").
        seed: non-negative integer.

    Returns:
        Watertight mesh, metres, canonical frame (+Z up, bounding-box centre at the origin).

    Raises:
        ValueError: unknown category.
    """
    if category not in CATEGORIES:
        raise ValueError(f"unknown category {category!r}; known: {sorted(CATEGORIES)}")
    return CATEGORIES[category].build(int(seed))[0]


def make_shape_with_parts(category: str, seed: int) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """`make_shape` plus a convex decomposition for physics simulation.

    Returns:
        (mesh, parts): the watertight mesh and a list of (K, 3) float64 point sets in the same canonical frame
        whose convex hulls approximate the solid from inside (concave mugs and bowls: wall sectors, base disk,
        handle segments; convex shapes: one piece).

    Raises:
        ValueError: unknown category.
    """
    if category not in CATEGORIES:
        raise ValueError(f"unknown category {category!r}; known: {sorted(CATEGORIES)}")
    return CATEGORIES[category].build(int(seed))


FAMILIES: dict[str, tuple[str, ...]] = {"kitchen": ("mug", "bowl", "bottle", "can")}
"""Training families: one prior over several categories, named by family (the paper's kitchen prior covers mugs,
bowls, bottles and cans). A category is a family of itself."""


def family_members(name: str) -> tuple[str, ...]:
    """The categories of a training family (`FAMILIES`), or `(name,)` for a single category.

    Raises:
        ValueError: neither a family nor a registered category.
    """
    if name in FAMILIES:
        return FAMILIES[name]
    if name not in CATEGORIES:
        raise ValueError(f"unknown category {name!r}; known: {sorted(CATEGORIES)}, families: {sorted(FAMILIES)}")
    return (name,)


def variant_of(name: str) -> str:
    """The variant a procedural training object stands for, from its name ``<category>_<seed>``: its category (a
    family's member: mug, bowl, bottle, can), or for a chair its base (four_legs, stool, sled, cantilever,
    swivel; `efem_viz.data.chairs.sample_chair_params`). Any other name is its own variant."""
    category, sep, seed = name.rpartition("_")
    if not sep or not category:
        return name
    if category == "chair" and seed.isdigit():
        from efem_viz.data.chairs import sample_chair_params

        return sample_chair_params(int(seed)).base
    return category


def family_seeds(name: str, split: Split, n: int) -> list[tuple[str, int]]:
    """The first `n` objects of a family's split as (category, seed): object i is member i mod k (k members)
    with that member's seed number i div k, so every prefix is balanced over the members.

    Raises:
        ValueError: unknown family/category or split, or more objects than the split holds.
    """
    members = family_members(name)
    seeds = split_seeds(members[0], split)
    k = len(members)
    if n < 0 or (n + k - 1) // k > len(seeds):
        raise ValueError(f"split {split!r} of {name!r} has {len(seeds) * k} objects, asked for {n}")
    return [(members[i % k], seeds[i // k]) for i in range(n)]


def split_seeds(category: str, split: Split) -> range:
    """Seeds of a data split; the train, val and test ranges are disjoint (the same for every category).

    Args:
        category: a key of `CATEGORIES`.
        split: "train" (0..99 999), "val" (100 000..100 999) or "test" (200 000..200 999).

    Returns:
        A `range` of seeds.

    Raises:
        ValueError: unknown category or split.
    """
    if category not in CATEGORIES:
        raise ValueError(f"unknown category {category!r}; known: {sorted(CATEGORIES)}")
    if split not in _SPLIT_RANGES:
        raise ValueError(f"unknown split {split!r}; expected one of {sorted(_SPLIT_RANGES)}")
    return _SPLIT_RANGES[split]
