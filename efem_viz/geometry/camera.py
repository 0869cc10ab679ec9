"""Pinhole depth cameras: projection, a depth image of a point cloud, and free-space ("seen-through") tests.

One home for the camera model (OpenCV convention: x right, y down, z forward; ``T_world_camera`` maps camera
coordinates to the world). The scene generator scans with it, and real frames carry one in their provenance
(`data.rgbd.import_rgbd` writes ``K``, ``image_size`` and ``T_world_camera``).

A single-view depth frame says more than where surfaces are: along every pixel's ray, the space in front of
the measured depth is empty. A completed shape that puts surface where the camera saw through to something
behind it (a mug's handle or body over the table, a bowl's far rim in front of the wall) contradicts the frame;
`DepthView.seen_through` measures the fraction of a shape's surface samples that do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole depth camera (OpenCV convention: x right, y down, z forward)."""

    K: np.ndarray
    """(3, 3) intrinsics."""
    T_world_camera: np.ndarray
    """(4, 4) camera-to-world transform."""
    width: int
    height: int

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World points → pixel column ``u``, row ``v`` (rounded, int64), depth ``z`` (m) and ``ok`` (in front
        of the camera, z > 1 mm, and inside the image)."""
        R, t = self.T_world_camera[:3, :3], self.T_world_camera[:3, 3]
        pc = (np.asarray(points, np.float64) - t) @ R  # world -> camera: R^T (x - t)
        z = pc[:, 2]
        zs = np.maximum(z, 1e-6)
        u = np.round(self.K[0, 0] * pc[:, 0] / zs + self.K[0, 2])
        v = np.round(self.K[1, 1] * pc[:, 1] / zs + self.K[1, 2])
        ok = (z > 1e-3) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        u = np.where(ok, u, 0).astype(np.int64)
        v = np.where(ok, v, 0).astype(np.int64)
        return u, v, z, ok

    def scaled(self, factor: float) -> "Camera":
        """The same camera with ``factor`` times the pixels along each side (intrinsics scaled; factor < 1 is a
        coarser image of the same rays)."""
        K = self.K.astype(np.float64).copy()
        K[:2] *= float(factor)
        return Camera(K=K, T_world_camera=self.T_world_camera, width=max(1, int(np.ceil(self.width * factor))),
                      height=max(1, int(np.ceil(self.height * factor))))

    @classmethod
    def from_provenance(cls, prov: Mapping[str, Any] | None) -> "Camera | None":
        """The capture camera recorded by `data.rgbd.import_rgbd` (``K``, ``image_size``, ``T_world_camera``),
        or None when the scene has none (fused or synthetic scans) or the record is malformed (`parse` says
        why)."""
        return cls.parse(prov)[0]

    @classmethod
    def parse(cls, prov: Mapping[str, Any] | None) -> tuple["Camera | None", str | None]:
        """(camera, problem): the recorded capture camera, or None and — when a camera *was* recorded (``K`` or
        ``T_world_camera`` present) but cannot be used — what is wrong with it, in words. No camera recorded:
        (None, None); an ``image_size`` alone (the synthetic generator records its renders' size) is no camera."""
        keys = ("K", "T_world_camera", "image_size")
        if not prov or not any(k in prov for k in ("K", "T_world_camera")):
            return None, None
        missing = [k for k in keys if k not in prov]
        if missing:
            return None, f"{', '.join(missing)} missing"
        try:
            K = np.asarray(prov["K"], np.float64)
            T = np.asarray(prov["T_world_camera"], np.float64)
        except (TypeError, ValueError):
            return None, "K or T_world_camera is not a numeric matrix"
        try:
            w, h = (int(x) for x in prov["image_size"])
        except (TypeError, ValueError):
            return None, f"image_size {str(prov['image_size'])[:40]!r} is not two integers"
        if K.shape != (3, 3):
            return None, f"K has shape {K.shape}, not (3, 3)"
        if T.shape != (4, 4):
            return None, f"T_world_camera has shape {T.shape}, not (4, 4)"
        if not np.isfinite(K).all() or not np.isfinite(T).all():
            return None, "K or T_world_camera holds NaN or infinite values"
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            return None, f"focal lengths fx={K[0, 0]:g}, fy={K[1, 1]:g} are not positive"
        if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
            return None, f"image_size {w}x{h} is outside 1..{MAX_IMAGE_SIDE}"
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
            return None, "the rotation of T_world_camera is not a rotation"
        return cls(K=K, T_world_camera=T, width=w, height=h), None


MAX_VIEW_PIXELS = 1 << 22
"""Most pixels of a `DepthView` window (4.2 M, 16 MB): a camera whose declared focal length and image size would
spread the scene over more is viewed at a coarser resolution (`Camera.scaled`); a real 640 x 480 frame uses 0.3 M."""

MAX_IMAGE_SIDE = 16384
"""Largest image side a recorded camera may declare (sensors top out near 4K; the depth view is cropped to the
scene's projected bounds, so a large declared size costs no memory by itself)."""


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world pose of an OpenCV camera at ``eye`` looking at ``target`` (+Z world up)."""
    f = target - eye
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, f, eye
    return T


@dataclass(frozen=True)
class DepthView:
    """The depth image a camera saw, rebuilt from the scene's points (the nearest point per pixel).

    Scene points are voxel-thinned, so each is splatted over a ``splat × splat`` pixel footprint (a minimum
    filter): holes between voxels close, and at silhouettes the nearer surface wins, which errs toward "not
    seen through". Pixels no point reaches (outside the cropped scene, sensor holes) are unknown (``inf``).
    Only the window of the image the scene's points fall in is kept (float32): its size is bounded by the scene,
    not by the declared image size, and by `MAX_VIEW_PIXELS` (beyond it the view is of `Camera.scaled`, whose
    camera it keeps: `seen_through` projects with the same one).
    """

    camera: Camera
    depth: np.ndarray
    """(rows, cols) float32 metres of the window starting at pixel (`u0`, `v0`); inf where nothing was observed."""
    u0: int = 0
    v0: int = 0

    @classmethod
    def of_points(cls, camera: Camera, points: np.ndarray, *, splat: int = 5, lateral: float = 0.0,
                  edge: float | None = None) -> "DepthView":
        """The depth view of scene points.

        Args:
            camera: the capture camera.
            points: (N, 3) scene points, world frame.
            splat: pixel footprint of one point (odd; the minimum filter's size).
            lateral: extra sideways tolerance (m): the footprint grows by ``ceil(f · lateral / z̃)`` pixels on
                each side (z̃ the median observed depth), so a completed shape whose silhouette overhangs the
                object it fits by up to about this much is not counted as seen through there (scale
                errors of a few millimetres put a fit's rim and handle over the background behind it).
            edge: pixels whose observed depth varies by more than this (m) within the splat window (silhouettes,
                mixed pixels, hole borders) become unobserved: no evidence of free space there. None: kept.
        """
        from scipy.ndimage import minimum_filter

        u, v, z, ok = camera.project(points)
        if not ok.any():
            return cls(camera=camera, depth=np.full((1, 1), np.inf, np.float32), u0=0, v0=0)
        area = float(u[ok].max() - u[ok].min() + 1) * float(v[ok].max() - v[ok].min() + 1)
        if area > MAX_VIEW_PIXELS:  # bounded by the scene, whatever the intrinsics declare
            camera = camera.scaled(0.95 * np.sqrt(MAX_VIEW_PIXELS / area))
            u, v, z, ok = camera.project(points)
        size = int(splat)
        if lateral > 0:
            f = float(max(camera.K[0, 0], camera.K[1, 1]))
            size += 2 * int(np.ceil(f * float(lateral) / max(float(np.median(z[ok])), 1e-6)))
        pad = size // 2 + 1
        u0, v0 = max(int(u[ok].min()) - pad, 0), max(int(v[ok].min()) - pad, 0)
        u1, v1 = min(int(u[ok].max()) + pad + 1, camera.width), min(int(v[ok].max()) + pad + 1, camera.height)
        depth = np.full((v1 - v0, u1 - u0), np.inf, np.float32)
        np.minimum.at(depth, (v[ok] - v0, u[ok] - u0), z[ok].astype(np.float32))
        if size > 1:
            depth = minimum_filter(depth, size=size, mode="nearest")
        if edge is not None:
            from scipy.ndimage import maximum_filter

            window = max(int(splat), 3)
            with np.errstate(invalid="ignore"):  # inf - inf next to unobserved pixels: NaN, i.e. an edge
                spread = maximum_filter(depth, size=window, mode="nearest") - minimum_filter(depth, size=window,
                                                                                            mode="nearest")
            depth = np.where(np.isfinite(spread) & (spread <= edge), depth, np.inf).astype(np.float32)
        return cls(camera=camera, depth=depth, u0=u0, v0=v0)

    def depth_at(self, u: int, v: int) -> float:
        """Observed depth (m) at pixel column ``u``, row ``v``; inf where nothing was observed."""
        rows, cols = self.depth.shape
        if self.u0 <= u < self.u0 + cols and self.v0 <= v < self.v0 + rows:
            return float(self.depth[v - self.v0, u - self.u0])
        return float("inf")

    def seen_through(self, points: np.ndarray, margin: float, *, per_depth2: float = 0.0) -> tuple[float, float]:
        """(fraction of the known ``points`` that lie more than ``margin`` metres in front of the observed
        surface on their pixel — where the camera saw through them —, fraction of ``points`` that are known).

        The margin grows by ``per_depth2`` x (observed depth)² (sensor noise grows with the square of the range).
        A point is known when it projects into the image onto an observed pixel. Points behind the observed
        surface (occluded) or on it agree with the frame. (0, 0) when no point is known.
        """
        if not len(points):
            return 0.0, 0.0
        u, v, z, ok = self.camera.project(points)
        rows, cols = self.depth.shape
        ok = ok & (u >= self.u0) & (u < self.u0 + cols) & (v >= self.v0) & (v < self.v0 + rows)
        d = np.full(len(z), np.inf)
        d[ok] = self.depth[v[ok] - self.v0, u[ok] - self.u0]
        known = np.isfinite(d)
        n_known = int(known.sum())
        if n_known == 0:
            return 0.0, 0.0
        through = known & (d > z + margin + per_depth2 * np.where(known, d, 0.0) ** 2)
        return float(through.sum()) / n_known, n_known / len(z)
