"""A parametric chair family: four-legged chairs, stools, sled and cantilever frames, swivel chairs on a star foot;
solid, slatted and curved backs; with and without arms.

Every chair is a union (manifold3d) of convex primitives — boxes, round tubes with ball joints, balls for casters —
so the result is one watertight solid and the primitives themselves are its convex collision pieces. Deterministic
in the integer seed; metres; the canonical frame of `efem_viz.data.procedural`: +Z up, bounding-box centre at the
origin, the seat's front toward -Y (the back at +Y).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

from efem_viz.data.solid import finish_solid

Base = Literal["four_legs", "stool", "sled", "cantilever", "swivel"]
Back = Literal["solid", "slatted", "curved", "none"]

BASES: tuple[Base, ...] = ("four_legs", "stool", "sled", "cantilever", "swivel")
BACKS: tuple[Back, ...] = ("solid", "slatted", "curved", "none")


@dataclass(frozen=True)
class ChairParams:
    """Parameters of one procedural chair (metres; seat front toward -Y)."""

    base: Base
    back: Back
    arms: bool
    seat_height: float
    """Top of the seat above the floor."""
    seat_width: float
    seat_depth: float
    seat_thickness: float
    back_height: float
    """Height of the back above the seat."""
    back_tilt: float
    """Backward tilt of the back (radians)."""
    back_thickness: float
    leg: float
    """Leg / tube radius (round) or half-width (square legs)."""
    square_legs: bool
    slats: int
    """Vertical slats of a slatted back."""


def sample_chair_params(seed: int) -> ChairParams:
    """The parameters of chair `seed` (the variant mix: about a third four-legged, the rest stools, sleds,
    cantilevers and swivel chairs; stools have no back, swivel chairs no slatted back)."""
    rng = np.random.default_rng([int(seed), 0x4368616972])
    base: Base = BASES[int(rng.choice(len(BASES), p=[0.34, 0.14, 0.16, 0.16, 0.20]))]
    back: Back = "none" if base == "stool" else BACKS[int(rng.choice(3, p=[0.4, 0.3, 0.3]))]
    if base == "swivel" and back == "slatted":
        back = "solid"
    stool_high = base == "stool" and rng.uniform() < 0.4
    return ChairParams(
        base=base, back=back,
        arms=bool(base in ("four_legs", "swivel", "sled") and back != "none" and rng.uniform() < 0.35),
        seat_height=float(rng.uniform(0.62, 0.78) if stool_high else rng.uniform(0.40, 0.50)),
        seat_width=float(rng.uniform(0.32, 0.40) if base == "stool" else rng.uniform(0.40, 0.56)),
        seat_depth=float(rng.uniform(0.32, 0.40) if base == "stool" else rng.uniform(0.38, 0.50)),
        seat_thickness=float(rng.uniform(0.02, 0.07)),
        back_height=float(rng.uniform(0.30, 0.55)),
        back_tilt=float(np.radians(rng.uniform(0.0, 15.0))),
        back_thickness=float(rng.uniform(0.02, 0.045)),
        leg=float(rng.uniform(0.011, 0.022)),
        square_legs=bool(base in ("four_legs", "stool") and rng.uniform() < 0.5),
        slats=int(rng.integers(3, 7)),
    )


# ------------------------------------------------------------------------------------------- primitives
def _box(lo: np.ndarray | list[float], hi: np.ndarray | list[float]) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    box = trimesh.creation.box(extents=hi - lo)
    box.apply_translation((lo + hi) / 2)
    return box


def _tube(a: np.ndarray | list[float], b: np.ndarray | list[float], r: float) -> list[trimesh.Trimesh]:
    """A round tube from a to b with a ball at each end (so joined tubes bend smoothly)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    out = [trimesh.creation.cylinder(radius=r, segment=np.stack([a, b]), sections=16)]
    for p in (a, b):
        ball = trimesh.creation.icosphere(subdivisions=1, radius=r)
        ball.apply_translation(p)
        out.append(ball)
    return out


def _leg(x: float, y: float, z0: float, z1: float, p: ChairParams) -> list[trimesh.Trimesh]:
    if p.square_legs:
        return [_box([x - p.leg, y - p.leg, z0], [x + p.leg, y + p.leg, z1])]
    return [trimesh.creation.cylinder(radius=p.leg, segment=np.array([[x, y, z0], [x, y, z1]]), sections=16)]


def _rotate_about_x(mesh: trimesh.Trimesh, angle: float, pivot: np.ndarray) -> trimesh.Trimesh:
    mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, [1.0, 0.0, 0.0], pivot))
    return mesh


# ------------------------------------------------------------------------------------------- parts
def _seat(p: ChairParams) -> list[trimesh.Trimesh]:
    w, d, h, t = p.seat_width, p.seat_depth, p.seat_height, p.seat_thickness
    return [_box([-w / 2, -d / 2, h - t], [w / 2, d / 2, h])]


def _base(p: ChairParams) -> list[trimesh.Trimesh]:
    w, d, h, t, r = p.seat_width, p.seat_depth, p.seat_height, p.seat_thickness, p.leg
    under = h - t + 0.002  # parts reach a little into the seat so that the union is one solid
    ix, iy = w / 2 - 1.5 * r, d / 2 - 1.5 * r
    if p.base in ("four_legs", "stool"):
        out = [m for sx in (-1, 1) for sy in (-1, 1) for m in _leg(sx * ix, sy * iy, 0.0, under, p)]
        if p.base == "stool" or p.seat_height > 0.6:  # a foot ring of rails
            zr = 0.35 * h
            out += [_box([-ix, sy * iy - r * 0.6, zr - r * 0.6], [ix, sy * iy + r * 0.6, zr + r * 0.6])
                    for sy in (-1, 1)]
        return out
    if p.base == "sled":  # a closed loop per side: floor runner, two uprights, a bar under the seat
        out = []
        for sx in (-1, 1):
            x = sx * ix
            f, b = [x, -iy, r], [x, iy, r]
            ft, bt = [x, -iy, under], [x, iy, under]
            out += _tube(f, b, r) + _tube(f, ft, r) + _tube(b, bt, r)
        return out
    if p.base == "cantilever":  # per side: floor bar, an upright at the front, the seat support back to the rear
        out = []
        for sx in (-1, 1):
            x = sx * ix
            rear, front = [x, iy + 0.04, r], [x, -iy, r]
            top_front, top_rear = [x, -iy, under], [x, iy, under]
            out += _tube(rear, front, r) + _tube(front, top_front, r) + _tube(top_front, top_rear, r)
        return out
    # swivel: a gas column on a five-armed star foot with casters
    col_r = max(0.022, 1.4 * r)
    foot_z = 0.07
    out = [trimesh.creation.cylinder(radius=col_r, segment=np.array([[0, 0, foot_z], [0, 0, under]]), sections=20)]
    arm = 0.26 + 0.2 * (p.seat_width - 0.40)
    for k in range(5):
        a = 2 * np.pi * k / 5 + np.pi / 10
        tip = np.array([arm * np.cos(a), arm * np.sin(a), foot_z])
        out += _tube([0.0, 0.0, foot_z], tip, 0.018)
        caster = trimesh.creation.icosphere(subdivisions=2, radius=0.025)
        caster.apply_translation(tip + [0.0, 0.0, -0.045])
        out += [caster] + _tube(tip, tip + [0.0, 0.0, -0.03], 0.008)
    return out


def _back(p: ChairParams) -> list[trimesh.Trimesh]:
    if p.back == "none":
        return []
    w, d, h, bt, bh = p.seat_width, p.seat_depth, p.seat_height, p.back_thickness, p.back_height
    y0 = d / 2 - bt  # the back stands on the seat's rear edge
    base_z = h - p.seat_thickness / 2
    pivot = np.array([0.0, d / 2, base_z])
    parts: list[trimesh.Trimesh] = []
    if p.back == "solid":
        parts = [_box([-w / 2, y0, base_z], [w / 2, d / 2, h + bh])]
    elif p.back == "slatted":
        post = max(p.leg, 0.015)
        rail = 0.05
        parts = [_box([sx * w / 2 - (2 * post if sx > 0 else 0), y0, base_z], [sx * w / 2 + (0 if sx > 0 else 2 * post),
                      d / 2, h + bh]) for sx in (-1, 1)]
        parts.append(_box([-w / 2, y0, h + bh - rail], [w / 2, d / 2, h + bh]))
        xs = np.linspace(-w / 2 + 2 * post, w / 2 - 2 * post, p.slats + 2)[1:-1]
        sw = min(0.03, (w - 4 * post) / (2 * p.slats + 1))
        parts += [_box([x - sw / 2, y0 + 0.25 * bt, h - 0.005], [x + sw / 2, d / 2 - 0.25 * bt, h + bh - rail + 0.005])
                  for x in xs]
    else:  # curved: panels along an arc that wraps around the sitter
        n = 9
        radius = max(w * 0.75, 0.35)
        half = np.arcsin(min(0.99, (w / 2) / radius))
        for a in np.linspace(-half, half, n):
            panel = _box([-w / (n - 1) * 0.62, -bt / 2, 0.0], [w / (n - 1) * 0.62, bt / 2, bh + p.seat_thickness / 2])
            panel.apply_transform(trimesh.transformations.rotation_matrix(-a, [0.0, 0.0, 1.0]))
            cx, cy = radius * np.sin(a), d / 2 - bt / 2 - radius * (1 - np.cos(a))
            panel.apply_translation([cx, cy, base_z])
            parts.append(panel)
    return [_rotate_about_x(m, -p.back_tilt, pivot) for m in parts]


def _arms(p: ChairParams) -> list[trimesh.Trimesh]:
    if not p.arms:
        return []
    w, d, h = p.seat_width, p.seat_depth, p.seat_height
    z = h + 0.20
    r = max(p.leg, 0.015)
    out = []
    for sx in (-1, 1):
        x = sx * (w / 2 - r)
        out.append(_box([x - 0.025, -d / 2 + 0.03, z - 0.02], [x + 0.025, d / 2 - 0.01, z]))
        out += _tube([x, -d / 2 + 0.06, h - 0.01], [x, -d / 2 + 0.06, z - 0.01], r)
    return out


def chair_with_parts(seed: int, params: ChairParams | None = None) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """Chair `seed` (or `params`): the watertight mesh and its convex pieces, canonical frame.

    Raises:
        RuntimeError: the union is not a watertight solid (should not happen).
    """
    p = sample_chair_params(seed) if params is None else params
    prims = _seat(p) + _base(p) + _back(p) + _arms(p)
    mesh = trimesh.boolean.union(prims, engine="manifold")
    return finish_solid(mesh, [np.asarray(m.vertices, np.float64).copy() for m in prims], f"chair {seed}")


def make_chair(seed: int, params: ChairParams | None = None) -> trimesh.Trimesh:
    """A watertight procedural chair, metres, canonical frame (+Z up, bbox centre at the origin, front -Y)."""
    return chair_with_parts(seed, params)[0]
