"""Posed RGB-D sequences and multi-view rigs fused into one scan, as the paper's real scenes were made.

A sequence is a folder of depth images with a camera pose per frame (and colour images), in one of the layouts:

* **7-Scenes style**: ``frame-000000.depth.png`` / ``.color.png`` / ``.pose.txt`` (a 4x4 camera-to-world matrix),
  the intrinsics from ``camera-intrinsics.txt`` / ``intrinsics.txt`` in the folder (3x3 or 4x4) or given;
* **ScanNet's exported frames** (SensReader): ``depth/<i>.png``, ``color/<i>.jpg``, ``pose/<i>.txt``,
  ``intrinsic/intrinsic_depth.txt``; colour images larger than the depth are resampled to it;
* **a list with a poses file**: ``depth/`` and ``color/`` folders (or depth images alone) sorted by name, and a poses
  file with one camera-to-world matrix per frame (16 numbers per line, or 4 lines of 4), in frame order.

Depth PNGs hold millimetres (``depth_scale`` 1000; TUM's files hold 5000 per metre). `fuse_sequence` integrates
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
    """"7-scenes", "scannet" or "poses-file"."""


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
    elif poses is not None:
        layout = "poses-file"
        depth_dir = folder / "depth" if (folder / "depth").is_dir() else folder
        depths = sorted((p for p in depth_dir.glob("*.png") if "color" not in p.name), key=lambda p: (_number(p), p.name))
        color_dir = folder / "color" if (folder / "color").is_dir() else None
        colors = sorted(color_dir.glob("*.*"), key=lambda p: (_number(p), p.name)) if color_dir else []
        if colors and len(colors) != len(depths):
            raise SceneError(f"{color_dir}: {len(colors)} colour images for {len(depths)} depth images")
        Ts = _poses_file(Path(poses), len(depths))
        frames = [PosedFrame(d, colors[k] if colors else None, Ts[k]) for k, d in enumerate(depths)]
        k_file = next((folder / n for n in _INTRINSICS_NAMES if (folder / n).is_file()), None)
    else:
        raise SceneError(f"{folder}: no sequence layout recognised (7-Scenes frame-*.depth.png + .pose.txt, "
                         "ScanNet depth/ + pose/ + intrinsic/, or depth images with --poses FILE)")
    if not frames:
        raise SceneError(f"{folder}: no depth frames found")
    frames = frames[:: max(1, int(every))]
    if len(frames) > MAX_FRAMES:
        raise SceneError(f"{folder}: {len(frames)} frames, more than {MAX_FRAMES}; keep every N-th with --every")
    if K is None:
        if k_file is None:
            raise SceneError(f"{folder}: no intrinsics file ({', '.join(_INTRINSICS_NAMES)}); pass --fx --fy --cx --cy")
        K = _intrinsics(k_file)
    return Sequence(tuple(frames), np.asarray(K, np.float64), layout)


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
                    every: int = 1, voxel: float = 0.004, max_depth: float = 3.0, depth_scale: float = 1000.0,
                    up: str = "auto", seed: int = 0) -> Scene:
    """A sequence folder fused into one scene in the scene frame (module docstring), every camera recorded.

    Raises:
        SceneError: as `find_sequence`, `fuse_sequence` and `data.scan.import_scan`.
    """
    from efem_viz.data.scan import import_scan

    seq = find_sequence(folder, poses=poses, K=K, every=every)
    pts, nrm, cols, (w, h) = fuse_sequence(seq, voxel=voxel, max_depth=max_depth, depth_scale=depth_scale)
    fused = Scene.create(name, pts.astype(np.float32), normals=nrm.astype(np.float32) if len(nrm) else None,
                         colors=cols)
    scene, frame = import_scan(fused, units="m", up=up, seed=seed)  # type: ignore[arg-type]
    S = frame.to_scene.matrix()
    cams = [{"K": seq.K.tolist(), "T_world_camera": (S @ fr.T_world_camera).tolist(), "image_size": [w, h],
             "file": fr.depth.name} for fr in seq.frames]
    prov = {**dict(scene.provenance), "source": "rgbd_sequence", "layout": seq.layout, "frames": len(seq.frames),
            "voxel_m": voxel, "cameras": cams}
    return scene.replace(provenance=prov)
