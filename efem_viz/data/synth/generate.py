"""`generate_scene`: one synthetic scan, step after step (layout → poses → scan → fusion → labels).

Each step is a function of its own; one NumPy Generator, seeded from (seed, config), is passed through them in
the same order, so the same arguments give identical arrays. The scene's `Stage` (a table top, or a room floor
for chairs; chosen by the targets) sets the scale every step works at.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from efem_viz.data.synth.fusion import (
    crop_mesh,
    fuse_tsdf,
    remove_small_components,
    area_weighted_normals,
    voxel_average,
)
from efem_viz.data.synth.labels import label_points
from efem_viz.data.synth.layout import (
    CONFIGS,
    STRUCTURE_CONFIGS,
    Config,
    Mode,
    hang_on_tree,
    count_misplaced,
    SceneObject,
    place_on_shelf,
    place_upright,
    sample_objects,
)
from efem_viz.data.synth.physics import PENETRATION_TOLERANCE, simulate, contact_report
from efem_viz.data.synth.render import frame_points, RenderedFrame, make_cameras, render_frames
from efem_viz.data.synth.stage import Stage, stage_for

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.data.structures import Structure
    from efem_viz.geometry.camera import Camera

logger = logging.getLogger(__name__)


def generate_scene(
    config: Config,
    *,
    seed: int,
    n_objects: int | None = None,
    mode: Mode = "tsdf",
    distractors: bool = True,
    split: Literal["train", "val", "test"] = "test",
    voxel: float | None = None,
    image_size: tuple[int, int] = (640, 480),
    n_cameras: int | None = None,
    noise: bool | None = None,
    label_tolerance: float | None = None,
    name: str | None = None,
    timings: dict[str, float] | None = None,
    targets: str = "mug",
) -> "Scene":
    """Generate one synthetic scan (mugs or kitchen objects on a table, chairs on a floor) with per-point
    instance ground truth.

    Args:
        config: "z" (upright, random yaw), "so3" (dropped with random orientation), "pile" (stacked), "tree"
            (3-6 mugs hanging by their handles on the pegs of a mug tree), "box" (3-6 mugs dropped into an open
            box) or "shelf" (mugs upright on the 2-3 levels of a shelf); see `efem_viz.data.structures`.
        seed: scene seed; the same arguments give identical arrays.
        n_objects: number of labelled objects, 1..10 (default: drawn by the seed, 3..7 on the table, 2..5
            chairs).
        mode: "tsdf" (fused triangle mesh, vertices are the points) or "points" (merged back-projected depth,
            voxel-downsampled).
        distractors: add 0-2 unlabelled distractors (boxes, cans, bowls, bottles on the table; furniture-sized
            blocks, `procedural.cabinet_with_parts`, on the floor).
        split: which object seeds to draw from (`procedural.split_seeds`).
        voxel: TSDF voxel / point downsampling voxel, metres (default: the stage's, 4 mm on the table, 1 cm on
            the floor).
        image_size: (width, height) of the virtual depth cameras.
        n_cameras: number of cameras around the objects (default: the stage's, 4 at the table's corners, 8 on
            the floor).
        noise: add depth noise, dropout and colour noise (default: the stage's, on for the table, off, ideal
            depth, on the floor).
        label_tolerance: a point takes the nearest true surface's id when closer than this (metres; default:
            the stage's, 1 cm on the table, 2.5 cm on the floor).
        name: scene name (default "<config>_<seed>").
        timings: if given, filled with the seconds spent per step (poses, scan, fusion, labels); kept out of
            the provenance so that regenerating a scene gives identical files.
        targets: what the labelled objects are (a key of `stage.TARGET_STAGES`): "mug"; "kitchen" (a training
            family: mugs, bowls, bottles and cans mixed, the paper's SynKit; boxes as distractors); or "chair"
            (the paper's SynChairs: procedural chairs on a 6 m square floor scanned from about 3 m, cabinets as
            distractors). All but "mug" take the configurations z, so3 and pile only.

    Returns:
        A `Scene` (world frame, metres, +Z up, the support's top (table or floor) at z = 0) with `instance`
        (labelled object k -> k, else 0), categories {k: its category} for the labelled objects with labelled
        points, and provenance (config, seed, the command that repeats it, voxel, the support, objects with
        category/seed/instance id/T_world_object, cameras, noise model, max penetration).

    Raises:
        ValueError: bad config, targets (or a configuration the targets do not take), mode, split, object
            count, voxel or image size.
    """
    import open3d as o3d

    from efem_viz.data.scene import Scene

    stage = _check_arguments(config, targets=targets, mode=mode, split=split, n_objects=n_objects, voxel=voxel,
                             image_size=image_size, n_cameras=n_cameras)
    voxel = stage.voxel if voxel is None else voxel
    n_cameras = stage.n_cameras if n_cameras is None else n_cameras
    noise = stage.noise if noise is None else noise
    label_tolerance = stage.label_tolerance if label_tolerance is None else label_tolerance
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    clock = [time.perf_counter()]  # the end of each step
    rng = np.random.default_rng([int(seed), CONFIGS.index(config), 0x5CE7E])
    objs, structure = _draw_objects(config, seed, rng, n_objects=n_objects, distractors=distractors, split=split,
                                    targets=targets, stage=stage)
    objs, poses = _pose_objects(config, seed, objs, structure, rng, stage=stage)
    clock.append(time.perf_counter())
    scan = _scan(config, objs, structure, rng, stage=stage, n_cameras=n_cameras, image_size=image_size,
                 noise=noise)
    clock.append(time.perf_counter())
    fused = _fuse(scan, mode=mode, voxel=voxel, what=f"scene {config}_{seed}")
    clock.append(time.perf_counter())
    labels = label_points(scan.raycaster, fused.points, n_fixtures=scan.n_fixtures, objects=objs,
                          tolerance=label_tolerance)
    provenance = _provenance(
        config, seed, n_objects=n_objects, mode=mode, distractors=distractors, split=split, voxel=voxel,
        image_size=image_size, n_cameras=n_cameras, noise=noise, label_tolerance=label_tolerance, objs=objs,
        targets=targets, stage=stage,
        structure=structure, poses=poses, scan=scan, counts=labels.counts,
    )  # fmt: skip
    clock.append(time.perf_counter())
    steps = {k: round(b - a, 3) for k, a, b in zip(("poses", "scan", "fusion", "labels"), clock, clock[1:])}
    if timings is not None:
        timings.update(steps)
    logger.debug("scene %s_%d steps (s): %s", config, seed, steps)
    return Scene.create(name or f"{config}_{seed}", fused.points.astype(np.float32),
                        normals=fused.normals.astype(np.float32),
                        colors=np.clip(np.round(fused.colors), 0, 255).astype(np.uint8), faces=fused.faces,
                        instance=labels.instance, categories=labels.categories,
                        provenance=json.loads(json.dumps(provenance)))


def _check_arguments(
    config: str, *, targets: str, mode: str, split: str, n_objects: int | None, voxel: float | None,
    image_size: tuple[int, int], n_cameras: int | None,
) -> Stage:
    """The stage of `targets` (`stage.stage_for`); ValueError for an argument of `generate_scene` out of its
    range, or a structure configuration (tree, box, shelf) with other targets than mugs."""
    if config not in CONFIGS:
        raise ValueError(f"unknown config {config!r}; expected one of {CONFIGS}")
    stage = stage_for(targets)
    if targets != "mug" and config in STRUCTURE_CONFIGS:
        raise ValueError(f"config {config!r} holds mugs only; {targets} scenes are z, so3 or pile")
    if mode not in ("tsdf", "points"):
        raise ValueError(f"unknown mode {mode!r}; expected 'tsdf' or 'points'")
    if split not in ("train", "val", "test"):
        raise ValueError(f"unknown split {split!r}; expected 'train', 'val' or 'test'")
    if n_objects is not None and not 1 <= int(n_objects) <= 10:
        raise ValueError(f"n_objects must be in 1..10, got {n_objects}")
    if voxel is not None and not 0.0005 <= voxel <= 0.05:
        raise ValueError(f"voxel must be in [0.0005, 0.05] m, got {voxel}")
    if len(image_size) != 2 or min(image_size) < 16:
        raise ValueError(f"image_size must be (width, height) >= 16, got {image_size}")
    if n_cameras is not None and n_cameras < 1:
        raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
    return stage


# ====================================================================================== layout
def _draw_objects(
    config: str, seed: int, rng: np.random.Generator, *, n_objects: int | None, distractors: bool, split: str,
    targets: str, stage: Stage,
) -> tuple[list[SceneObject], "Structure | None"]:
    """The scene's supporting structure (tree, box, shelf configurations) and its objects: the labelled object
    count (drawn from the stage's range by the seed unless given; at most 6, or what the structure holds, in a
    structure) and the labelled objects and distractors."""
    lo, hi = stage.object_count
    hi = min(hi, 6) if config in ("tree", "box") else hi
    n_mugs = int(rng.integers(lo, hi + 1)) if n_objects is None else int(n_objects)
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
        objs = sample_objects(rng, n_mugs=n_mugs, distractors=distractors, split=split,
                               hole=PEG_RADIUS + PEG_PLAY if config == "tree" else None, stage=stage)
    else:
        objs = sample_objects(rng, n_mugs=n_mugs, distractors=distractors, split=split, targets=targets,
                               stage=stage)
    return objs, structure


# ====================================================================================== poses
@dataclass(frozen=True)
class _Poses:
    """How the final poses were reached."""

    attempts: int
    """Drops tried (1 for the configurations placed without physics)."""
    misplaced: int
    """Objects off their pegs or out of the box in the poses kept."""
    penetration: float
    """Largest interpenetration of the poses kept (metres)."""


def _pose_objects(
    config: str, seed: int, objs: list[SceneObject], structure: "Structure | None", rng: np.random.Generator, *,
    stage: Stage,
) -> tuple[list[SceneObject], _Poses]:
    """Place the objects: by construction ("z", "shelf"; the shelf may keep fewer objects), else by physics,
    dropped again (at most 5 times) until nothing is misplaced or interpenetrates; the best drop is kept.

    Returns:
        The objects (posed in place; the list the scene keeps) and how the poses were reached.
    """
    if config == "z":
        place_upright(objs, rng, stage=stage)  # disjoint footprints, resting on the support: no contact
        return objs, _Poses(1, 0, 0.0)
    if config == "shelf":
        assert structure is not None
        objs = place_on_shelf(objs, structure, rng)  # upright on the levels, disjoint footprints: no contact
        return objs, _Poses(1, 0, 0.0)
    best: tuple[tuple[int, float], list[np.ndarray]] | None = None
    fixed = structure.pieces if structure is not None else []
    attempts = 0
    for attempts in range(1, 6):
        _drop(config, objs, structure, rng, stage=stage)
        rep = contact_report([o.world_mesh() for o in objs], fixed=fixed, rays=stage.contact_rays)
        key = (count_misplaced(config, objs, structure), rep["max_penetration"])
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
    return objs, _Poses(attempts, misplaced, penetration)


def _drop(config: str, objs: list[SceneObject], structure: "Structure | None", rng: np.random.Generator, *,
          stage: Stage) -> None:
    """One physics drop of the configuration ("tree", "box", "so3" scattered, "pile") onto the stage."""
    if config == "tree":
        assert structure is not None
        hang_on_tree(objs, structure, rng)
        simulate(objs, rng, layout="hang", stage=stage, statics=structure.parts())
    elif config == "box":
        assert structure is not None
        simulate(objs, rng, layout="box", stage=stage, statics=structure.parts(), floor=structure.floor)
    else:
        simulate(objs, rng, layout="scatter" if config == "so3" else "pile", stage=stage)


# ====================================================================================== scan
@dataclass(frozen=True)
class _Scan:
    """The ray-casting scene and what the cameras saw."""

    raycaster: Any
    """open3d `RaycastingScene`: geometry 0 = the support (table or floor), then the structure's pieces, then
    the objects."""
    n_fixtures: int
    """Background geometries (the support and the structure's pieces) before the objects."""
    crop_lo: np.ndarray
    """(3,) float64 lower corner of the box the scan keeps (world)."""
    crop_hi: np.ndarray
    """(3,) float64 upper corner."""
    cameras: list["Camera"]
    frames: list[RenderedFrame]
    visible_px: np.ndarray
    """(G,) int64 pixels per geometry seen over all frames."""


def _scan(
    config: str, objs: list[SceneObject], structure: "Structure | None", rng: np.random.Generator, *, stage: Stage,
    n_cameras: int, image_size: tuple[int, int], noise: bool,
) -> _Scan:
    """Build the ray-casting scene (the stage's support, structure, objects), place the cameras for the
    configuration around the objects' bounds and render one noisy depth frame per camera."""
    import open3d as o3d
    import trimesh

    from efem_viz._typeshims import o3d_tensor

    half = stage.half_size
    support = trimesh.creation.box(extents=[2 * half, 2 * half, stage.thickness])
    support.apply_translation([0, 0, -stage.thickness / 2])
    # geometry 0 = the support, then the structure's pieces (background too), then the objects
    fixtures = list(structure.pieces) if structure is not None else []
    n_fix = 1 + len(fixtures)
    world = [support] + fixtures + [o.world_mesh() for o in objs]
    rc = o3d.t.geometry.RaycastingScene()
    for m in world:
        rc.add_triangles(
            o3d_tensor(np.asarray(m.vertices, np.float32)),
            o3d_tensor(np.asarray(m.faces, np.uint32)),
        )
    fix_colors = [structure.color] * len(fixtures) if structure is not None else []
    albedo = np.stack([np.array(stage.color, np.float64)] + fix_colors + [o.color for o in objs])
    obj_lo = np.min([m.bounds[0] for m in world[n_fix:]], axis=0)
    obj_hi = np.max([m.bounds[1] for m in world[n_fix:]], axis=0)
    margin = stage.crop_margin
    crop_lo = np.array([max(obj_lo[0] - margin, -half), max(obj_lo[1] - margin, -half), -stage.crop_below])
    crop_hi = np.array(
        [min(obj_hi[0] + margin, half), min(obj_hi[1] + margin, half), obj_hi[2] + stage.crop_above]
    )
    target = np.array([(obj_lo[0] + obj_hi[0]) / 2, (obj_lo[1] + obj_hi[1]) / 2, stage.aim_height])
    heights: tuple[float, float] | None = None  # the stage's
    front: np.ndarray | None = None
    if config == "tree":
        target[2] = (obj_lo[2] + obj_hi[2]) / 2
        heights = (0.35, 0.6)
    elif config == "box":
        heights = (0.6, 0.8)
    elif config == "shelf":
        assert structure is not None
        target[2] = (obj_lo[2] + obj_hi[2]) / 2
        heights, front = (0.1, obj_hi[2] + 0.2), structure.front
    reach = max(float(np.linalg.norm(np.asarray(m.vertices)[:, :2] - target[:2], axis=1).max()) for m in world[n_fix:])
    cams = make_cameras(rng, target, stage=stage, n_cameras=n_cameras, image_size=image_size, heights=heights,
                         front=front, reach=reach)
    frames = [
        render_frames(rc, c, albedo, rng, noise=noise, crop_lo=crop_lo, crop_hi=crop_hi, max_range=stage.max_range)
        for c in cams
    ]
    visible_px = np.zeros(len(world), np.int64)
    for fr in frames:
        ids, cnt = np.unique(fr.visible_ids[fr.visible_ids >= 0], return_counts=True)
        visible_px[ids] += cnt
    return _Scan(rc, n_fix, crop_lo, crop_hi, cams, frames, visible_px)


# ====================================================================================== fusion
@dataclass(frozen=True)
class _Fused:
    """The scan's points: mesh vertices (TSDF) or voxel-averaged points."""

    points: np.ndarray
    """(N, 3) float64 world."""
    colors: np.ndarray
    """(N, 3) float64 RGB 0..255."""
    normals: np.ndarray
    """(N, 3) float64 unit normals, world."""
    faces: np.ndarray | None
    """(M, 3) faces of the TSDF mesh, None for points."""


def _fuse(scan: _Scan, *, mode: str, voxel: float, what: str) -> _Fused:
    """Fuse the frames: a TSDF mesh cropped to the scan box without its small components ("tsdf"), or the
    back-projected points voxel-averaged, normals estimated and oriented towards the sensors ("points").

    Raises:
        RuntimeError: the fusion produced nothing (`what` names the scene).
    """
    import open3d as o3d

    crop_lo, crop_hi, frames, cams = scan.crop_lo, scan.crop_hi, scan.frames, scan.cameras
    if mode == "tsdf":
        v, f, c = fuse_tsdf(frames, cams, voxel=voxel, lo=crop_lo, hi=crop_hi)
        inside = np.all((v >= crop_lo - voxel) & (v <= crop_hi + voxel), axis=1)
        idx, f = crop_mesh(v, f, inside)
        v, c = v[idx], c[idx]
        keep, f = remove_small_components(v, f, min_faces=20)
        idx, f = crop_mesh(v, f, keep)
        points, colors, faces = v[idx], c[idx], f
        if len(points) == 0:
            raise RuntimeError(f"{what}: TSDF fusion produced an empty mesh")
        return _Fused(points, colors, area_weighted_normals(points, faces), faces)
    parts = [frame_points(fr, cam) for fr, cam in zip(frames, cams)]
    p_all = np.concatenate([q[0] for q in parts])
    c_all = np.concatenate([q[1] for q in parts])
    n_all = np.concatenate([q[2] for q in parts])
    if len(p_all) == 0:
        raise RuntimeError(f"{what}: the cameras saw nothing")
    points, colors, n_avg = voxel_average(p_all, c_all, n_all, voxel)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    normals = np.asarray(pcd.normals, np.float64).copy()
    # orient like the (averaged) sensor-facing surface normals
    flip = np.sum(normals * n_avg, axis=1) < 0
    normals[flip] *= -1
    return _Fused(points, colors, normals, None)


# ====================================================================================== provenance
def _provenance(
    config: str, seed: int, *, n_objects: int | None, mode: str, distractors: bool, split: str, voxel: float,
    image_size: tuple[int, int], n_cameras: int, noise: bool, label_tolerance: float, objs: list[SceneObject],
    structure: "Structure | None", poses: _Poses, scan: _Scan, counts: np.ndarray, targets: str, stage: Stage,
) -> dict[str, Any]:
    """What made the scene: the arguments (and the command that repeats them), the support (table or floor),
    the crop, every object (category, seed, instance id, pose, pixels seen, points labelled), the cameras, the
    physics outcome."""
    n_fix = scan.n_fixtures
    provenance: dict[str, Any] = {
        "generator": "efem_viz.data.synth",
        "command": _command(config, seed, n_objects, mode, distractors, split, voxel, targets, stage=stage),
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
        stage.support: {"half_size": stage.half_size, "top_z": 0.0},
        "crop": [scan.crop_lo.round(4).tolist(), scan.crop_hi.round(4).tolist()],
        "mug_seeds": [o.seed for o in objs if o.category == "mug"],
        "objects": [
            {
                "category": o.category,
                "seed": o.seed,
                "instance_id": o.label,
                "T_world_object": np.round(o.T_world_object, 6).tolist(),
                "visible_pixels": int(scan.visible_px[i + n_fix]),
                "labelled_points": int(counts[o.label]) if o.label > 0 else 0,
            }
            for i, o in enumerate(objs)
        ],
        "cameras": [
            {"K": np.round(c.K, 4).tolist(), "T_world_camera": np.round(c.T_world_camera, 6).tolist(),
             "size": [c.width, c.height]}
            for c in scan.cameras
        ],  # fmt: skip
        "max_penetration_m": round(float(poses.penetration), 5),
        "drops": poses.attempts,
    }
    if targets != "mug":
        provenance["targets"] = targets
    if structure is not None:
        provenance["structure"] = structure.describe()
        provenance["misplaced_objects"] = int(poses.misplaced)
    return provenance


def _command(
    config: str, seed: int, n_objects: int | None, mode: str, distractors: bool, split: str, voxel: float,
    targets: str, *, stage: Stage,
) -> str:
    """The `efem-viz generate` command line that makes this scene again (the voxel only when not the stage's
    default)."""
    cmd = f"efem-viz generate --config {config} --seed {seed} --count 1 --mode {mode}"
    if targets != "mug":
        cmd += f" --targets {targets}"
    if n_objects is not None:
        cmd += f" --objects {n_objects}"
    if not distractors:
        cmd += " --no-distractors"
    if split != "test":
        cmd += f" --split {split}"
    if voxel != stage.voxel:
        cmd += f" --voxel {voxel}"
    return cmd
