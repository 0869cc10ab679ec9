"""Virtual depth cameras and their images: camera placement, Kinect-like noise, ray-cast frames, back-projection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from efem_viz.data.synth.stage import Stage
from efem_viz.geometry.camera import Camera, look_at


# ====================================================================================== scanning
def make_cameras(
    rng: np.random.Generator, target: np.ndarray, *, stage: Stage, n_cameras: int, image_size: tuple[int, int],
    heights: tuple[float, float] | None = None, front: np.ndarray | None = None, reach: float = 0.0,
) -> list[Camera]:
    """Depth cameras looking at `target`: on the stage's camera ring, at its diagonals for 4 cameras (eye heights
    drawn from `heights`, default the stage's), or, with a `front` direction (a shelf), spread over ±55° about
    it, 0.6-0.75 m away, at heights rising through `heights`. The ring is centred on the support's centre
    (a table: the cameras at its corners) or, where the stage has a camera standoff, on the target, widened
    to the standoff beyond `reach` (the objects' farthest horizontal distance from the target). Each aim point
    moves horizontally by up to the stage's aim jitter."""
    heights = stage.camera_heights if heights is None else heights
    jitter = stage.aim_jitter
    centre, ring = np.zeros(2), stage.camera_ring
    if stage.camera_standoff is not None:
        centre, ring = np.asarray(target[:2], np.float64), max(ring, reach + stage.camera_standoff)
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
            tgt = target + np.array([*rng.uniform(-jitter, jitter, 2), 0.0])
            cams.append(Camera(K, look_at(eye, tgt), w, h))
        return cams
    az0 = np.pi / 4 + rng.uniform(-0.15, 0.15)
    for i in range(n_cameras):
        az = az0 + 2 * np.pi * i / n_cameras + rng.uniform(-0.1, 0.1)
        horiz = ring * rng.uniform(0.9, 1.05)
        eye = np.array([centre[0] + horiz * math.cos(az), centre[1] + horiz * math.sin(az), rng.uniform(*heights)])
        tgt = target + np.array([*rng.uniform(-jitter, jitter, 2), 0.0])
        cams.append(Camera(K, look_at(eye, tgt), w, h))
    return cams


def _depth_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect v1 axial noise (Nguyen et al. 2012): sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4 m)^2, z in metres."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


@dataclass
class RenderedFrame:
    depth: np.ndarray  # (H, W) float32, 0 = no measurement
    color: np.ndarray  # (H, W, 3) uint8
    normal: np.ndarray  # (H, W, 3) float32, true surface normal towards the camera
    visible_ids: np.ndarray  # (H, W) int32 geometry index (-1 none)


def render_frames(
    scene: Any,
    cam: Camera,
    albedo: np.ndarray,
    rng: np.random.Generator,
    *,
    noise: bool,
    crop_lo: np.ndarray,
    crop_hi: np.ndarray,
    max_range: float,
) -> RenderedFrame:
    """Ray-cast one depth frame of `scene` (geometry i coloured `albedo[i]`) from `cam`: depth up to `max_range`,
    with Kinect-like noise (`_depth_sigma`, dropout at grazing angles) when `noise`, measurements outside the
    box [crop_lo, crop_hi] removed."""
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
    hit = np.isfinite(z) & (z < max_range)
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
    return RenderedFrame(depth, color, nrm.astype(np.float32), np.where(valid, gid, -1).astype(np.int32))


def frame_points(frame: RenderedFrame, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = frame.depth > 0
    v, u = np.nonzero(m)
    z = frame.depth[m].astype(np.float64)
    x = (u - cam.K[0, 2]) / cam.K[0, 0] * z
    y = (v - cam.K[1, 2]) / cam.K[1, 1] * z
    p_cam = np.stack([x, y, z], -1)
    p = p_cam @ cam.T_world_camera[:3, :3].T + cam.T_world_camera[:3, 3]
    return p, frame.color[m], frame.normal[m].astype(np.float64)
