"""The scenes part: read a scene of the discovered list, make it the open one, and the display settings."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.viewer.scene_list import SceneEntry, is_inside
from efem_viz.viewer.state import COLOR_MODES, VIEW_MODES

if TYPE_CHECKING:
    from pathlib import Path

    from efem_viz.data.scene import Scene
    from efem_viz.viewer.parts.core import ViewerCore

log = logging.getLogger(__name__)

MAX_VIEW_COORDINATE = 1e5
"""Largest |coordinate| (metres) of a scene the viewer opens: beyond, it is not a metric scan (a file in other
units, or damaged), and the drawing maths would overflow."""


class ScenePart:
    """Opens scenes (only inside the given paths) and holds the display choices (points or mesh, colours, view)."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""

    def read_scene(self, name: str) -> tuple[SceneEntry, Scene] | None:
        """Load a scene of the list (no state change). None, with the status saying why, when it cannot."""
        from efem_viz.data.io import holds_predictions, load_scene
        from efem_viz.data.scan import scene_in_scene_frame

        try:
            entry = self.core.state.entry(name)
        except KeyError as exc:
            self.core.set_status(str(exc), error=True)
            return None
        if not is_inside(entry.path, self.core.roots):  # never read outside the given paths
            self.core.set_status(f"refusing to open {entry.path}: outside the given paths", error=True)
            return None
        self.core.set_status(f"Loading {entry.name} …")
        try:
            scene, notice = scene_in_scene_frame(load_scene(entry.path, max_points=self.core.max_points))
            if notice is not None:
                log.warning("%s", notice)
                self.core.set_status(notice)
            reach = float(np.abs(scene.points).max()) if scene.num_points else 0.0
            if not reach <= MAX_VIEW_COORDINATE:
                raise ValueError(f"coordinates reach {reach:.3g} m: not a scan in metres (the viewer shows scenes "
                                 f"within ±{MAX_VIEW_COORDINATE:.0e} m)")
            if holds_predictions(entry.path) and scene.instance is not None:
                scene = scene.with_labels(None, {})  # a segment output's labels are its predictions: no ground truth
        except Exception as exc:  # noqa: BLE001 - SceneError, OSError, parser errors: show, stay up
            self.core.set_status(f"Could not open {entry.path.name}: {exc}", error=True)
            return None
        return entry, scene

    def show_scene(self, entry: SceneEntry, scene: Scene) -> None:
        """Make `scene` the open scene (no result yet; a run of the previous scene is cancelled)."""
        with self.core.lock:
            s = self.core.state
            s.playing = False
            if s.running:
                self.core.cancel_event.set()  # the run belongs to the previous scene
            self.core.forget_views()
            self.core.scene_generation += 1
            s.scene_name, s.scene, s.result, s.result_source = entry.name, scene, None, ""
            s.step, s.selected, s.color_mode, s.view_mode = 0, None, "rgb", "result"
            if scene.is_mesh and s.display == "points":
                s.display = "mesh"
            elif not scene.is_mesh:
                s.display = "points"

    def open_scene(self, name: str) -> Scene | None:
        """Open a scene of the list (`state.entries`). Returns it, or None (status says why; the previous scene
        stays). Its saved result is not loaded: call `load_result()`."""
        got = self.read_scene(name)
        if got is None:
            return None
        self.show_scene(*got)
        self.core.set_status(f"Opened {got[0].name} ({got[1].num_points:,} points).")
        return got[1]

    def saved_result_path(self) -> Path | None:
        """The open scene's saved result when one exists and may be read, else None."""
        s = self.core.state
        if s.scene_name is None:
            return None
        p = s.entry(s.scene_name).trace_path
        return p if p.is_file() and self.core.allowed(p) else None

    def set_display(self, display: str) -> None:
        """'points' or 'mesh'."""
        if display not in ("points", "mesh"):
            raise ValueError(f"display must be 'points' or 'mesh', got {display!r}")
        self.core.state.display = display  # type: ignore[assignment]

    def set_color_mode(self, mode: str) -> None:
        """'rgb', 'instances', 'gt_match' or 'weights' (the instance colourings show the result view)."""
        if mode not in COLOR_MODES.values():
            raise ValueError(f"unknown colour mode {mode!r}; expected one of {sorted(COLOR_MODES.values())}")
        self.core.state.color_mode = mode  # type: ignore[assignment]

    def set_view_mode(self, mode: str) -> None:
        """"step" or "result"."""
        if mode not in VIEW_MODES.values():
            raise ValueError(f"unknown view mode {mode!r}; expected one of {sorted(VIEW_MODES.values())}")
        self.core.state.view_mode = mode  # type: ignore[assignment]

    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None:
        """Show or hide the final instances' meshes, boxes and axes."""
        s = self.core.state
        s.show_meshes, s.show_obbs, s.show_axes = bool(meshes), bool(obbs), bool(axes)

    def recolored(self) -> bool:
        """Whether the points carry other colours than the scene's (the mesh display then overlays them)."""
        s = self.core.state
        if s.color_mode == "weights":
            return True
        return s.color_mode != "rgb" and s.view_mode == "result"
