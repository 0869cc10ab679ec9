"""Physics of the dropped configurations (pybullet over convex pieces) and the contact check of final poses."""

from __future__ import annotations

import os
import tempfile
from typing import TYPE_CHECKING, Any, Literal, Sequence, cast

import numpy as np

from efem_viz.data.synth.layout import SceneObject, scatter_xy
from efem_viz.geometry.transforms import random_rotation
from efem_viz.data.synth.stage import Stage
from efem_viz.geometry.transforms import rotation_to_quat_wxyz

if TYPE_CHECKING:
    import trimesh


PENETRATION_TOLERANCE = 0.002
"""Largest accepted interpenetration depth between final meshes (metres)."""

COLLISION_SHRINK = 0.0008
"""Collision pieces are pulled in by this much (metres) to offset Bullet's convex-hull margin."""


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


def simulate(
    objs: list[SceneObject],
    rng: np.random.Generator,
    *,
    layout: Literal["scatter", "pile", "box", "hang"],
    stage: Stage,
    statics: Sequence[np.ndarray] = (),
    floor: tuple[np.ndarray, np.ndarray] | None = None,
    floor_top: float = 0.0,
    max_seconds: float = 6.0,
) -> None:
    """Drop the objects with random orientations (pybullet, DIRECT mode) onto the stage's support (a table or
    a floor, its top at z = 0) and store their resting poses.

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
        support = pb.createCollisionShape(
            pb.GEOM_BOX, halfExtents=[stage.half_size, stage.half_size, 0.05], physicsClientId=cid
        )
        tid = pb.createMultiBody(0, support, basePosition=[0, 0, -0.05], physicsClientId=cid)
        pb.changeDynamics(tid, -1, lateralFriction=0.8, physicsClientId=cid)
        coms = [np.asarray(o.mesh.center_mass, np.float64) for o in objs]
        if layout == "hang":
            rots = [o.T_world_object[:3, :3].copy() for o in objs]
        else:
            rots = [random_rotation(rng) for _ in objs]
        radii = [
            float(np.linalg.norm(np.asarray(o.mesh.vertices) - c, axis=1).max()) for o, c in zip(objs, coms)
        ]
        xy = scatter_xy(rng, radii, stage=stage, gap=0.005) if layout == "scatter" else None
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
                    pos = _drop_position(pb, cid, bodies, rng, radius=radii[k],
                                         floor=floor if layout == "box" else None,
                                         floor_top=floor_top, spread=stage.pile_spread)
                bodies.append(_add_body(pb, cid, o, shape, pos, R, layout=layout))
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


def _drop_position(pb: Any, cid: int, bodies: list[int], rng: np.random.Generator, *, radius: float,
                   floor: tuple[np.ndarray, np.ndarray] | None, floor_top: float, spread: float) -> list[float]:
    """Where a piled or boxed object of bounding radius `radius` is dropped from: just clear of `floor_top` and of
    the top of the `bodies` already lying there, above a random spot of `floor` (box), else above the centre of
    the pile so far (or near the origin for the first), moved by a normal offset of deviation `spread`."""
    top = floor_top
    if bodies:
        top = max(top, max(pb.getAABB(b, physicsClientId=cid)[1][2] for b in bodies))
    if floor is not None:
        lo, hi = np.asarray(floor[0], np.float64), np.asarray(floor[1], np.float64)
        inset = np.minimum(radius, (hi - lo) / 2 - 0.005)
        centre = rng.uniform(lo + inset, hi - inset)
    elif bodies:  # pile: above the centre of the pile so far, just clear of its top
        poses = [pb.getBasePositionAndOrientation(b, physicsClientId=cid) for b in bodies]
        centre = np.mean([q[0] for q in poses], axis=0)[:2] + rng.normal(0.0, spread, 2)
    else:
        centre = rng.normal(0.0, spread, 2)
    return [centre[0], centre[1], top + radius + 0.005]


def _add_body(pb: Any, cid: int, o: SceneObject, shape: int, pos: list[float], R: np.ndarray, *,
              layout: Literal["scatter", "pile", "box", "hang"]) -> int:
    """Add one object as a rigid body at `pos` (its centre of mass, world frame) turned by `R`: mass from its
    volume, friction and damping for the layout (hanging objects damped more). Returns the body id."""
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
    return b


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
    fixed: Sequence["trimesh.Trimesh"] = (), rays: int = 1,
) -> dict[str, Any]:
    """Interpenetration and contact of posed meshes (world frame, the support's top (table or floor) at z = 0).

    Args:
        objs_world: watertight meshes in the world frame.
        samples: surface samples per mesh (plus its vertices) used to probe the others.
        seed: seed of the surface sampling.
        fixed: watertight pieces of a fixed structure (world frame): objects must not penetrate them; the pieces
            may overlap each other.
        rays: rays cast per probe to tell inside from outside (odd): one ray through an edge or a vertex can
            flip a probe's sign, and a majority of three votes the flip away (solids built of boxes, as the
            chairs, meet such rays often).

    Returns:
        {"max_penetration": metres (objects into each other, into the structure, or below the support's top),
         "pair_penetration": (K, K) array, [i, j] = deepest point of i inside j,
         "pair_gap": (K, K) array, [i, j] = smallest distance from i's surface to j (0 when touching or
         penetrating; inf when their bounding boxes are more than 1 cm apart),
         "gap": (K,) distance from each object to the nearest other object, structure piece or the support's top}.
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
            sd = scene.compute_signed_distance(o3d_tensor(p[near]), nsamples=rays).numpy()
            pen[i, j] = max(-float(sd.min()), 0.0)
            pair_gap[i, j] = max(float(sd.min()), 0.0)
            gap[i] = min(gap[i], pair_gap[i, j])
    return {
        "max_penetration": float(max(pen.max(initial=0.0), table_pen)),
        "pair_penetration": pen[:k, :k],
        "pair_gap": pair_gap[:k, :k],
        "gap": gap[:k],
    }
