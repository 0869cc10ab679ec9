"""Scene layout: the configurations, the objects drawn for a scene and their placement on the scene's stage
(upright scatter, shelf levels, pegs of a mug tree) before physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Sequence

import numpy as np

from efem_viz.data.synth.stage import TABLETOP, Stage

if TYPE_CHECKING:
    import trimesh

    from efem_viz.data.structures import Structure


Config = Literal["z", "so3", "pile", "tree", "box", "shelf"]
Mode = Literal["tsdf", "points"]
CONFIGS: tuple[str, ...] = ("z", "so3", "pile", "tree", "box", "shelf")
"""Scene configurations (their order seeds the generator: append only)."""
STRUCTURE_CONFIGS: tuple[str, ...] = ("tree", "box", "shelf")
"""Configurations with a supporting structure (`efem_viz.data.structures`)."""

TABLE_HALF = TABLETOP.half_size
"""Half side of the square table top (metres); the top face is at z = 0."""
TREE_SCATTER_RETRIES = 12
"""Fresh draws of the tree configuration's distractor places after the first finds no room, each on a square 2.5 cm
wider a side, up to the table's edge."""
TABLE_THICKNESS = TABLETOP.thickness
DISTRACTOR_CATEGORIES: tuple[str, ...] = TABLETOP.distractors
"""The distractors of tabletop scenes."""

_MUG_COLORS = np.array(
    [
        [235, 235, 230],
        [200, 40, 40],
        [40, 80, 170],
        [240, 200, 60],
        [60, 140, 80],
        [50, 50, 55],
        [230, 120, 160],
        [120, 190, 220],
        [150, 90, 60],
        [245, 150, 40],
    ],
    dtype=np.float64,
)
_DISTRACTOR_COLORS = np.array(
    [[170, 170, 150], [120, 120, 200], [100, 160, 100], [200, 170, 120]], dtype=np.float64
)


# ====================================================================================== objects and poses
@dataclass
class SceneObject:
    category: str
    seed: int
    label: int
    """Instance id in the ground truth (0 = distractor)."""
    mesh: "trimesh.Trimesh"
    """Canonical-frame mesh (metres)."""
    parts: list[np.ndarray]
    """Convex collision pieces, canonical frame."""
    color: np.ndarray
    T_world_object: np.ndarray = field(default_factory=lambda: np.eye(4))
    hole: tuple[np.ndarray, float] | None = None
    """Mugs of the tree configuration: the handle opening (canonical centre, clearance), see `handle_hole`."""

    def world_mesh(self) -> "trimesh.Trimesh":
        m = self.mesh.copy()
        m.apply_transform(self.T_world_object)
        return m


def sample_objects(
    rng: np.random.Generator, *, n_mugs: int, distractors: bool, split: str, hole: float | None = None,
    targets: str = "mug", stage: Stage,
) -> list[SceneObject]:
    """The scene's mugs (labels 1..n) and 0-2 distractors (label 0). With `hole`, only mugs whose handle
    opening clears that radius (m) are drawn (the tree configuration hangs them on pegs). Other `targets`, a
    training family (`procedural.FAMILIES`, e.g. "kitchen") or a category ("chair"): the labelled objects are
    drawn from its members, each object's category by the seed, and the distractors from the stage's
    distractor categories outside the family (boxes on the table, cabinets on the floor)."""
    from efem_viz.data.procedural import handle_hole, make_shape_with_parts, split_seeds

    seeds = split_seeds("mug", split)  # type: ignore[arg-type]
    if targets != "mug":
        return _sample_family(rng, targets, n_objects=n_mugs, distractors=distractors, seeds=seeds,
                              distractor_categories=stage.distractors)
    # (seed, (mesh, parts), handle opening) of each mug, each mug built once
    mugs: list[tuple[int, tuple[trimesh.Trimesh, list[np.ndarray]], tuple[np.ndarray, float] | None]] = []
    if hole is None:
        for i in rng.choice(len(seeds), size=n_mugs, replace=False):
            mugs.append((int(seeds[i]), make_shape_with_parts("mug", int(seeds[i])), None))
    else:
        for i in rng.choice(len(seeds), size=min(len(seeds), 20 * n_mugs), replace=False):
            built = make_shape_with_parts("mug", int(seeds[i]))
            opening = handle_hole(built[0])
            if opening is not None and opening[1] >= hole:
                mugs.append((int(seeds[i]), built, opening))
                if len(mugs) == n_mugs:
                    break
        if len(mugs) < n_mugs:
            raise RuntimeError(f"only {len(mugs)} of the {split} mugs drawn have a handle opening of "
                               f"{hole * 1000:.0f} mm")
    objs: list[SceneObject] = []
    colors = rng.permutation(len(_MUG_COLORS))
    for k, (s, (mesh, parts), opening) in enumerate(mugs):
        objs.append(SceneObject("mug", s, k + 1, mesh, parts, _MUG_COLORS[colors[k % len(colors)]], hole=opening))
    if distractors:
        n_d = int(rng.integers(0, 3))
        for _ in range(n_d):
            cat = stage.distractors[int(rng.integers(len(stage.distractors)))]
            s = int(seeds[int(rng.integers(len(seeds)))])
            mesh, parts = make_shape_with_parts(cat, s)
            col = _DISTRACTOR_COLORS[int(rng.integers(len(_DISTRACTOR_COLORS)))]
            objs.append(SceneObject(cat, s, 0, mesh, parts, col))
    return objs


def _sample_family(rng: np.random.Generator, family: str, *, n_objects: int, distractors: bool,
                   seeds: range, distractor_categories: Sequence[str]) -> list[SceneObject]:
    """`sample_objects` for a training family's (or a single category's) scene: labelled objects of its member
    categories (one seed each, not repeated within a category), then 0-2 distractors of the
    `distractor_categories` outside the family."""
    from efem_viz.data.procedural import family_members, make_shape_with_parts

    members = family_members(family)
    others = tuple(c for c in distractor_categories if c not in members)
    cats = [members[int(i)] for i in rng.integers(len(members), size=n_objects)]
    picks = rng.choice(len(seeds), size=n_objects, replace=False)
    colors = rng.permutation(len(_MUG_COLORS))
    objs: list[SceneObject] = []
    for k, (cat, i) in enumerate(zip(cats, picks)):
        mesh, parts = make_shape_with_parts(cat, int(seeds[int(i)]))
        objs.append(SceneObject(cat, int(seeds[int(i)]), k + 1, mesh, parts, _MUG_COLORS[colors[k % len(colors)]]))
    if distractors and others:
        for _ in range(int(rng.integers(0, 3))):
            cat = others[int(rng.integers(len(others)))]
            s = int(seeds[int(rng.integers(len(seeds)))])
            mesh, parts = make_shape_with_parts(cat, s)
            objs.append(SceneObject(cat, s, 0, mesh, parts,
                                    _DISTRACTOR_COLORS[int(rng.integers(len(_DISTRACTOR_COLORS)))]))
    return objs


def _yaw(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _footprint_radius(mesh: "trimesh.Trimesh", R: np.ndarray) -> tuple[np.ndarray, float]:
    """xy centre (of the rotated bbox) and radius of the rotated mesh's footprint circle."""
    v = np.asarray(mesh.vertices) @ R.T
    c = (v[:, :2].min(0) + v[:, :2].max(0)) / 2
    return c, float(np.linalg.norm(v[:, :2] - c, axis=1).max())


def scatter_xy(rng: np.random.Generator, radii: Sequence[float], *, stage: Stage, gap: float = 0.01) -> np.ndarray:
    """Non-overlapping disc centres (K, 2) around the origin (rejection sampling in a square that starts at the
    stage's scatter size and grows towards the support's edge)."""
    n = len(radii)
    start, per_object = stage.scatter_start
    first_inset, last_inset = stage.scatter_inset
    half = min(start + per_object * n, stage.half_size - first_inset)
    for _ in range(50):
        centres: list[np.ndarray] = []
        ok = True
        for r in radii:
            for _ in range(300):
                c = rng.uniform(-half, half, 2)
                if all(np.linalg.norm(c - q) >= r + rq + gap for q, rq in zip(centres, radii)):
                    centres.append(c)
                    break
            else:
                ok = False
                break
        if ok:
            return np.array(centres).reshape(n, 2)
        half = min(half * 1.15, stage.half_size - last_inset)
    raise RuntimeError(f"could not place {n} objects without overlap on the {stage.support}")


def place_upright(objs: list[SceneObject], rng: np.random.Generator, *, stage: Stage) -> None:
    """z configuration: upright, random yaw, resting on the stage's support (table or floor), footprints
    disjoint."""
    rots = [_yaw(float(rng.uniform(0, 2 * np.pi))) for _ in objs]
    foot = [_footprint_radius(o.mesh, R) for o, R in zip(objs, rots)]
    xy = scatter_xy(rng, [r for _, r in foot], stage=stage)
    for o, R, (c, _), p in zip(objs, rots, foot, xy):
        _rest_upright(o, R, p, 0.0, c)


def _scatter_in(
    rng: np.random.Generator, radii: Sequence[float], lo: np.ndarray, hi: np.ndarray, *, gap: float = 0.01,
    keep_out: tuple[np.ndarray, float] | None = None,
) -> np.ndarray | None:
    """Non-overlapping disc centres (K, 2) inside the rectangle [lo, hi] (discs wholly inside when they fit),
    outside the disc `keep_out` (centre, radius); None when rejection sampling finds no room."""
    centres: list[np.ndarray] = []
    for r in radii:
        inset = np.minimum(r, (hi - lo) / 2)
        for _ in range(400):
            c = rng.uniform(lo + inset, hi - inset)
            if keep_out is not None and np.linalg.norm(c - keep_out[0]) < r + keep_out[1] + gap:
                continue
            if all(np.linalg.norm(c - q) >= r + rq + gap for q, rq in zip(centres, radii)):
                centres.append(c)
                break
        else:
            return None
    return np.array(centres).reshape(len(radii), 2)


def _rest_upright(o: SceneObject, R: np.ndarray, xy: np.ndarray, z: float, foot_centre: np.ndarray) -> None:
    """Pose `o` with rotation R so that its footprint centre is at xy and its lowest point at height z."""
    zmin = float((np.asarray(o.mesh.vertices) @ R.T)[:, 2].min())
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [xy[0] - foot_centre[0], xy[1] - foot_centre[1], z - zmin]
    o.T_world_object = T


def place_on_shelf(objs: list[SceneObject], shelf: "Structure", rng: np.random.Generator) -> list[SceneObject]:
    """shelf configuration: upright, random yaw, disjoint footprints, one object after the other on the level
    that holds the fewest so far (ties broken at random) where it fits. A distractor that fits nowhere is left
    out; returns the objects placed.

    Raises:
        ValueError: a mug fits on no level (more mugs than the shelf holds).
    """
    from efem_viz.data.structures import level_to_world

    levels = shelf.levels
    placed: list[list[tuple[np.ndarray, float]]] = [[] for _ in levels]
    kept: list[SceneObject] = []
    for o in objs:
        R = _yaw(float(rng.uniform(0, 2 * np.pi)))
        foot_c, r = _footprint_radius(o.mesh, R)
        order = sorted(range(len(levels)), key=lambda i: (len(placed[i]), float(rng.uniform())))
        spot: tuple[int, np.ndarray] | None = None
        for li in order:
            lv = levels[li]
            inset = np.minimum(r, (lv.hi - lv.lo) / 2)
            for _ in range(300):
                c = rng.uniform(lv.lo + inset, lv.hi - inset)
                if all(np.linalg.norm(c - q) >= r + rq + 0.008 for q, rq in placed[li]):
                    spot = (li, c)
                    break
            if spot is not None:
                break
        if spot is None:
            if o.label > 0:
                n_mugs = sum(q.label > 0 for q in objs)
                raise ValueError(f"{n_mugs} mugs do not fit on this shelf's {len(levels)} levels (mug {o.label} "
                                 f"finds no room); ask for fewer objects")
            continue
        li, c = spot
        placed[li].append((c, r))
        _rest_upright(o, R, level_to_world(shelf, c), levels[li].z, foot_c)
        kept.append(o)
    return kept


def hang_on_tree(objs: list[SceneObject], tree: "Structure", rng: np.random.Generator) -> None:
    """tree configuration, start poses: each mug threaded on its own peg (the peg through the middle of its
    handle opening, 55-75 % out along the peg) and turned about the peg so that its centre of mass hangs
    below; distractors upright on the table around the base. Physics (`simulate(layout="hang")`) settles
    them: the mugs drop onto the pegs, swing and tilt as they hang."""
    from efem_viz.geometry.transforms import rotation_about_axis, rotation_between

    mugs = [o for o in objs if o.label > 0]
    pegs = [tree.pegs[i] for i in rng.permutation(len(tree.pegs))[: len(mugs)]]
    down = np.array([0.0, 0.0, -1.0])
    for o, peg in zip(mugs, pegs):
        assert o.hole is not None, "tree mugs are drawn with a handle opening"
        centre, _ = o.hole
        d = peg.direction
        R0 = rotation_between(np.array([0.0, 1.0, 0.0]), d)  # the opening's axis (canonical Y) along the peg
        v = R0 @ (np.asarray(o.mesh.center_mass, np.float64) - centre)
        v_perp = v - np.dot(v, d) * d
        g_perp = down - np.dot(down, d) * d
        # turn about the peg so that the centre of mass lies below it
        ang = math.atan2(np.dot(np.cross(v_perp, g_perp), d), np.dot(v_perp, g_perp))
        R = rotation_about_axis(d, ang) @ R0
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = peg.point(float(rng.uniform(0.55, 0.75))) - R @ centre
        o.T_world_object = T
    others = [o for o in objs if o.label == 0]
    if others:
        rots = [_yaw(float(rng.uniform(0, 2 * np.pi))) for _ in others]
        foot = [_footprint_radius(o.mesh, R) for o, R in zip(others, rots)]
        reach = max(p.length for p in tree.pegs) + 0.12
        xy = None
        for retry in range(TREE_SCATTER_RETRIES + 1):  # a failed draw: again on a square up to the table's edge
            half = min(reach + 0.1 + 0.025 * retry, TABLE_HALF - 0.01)
            xy = _scatter_in(rng, [r for _, r in foot], np.full(2, -half), np.full(2, half),
                             keep_out=(np.zeros(2), reach))
            if xy is not None:
                break
        if xy is None:
            raise RuntimeError(f"no room for {len(others)} distractors on the table around the mug tree "
                               f"(footprint radii {', '.join(f'{r:.2f}' for _, r in foot)} m); ask for fewer")
        for o, R, (c, _), p in zip(others, rots, foot, xy):
            _rest_upright(o, R, p, 0.0, c)


def count_misplaced(config: str, objs: list[SceneObject], structure: "Structure | None") -> int:
    """How many objects did not end where the configuration puts them: tree mugs that fell off their pegs
    (lowest point within 3 cm of the table, or more than 25 cm from the post), box objects outside the walls."""
    if structure is None or config not in ("tree", "box"):
        return 0
    bad = 0
    for o in objs:
        v = np.asarray(o.world_mesh().vertices)
        if config == "tree" and o.label > 0:
            centre = v.mean(axis=0)
            bad += int(v[:, 2].min() < 0.03 or np.linalg.norm(centre[:2]) > 0.25)
        elif config == "box":
            assert structure.floor is not None
            lo, hi = structure.floor
            c = v.mean(axis=0)[:2]
            bad += int(np.any(c < lo - 0.005) or np.any(c > hi + 0.005))
    return bad
