"""The lasso tool's outline: screen points clicked in one camera view, and the 3-D polyline that shows them.

Pure (numpy only). The app (`annotator.app`) adds a point per Ctrl/Cmd+click of the lasso tool, draws
`segments()`, and on Apply selects with `annotator.selection.lasso_select` through the first click's camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np

MAX_LASSO_POINTS = 500
"""Most outline points one lasso may have (a client cannot grow it without bound)."""
MARKER_DEPTH = 0.05
"""The drawn outline floats this far (metres) in front of the camera along each click's ray."""


class LassoCamera(NamedTuple):
    """The camera of the first click: every outline point is in its screen coordinates."""

    position: np.ndarray
    """(3,) float64, world."""
    wxyz: np.ndarray
    """(4,) float64 orientation (viser / OpenCV camera)."""
    fov: float
    """Vertical field of view, radians."""
    aspect: float
    """Width / height."""


@dataclass
class LassoOutline:
    """The outline being drawn."""

    points: list[tuple[float, float]] = field(default_factory=list)
    """Outline in [0, 1] screen coordinates of `camera` (OpenCV: u right, v down)."""
    world: list[np.ndarray] = field(default_factory=list)
    """(3,) float64 world position drawn for each point."""
    camera: LassoCamera | None = None
    """The first click's camera (None while empty)."""
    max_points: int = MAX_LASSO_POINTS

    def __len__(self) -> int:
        return len(self.points)

    def add(
        self,
        screen_pos: Sequence[float] | Sequence[Sequence[float]],
        *,
        ray_origin: Sequence[float] | np.ndarray,
        ray_direction: Sequence[float] | np.ndarray,
        camera: LassoCamera,
    ) -> int:
        """Add a clicked point (clamped to the screen); the camera is kept from the first point.

        Args:
            screen_pos: (u, v) of the click in [0, 1], OpenCV image coordinates: what a browser click delivers as
                `viser.SceneClickEvent.screen_pos` (the legacy `ScenePointerEvent`'s one-point `((u, v),)` is
                taken too).
            ray_origin: (3,) world origin of the click's ray.
            ray_direction: (3,) world direction of the click's ray.
            camera: the client's camera at this click.

        Returns:
            The number of outline points.

        Raises:
            ValueError: the outline already has `max_points` points, or `screen_pos` is not one finite (u, v).
        """
        if len(self.points) >= self.max_points:
            raise ValueError(f"a lasso has at most {self.max_points} points")
        uv = _screen_point(screen_pos)
        if not self.points:
            self.camera = camera
        u, v = uv
        self.points.append((min(max(u, 0.0), 1.0), min(max(v, 0.0), 1.0)))
        origin = np.asarray(ray_origin, np.float64)
        direction = np.asarray(ray_direction, np.float64)
        self.world.append(origin + MARKER_DEPTH * direction / max(float(np.linalg.norm(direction)), 1e-9))
        return len(self.points)

    def polygon(self) -> tuple[LassoCamera, np.ndarray]:
        """The camera and the (P, 2) float64 outline to select with.

        Raises:
            ValueError: fewer than 3 points.
        """
        if len(self.points) < 3 or self.camera is None:
            raise ValueError(f"the lasso has {len(self.points)} points; Ctrl/Cmd+click at least 3")
        return self.camera, np.asarray(self.points, np.float64)

    def clear(self) -> None:
        """Drop the outline."""
        self.points.clear()
        self.world.clear()
        self.camera = None

    def segments(self) -> np.ndarray | None:
        """(P, 2, 3) float32 closed polyline through the drawn points, or None with fewer than 2 points."""
        if len(self.world) < 2:
            return None
        w = np.asarray(self.world, np.float32)
        return np.stack([w, np.roll(w, -1, axis=0)], axis=1)


def _screen_point(screen_pos: Sequence[float] | Sequence[Sequence[float]]) -> tuple[float, float]:
    """(u, v) from a click's screen position: a pair, or a single pair wrapped once (legacy pointer events).

    Raises:
        ValueError: anything else (a box's two corners, NaN, text).
    """
    try:
        a = np.asarray(screen_pos, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"a click's screen position must be (u, v), got {screen_pos!r}") from None
    if a.shape != (2,) or not np.isfinite(a).all():
        raise ValueError(f"a click's screen position must be two finite numbers (u, v), got {screen_pos!r}")
    return float(a[0]), float(a[1])
