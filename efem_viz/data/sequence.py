"""Posed RGB-D sequences and multi-view rigs fused into one scan, as the paper's real scenes were made.

A sequence is a folder of depth images with a camera pose per frame (and colour images), in one of the layouts:

* **7-Scenes style**: ``frame-000000.depth.png`` / ``.color.png`` / ``.pose.txt`` (a 4x4 camera-to-world matrix),
  the intrinsics from ``camera-intrinsics.txt`` / ``intrinsics.txt`` in the folder (3x3 or 4x4) or given;
* **ScanNet's exported frames** (SensReader): ``depth/<i>.png``, ``color/<i>.jpg``, ``pose/<i>.txt``,
  ``intrinsic/intrinsic_depth.txt``; colour images larger than the depth are resampled to it;
* **TUM RGB-D** (the Freiburg benchmark's folders): ``depth.txt`` / ``rgb.txt`` (``timestamp path`` lines) and
  ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``). The streams are associated by time, as the benchmark's
  own tools do: each depth image takes the colour image nearest in time (within `TUM_MAX_DT`) and the pose
  interpolated between the two ground-truth samples around it (translation linearly, rotation by slerp; a frame
  outside the ground truth or in a gap longer than `TUM_MAX_GAP` is skipped, as tracking-lost ScanNet frames are).
  The intrinsics come from a file in the folder, or are given, or are the benchmark's published ones for a folder
  named after a Freiburg 1, 2 or 3 sequence (said in one line);
* **a list with a poses file**: ``depth/`` and ``color/`` folders (or depth images alone) sorted by name, and a poses
  file with one camera-to-world matrix per frame (16 numbers per line, or 4 lines of 4), in frame order.

Depth PNGs hold millimetres (``depth_scale`` 1000) except in the TUM layout (5000 per metre, its own
`Sequence.depth_scale`). `fuse_sequence` integrates
every frame into Open3D's TSDF voxel block grid and takes its surface's vertices; `import_sequence` then brings the
scan into the scene frame (support plane at z = 0, +Z up, `data.scan.import_scan`) and records every camera
(``provenance["cameras"]``, moved into the scene frame) so that camera-aware checks can use all of them.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.scene import Scene, SceneError

log = logging.getLogger(__name__)

MAX_FRAMES = 2000
"""Most frames one import fuses (a longer sequence: pass --every N)."""
_INTRINSICS_NAMES = ("camera-intrinsics.txt", "intrinsics.txt", "intrinsic.txt", "K.txt")
TUM_MAX_DT = 0.02
"""Seconds: a TUM depth image takes the colour image nearest in time within this (the benchmark's association)."""
TUM_MAX_GAP = 0.1
"""Seconds: the longest gap between two ground-truth samples a TUM frame's pose is interpolated across."""
TUM_DEPTH_SCALE = 5000.0
"""TUM RGB-D depth PNG units per metre."""
TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
"""fx, fy, cx, cy the TUM RGB-D benchmark publishes for its three Kinects (its depth images are registered to
the colour camera), used for a folder named after one of their sequences when no intrinsics are given."""
_MAX_LIST_LINES = 1_000_000


@dataclass(frozen=True)
class PosedFrame:
    """One frame of a sequence: its files and its camera."""

    depth: Path
    color: Path | None
    T_world_camera: np.ndarray
    """(4, 4) camera-to-world (OpenCV camera: x right, y down, z forward)."""


@dataclass(frozen=True)
class Sequence:
    """The frames of a sequence, their shared intrinsics and where they came from."""

    frames: tuple[PosedFrame, ...]
    K: np.ndarray
    """(3, 3) depth intrinsics."""
    layout: str
    """"7-scenes", "scannet", "tum" or "poses-file"."""
    depth_scale: float = 1000.0
    """Depth PNG units per metre of this layout (TUM: 5000)."""


def read_matrix(path: Path, rows: int = 4) -> np.ndarray:
    """A whitespace-separated matrix file (a pose 4x4, intrinsics 3x3 or 4x4), checked finite.

    Raises:
        SceneError: not numbers, the wrong count, NaN or infinite values.
    """
    try:
        vals = np.array(path.read_text(errors="replace").split(), dtype=np.float64)
    except ValueError:
        raise SceneError(f"{path}: not a matrix of numbers") from None
    if vals.size != rows * rows:
        raise SceneError(f"{path}: expected {rows * rows} numbers ({rows}x{rows}), got {vals.size}")
    if not np.isfinite(vals).all():
        raise SceneError(f"{path}: the matrix holds NaN or infinite values (an invalid pose)")
    return vals.reshape(rows, rows)


def _intrinsics(path: Path) -> np.ndarray:
    vals = path.read_text(errors="replace").split()
    K = read_matrix(path, 4 if len(vals) == 16 else 3)[:3, :3]
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise SceneError(f"{path}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def check_pose(T: np.ndarray, where: str) -> np.ndarray:
    """A camera-to-world pose, checked to be rigid (a rotation and a translation).

    Raises:
        SceneError: NaN, not 4x4, not a proper rotation.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise SceneError(f"{where}: the pose must be a finite 4x4 matrix")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise SceneError(f"{where}: the pose is not a rigid transform (rotation and translation)")
    return T


def _number(p: Path) -> int:
    m = re.findall(r"\d+", p.stem)
    return int(m[-1]) if m else -1


def _poses_file(path: Path, n: int) -> list[np.ndarray]:
    try:
        vals = np.array(path.read_text(errors="replace").split(), dtype=np.float64)
    except ValueError:
        raise SceneError(f"{path}: not a poses file of numbers") from None
    if vals.size % 16:
        raise SceneError(f"{path}: {vals.size} numbers is not a whole number of 4x4 poses")
    poses = vals.reshape(-1, 4, 4)
    if len(poses) != n:
        raise SceneError(f"{path}: {len(poses)} poses for {n} depth frames; one pose per frame is needed")
    return [check_pose(T, f"{path} pose {k}") for k, T in enumerate(poses)]


def _tum_list(path: Path, columns: int) -> list[list[str]]:
    """The rows of a TUM list file (``#`` comments and blank lines skipped), each with at least `columns` fields."""
    rows = []
    with open(path, errors="replace") as fh:
        for n, line in enumerate(fh, 1):
            if n > _MAX_LIST_LINES:
                raise SceneError(f"{path}: more than {_MAX_LIST_LINES:,} lines: not a TUM list")
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            if len(fields) < columns:
                raise SceneError(f"{path}:{n}: {len(fields)} fields, a TUM list line has {columns}")
            rows.append(fields)
    return rows


def _stamps(rows: list[list[str]], path: Path) -> np.ndarray:
    try:
        t = np.array([float(r[0]) for r in rows], np.float64)
    except ValueError:
        raise SceneError(f"{path}: a timestamp is not a number") from None
    if not np.isfinite(t).all():
        raise SceneError(f"{path}: NaN or infinite timestamps")
    return t


def _inside(folder: Path, rel: str, where: str) -> Path:
    """A file a list names, resolved, and refused when it lies outside the sequence folder."""
    p = (folder / rel).resolve()
    if not p.is_relative_to(folder.resolve()):
        raise SceneError(f"{where}: {rel!r} lies outside the sequence folder")
    return p


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    if float(q0 @ q1) < 0.0:  # the shorter arc
        q1 = -q1
    dot = min(1.0, float(q0 @ q1))
    ang = np.arccos(dot)
    if ang < 1e-9:
        return q0
    return (np.sin((1 - f) * ang) * q0 + np.sin(f * ang) * q1) / np.sin(ang)


def tum_pose_at(t: float, stamps: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
    """The camera-to-world pose at time `t` from ground-truth samples ``(tx ty tz qx qy qz qw)`` at sorted
    `stamps`: interpolated between the samples around `t` (None outside them or across a gap > `TUM_MAX_GAP`)."""
    i = int(np.searchsorted(stamps, t))
    if i < len(stamps) and stamps[i] == t:
        lo = hi = i
    elif i == 0 or i == len(stamps):
        return None
    else:
        lo, hi = i - 1, i
    if stamps[hi] - stamps[lo] > TUM_MAX_GAP:
        return None
    f = 0.0 if hi == lo else (t - stamps[lo]) / (stamps[hi] - stamps[lo])
    q0, q1 = poses[lo, 3:] / np.linalg.norm(poses[lo, 3:]), poses[hi, 3:] / np.linalg.norm(poses[hi, 3:])
    q = _slerp(q0, q1, f)
    T = np.eye(4)
    T[:3, :3] = _quat_to_matrix(q / np.linalg.norm(q))
    T[:3, 3] = (1 - f) * poses[lo, :3] + f * poses[hi, :3]
    return T


def _tum_frames(folder: Path) -> list[PosedFrame]:
    """The frames of a TUM RGB-D folder, associated by time (module docstring)."""
    depth_rows = _tum_list(folder / "depth.txt", 2)
    gt_rows = _tum_list(folder / "groundtruth.txt", 8)
    if not gt_rows:
        raise SceneError(f"{folder / 'groundtruth.txt'}: no poses")
    gt_t = _stamps(gt_rows, folder / "groundtruth.txt")
    try:
        gt = np.array([[float(v) for v in r[1:8]] for r in gt_rows], np.float64)
    except ValueError:
        raise SceneError(f"{folder / 'groundtruth.txt'}: a pose value is not a number") from None
    bad = ~np.isfinite(gt).all(axis=1) | (np.linalg.norm(gt[:, 3:], axis=1) < 1e-6)
    gt_t, gt = gt_t[~bad], gt[~bad]
    order = np.argsort(gt_t, kind="stable")
    gt_t, gt = gt_t[order], gt[order]
    rgb_rows = _tum_list(folder / "rgb.txt", 2) if (folder / "rgb.txt").is_file() else []
    rgb_t = _stamps(rgb_rows, folder / "rgb.txt") if rgb_rows else np.zeros(0)
    frames: list[PosedFrame] = []
    skipped = 0
    for t, row in zip(_stamps(depth_rows, folder / "depth.txt"), depth_rows):
        T = tum_pose_at(float(t), gt_t, gt)
        if T is None:
            skipped += 1
            continue
        color = None
        if len(rgb_t):
            j = int(np.argmin(np.abs(rgb_t - t)))
            if abs(rgb_t[j] - t) <= TUM_MAX_DT:
                color = _inside(folder, rgb_rows[j][1], str(folder / "rgb.txt"))
        depth = _inside(folder, row[1], str(folder / "depth.txt"))
        if not depth.is_file():
            raise SceneError(f"{depth}: missing (depth.txt names it)")
        frames.append(PosedFrame(depth, color if color is not None and color.is_file() else None,
                                 check_pose(T, f"{folder / 'groundtruth.txt'} at {t:.4f}")))
    if skipped:
        log.info("%s: %d depth frames outside the ground truth's time span or in its gaps: skipped", folder, skipped)
    return frames


def _tum_intrinsics(folder: Path) -> np.ndarray | None:
    """The benchmark's published intrinsics for a folder named after a Freiburg sequence, else None."""
    for key, (fx, fy, cx, cy) in TUM_INTRINSICS.items():
        if key in folder.resolve().name.lower():
            log.warning("%s: the TUM RGB-D %s intrinsics (fx %.1f fy %.1f cx %.1f cy %.1f), by the folder's name; "
                        "pass --fx --fy --cx --cy to use others", folder, key, fx, fy, cx, cy)
            return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return None


def find_sequence(folder: Path, *, poses: Path | None = None, K: np.ndarray | None = None,
                  every: int = 1) -> Sequence:
    """The frames of a sequence folder in one of the module's layouts (`poses`: a poses file; `K`: intrinsics when
    the folder has none; `every`: keep every N-th frame).

    Raises:
        SceneError: no layout recognised, missing poses or intrinsics, a pose file that does not match the frames,
            an invalid pose, more than `MAX_FRAMES` frames.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: not a folder of frames")
    layout: str
    frames: list[PosedFrame] = []
    k_file: Path | None = None
    seven = sorted(folder.glob("frame-*.depth.png"), key=_number)
    if seven and poses is None:
        layout = "7-scenes"
        for d in seven:
            stem = d.name[: -len(".depth.png")]
            pose = folder / f"{stem}.pose.txt"
            if not pose.is_file():
                raise SceneError(f"{pose}: missing (every depth frame needs its pose)")
            color = folder / f"{stem}.color.png"
            frames.append(PosedFrame(d, color if color.is_file() else None,
                                     check_pose(read_matrix(pose), str(pose))))
        k_file = next((folder / n for n in _INTRINSICS_NAMES if (folder / n).is_file()), None)
    elif (folder / "depth").is_dir() and (folder / "pose").is_dir() and poses is None:
        layout = "scannet"
        for d in sorted((folder / "depth").glob("*.png"), key=_number):
            pose = folder / "pose" / f"{d.stem}.txt"
            if not pose.is_file():
                raise SceneError(f"{pose}: missing (every depth frame needs its pose)")
            try:
                T = read_matrix(pose)
            except SceneError as exc:
                if "NaN or infinite" not in str(exc):
                    raise
                log.info("%s: tracking lost in this frame (an invalid pose): skipped", pose)
                continue
            color = next((c for c in (folder / "color" / f"{d.stem}{s}" for s in (".jpg", ".png")) if c.is_file()),
                         None)
            frames.append(PosedFrame(d, color, check_pose(T, str(pose))))
        k_file = folder / "intrinsic" / "intrinsic_depth.txt"
        k_file = k_file if k_file.is_file() else None
    elif (folder / "depth.txt").is_file() and (folder / "groundtruth.txt").is_file() and poses is None:
        layout = "tum"
        frames = _tum_frames(folder)
        k_file = next((folder / n for n in _INTRINSICS_NAMES if (folder / n).is_file()), None)
        if K is None and k_file is None:
            K = _tum_intrinsics(folder)
    elif poses is not None:
        layout = "poses-file"
        depth_dir = folder / "depth" if (folder / "depth").is_dir() else folder
        depths = sorted((p for p in depth_dir.glob("*.png") if "color" not in p.name),
                        key=lambda p: (_number(p), p.name))
        color_dir = folder / "color" if (folder / "color").is_dir() else None
        colors = sorted(color_dir.glob("*.*"), key=lambda p: (_number(p), p.name)) if color_dir else []
        if colors and len(colors) != len(depths):
            raise SceneError(f"{color_dir}: {len(colors)} colour images for {len(depths)} depth images")
        Ts = _poses_file(Path(poses), len(depths))
        frames = [PosedFrame(d, colors[k] if colors else None, Ts[k]) for k, d in enumerate(depths)]
        k_file = next((folder / n for n in _INTRINSICS_NAMES if (folder / n).is_file()), None)
    else:
        raise SceneError(f"{folder}: no sequence layout recognised (7-Scenes frame-*.depth.png + .pose.txt, "
                         "ScanNet depth/ + pose/ + intrinsic/, TUM depth.txt + groundtruth.txt, or depth images "
                         "with --poses FILE)")
    if not frames:
        raise SceneError(f"{folder}: no depth frames found" + (" with a ground-truth pose" if layout == "tum" else ""))
    frames = frames[:: max(1, int(every))]
    if len(frames) > MAX_FRAMES:
        raise SceneError(f"{folder}: {len(frames)} frames, more than {MAX_FRAMES}; keep every N-th with --every")
    if K is None:
        if k_file is None:
            raise SceneError(f"{folder}: no intrinsics file ({', '.join(_INTRINSICS_NAMES)}); pass --fx --fy --cx --cy")
        K = _intrinsics(k_file)
    return Sequence(tuple(frames), np.asarray(K, np.float64), layout,
                    depth_scale=TUM_DEPTH_SCALE if layout == "tum" else 1000.0)


def _resample_nearest(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A colour image resampled (nearest) to the depth image's (H, W)."""
    h, w = shape
    rows = np.minimum((np.arange(h) + 0.5) * img.shape[0] / h, img.shape[0] - 1).astype(int)
    cols = np.minimum((np.arange(w) + 0.5) * img.shape[1] / w, img.shape[1] - 1).astype(int)
    return img[rows][:, cols]


def fuse_sequence(seq: Sequence, *, voxel: float = 0.004, trunc_voxels: float = 4.0, max_depth: float = 3.0,
                  depth_scale: float = 1000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Integrate every frame into Open3D's TSDF voxel block grid (`trunc_voxels` voxels of truncation) and take
    the vertices of its surface.

    Returns:
        points (P, 3) float64 and normals (P, 3) in the poses' world frame, colours (P, 3) uint8, the depth
        image size (W, H).

    Raises:
        SceneError: an unreadable image, depth images of different sizes, no surface at all.
    """
    import importlib

    from efem_viz.data.rgbd import read_depth_image, read_rgb_image

    o3d: Any = importlib.import_module("open3d")  # untyped where it matters (tensor API stubs disagree)

    f32 = o3d.core.float32
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(f32, f32, f32), attr_channels=(1, 1, 3),
        voxel_size=float(voxel), block_resolution=16, block_count=40000, device=o3d.core.Device("CPU:0"))
    K = o3d.core.Tensor(seq.K)
    trunc = float(trunc_voxels)
    size: tuple[int, int] | None = None
    for k, fr in enumerate(seq.frames):
        depth_m = read_depth_image(fr.depth) * np.float32(1000.0 / depth_scale)
        h, w = depth_m.shape
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise SceneError(f"{fr.depth}: depth image {w}x{h}, the sequence's first is {size[0]}x{size[1]}")
        rgb = read_rgb_image(fr.color) if fr.color is not None else np.full((h, w, 3), 160, np.uint8)
        if rgb.shape[:2] != (h, w):
            rgb = _resample_nearest(rgb, (h, w))
        depth = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth_m, np.float32)))
        color = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb, np.float32) / 255.0))
        extrinsic = o3d.core.Tensor(np.linalg.inv(fr.T_world_camera))
        blocks = grid.compute_unique_block_coordinates(depth, K, extrinsic, 1.0, float(max_depth), trunc)
        grid.integrate(blocks, depth, color, K, K, extrinsic, 1.0, float(max_depth), trunc)
        log.debug("integrated frame %d of %d", k + 1, len(seq.frames))
    # the surface's vertices (Open3D 0.20's point extraction of a voxel block grid returns nothing)
    mesh = grid.extract_triangle_mesh(weight_threshold=min(1.0, float(len(seq.frames))) - 0.5)
    pts = mesh.vertex.positions.numpy().astype(np.float64)
    if not len(pts):
        raise SceneError("the fused sequence has no surface (poses or depth scale wrong?)")
    nrm = mesh.vertex.normals.numpy().astype(np.float64) if "normals" in mesh.vertex else np.zeros((0, 3))
    cols = np.clip(np.round(mesh.vertex.colors.numpy() * 255.0), 0, 255).astype(np.uint8)
    assert size is not None
    return pts, nrm, cols, size


def import_sequence(folder: Path, *, name: str, poses: Path | None = None, K: np.ndarray | None = None,
                    every: int = 1, voxel: float = 0.004, max_depth: float = 3.0, depth_scale: float | None = None,
                    up: str = "auto", seed: int = 0) -> Scene:
    """A sequence folder fused into one scene in the scene frame (module docstring), every camera recorded
    (`depth_scale`: depth PNG units per metre; None: the layout's, `Sequence.depth_scale`).

    Raises:
        SceneError: as `find_sequence`, `fuse_sequence` and `data.scan.import_scan`.
    """
    from efem_viz.data.scan import import_scan

    seq = find_sequence(folder, poses=poses, K=K, every=every)
    scale = seq.depth_scale if depth_scale is None else float(depth_scale)
    pts, nrm, cols, (w, h) = fuse_sequence(seq, voxel=voxel, max_depth=max_depth, depth_scale=scale)
    fused = Scene.create(name, pts.astype(np.float32), normals=nrm.astype(np.float32) if len(nrm) else None,
                         colors=cols)
    scene, frame = import_scan(fused, units="m", up=up, seed=seed)  # type: ignore[arg-type]
    S = frame.to_scene.matrix()
    cams = [{"K": seq.K.tolist(), "T_world_camera": (S @ fr.T_world_camera).tolist(), "image_size": [w, h],
             "file": fr.depth.name} for fr in seq.frames]
    prov = {**dict(scene.provenance), "source": "rgbd_sequence", "layout": seq.layout, "frames": len(seq.frames),
            "voxel_m": voxel, "cameras": cams}
    return scene.replace(provenance=prov)
