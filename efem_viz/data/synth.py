"""Synthetic tabletop scans with per-point ground truth: procedural mugs (+ distractors) on a table.

The six configurations of the EFEM paper's synthetic mug scenes:
  * ``"z"``: mugs upright with a random yaw, placed without overlap;
  * ``"so3"``: objects dropped with a random orientation (pybullet) and resting on the table;
  * ``"pile"``: objects dropped one after the other onto the ones already lying there (pybullet), so that
    they stack, lean on and touch each other;
  * ``"tree"``: mugs threaded by their handles on the pegs of a mug tree, then settled by pybullet (they drop
    onto the pegs and hang tilted); only mugs whose handle opening clears a peg are drawn;
  * ``"box"``: objects dropped one after the other into an open box whose walls hide part of them;
  * ``"shelf"``: objects upright on the 2-3 levels of a shelf, partly hidden by the level above; the cameras
    stand in front of it.
The supporting structures (`efem_viz.data.structures`) are background (id 0), like the table.
Physics uses a convex decomposition of every object (`procedural.make_shape_with_parts`); final poses are
checked for interpenetration with signed distances on the exact meshes (dropped again when above tolerance).

The table top (0.8 x 0.8 m, top face at z = 0) is scanned by virtual depth cameras at the table corners
looking at the objects (open3d ray casting; pinhole 640 x 480, Kinect-like axial noise
sigma(z) = 1.2 mm + 1.9 mm (z - 0.4)^2 and dropout at grazing angles), then fused by a projective TSDF into
a mesh (``mode="tsdf"``) or merged and voxel-downsampled as points (``mode="points"``). Ground truth: each
output point takes the label of the nearest true surface (table, object or distractor) when closer than
`label_tolerance`; mug k has id k, everything else 0.

World frame: metres, +Z up, table top at z = 0. Same arguments -> identical arrays.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Sequence, cast

import numpy as np

from efem_viz.geometry.camera import Camera, look_at
from efem_viz.geometry.transforms import rotation_to_quat_wxyz

if TYPE_CHECKING:
    import trimesh

    from efem_viz.data.scene import Scene
    from efem_viz.data.structures import Structure

logger = logging.getLogger(__name__)

Config = Literal["z", "so3", "pile", "tree", "box", "shelf"]
Mode = Literal["tsdf", "points"]
CONFIGS: tuple[str, ...] = ("z", "so3", "pile", "tree", "box", "shelf")
"""Scene configurations (their order seeds the generator: append only)."""
STRUCTURE_CONFIGS: tuple[str, ...] = ("tree", "box", "shelf")
"""Configurations with a supporting structure (`efem_viz.data.structures`)."""

TABLE_HALF = 0.4
"""Half side of the square table top (metres); the top face is at z = 0."""
TABLE_THICKNESS = 0.04
DISTRACTOR_CATEGORIES: tuple[str, ...] = ("box", "can", "bowl", "bottle")
PENETRATION_TOLERANCE = 0.002
"""Largest accepted interpenetration depth between final meshes (metres)."""

COLLISION_SHRINK = 0.0008
"""Collision pieces are pulled in by this much (metres) to offset Bullet's convex-hull margin."""

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
_TABLE_COLOR = np.array([190, 155, 115], dtype=np.float64)
_DISTRACTOR_COLORS = np.array(
    [[170, 170, 150], [120, 120, 200], [100, 160, 100], [200, 170, 120]], dtype=np.float64
)


# ====================================================================================== objects and poses
@dataclass
class _Object:
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


def _sample_objects(
    rng: np.random.Generator, *, n_mugs: int, distractors: bool, split: str, hole: float | None = None
) -> list[_Object]:
    """The scene's mugs (labels 1..n) and 0-2 distractors (label 0). With `hole`, only mugs whose handle
    opening clears that radius (m) are drawn (the tree configuration hangs them on pegs)."""
    from efem_viz.data.procedural import handle_hole, make_shape_with_parts, split_seeds

    seeds = split_seeds("mug", split)  # type: ignore[arg-type]
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
    objs: list[_Object] = []
    colors = rng.permutation(len(_MUG_COLORS))
    for k, (s, (mesh, parts), opening) in enumerate(mugs):
        objs.append(_Object("mug", s, k + 1, mesh, parts, _MUG_COLORS[colors[k % len(colors)]], hole=opening))
    if distractors:
        n_d = int(rng.integers(0, 3))
        for _ in range(n_d):
            cat = DISTRACTOR_CATEGORIES[int(rng.integers(len(DISTRACTOR_CATEGORIES)))]
            s = int(seeds[int(rng.integers(len(seeds)))])
            mesh, parts = make_shape_with_parts(cat, s)
            col = _DISTRACTOR_COLORS[int(rng.integers(len(_DISTRACTOR_COLORS)))]
            objs.append(_Object(cat, s, 0, mesh, parts, col))
    return objs


def _yaw(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    from efem_viz.geometry.transforms import random_rotation

    return random_rotation(rng)


def _footprint_radius(mesh: "trimesh.Trimesh", R: np.ndarray) -> tuple[np.ndarray, float]:
    """xy centre (of the rotated bbox) and radius of the rotated mesh's footprint circle."""
    v = np.asarray(mesh.vertices) @ R.T
    c = (v[:, :2].min(0) + v[:, :2].max(0)) / 2
    return c, float(np.linalg.norm(v[:, :2] - c, axis=1).max())


def _scatter_xy(rng: np.random.Generator, radii: Sequence[float], *, gap: float = 0.01) -> np.ndarray:
    """Non-overlapping disc centres (K, 2) around the origin (rejection sampling in a growing square)."""
    n = len(radii)
    half = min(0.04 + 0.02 * n, TABLE_HALF - 0.12)
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
        half = min(half * 1.15, TABLE_HALF - 0.05)
    raise RuntimeError(f"could not place {n} objects without overlap on the table")


def _place_upright(objs: list[_Object], rng: np.random.Generator) -> None:
    """z configuration: upright, random yaw, resting on the table, footprints disjoint."""
    rots = [_yaw(float(rng.uniform(0, 2 * np.pi))) for _ in objs]
    foot = [_footprint_radius(o.mesh, R) for o, R in zip(objs, rots)]
    xy = _scatter_xy(rng, [r for _, r in foot])
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


def _rest_upright(o: _Object, R: np.ndarray, xy: np.ndarray, z: float, foot_centre: np.ndarray) -> None:
    """Pose `o` with rotation R so that its footprint centre is at xy and its lowest point at height z."""
    zmin = float((np.asarray(o.mesh.vertices) @ R.T)[:, 2].min())
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [xy[0] - foot_centre[0], xy[1] - foot_centre[1], z - zmin]
    o.T_world_object = T


def _place_on_shelf(objs: list[_Object], shelf: "Structure", rng: np.random.Generator) -> list[_Object]:
    """shelf configuration: upright, random yaw, disjoint footprints, one object after the other on the level
    that holds the fewest so far (ties broken at random) where it fits. A distractor that fits nowhere is left
    out; returns the objects placed.

    Raises:
        ValueError: a mug fits on no level (more mugs than the shelf holds).
    """
    from efem_viz.data.structures import level_to_world

    levels = shelf.levels
    placed: list[list[tuple[np.ndarray, float]]] = [[] for _ in levels]
    kept: list[_Object] = []
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


def _hang_on_tree(objs: list[_Object], tree: "Structure", rng: np.random.Generator) -> None:
    """tree configuration, start poses: each mug threaded on its own peg (the peg through the middle of its
    handle opening, 55-75 % out along the peg) and turned about the peg so that its centre of mass hangs
    below; distractors upright on the table around the base. Physics (`_simulate(layout="hang")`) settles
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
        xy = _scatter_in(rng, [r for _, r in foot], np.full(2, -reach - 0.1), np.full(2, reach + 0.1),
                         keep_out=(np.zeros(2), reach))
        if xy is None:
            raise RuntimeError("no room for the distractors around the mug tree")
        for o, R, (c, _), p in zip(others, rots, foot, xy):
            _rest_upright(o, R, p, 0.0, c)


def _misplaced(config: str, objs: list[_Object], structure: "Structure | None") -> int:
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


def _write_parts_obj(parts: Sequence[np.ndarray], path: str, *, shrink: float = 0.0) -> None:
    """Write convex pieces as separate OBJ objects (pybullet makes a compound of their convex hulls).

    Args:
        parts: list of (K, 3) point sets.
        path: destination .obj.
        shrink: move every hull vertex this far (metres) towards the piece centroid (at most halfway).
    """
    from scipy.spatial import ConvexHull

    lines: list[str] = []
    off = 1
    for k, pts in enumerate(parts):
        hull = ConvexHull(pts)
        v = pts[hull.vertices]
        if shrink > 0:  # Bullet inflates convex hulls by a collision margin: pull the vertices in by that
            c = v.mean(axis=0)
            d = v - c
            ln = np.linalg.norm(d, axis=1, keepdims=True)
            v = c + d * np.maximum(ln - shrink, 0.5 * ln) / np.maximum(ln, 1e-12)
        remap = np.zeros(len(pts), np.int64)
        remap[hull.vertices] = np.arange(len(hull.vertices)) + off  # 1-based OBJ indices
        tri = remap[hull.simplices]
        lines.append(f"o part{k}")
        lines.extend(f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v)
        lines.extend(f"f {a} {b} {c}" for a, b, c in tri)
        off += len(v)
    with open(path, "w", encoding="ascii") as fh:
        fh.write("\n".join(lines) + "\n")


def _simulate(
    objs: list[_Object],
    rng: np.random.Generator,
    *,
    layout: Literal["scatter", "pile", "box", "hang"],
    statics: Sequence[np.ndarray] = (),
    floor: tuple[np.ndarray, np.ndarray] | None = None,
    floor_top: float = 0.0,
    max_seconds: float = 6.0,
) -> None:
    """Drop the objects with random orientations (pybullet, DIRECT mode) and store their resting poses.

    scatter: all objects at once, each above its own non-overlapping spot. pile: one after the other, just
    above the top of the objects already lying there (near their centre), each settling before the next is
    dropped, so that they land on and slide against each other. box: one after the other above a random spot
    of `floor` (xy rectangle), clear of `floor_top` and of what already lies there. hang: every object starts
    at its current `T_world_object` (e.g. a mug threaded on a peg) and all settle together. `statics` are
    convex pieces (world frame) of a fixed structure (a box's walls, a mug tree).
    """
    import pybullet as pb

    dt = 1.0 / 240.0
    cid = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81, physicsClientId=cid)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=dt, numSolverIterations=60, deterministicOverlappingPairs=1, physicsClientId=cid
        )
        table = pb.createCollisionShape(
            pb.GEOM_BOX, halfExtents=[TABLE_HALF, TABLE_HALF, 0.05], physicsClientId=cid
        )
        tid = pb.createMultiBody(0, table, basePosition=[0, 0, -0.05], physicsClientId=cid)
        pb.changeDynamics(tid, -1, lateralFriction=0.8, physicsClientId=cid)
        coms = [np.asarray(o.mesh.center_mass, np.float64) for o in objs]
        if layout == "hang":
            rots = [o.T_world_object[:3, :3].copy() for o in objs]
        else:
            rots = [_random_rotation(rng) for _ in objs]
        radii = [
            float(np.linalg.norm(np.asarray(o.mesh.vertices) - c, axis=1).max()) for o, c in zip(objs, coms)
        ]
        xy = _scatter_xy(rng, radii, gap=0.005) if layout == "scatter" else None
        bodies: list[int] = []
        with tempfile.TemporaryDirectory(prefix="efem_synth_") as tmp:
            if len(statics):
                fn = os.path.join(tmp, "structure.obj")
                _write_parts_obj(list(statics), fn)
                shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=fn, physicsClientId=cid)
                sid = pb.createMultiBody(0, shape, basePosition=[0, 0, 0], physicsClientId=cid)
                pb.changeDynamics(sid, -1, lateralFriction=0.6, physicsClientId=cid)
            for k, (o, R, c) in enumerate(zip(objs, rots, coms)):
                fn = os.path.join(tmp, f"obj{k}.obj")
                _write_parts_obj([q - c for q in o.parts], fn, shrink=COLLISION_SHRINK)
                shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=fn, physicsClientId=cid)
                if layout == "hang":
                    pos = (o.T_world_object[:3, :3] @ c + o.T_world_object[:3, 3]).tolist()
                elif xy is not None:
                    pos = [xy[k, 0], xy[k, 1], radii[k] + 0.005 + float(rng.uniform(0, 0.02))]
                else:
                    top = floor_top
                    if bodies:
                        top = max(top, max(pb.getAABB(b, physicsClientId=cid)[1][2] for b in bodies))
                    if layout == "box" and floor is not None:
                        lo, hi = np.asarray(floor[0], np.float64), np.asarray(floor[1], np.float64)
                        inset = np.minimum(radii[k], (hi - lo) / 2 - 0.005)
                        centre = rng.uniform(lo + inset, hi - inset)
                    elif bodies:  # pile: above the centre of the pile so far, just clear of its top
                        poses = [pb.getBasePositionAndOrientation(b, physicsClientId=cid) for b in bodies]
                        centre = np.mean([q[0] for q in poses], axis=0)[:2] + rng.normal(0.0, 0.015, 2)
                    else:
                        centre = rng.normal(0.0, 0.015, 2)
                    pos = [centre[0], centre[1], top + radii[k] + 0.005]
                b = pb.createMultiBody(
                    max(float(o.mesh.volume) * 2000.0, 0.02),
                    shape,
                    basePosition=pos,
                    baseOrientation=np.roll(rotation_to_quat_wxyz(R), -1).tolist(),  # pybullet: xyzw
                    physicsClientId=cid,
                )
                pb.changeDynamics(
                    b,
                    -1,
                    lateralFriction=0.8,
                    spinningFriction=0.003,
                    rollingFriction=0.002 if layout in ("pile", "box") else 0.0005,
                    restitution=0.05,
                    linearDamping=0.3 if layout != "hang" else 0.6,
                    angularDamping=0.3 if layout != "hang" else 0.6,
                    physicsClientId=cid,
                )
                bodies.append(b)
                if layout in ("pile", "box"):
                    _settle(pb, cid, bodies, max_steps=int(3.0 / dt), min_steps=240)
        _settle(pb, cid, bodies, max_steps=int(max_seconds / dt))
        for o, b, c in zip(objs, bodies, coms):
            pos, quat = pb.getBasePositionAndOrientation(b, physicsClientId=cid)
            R = np.asarray(pb.getMatrixFromQuaternion(quat), np.float64).reshape(3, 3)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = np.asarray(pos) - R @ c
            o.T_world_object = T
    finally:
        pb.disconnect(physicsClientId=cid)


def _settle(
    pb: Any, cid: int, bodies: list[int], *, max_steps: int, min_steps: int = 120, check_every: int = 24
) -> int:
    """Step until every body is (nearly) at rest (after `min_steps`) or `max_steps`; returns the steps."""
    steps = 0
    while steps < max_steps:
        for _ in range(check_every):
            pb.stepSimulation(physicsClientId=cid)
        steps += check_every
        if steps < min_steps:
            continue
        moving = False
        for b in bodies:
            v, w = pb.getBaseVelocity(b, physicsClientId=cid)
            if np.linalg.norm(v) > 0.004 or np.linalg.norm(w) > 0.05:
                moving = True
                break
        if not moving:
            break
    return steps


# ====================================================================================== checks
def contact_report(
    objs_world: Sequence["trimesh.Trimesh"], *, samples: int = 3000, seed: int = 0,
    fixed: Sequence["trimesh.Trimesh"] = (),
) -> dict[str, Any]:
    """Interpenetration and contact of posed meshes (world frame, table top at z = 0).

    Args:
        objs_world: watertight meshes in the world frame.
        samples: surface samples per mesh (plus its vertices) used to probe the others.
        seed: seed of the surface sampling.
        fixed: watertight pieces of a fixed structure (world frame): objects must not penetrate them; the pieces
            may overlap each other.

    Returns:
        {"max_penetration": metres (objects into each other, into the structure, or below the table top),
         "pair_penetration": (K, K) array, [i, j] = deepest point of i inside j,
         "pair_gap": (K, K) array, [i, j] = smallest distance from i's surface to j (0 when touching or
         penetrating; inf when their bounding boxes are more than 1 cm apart),
         "gap": (K,) distance from each object to the nearest other object, structure piece or the table top}.
    """
    import open3d as o3d
    import trimesh

    from efem_viz._typeshims import o3d_tensor

    k = len(objs_world)
    meshes = list(objs_world) + list(fixed)
    n = len(meshes)
    probes = []
    for i, m in enumerate(meshes):
        # cast: trimesh's inferred return is a union over its optional outputs; these args give (points, faces)
        s, _ = cast("tuple[np.ndarray, np.ndarray]", trimesh.sample.sample_surface(m, samples, seed=seed + i))
        probes.append(np.concatenate([np.asarray(m.vertices), s]).astype(np.float32))
    pen = np.zeros((n, n))
    pair_gap = np.full((n, n), np.inf)
    gap = np.array([max(float(p[:, 2].min()), 0.0) for p in probes[:k]] + [np.inf] * (n - k))
    table_pen = max([max(-float(p[:, 2].min()), 0.0) for p in probes], default=0.0)
    for j, mj in enumerate(meshes):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d_tensor(np.asarray(mj.vertices, np.float32)),
            o3d_tensor(np.asarray(mj.faces, np.uint32)),
        )
        lo, hi = mj.bounds[0] - 0.01, mj.bounds[1] + 0.01
        for i in range(n):
            if i == j or (i >= k and j >= k):
                continue
            p = probes[i]
            near = np.all((p >= lo) & (p <= hi), axis=1)
            if not near.any():
                continue
            sd = scene.compute_signed_distance(o3d_tensor(p[near])).numpy()
            pen[i, j] = max(-float(sd.min()), 0.0)
            pair_gap[i, j] = max(float(sd.min()), 0.0)
            gap[i] = min(gap[i], pair_gap[i, j])
    return {
        "max_penetration": float(max(pen.max(initial=0.0), table_pen)),
        "pair_penetration": pen[:k, :k],
        "pair_gap": pair_gap[:k, :k],
        "gap": gap[:k],
    }


# ====================================================================================== scanning
def _make_cameras(
    rng: np.random.Generator, target: np.ndarray, *, n_cameras: int, image_size: tuple[int, int],
    heights: tuple[float, float] = (0.45, 0.6), front: np.ndarray | None = None,
) -> list[Camera]:
    """Depth cameras looking at `target`: around the table at its corners (eye heights drawn from `heights`),
    or, with a `front` direction (a shelf), spread over ±55° about it, 0.6-0.75 m away, at heights rising
    through `heights`."""
    w, h = image_size
    f = 525.0 * w / 640.0
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    cams = []
    if front is not None:
        az_f = math.atan2(front[1], front[0])
        for i in range(n_cameras):
            frac = i / max(n_cameras - 1, 1)
            az = az_f + np.deg2rad(-55.0 + 110.0 * frac) + rng.uniform(-0.08, 0.08)
            dist = rng.uniform(0.6, 0.75)
            z = heights[0] + (heights[1] - heights[0]) * ((i * 2 + 1) % n_cameras) / n_cameras
            eye = np.array([target[0] + dist * math.cos(az), target[1] + dist * math.sin(az), z])
            tgt = target + np.array([*rng.uniform(-0.02, 0.02, 2), 0.0])
            cams.append(Camera(K, look_at(eye, tgt), w, h))
        return cams
    az0 = np.pi / 4 + rng.uniform(-0.15, 0.15)
    for i in range(n_cameras):
        az = az0 + 2 * np.pi * i / n_cameras + rng.uniform(-0.1, 0.1)
        horiz = TABLE_HALF * math.sqrt(2) * rng.uniform(0.9, 1.05)
        eye = np.array([horiz * math.cos(az), horiz * math.sin(az), rng.uniform(*heights)])
        tgt = target + np.array([*rng.uniform(-0.02, 0.02, 2), 0.0])
        cams.append(Camera(K, look_at(eye, tgt), w, h))
    return cams


def _depth_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect v1 axial noise (Nguyen et al. 2012): sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4 m)^2, z in metres."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


@dataclass
class _Frame:
    depth: np.ndarray  # (H, W) float32, 0 = no measurement
    color: np.ndarray  # (H, W, 3) uint8
    normal: np.ndarray  # (H, W, 3) float32, true surface normal towards the camera
    visible_ids: np.ndarray  # (H, W) int32 geometry index (-1 none)


def _render(
    scene: Any,
    cam: Camera,
    albedo: np.ndarray,
    rng: np.random.Generator,
    *,
    noise: bool,
    crop_lo: np.ndarray,
    crop_hi: np.ndarray,
) -> _Frame:
    from efem_viz._typeshims import o3d_tensor

    h, w = cam.height, cam.width
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    R, t = cam.T_world_camera[:3, :3], cam.T_world_camera[:3, 3]
    d_world = d_cam @ R.T
    rays = np.concatenate([np.broadcast_to(t, d_world.shape), d_world], -1).astype(np.float32)
    ans = scene.cast_rays(o3d_tensor(rays))
    z = ans["t_hit"].numpy().astype(np.float64)  # ray direction has unit z in the camera: t = depth
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    nrm = ans["primitive_normals"].numpy().astype(np.float64)
    hit = np.isfinite(z) & (z < 3.0)
    gid = np.where(hit, gid, -1)
    d_unit = d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)
    cos = np.sum(nrm * d_unit, axis=-1)
    nrm = np.where((cos > 0)[..., None], -nrm, nrm)
    cos = np.abs(cos)
    valid = hit.copy()
    if noise:
        angle = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
        p_drop = np.clip((angle - 65.0) / 20.0, 0.0, 1.0) + 0.003
        valid &= rng.uniform(size=z.shape) >= p_drop
        z = z + rng.standard_normal(z.shape) * _depth_sigma(np.where(hit, z, 0.0))
    pts = t + d_world * np.where(valid, z, 0.0)[..., None]
    valid &= np.all((pts >= crop_lo) & (pts <= crop_hi), axis=-1)
    depth = np.where(valid, z, 0.0).astype(np.float32)
    base = albedo[np.clip(gid, 0, None)]
    shade = 0.55 + 0.45 * cos
    col = base * shade[..., None]
    if noise:
        col = col + rng.normal(0.0, 3.0, col.shape)
    color = np.where(hit[..., None], np.clip(np.round(col), 0, 255), 0).astype(np.uint8)
    return _Frame(depth, color, nrm.astype(np.float32), np.where(valid, gid, -1).astype(np.int32))


def _backproject(frame: _Frame, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = frame.depth > 0
    v, u = np.nonzero(m)
    z = frame.depth[m].astype(np.float64)
    x = (u - cam.K[0, 2]) / cam.K[0, 0] * z
    y = (v - cam.K[1, 2]) / cam.K[1, 1] * z
    p_cam = np.stack([x, y, z], -1)
    p = p_cam @ cam.T_world_camera[:3, :3].T + cam.T_world_camera[:3, 3]
    return p, frame.color[m], frame.normal[m].astype(np.float64)


def _voxel_average(
    points: np.ndarray, colors: np.ndarray, normals: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average points/colours/normals per voxel; output sorted by voxel key (deterministic)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    n = len(counts)

    def avg(a: np.ndarray) -> np.ndarray:
        out = np.zeros((n, a.shape[1]))
        np.add.at(out, inv, a)
        return out / counts[:, None]

    return avg(points), avg(colors.astype(np.float64)), avg(normals)


def _fuse_tsdf(
    frames: Sequence[_Frame],
    cams: Sequence[Camera],
    *,
    voxel: float,
    lo: np.ndarray,
    hi: np.ndarray,
    trunc_voxels: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse depth frames into a truncated signed distance grid over the box [lo, hi] and mesh its zero level.

    Projective TSDF (Curless & Levoy / KinectFusion): every voxel centre in front of a measurement or less
    than `trunc_voxels * voxel` behind it takes the mean of the truncated signed distances of all cameras;
    marching cubes (scikit-image) runs only on cubes whose 8 corners were observed. Pure NumPy, deterministic.

    Args:
        frames: depth (H, W) float32 metres (0 = none) and colour (H, W, 3) uint8 per camera.
        cams: the cameras (intrinsics, T_world_camera).
        voxel: voxel size, metres.
        lo, hi: (3,) world-frame corners of the fused box (the grid origin moves by up to half a voxel in z).
        trunc_voxels: truncation distance in voxels.

    Returns:
        vertices (V, 3) float64 world frame, faces (F, 3) int64 (outward = towards the cameras),
        colours (V, 3) float64 in [0, 255].
    """
    from skimage.measure import marching_cubes

    from scipy.ndimage import binary_dilation

    # put the table top (z = 0) halfway between two voxel layers: a surface running exactly through voxel
    # centres makes marching cubes emit degenerate triangles, which leaves holes and doubles the vertex count
    lo = np.array(lo, dtype=np.float64)
    lo[2] = (math.floor(lo[2] / voxel) + 0.5) * voxel
    dims = np.maximum(np.ceil((hi - lo) / voxel).astype(int) + 1, 2)
    trunc = trunc_voxels * voxel
    # only voxels within the truncation band of some measurement can carry |tsdf| < 1: find them first
    occ = np.zeros(tuple(dims), bool)
    for fr, cam in zip(frames, cams):
        p, _, _ = _backproject(fr, cam)
        ijk = np.round((p - lo) / voxel).astype(np.int64)
        ijk = ijk[np.all((ijk >= 0) & (ijk < dims), axis=1)]
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    r = int(math.ceil(trunc_voxels))
    ball = np.linalg.norm(np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1], axis=0) <= r + 0.5
    active = np.nonzero(binary_dilation(occ, structure=ball).ravel())[0]
    ii, jj, kk = np.unravel_index(active, tuple(dims))
    centres = lo + voxel * np.stack([ii, jj, kk], axis=1).astype(np.float64)
    n = len(centres)
    tsdf = np.zeros(n, np.float32)
    weight = np.zeros(n, np.float32)
    color = np.zeros((n, 3), np.float32)
    cweight = np.zeros(n, np.float32)
    for fr, cam in zip(frames, cams):
        u, v, z, ok = cam.project(centres)
        idx = np.nonzero(ok)[0]
        ui, vi = u[idx], v[idx]
        d = fr.depth[vi, ui].astype(np.float64)
        sdf = d - z[idx]
        use = (d > 0) & (sdf > -trunc)
        idx, sdf, ui, vi = idx[use], sdf[use], ui[use], vi[use]
        val = np.minimum(sdf / trunc, 1.0).astype(np.float32)
        tsdf[idx] = (tsdf[idx] * weight[idx] + val) / (weight[idx] + 1.0)
        weight[idx] += 1.0
        near = np.abs(sdf) < trunc
        cidx = idx[near]
        rgb = fr.color[vi[near], ui[near]].astype(np.float32)
        color[cidx] = (color[cidx] * cweight[cidx, None] + rgb) / (cweight[cidx, None] + 1.0)
        cweight[cidx] += 1.0
    vol = np.ones(tuple(dims), np.float32)
    vol.ravel()[active] = tsdf
    # usable corners: observed, and not truncated (a jump from +1 to a negative value is a depth-discontinuity
    # or frustum-border artefact, not a surface)
    good = np.zeros(tuple(dims), bool)
    good.ravel()[active] = (weight > 0) & (np.abs(tsdf) < 0.999)
    seen = good
    # a cube is meshed only when all 8 corners are usable (the mask applies to the cube's first corner)
    cube = seen.copy()
    cube[:-1, :-1, :-1] = (
        seen[:-1, :-1, :-1] & seen[1:, :-1, :-1] & seen[:-1, 1:, :-1] & seen[:-1, :-1, 1:]
        & seen[1:, 1:, :-1] & seen[1:, :-1, 1:] & seen[:-1, 1:, 1:] & seen[1:, 1:, 1:]
    )  # fmt: skip
    cube[-1, :, :] = False
    cube[:, -1, :] = False
    cube[:, :, -1] = False
    if not cube.any() or vol[cube].min() >= 0 or vol[cube].max() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(voxel, voxel, voxel), mask=cube)
    # with the default gradient_direction="descent", scikit-image winds the faces so that their normals point
    # towards increasing values: + is free space, so the normals face the cameras (checked in tests)
    faces = faces.astype(np.int64)
    full_col = np.zeros((int(np.prod(dims)), 3), np.float32)
    full_col[active] = color
    ijk = np.clip(np.round(verts / voxel).astype(np.int64), 0, dims - 1)
    flat = np.ravel_multi_index((ijk[:, 0], ijk[:, 1], ijk[:, 2]), tuple(dims))
    vcol = full_col[flat].astype(np.float64)
    # merge coincident vertices (the masked marching cubes can emit a few) and drop collapsed faces
    uniq, first, inv = np.unique(verts, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    faces = inv[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    return uniq.astype(np.float64) + lo, faces, vcol[first]


def _remove_small_components(v: np.ndarray, f: np.ndarray, min_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Drop connected components with fewer than `min_faces` faces (TSDF speckles from noise)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    if len(f) == 0:
        return np.zeros(0, bool), f
    n = len(v)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(adj, directed=False)
    face_comp = comp[f[:, 0]]
    sizes = np.bincount(face_comp, minlength=comp.max() + 1)
    keep_face = sizes[face_comp] >= min_faces
    keep_vert = np.zeros(n, bool)
    keep_vert[f[keep_face].reshape(-1)] = True
    return keep_vert, f[keep_face]


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals of a mesh ((0, 0, 1) for vertices without area)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], fn)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(ln > 1e-20, acc / np.maximum(ln, 1e-20), np.array([0.0, 0.0, 1.0]))
    return out


def _crop_mesh(
    v: np.ndarray, f: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the vertices in `keep` and the faces whose three vertices are kept; returns (index, faces)."""
    idx = np.nonzero(keep)[0]
    remap = -np.ones(len(v), np.int64)
    remap[idx] = np.arange(len(idx))
    fr = remap[f]
    fr = fr[(fr >= 0).all(axis=1)]
    return idx, fr


# ====================================================================================== main entry
def generate_scene(
    config: Config,
    *,
    seed: int,
    n_objects: int | None = None,
    mode: Mode = "tsdf",
    distractors: bool = True,
    split: Literal["train", "val", "test"] = "test",
    voxel: float = 0.004,
    image_size: tuple[int, int] = (640, 480),
    n_cameras: int = 4,
    noise: bool = True,
    label_tolerance: float = 0.01,
    name: str | None = None,
    timings: dict[str, float] | None = None,
) -> "Scene":
    """Generate one synthetic tabletop scan with per-point instance ground truth.

    Args:
        config: "z" (upright, random yaw), "so3" (dropped with random orientation), "pile" (stacked), "tree"
            (3-6 mugs hanging by their handles on the pegs of a mug tree), "box" (3-6 mugs dropped into an open
            box) or "shelf" (mugs upright on the 2-3 levels of a shelf); see `efem_viz.data.structures`.
        seed: scene seed; the same arguments give identical arrays.
        n_objects: number of mugs, 1..10 (default: drawn from 3..7 by the seed).
        mode: "tsdf" (fused triangle mesh, vertices are the points) or "points" (merged back-projected depth,
            voxel-downsampled).
        distractors: add 0-2 unlabelled distractors (boxes, cans, bowls, bottles).
        split: which mug seeds to draw from (`procedural.split_seeds`).
        voxel: TSDF voxel / point downsampling voxel, metres.
        image_size: (width, height) of the virtual depth cameras.
        n_cameras: number of cameras around the table (at the corners for 4).
        noise: add depth noise, dropout and colour noise.
        label_tolerance: a point takes the nearest true surface's id when closer than this (metres).
        name: scene name (default "<config>_<seed>").
        timings: if given, filled with the seconds spent per stage (poses, scan, fusion, labels); kept out of
            the provenance so that regenerating a scene gives identical files.

    Returns:
        A `Scene` (world frame, metres, +Z up, table top at z = 0) with `instance` (mug k -> k, else 0),
        categories {k: "mug"} for the mugs with labelled points, and provenance (config, seed, objects with
        category/seed/instance id/T_world_object, cameras, noise model, max penetration).

    Raises:
        ValueError: bad config, mode, split, object count, voxel or image size.
    """
    import open3d as o3d

    from efem_viz._typeshims import o3d_tensor
    from efem_viz.data.scene import Scene

    if config not in CONFIGS:
        raise ValueError(f"unknown config {config!r}; expected one of {CONFIGS}")
    if mode not in ("tsdf", "points"):
        raise ValueError(f"unknown mode {mode!r}; expected 'tsdf' or 'points'")
    if split not in ("train", "val", "test"):
        raise ValueError(f"unknown split {split!r}; expected 'train', 'val' or 'test'")
    if n_objects is not None and not 1 <= int(n_objects) <= 10:
        raise ValueError(f"n_objects must be in 1..10, got {n_objects}")
    if not 0.0005 <= voxel <= 0.05:
        raise ValueError(f"voxel must be in [0.0005, 0.05] m, got {voxel}")
    if len(image_size) != 2 or min(image_size) < 16:
        raise ValueError(f"image_size must be (width, height) >= 16, got {image_size}")
    if n_cameras < 1:
        raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), CONFIGS.index(config), 0x5CE7E])
    n_mugs = int(rng.integers(3, 7 if config in ("tree", "box") else 8)) if n_objects is None else int(n_objects)
    structure: Structure | None = None
    if config in STRUCTURE_CONFIGS:
        from efem_viz.data.structures import PEG_PLAY, PEG_RADIUS, make_structure

        structure = make_structure(config, rng, n_objects=n_mugs)  # type: ignore[arg-type]
        if config == "shelf" and n_objects is None:
            n_mugs = min(n_mugs, 2 * len(structure.levels))  # two mugs per level always fit
        if config == "tree" and n_mugs > len(structure.pegs) and n_objects is None:
            n_mugs = len(structure.pegs)  # one mug per peg
        elif config == "tree" and n_mugs > len(structure.pegs):
            logger.warning("scene %s_%d: the tree has %d pegs, hanging %d of the %d mugs", config, seed,
                           len(structure.pegs), len(structure.pegs), n_mugs)
            n_mugs = len(structure.pegs)
        objs = _sample_objects(rng, n_mugs=n_mugs, distractors=distractors, split=split,
                               hole=PEG_RADIUS + PEG_PLAY if config == "tree" else None)
    else:
        objs = _sample_objects(rng, n_mugs=n_mugs, distractors=distractors, split=split)

    # ---- poses
    penetration = 0.0
    attempts = 0
    misplaced = 0
    if config == "z":
        _place_upright(objs, rng)  # disjoint footprints, resting on the table: no contact by construction
        attempts = 1
    elif config == "shelf":
        assert structure is not None
        objs = _place_on_shelf(objs, structure, rng)  # upright on the levels, disjoint footprints: no contact
        attempts = 1
    else:
        best: tuple[tuple[int, float], list[np.ndarray]] | None = None
        fixed = structure.pieces if structure is not None else []
        for attempts in range(1, 6):
            if config == "tree":
                assert structure is not None
                _hang_on_tree(objs, structure, rng)
                _simulate(objs, rng, layout="hang", statics=structure.parts())
            elif config == "box":
                assert structure is not None
                _simulate(objs, rng, layout="box", statics=structure.parts(), floor=structure.floor)
            else:
                _simulate(objs, rng, layout="scatter" if config == "so3" else "pile")
            rep = contact_report([o.world_mesh() for o in objs], fixed=fixed)
            key = (_misplaced(config, objs, structure), rep["max_penetration"])
            if best is None or key < best[0]:
                best = (key, [o.T_world_object.copy() for o in objs])
            if key[0] == 0 and key[1] <= PENETRATION_TOLERANCE:
                break
            logger.info("scene %s_%d: %d objects misplaced, penetration %.4f m, dropping again", config, seed,
                        key[0], key[1])
        assert best is not None
        misplaced, penetration = best[0]
        for o, T in zip(objs, best[1]):
            o.T_world_object = T
        if penetration > PENETRATION_TOLERANCE:
            logger.warning(
                "scene %s_%d: interpenetration %.1f mm after %d drops (tolerance %.1f mm)",
                config, seed, penetration * 1e3, attempts, PENETRATION_TOLERANCE * 1e3,
            )  # fmt: skip
        if misplaced:
            logger.warning("scene %s_%d: %d objects did not stay %s after %d drops", config, seed, misplaced,
                           "on their pegs" if config == "tree" else "in the box", attempts)
    t_pose = time.perf_counter()

    # ---- ray-casting scene: geometry 0 = table, 1.. = objects
    import trimesh

    table = trimesh.creation.box(extents=[2 * TABLE_HALF, 2 * TABLE_HALF, TABLE_THICKNESS])
    table.apply_translation([0, 0, -TABLE_THICKNESS / 2])
    # geometry 0 = table, then the structure's pieces (background too), then the objects
    fixtures = list(structure.pieces) if structure is not None else []
    n_fix = 1 + len(fixtures)
    world = [table] + fixtures + [o.world_mesh() for o in objs]
    rc = o3d.t.geometry.RaycastingScene()
    for m in world:
        rc.add_triangles(
            o3d_tensor(np.asarray(m.vertices, np.float32)),
            o3d_tensor(np.asarray(m.faces, np.uint32)),
        )
    fix_colors = [structure.color] * len(fixtures) if structure is not None else []
    albedo = np.stack([_TABLE_COLOR] + fix_colors + [o.color for o in objs])
    obj_lo = np.min([m.bounds[0] for m in world[n_fix:]], axis=0)
    obj_hi = np.max([m.bounds[1] for m in world[n_fix:]], axis=0)
    margin = 0.04
    crop_lo = np.array([max(obj_lo[0] - margin, -TABLE_HALF), max(obj_lo[1] - margin, -TABLE_HALF), -0.02])
    crop_hi = np.array(
        [min(obj_hi[0] + margin, TABLE_HALF), min(obj_hi[1] + margin, TABLE_HALF), obj_hi[2] + 0.03]
    )
    target = np.array([(obj_lo[0] + obj_hi[0]) / 2, (obj_lo[1] + obj_hi[1]) / 2, 0.04])
    if config == "tree":
        target[2] = (obj_lo[2] + obj_hi[2]) / 2
        cams = _make_cameras(rng, target, n_cameras=n_cameras, image_size=image_size, heights=(0.35, 0.6))
    elif config == "box":
        cams = _make_cameras(rng, target, n_cameras=n_cameras, image_size=image_size, heights=(0.6, 0.8))
    elif config == "shelf":
        assert structure is not None
        target[2] = (obj_lo[2] + obj_hi[2]) / 2
        cams = _make_cameras(rng, target, n_cameras=n_cameras, image_size=image_size,
                             heights=(0.1, obj_hi[2] + 0.2), front=structure.front)
    else:
        cams = _make_cameras(rng, target, n_cameras=n_cameras, image_size=image_size)
    frames = [_render(rc, c, albedo, rng, noise=noise, crop_lo=crop_lo, crop_hi=crop_hi) for c in cams]
    visible_px = np.zeros(len(world), np.int64)
    for fr in frames:
        ids, cnt = np.unique(fr.visible_ids[fr.visible_ids >= 0], return_counts=True)
        visible_px[ids] += cnt
    t_scan = time.perf_counter()

    # ---- fusion / merging
    faces: np.ndarray | None
    if mode == "tsdf":
        v, f, c = _fuse_tsdf(frames, cams, voxel=voxel, lo=crop_lo, hi=crop_hi)
        inside = np.all((v >= crop_lo - voxel) & (v <= crop_hi + voxel), axis=1)
        idx, f = _crop_mesh(v, f, inside)
        v, c = v[idx], c[idx]
        keep, f = _remove_small_components(v, f, min_faces=20)
        idx, f = _crop_mesh(v, f, keep)
        points, colors, faces = v[idx], c[idx], f
        if len(points) == 0:
            raise RuntimeError(f"scene {config}_{seed}: TSDF fusion produced an empty mesh")
        normals = _vertex_normals(points, faces)
    else:
        parts = [_backproject(fr, cam) for fr, cam in zip(frames, cams)]
        p_all = np.concatenate([q[0] for q in parts])
        c_all = np.concatenate([q[1] for q in parts])
        n_all = np.concatenate([q[2] for q in parts])
        if len(p_all) == 0:
            raise RuntimeError(f"scene {config}_{seed}: the cameras saw nothing")
        points, colors, n_avg = _voxel_average(p_all, c_all, n_all, voxel)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        normals = np.asarray(pcd.normals, np.float64).copy()
        # orient like the (averaged) sensor-facing surface normals
        flip = np.sum(normals * n_avg, axis=1) < 0
        normals[flip] *= -1
        faces = None
    t_fuse = time.perf_counter()

    # ---- ground truth: nearest true surface within tolerance
    q = rc.compute_closest_points(o3d_tensor(points.astype(np.float32)))
    gid = q["geometry_ids"].numpy().astype(np.int64)
    dist = np.linalg.norm(q["points"].numpy() - points.astype(np.float32), axis=1)
    labels_of_geom = np.array([0] * n_fix + [o.label for o in objs], np.int32)
    instance = np.where(dist < label_tolerance, labels_of_geom[gid], 0).astype(np.int32)
    present = set(np.unique(instance[instance > 0]).tolist())
    categories = {o.label: "mug" for o in objs if o.label in present}
    counts = np.bincount(instance, minlength=len(objs) + 1)

    provenance: dict[str, Any] = {
        "generator": "efem_viz.data.synth",
        "command": _command(config, seed, n_objects, mode, distractors, split, voxel),
        "config": config,
        "seed": int(seed),
        "mode": mode,
        "split": split,
        "voxel": voxel,
        "distractors": distractors,
        "image_size": list(image_size),
        "n_cameras": n_cameras,
        "noise": "kinect sigma(z)=1.2mm+1.9mm*(z-0.4)^2, grazing dropout 65-85 deg" if noise else "none",
        "label_tolerance": label_tolerance,
        "table": {"half_size": TABLE_HALF, "top_z": 0.0},
        "crop": [crop_lo.round(4).tolist(), crop_hi.round(4).tolist()],
        "mug_seeds": [o.seed for o in objs if o.category == "mug"],
        "objects": [
            {
                "category": o.category,
                "seed": o.seed,
                "instance_id": o.label,
                "T_world_object": np.round(o.T_world_object, 6).tolist(),
                "visible_pixels": int(visible_px[i + n_fix]),
                "labelled_points": int(counts[o.label]) if o.label > 0 else 0,
            }
            for i, o in enumerate(objs)
        ],
        "cameras": [
            {"K": np.round(c.K, 4).tolist(), "T_world_camera": np.round(c.T_world_camera, 6).tolist(),
             "size": [c.width, c.height]}
            for c in cams
        ],  # fmt: skip
        "max_penetration_m": round(float(penetration), 5),
        "drops": attempts,
    }
    if structure is not None:
        provenance["structure"] = structure.describe()
        provenance["misplaced_objects"] = int(misplaced)
    stages = {
        "poses": round(t_pose - t0, 3),
        "scan": round(t_scan - t_pose, 3),
        "fusion": round(t_fuse - t_scan, 3),
        "labels": round(time.perf_counter() - t_fuse, 3),
    }
    if timings is not None:
        timings.update(stages)
    logger.debug("scene %s_%d stages (s): %s", config, seed, stages)
    return Scene.create(
        name or f"{config}_{seed}",
        points.astype(np.float32),
        normals=normals.astype(np.float32),
        colors=np.clip(np.round(colors), 0, 255).astype(np.uint8),
        faces=faces,
        instance=instance,
        categories=categories,
        provenance=json.loads(json.dumps(provenance)),
    )


def _command(
    config: str, seed: int, n_objects: int | None, mode: str, distractors: bool, split: str, voxel: float
) -> str:
    cmd = f"efem-viz generate --config {config} --seed {seed} --count 1 --mode {mode}"
    if n_objects is not None:
        cmd += f" --objects {n_objects}"
    if not distractors:
        cmd += " --no-distractors"
    if split != "test":
        cmd += f" --split {split}"
    if voxel != 0.004:
        cmd += f" --voxel {voxel}"
    return cmd


# ====================================================================================== CLI
@dataclass
class GenerateArgs:
    """Generate synthetic tabletop scans (procedural mugs on a table) with per-point ground truth."""

    config: Config = "z"
    """Scene configuration: z (upright mugs), so3 (random orientations), pile (stacked, touching), tree (hanging
    on a mug tree), box (inside an open box), shelf (on the levels of a shelf)."""
    count: int = 1
    """Number of scenes; scene i uses seed `seed + i`."""
    seed: int = 0
    """Seed of the first scene."""
    out: Path = Path("generated")
    """Output folder; files are named <prefix><config>_<seed>.ply."""
    mode: Mode = "tsdf"
    """tsdf: fused mesh (like the paper's scans); points: merged depth points, voxel-downsampled."""
    objects: int | None = None
    """Mugs per scene, 1..10 (default: 3..7 drawn by the seed)."""
    distractors: bool = True
    """Add 0-2 unlabelled distractor objects (boxes, cans, bowls, bottles)."""
    split: Literal["train", "val", "test"] = "test"
    """Mug seed split to draw from."""
    voxel: float = 0.004
    """TSDF voxel / point spacing in metres."""
    prefix: str = ""
    """Prefix of the file and scene names (e.g. "syn_" gives syn_z_0.ply)."""

    def run(self) -> int:
        """Generate the scenes with a progress bar; returns the exit code."""
        from tqdm import tqdm

        from efem_viz.data.io import save_scene

        if self.count < 1:
            raise ValueError(f"--count must be >= 1, got {self.count}")
        self.out.mkdir(parents=True, exist_ok=True)
        bar = tqdm(range(self.seed, self.seed + self.count), desc=f"generate {self.config}", unit="scene")
        for s in bar:
            name = f"{self.prefix}{self.config}_{s}"
            scene = generate_scene(
                self.config,
                seed=s,
                n_objects=self.objects,
                mode=self.mode,
                distractors=self.distractors,
                split=self.split,
                voxel=self.voxel,
                name=name,
            )
            if self.prefix:
                prov = dict(scene.provenance)
                prov["command"] = f"{prov['command']} --prefix {self.prefix}"
                scene = dataclasses.replace(scene, provenance=prov)
            path = save_scene(scene, self.out / f"{name}.ply")
            bar.set_postfix(points=scene.num_points, mugs=len(scene.categories))
            logger.info("wrote %s (%d points, %d mugs)", path, scene.num_points, len(scene.categories))
        return 0
