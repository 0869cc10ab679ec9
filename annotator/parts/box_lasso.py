"""The box and lasso part: select the vertices inside a screen rectangle or outline seen from a camera."""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from annotator import selection as sel
from annotator.labels import Delta
from annotator.lasso import LassoCamera, LassoOutline

if TYPE_CHECKING:
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart
    from annotator.parts.paint import PaintPart


class BoxLassoPart:
    """Box and lasso selection, painted with the active instance (erased with an erasing tool)."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks, painting: PaintPart) -> None:
        self.scan, self.toolbox, self.hooks, self.painting = scan, toolbox, hooks, painting
        self.lasso_outline = LassoOutline()
        """The lasso tool's outline (screen points of one view)."""

    def box(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float,
            screen_min: tuple[float, float], screen_max: tuple[float, float], client: str = "") -> Delta | None:
        """Box select with a camera, painted with the active instance (erased with the erase tool)."""
        counts: dict[str, int] = {}
        idx = sel.box_select(self.scan.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect,
                             screen_min=screen_min, screen_max=screen_max, facing=self._facing(), counts=counts)
        with self.painting.edit_source(_source("box select", counts)):
            return self._told(self.painting.paint(idx, erase=self.toolbox.tool.erase, client=client), "box select")

    def lasso(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float, polygon: np.ndarray,
              client: str = "") -> Delta | None:
        """Lasso select with a camera: vertices inside a screen outline, painted with the active instance (erased
        with the erase tool); `Box select: visible/front/all` decides whether hidden surface is taken too."""
        counts: dict[str, int] = {}
        idx = sel.lasso_select(self.scan.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect, polygon=polygon,
                               facing=self._facing(), counts=counts)
        with self.painting.edit_source(_source("lasso", counts)):
            return self._told(self.painting.paint(idx, erase=self.toolbox.tool.erase, client=client), "lasso")

    def _told(self, delta: Delta | None, what: str) -> Delta | None:
        """A box or lasso selection reaches far more vertices than a brush dab, hidden ones included: when it took
        vertices of other instances the user is told at once (and how to undo or avoid it), not only in the edit
        history."""
        taken = 0 if delta is None or self.toolbox.tool.erase else int(np.count_nonzero(delta.before > 0))
        if taken:
            self.hooks.notify(f"The {what} took {taken:,} labelled vertices",
                              "they belonged to other instances: Ctrl+Z undoes it, and 'Only unlabelled vertices' "
                              "keeps labelled vertices out of a selection")
        return delta

    def _facing(self) -> sel.Facing:
        mode = self.toolbox.settings.box_facing
        return mode if mode in ("visible", "front", "all") else "visible"  # type: ignore[return-value]

    def add_lasso_point(self, screen_pos: Sequence[float] | Sequence[Sequence[float]], *,
                        ray_origin: Sequence[float] | np.ndarray, ray_direction: Sequence[float] | np.ndarray,
                        camera: LassoCamera) -> int:
        """Lasso tool: add a clicked screen point to the outline (the first point's camera is used); returns the
        number of outline points (see `annotator.lasso.LassoOutline.add`).

        Raises:
            ValueError: the outline is full, or `screen_pos` is not one finite (u, v).
        """
        n = self.lasso_outline.add(screen_pos, ray_origin=ray_origin, ray_direction=ray_direction, camera=camera)
        self.hooks.on_lasso()
        return n

    def apply_lasso(self, *, client: str = "") -> Delta | None:
        """Select inside the outline drawn with the lasso tool, then clear it."""
        camera, polygon = self.lasso_outline.polygon()
        self.clear_lasso()
        return self.lasso(position=camera.position, wxyz=camera.wxyz, fov=camera.fov, aspect=camera.aspect,
                          polygon=polygon, client=client)

    def clear_lasso(self) -> None:
        """Drop the lasso outline."""
        self.lasso_outline.clear()
        self.hooks.on_lasso()


def _source(tool: str, counts: dict[str, int]) -> str:
    """The edit's source label: the tool, and how many hidden vertices it left out ("lasso, 2,670 hidden left
    out"), so the history says what was taken and what was not."""
    hidden = counts.get("hidden", 0)
    return f"{tool}, {hidden:,} hidden left out" if hidden else tool
