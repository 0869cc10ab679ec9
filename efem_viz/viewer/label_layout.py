"""Where the instances' text labels go so that they do not overlap (pure numpy, no viser).

Each label wants to sit just above the top of its instance's box (`anchor`). Labels of objects that stand close
together (a cup on a plate, a row of mugs) would cover each other, so `place_labels` lifts some of them straight up
(world +Z) until no two overlap on screen, most confident first: the most confident label keeps its spot, the
others stack above it. A lifted label hangs on a thin vertical leader line down to its box (`leader_segments`).

Screen geometry: viser draws a label at a constant size on screen (`font_size_mode="screen"`: a 12 px em, whatever
the zoom), centred above its position (`anchor="bottom-center"`), with a padded white background. Overlap is
checked in the image of the viewer's *fitted view* (the camera every browser starts on and *Reset view* returns to)
on a canvas `REFERENCE_VIEW_PX` pixels tall: labels that do not overlap there do not overlap from any closer
camera in that direction either (zooming in spreads the anchors apart while the labels keep their size). Text
width is estimated from the number of characters (`CHAR_EM`), so a label is given a little more room than it
needs. Deterministic: the same anchors and texts give the same positions.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from efem_viz.serve.camera import View

REFERENCE_VIEW_PX = 800.0
"""Canvas height (CSS px) the layout assumes; viser's own reference height for screen-size labels."""
EM_PX = 12.0
"""Height of a label's em in CSS px (viser 1.1 screen-mode labels at `font_screen_scale` 1)."""
CHAR_EM = 0.62
"""Estimated width of one character, in em (generous for a sans-serif with digits)."""
PAD_EM = 0.5
"""Padding of the label's background, in em, added to the width and (once) to the height."""
LINE_EM = 1.3
"""Height of one line of text, in em."""
GAP_PX = 3.0
"""Free space kept between two labels, px."""
FOV_RAD = 75.0 * np.pi / 180.0
"""Vertical field of view of viser's default camera (the fitted view keeps it)."""


def label_size_px(text: str) -> tuple[float, float]:
    """(width, height) in CSS px of a screen-size label showing `text` (an estimate, see `CHAR_EM`)."""
    return (len(str(text)) * CHAR_EM + PAD_EM) * EM_PX, (LINE_EM + PAD_EM) * EM_PX


class _Camera:
    """A pinhole camera on a `View` (OpenCV-like: x right, y up here, z forward), in CSS px of the canvas."""

    def __init__(self, view: View, *, fov: float, height_px: float) -> None:
        self.position = np.asarray(view.position, np.float64)
        forward = np.asarray(view.look_at, np.float64) - self.position
        self.forward = forward / (float(np.linalg.norm(forward)) or 1.0)
        right = np.cross(self.forward, np.asarray(view.up, np.float64))
        n = float(np.linalg.norm(right))
        if n < 1e-9:  # looking straight along up: any right will do
            right = np.cross(self.forward, np.array([0.0, 1.0, 0.0]))
            n = float(np.linalg.norm(right))
        self.right = right / n
        self.up = np.cross(self.right, self.forward)
        self.focal = 0.5 * float(height_px) / np.tan(0.5 * float(fov))

    def project(self, p: np.ndarray) -> tuple[float, float, float]:
        """(x, y, depth): screen px from the image centre (y up) and depth along the view, of world point `p`."""
        d = np.asarray(p, np.float64) - self.position
        depth = float(d @ self.forward)
        z = max(depth, 1e-9)
        return self.focal * float(d @ self.right) / z, self.focal * float(d @ self.up) / z, depth

    def lift_to(self, p: np.ndarray, y_px: float) -> np.ndarray:
        """`p` moved along world +Z until it projects at screen height `y_px` or a little above (Newton steps on
        the projected height, which grows with z and is convex in it while the camera looks down: the steps
        land at or just above the target and never pass the camera's plane)."""
        q = np.array(p, np.float64)
        zup = np.array([0.0, 0.0, 1.0])
        for _ in range(30):
            _, y, depth = self.project(q)
            if y >= y_px:
                break
            rate = self.focal * (float(zup @ self.up) - float(zup @ self.forward) * y / self.focal) / max(depth, 1e-9)
            if rate <= 0:  # the camera looks up at this point: lifting lowers it on screen; leave it
                break
            q[2] += (y_px - y) / rate + 1e-9
        return q


def label_rects(positions: np.ndarray, texts: Sequence[str], *, view: View, fov: float = FOV_RAD,
                height_px: float = REFERENCE_VIEW_PX) -> np.ndarray:
    """The screen rectangle of each label in `view` (what `place_labels` keeps apart).

    Args:
        positions: (K, 3) float label positions (the bottom centre of each label), world frame.
        texts: K label texts.
        view: the camera.
        fov: its vertical field of view, radians.
        height_px: canvas height, CSS px.

    Returns:
        (K, 4) float64 (left, bottom, right, top) in px from the image centre, y up.
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    if len(texts) != pos.shape[0]:
        raise ValueError(f"{pos.shape[0]} positions but {len(texts)} texts")
    cam = _Camera(view, fov=fov, height_px=height_px)
    out = np.zeros((pos.shape[0], 4))
    for k, p in enumerate(pos):
        x, y, _ = cam.project(p)
        w, h = label_size_px(texts[k])
        out[k] = (x - w / 2, y, x + w / 2, y + h)
    return out


def overlapping_pairs(rects: np.ndarray, *, gap: float = 0.0) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of rectangles ((K, 4) left, bottom, right, top) closer than `gap` in both axes."""
    r = np.asarray(rects, np.float64).reshape(-1, 4)
    out = []
    for i in range(r.shape[0]):
        for j in range(i + 1, r.shape[0]):
            if (r[i, 0] < r[j, 2] + gap and r[j, 0] < r[i, 2] + gap
                    and r[i, 1] < r[j, 3] + gap and r[j, 1] < r[i, 3] + gap):
                out.append((i, j))
    return out


def place_labels(
    anchors: np.ndarray,
    texts: Sequence[str],
    *,
    view: View,
    priority: np.ndarray | Sequence[float] | None = None,
    fov: float = FOV_RAD,
    height_px: float = REFERENCE_VIEW_PX,
) -> np.ndarray:
    """Lift labels straight up (world +Z) until no two overlap on screen in `view`; the highest priority first.

    Greedy and deterministic: labels are placed in order of descending `priority` (ties: in the given order);
    each stays at its anchor when nothing placed before covers it, else it is lifted just above the labels that
    do (by the screen gap `GAP_PX`). Only +Z changes; x and y stay those of the anchor.

    Args:
        anchors: (K, 3) float wanted label positions (bottom centre, just above each box), world frame, +Z up.
        texts: K label texts (their length sets the label width).
        view: the camera the labels must not overlap in (the viewer's fitted view).
        priority: (K,) float, e.g. the confidences (None: the given order).
        fov: the camera's vertical field of view, radians.
        height_px: canvas height, CSS px.

    Returns:
        (K, 3) float64 label positions, world frame.

    Raises:
        ValueError: anchors are not (K, 3) finite numbers, or texts / priority have another length.
    """
    a = np.asarray(anchors, np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
        raise ValueError(f"anchors must be (K, 3) finite numbers, got shape {a.shape}")
    k_n = a.shape[0]
    if len(texts) != k_n:
        raise ValueError(f"{k_n} anchors but {len(texts)} texts")
    prio = np.zeros(k_n) if priority is None else np.asarray(priority, np.float64).reshape(-1)
    if prio.shape[0] != k_n:
        raise ValueError(f"{k_n} anchors but {prio.shape[0]} priorities")
    cam = _Camera(view, fov=fov, height_px=height_px)
    out = a.copy()
    placed = np.zeros((0, 4))  # (left, bottom, right, top) px of the labels placed so far
    g = GAP_PX
    for k in np.argsort(-np.nan_to_num(prio, nan=-np.inf), kind="stable"):
        w, h = label_size_px(texts[int(k)])
        p = a[k].copy()
        for _ in range(len(placed) + 4):  # a lift clears the labels beside; more rounds absorb the perspective
            x, y, depth = cam.project(p)
            side = placed[(x - w / 2 < placed[:, 2] + g) & (placed[:, 0] < x + w / 2 + g)]
            if not ((y < side[:, 3] + g) & (side[:, 1] < y + h + g)).any():
                break
            # the lowest free spot at or above y between the labels placed beside this one
            spots = np.concatenate([[y], side[:, 3] + g])
            spots = np.sort(spots[spots >= y])
            clash = (spots[:, None] < side[None, :, 3] + g) & (side[None, :, 1] < spots[:, None] + h + g)
            p = cam.lift_to(p, float(spots[int(np.argmin(clash.any(axis=1)))]) + 0.01)
        x, y, _ = cam.project(p)
        placed = np.vstack([placed, [x - w / 2, y, x + w / 2, y + h]])
        out[k] = p
    return out


def leader_segments(anchors: np.ndarray, positions: np.ndarray, *, min_length: float = 1e-9) -> np.ndarray:
    """Leader lines from each anchor up to its lifted label (only for labels that were lifted).

    Args:
        anchors: (K, 3) float wanted positions, world frame.
        positions: (K, 3) float placed positions (`place_labels`).
        min_length: labels lifted less than this (metres) get no leader.

    Returns:
        (L, 2, 3) float32 segments, world frame (L = labels lifted).
    """
    a = np.asarray(anchors, np.float64).reshape(-1, 3)
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    moved = np.linalg.norm(p - a, axis=1) > min_length
    return np.stack([a[moved], p[moved]], axis=1).astype(np.float32)
