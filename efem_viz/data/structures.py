"""Supporting structures of the paper's arrangement scenes (`efem_viz.data.synth`): a mug tree, an open box and
a shelf, standing on the table (top face at z = 0, world frame, metres, +Z up).

Every structure is a list of convex pieces (cylinders and boxes), which serve both as render geometry and as
pybullet collision pieces; its points are labelled 0 (background) like the table. Each kind carries what the
placement of the objects needs: the tree its pegs, the box its inner floor and wall height, the shelf its
levels and the direction it opens to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    import trimesh

StructureKind = Literal["tree", "box", "shelf"]

PEG_RADIUS = 0.004
"""Radius of a mug tree's pegs (m); a mug hangs on one when its handle opening clears PEG_RADIUS + PEG_PLAY."""
PEG_PLAY = 0.002
"""Clearance beyond the peg radius a handle opening needs (m)."""

_WOOD = np.array([168.0, 124.0, 84.0])
_CARDBOARD = np.array([196.0, 160.0, 110.0])
_SHELF_WHITE = np.array([222.0, 218.0, 206.0])


@dataclass(frozen=True)
class Peg:
    """One peg of a mug tree: a cylinder from `root` (on the post) along the unit `direction`."""

    root: np.ndarray
    direction: np.ndarray
    length: float

    def point(self, s: float) -> np.ndarray:
        """The point at fraction `s` of the peg's length."""
        return self.root + s * self.length * self.direction


@dataclass(frozen=True)
class Level:
    """One shelf level: the board's top face at height `z`, usable rectangle [lo, hi] in the shelf's own xy
    (x across, y towards the open front; `level_to_world` turns it into the world frame)."""

    z: float
    lo: np.ndarray
    hi: np.ndarray


@dataclass
class Structure:
    """A supporting structure: convex pieces in the world frame, their colour, and placement data.

    Attributes:
        kind: "tree", "box" or "shelf".
        specs: the convex pieces as JSON-ready primitives (`piece_mesh`): {"box": [lo, hi], "T": 4x4} or
            {"cylinder": [a, b], "radius": r, "sections": n} (world frame).
        color: RGB albedo (0-255).
        pegs: the tree's pegs.
        floor: the box's inner floor [lo, hi] in xy (its bottom is the table top).
        wall_height: the box's wall height (m).
        levels: the shelf's levels, bottom first.
        front: unit xy direction the shelf opens to (where its cameras stand); the tree and box: zeros.
    """

    kind: StructureKind
    specs: list[dict[str, object]]
    color: np.ndarray
    pegs: list[Peg] = field(default_factory=list)
    floor: tuple[np.ndarray, np.ndarray] | None = None
    wall_height: float = 0.0
    levels: list[Level] = field(default_factory=list)
    front: np.ndarray = field(default_factory=lambda: np.zeros(2))

    @cached_property
    def pieces(self) -> list["trimesh.Trimesh"]:
        """The convex pieces as watertight meshes (world frame; built once)."""
        return [piece_mesh(sp) for sp in self.specs]

    def parts(self) -> list[np.ndarray]:
        """Convex collision pieces: each piece's vertices (world frame)."""
        return [np.asarray(p.vertices, np.float64) for p in self.pieces]

    def describe(self) -> dict[str, object]:
        """JSON-ready summary for a scene's provenance."""
        out: dict[str, object] = {"kind": self.kind, "pieces": self.specs,
                                  "color": [int(c) for c in self.color]}
        if self.pegs:
            out["pegs"] = [{"root": np.round(p.root, 4).tolist(), "direction": np.round(p.direction, 4).tolist(),
                            "length": round(p.length, 4)} for p in self.pegs]
        if self.floor is not None:
            out["floor"] = [np.round(self.floor[0], 4).tolist(), np.round(self.floor[1], 4).tolist()]
            out["wall_height"] = round(self.wall_height, 4)
        if self.levels:
            out["levels"] = [round(lv.z, 4) for lv in self.levels]
            out["front"] = np.round(self.front, 4).tolist()
        return out


def _box(lo: "np.ndarray | list[float]", hi: "np.ndarray | list[float]",
         T: np.ndarray | None = None) -> dict[str, object]:
    spec: dict[str, object] = {"box": [np.round(np.asarray(lo, np.float64), 6).tolist(),
                                       np.round(np.asarray(hi, np.float64), 6).tolist()]}
    if T is not None:
        spec["T"] = np.round(T, 6).tolist()
    return spec


def _cylinder(a: np.ndarray, b: np.ndarray, radius: float, sections: int = 16) -> dict[str, object]:
    """A cylinder of `radius` from point a to point b."""
    return {"cylinder": [np.round(a, 6).tolist(), np.round(b, 6).tolist()], "radius": round(float(radius), 6),
            "sections": int(sections)}


def piece_mesh(spec: dict[str, object]) -> "trimesh.Trimesh":
    """The watertight mesh of one structure piece (see `Structure.specs`); also rebuilds a scene's structure
    from its provenance (``provenance["structure"]["pieces"]``).

    Raises:
        ValueError: an unknown or malformed piece.
    """
    import trimesh

    try:
        if "box" in spec:
            lo, hi = (np.asarray(v, np.float64).reshape(3) for v in spec["box"])  # type: ignore[union-attr]
            m = trimesh.creation.box(extents=hi - lo)
            m.apply_translation((lo + hi) / 2)
            if "T" in spec:
                m.apply_transform(np.asarray(spec["T"], np.float64).reshape(4, 4))
            return m
        if "cylinder" in spec:
            a, b = (np.asarray(v, np.float64).reshape(3) for v in spec["cylinder"])  # type: ignore[union-attr]
            return trimesh.creation.cylinder(radius=float(spec["radius"]),  # type: ignore[arg-type]
                                             segment=np.stack([a, b]),
                                             sections=int(spec.get("sections", 16)))  # type: ignore[call-overload]
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"malformed structure piece {spec!r}: {e}") from None
    raise ValueError(f"unknown structure piece {spec!r}: expected a 'box' or a 'cylinder'")


def make_tree(rng: np.random.Generator) -> Structure:
    """A mug tree: a round base, a post and 4-8 pegs angled 25-35° upwards, in one tier (up to 5 pegs) or two
    tiers 11-13 cm apart, the upper one turned by half a peg spacing."""
    base_r = float(rng.uniform(0.075, 0.09))
    base_h = 0.015
    post_r = float(rng.uniform(0.011, 0.014))
    height = float(rng.uniform(0.38, 0.44))
    n_pegs = int(rng.integers(4, 9))
    tiers = [n_pegs] if n_pegs <= 5 else [math.ceil(n_pegs / 2), n_pegs // 2]
    z_top = height - 0.03
    tier_z = [z_top] if len(tiers) == 1 else [z_top - float(rng.uniform(0.11, 0.13)), z_top]
    az0 = float(rng.uniform(0, 2 * np.pi))
    pieces = [_cylinder(np.zeros(3), np.array([0.0, 0.0, base_h]), base_r, sections=32),
              _cylinder(np.array([0.0, 0.0, base_h]), np.array([0.0, 0.0, height]), post_r)]
    pegs: list[Peg] = []
    for i, (n, z) in enumerate(zip(tiers, tier_z)):
        for k in range(n):
            az = az0 + 2 * np.pi * (k + 0.5 * i) / n + float(rng.uniform(-0.1, 0.1))
            el = np.deg2rad(float(rng.uniform(25.0, 35.0)))
            d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            root = np.array([0.0, 0.0, z]) + 0.5 * post_r * np.array([math.cos(az), math.sin(az), 0.0])
            peg = Peg(root=root, direction=d, length=float(rng.uniform(0.085, 0.1)))
            pegs.append(peg)
            pieces.append(_cylinder(peg.root, peg.point(1.0), PEG_RADIUS, sections=12))
    return Structure("tree", pieces, _WOOD, pegs=pegs)


def make_box(rng: np.random.Generator, n_objects: int) -> Structure:
    """An open box on the table: walls 7-9 cm high (taller than half the tallest mug), 1 cm thick, an inner
    floor sized for `n_objects` (16-30 cm a side); its floor is the table top."""
    side = float(np.clip(0.11 + 0.027 * n_objects, 0.16, 0.30))
    a = side * float(rng.uniform(0.95, 1.1))
    b = side * float(rng.uniform(0.9, 1.05))
    h = float(rng.uniform(0.07, 0.09))
    t = 0.01
    lo, hi = np.array([-a / 2, -b / 2]), np.array([a / 2, b / 2])
    pieces = [
        _box([lo[0] - t, lo[1] - t, 0.0], [lo[0], hi[1] + t, h]),
        _box([hi[0], lo[1] - t, 0.0], [hi[0] + t, hi[1] + t, h]),
        _box([lo[0], lo[1] - t, 0.0], [hi[0], lo[1], h]),
        _box([lo[0], hi[1], 0.0], [hi[0], hi[1] + t, h]),
    ]
    return Structure("box", pieces, _CARDBOARD, floor=(lo, hi), wall_height=h)


def make_shelf(rng: np.random.Generator) -> Structure:
    """A shelf with 2 or 3 levels (boards 18-21 cm apart, 1.5 cm thick), side panels and a back panel; the
    lowest level is the table top. It opens towards a random horizontal direction (`front`)."""
    n_levels = int(rng.integers(2, 4))
    width = float(rng.uniform(0.46, 0.56))
    depth = float(rng.uniform(0.22, 0.26))
    gap = float(rng.uniform(0.18, 0.21))
    t = 0.015
    yaw = float(rng.uniform(0, 2 * np.pi))
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    # built in a local frame: x across, y from the back (−) to the open front (+), then turned by `yaw`
    T = np.eye(4)
    T[:3, :3] = rot
    local: list[tuple[list[float], list[float]]] = []
    levels_local = []
    top = (n_levels - 1) * gap + 0.155  # a top board 15.5 cm above the highest level (mugs are ≤ 13 cm tall)
    for i in range(n_levels):
        z = i * gap
        if i > 0:
            local.append(([-width / 2, -depth / 2, z - t], [width / 2, depth / 2, z]))
        levels_local.append(z)
    local.append(([-width / 2, -depth / 2, top], [width / 2, depth / 2, top + t]))
    local.append(([-width / 2 - t, -depth / 2, 0.0], [-width / 2, depth / 2, top + t]))
    local.append(([width / 2, -depth / 2, 0.0], [width / 2 + t, depth / 2, top + t]))
    local.append(([-width / 2 - t, -depth / 2 - t, 0.0], [width / 2 + t, -depth / 2, top + t]))
    pieces = [_box(lo, hi, T) for lo, hi in local]
    levels = []
    for z in levels_local:
        # the usable rectangle in the shelf's own frame (x across, y to the front; `level_to_world` turns it)
        levels.append(Level(z=z, lo=np.array([-width / 2 + 0.01, -depth / 2 + 0.01]),
                            hi=np.array([width / 2 - 0.01, depth / 2 - 0.01])))
    front = rot[:2, 1].copy()
    return Structure("shelf", pieces, _SHELF_WHITE, levels=levels, front=front)


def level_to_world(structure: Structure, xy_local: np.ndarray) -> np.ndarray:
    """Shelf-local xy (across, front) -> world xy (the shelf is turned about +Z so its local +y is `front`)."""
    f = structure.front
    across = np.array([f[1], -f[0]])
    xy_local = np.asarray(xy_local, np.float64)
    return xy_local[..., :1] * across + xy_local[..., 1:2] * f


def make_structure(kind: StructureKind, rng: np.random.Generator, *, n_objects: int) -> Structure:
    """The structure of scene configuration `kind`, drawn with `rng`."""
    if kind == "tree":
        return make_tree(rng)
    if kind == "box":
        return make_box(rng, n_objects)
    if kind == "shelf":
        return make_shelf(rng)
    raise ValueError(f"unknown structure {kind!r}; expected 'tree', 'box' or 'shelf'")
