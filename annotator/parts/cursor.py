"""The brush cursor's part: the ring of the brush radius where the brush last touched the scan."""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from annotator.tools import shown_settings

if TYPE_CHECKING:
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart


@dataclass(frozen=True)
class BrushCursor:
    """Where the brush cursor is drawn: the ring of the brush radius where the brush last touched the scan
    (viser 1.1 sends no pointer-move events, so it follows clicks and drags, not the hovering mouse)."""

    position: np.ndarray
    """(3,) float, the brush position on the surface, world frame."""
    normal: np.ndarray
    """(3,) float, the surface normal there."""
    radius: float
    """The brush radius the ring shows, metres."""
    visible: bool
    """Drawn: the active tool has a brush radius (brush, erase)."""


class CursorPart:
    """Where the brush cursor is drawn (it follows clicks and drags: viser sends no pointer moves)."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks) -> None:
        self.scan, self.toolbox, self.hooks = scan, toolbox, hooks
        self.cursor: BrushCursor | None = None
        """The brush cursor (None until the brush first touches the scan)."""
        self._cursor_lock = threading.Lock()

    def move_cursor(self, position: np.ndarray, vertex: int) -> BrushCursor:
        """Put the brush cursor (a ring of the brush radius) at a surface point.

        Args:
            position: (3,) float, the point on the surface, world frame.
            vertex: the scan vertex there (its normal orients the ring).
        """
        normal = np.asarray(self.scan.geom.normals[int(vertex)], np.float64).reshape(3).copy()
        with self._cursor_lock:
            cur = self.cursor = BrushCursor(np.asarray(position, np.float64).reshape(3).copy(), normal,
                                            self.toolbox.settings.radius, "radius" in shown_settings(self.toolbox.tool))
        self.hooks.on_cursor()
        return cur

    def refresh_cursor(self) -> BrushCursor | None:
        """The cursor with the current radius and tool (after a radius or tool change); None before the first."""
        with self._cursor_lock:
            if self.cursor is None:
                return None
            self.cursor = dataclasses.replace(self.cursor, radius=self.toolbox.settings.radius,
                                              visible="radius" in shown_settings(self.toolbox.tool))
        self.hooks.on_cursor()
        return self.cursor
