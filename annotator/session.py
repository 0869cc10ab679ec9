"""The annotator's headless session: every labelling action on typed data, no viser, no GUI handle.

`AnnotatorSession` opens one scan and its label store (`annotator.store.LabelStore`: journal first, autosaved
checkpoint, recovery) and does what the annotator does: paint and erase (dabs, strokes), region grow, fill, box
and lasso select, instances (new, update, delete, merge, pick, cycle), undo/redo, import, export, EFEM pre-labels
and their review, and click-to-segment with the shape prior (preview, accept, discard). It is the tools' host
(`annotator.tools.ToolHost`): a tool's functions get the session. `annotator.app.AnnotatorApp` is the thin viser
layer on top: it builds the GUI, translates events into session calls and draws what the session reports through
its hooks (`on_change`, `on_cursor`, `on_lasso`, `on_preview`, `on_segment`, `on_efem`, `notify`).

The session is a facade over its rooms (`annotator.rooms`, one job each; docs/INTERFACES.md): `scan` (the scan,
its geometry and label store, the warm-up), `instances` (the active tool and the instance table), `painting`,
`cursor_room`, `box_lasso`, `files` and `assist` (EFEM pre-labels, click-to-segment and its thread). Each action
is forwarded to its room; the session itself holds the hooks (`rooms.context.SessionHooks`) the rooms call.

A script or a notebook drives it directly::

    session = AnnotatorSession("sample_scenes/syn_z_1.ply", out_dir="labels")
    session.new_instance(category="mug")
    session.grow(seed=123)
    session.export("ply")
    session.close()

Threading: edits go through the store's lock; the click-to-segment run has its own thread (or the caller's with
`wait=True`).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Mapping, Sequence

import numpy as np

from annotator.io import MAX_SCAN_POINTS, LabelData
from annotator.lasso import LassoCamera, LassoOutline
from annotator.rooms.assist import AssistRoom
from annotator.rooms.box_lasso import BoxLassoRoom
from annotator.rooms.context import SessionHooks, Toolbox
from annotator.rooms.cursor import BrushCursor, CursorRoom
from annotator.rooms.files import FileRoom
from annotator.rooms.instances import InstanceRoom
from annotator.rooms.paint import PaintRoom, Stroke
from annotator.rooms.scan import ScanRoom
from annotator.tools import DEFAULT_TOOLS, Hit, Tool, ToolSettings, all_controls, check_tools, scaled_to_scan

if TYPE_CHECKING:
    from annotator.store import LabelStore
    from annotator.labels import Delta
    from annotator.selection import ScanGeometry
    from efem_viz.data.scene import Scene

__all__ = ["AnnotatorSession", "BrushCursor", "Stroke"]


TABLE_CLEARANCE_MIN = 0.005
"""Least height above the table (m) that region grow and fill keep to on an imported tabletop scan."""


def table_clearance(provenance: Mapping[str, Any] | None) -> float:
    """The default *Grow: min height* of a scan (m): on a tabletop imported from an RGB-D frame (`import-rgbd`: the
    table at z = 0) 2.5x the table fit's RMS residual, at least `TABLE_CLEARANCE_MIN`, to 1 mm (a grow from a mug
    then stops at the table instead of flooding it); 0 (off) for any other scan.

    Args:
        provenance: the scene's provenance (`Scene.provenance`).
    """
    prov = dict(provenance or {})
    if prov.get("source") != "rgbd":
        return 0.0
    try:
        rms = float(prov.get("plane_residual_rms_m", 0.0))
    except (TypeError, ValueError):
        rms = 0.0
    rms = rms if np.isfinite(rms) and 0.0 <= rms < 0.05 else 0.0
    return round(max(TABLE_CLEARANCE_MIN, 2.5 * rms), 3)


class AnnotatorSession(SessionHooks):
    """One scan, its label store and every annotator action.

    Args:
        scan_path: the scan (PLY/OBJ/OFF/GLB/NPZ scene, or an RGB-D frame .npz). Never written.
        labels_path: labels to start a *new* session from (ignored with a warning when the output directory
            already holds a journal for this scan: the session resumes instead).
        out_dir: where the journal, checkpoint and exports go (default: the current working directory). The
            journal and checkpoint live in `<out>/<stem>.annotate/`; read-only folders are refused.
        max_points: refuse scans with more vertices.
        autosave_delay: seconds between an edit and the checkpoint rewrite (the journal is always immediate).
        accept_scan_mismatch: resume a journal written for other geometry with the same vertex count.
        tools: the tool table (`annotator.tools.Tool` entries; default `DEFAULT_TOOLS`). The first is active.
        on_stage: called with what the opening does next (`ScanRoom`).

    Raises:
        LabelIOError: the scan or labels cannot be read; JournalError: the journal belongs to another scan.
    """

    def __init__(
        self,
        scan_path: str | Path,
        *,
        labels_path: str | Path | None = None,
        out_dir: str | Path | None = None,
        max_points: int = MAX_SCAN_POINTS,
        autosave_delay: float = 0.5,
        accept_scan_mismatch: bool = False,
        tools: Sequence[Tool] = DEFAULT_TOOLS,
        on_stage: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__()
        self.toolbox = Toolbox(tools)
        """The tool table and the settings the tools read."""
        self.scan = ScanRoom(scan_path, labels_path=labels_path, out_dir=out_dir, max_points=max_points,
                             autosave_delay=autosave_delay, accept_scan_mismatch=accept_scan_mismatch,
                             on_stage=on_stage)
        """The scan, its geometry and its label store."""
        diagonal = float(np.linalg.norm(np.ptp(self.scan.scene.points, axis=0)))
        self.toolbox.tools = scaled_to_scan(self.toolbox.tools, diagonal)  # sliders as long as the scan needs
        self.toolbox.tool_of = check_tools(self.toolbox.tools)
        settings = self.toolbox.settings
        radius = next(c for c in all_controls(self.toolbox.tools) if c.setting == "radius")
        settings.radius = float(np.clip(0.02 * diagonal, max(0.005, radius.min / radius.scale),
                                        radius.max / radius.scale))
        settings.grow_min_height = table_clearance(self.scan.scene.provenance)
        ls = self.scan.store.labelset
        if ls.instances:
            settings.active_id = max(ls.instances)
            settings.category = ls.instances[settings.active_id].category or "object"
        self.cursor_room = CursorRoom(self.scan, self.toolbox, self)
        """The brush cursor."""
        self.instances = InstanceRoom(self.scan, self.toolbox, self, self.cursor_room)
        """The active tool and the instance table."""
        self.painting = PaintRoom(self.scan, self.toolbox, self, self.cursor_room, self.instances, self)
        """Painting, erasing, region grow, fill, the active tool at a point."""
        self.box_lasso = BoxLassoRoom(self.scan, self.toolbox, self, self.painting)
        """Box and lasso selection."""
        self.files = FileRoom(self.scan, self.toolbox, self)
        """Label export and import."""
        self.assist = AssistRoom(self.scan, self.toolbox, self, self.instances, self.painting)
        """EFEM assistance: pre-labels and their review, click-to-segment."""

    def close(self) -> None:
        """Commit what was typed, flush the checkpoint and release the journal (idempotent)."""
        try:
            self.instances.flush_typing()
        finally:
            self.scan.close()

    # ================================================================== what the rooms hold
    @property
    def tools(self) -> tuple[Tool, ...]:
        """The tool table the toolbar, hotkeys, help and gestures read."""
        return self.toolbox.tools

    @property
    def tool_of(self) -> dict[str, Tool]:
        """The tools by name."""
        return self.toolbox.tool_of

    @property
    def tool(self) -> Tool:
        """The active tool's table entry."""
        return self.toolbox.tool

    @property
    def settings(self) -> ToolSettings:
        """What the tools read (`annotator.tools.ToolSettings`)."""
        return self.toolbox.settings

    @property
    def scan_path(self) -> Path:
        """The scan (never written)."""
        return self.scan.scan_path

    @property
    def scene(self) -> Scene:
        """The scan as a `Scene`."""
        return self.scan.scene

    @property
    def n(self) -> int:
        """The scan's vertex count."""
        return self.scan.n

    @property
    def out_dir(self) -> Path:
        """The output folder."""
        return self.scan.out_dir

    @property
    def stem(self) -> str:
        """The scan's file name without its suffix (names the journal and the exports)."""
        return self.scan.stem

    @property
    def roots(self) -> list[Path]:
        """The folders files are read from."""
        return self.scan.roots

    @property
    def work_dir(self) -> Path:
        """The journal's and checkpoint's folder."""
        return self.scan.work_dir

    @property
    def store(self) -> LabelStore:
        """The label store."""
        return self.scan.store

    @property
    def geom(self) -> ScanGeometry:
        """The scan's selection geometry."""
        return self.scan.geom

    @property
    def cursor(self) -> BrushCursor | None:
        """The brush cursor (None until the brush first touches the scan)."""
        return self.cursor_room.cursor

    @property
    def strokes(self) -> dict[int, Stroke]:
        """Drag strokes in progress, by client id."""
        return self.painting.strokes

    @property
    def lasso_outline(self) -> LassoOutline:
        """The lasso tool's outline."""
        return self.box_lasso.lasso_outline

    @property
    def preview(self) -> np.ndarray | None:
        """(N,) bool mask drawn highlighted (click-to-segment preview), or None."""
        return self.assist.preview

    @property
    def pending_segment(self) -> np.ndarray | None:
        """(K,) int32 vertices of the previewed segment, or None."""
        return self.assist.pending_segment

    @property
    def prelabel_cursor(self) -> int | None:
        """The pre-label Next / Previous went to last (None: not used yet)."""
        return self.assist.prelabel_cursor

    @prelabel_cursor.setter
    def prelabel_cursor(self, iid: int | None) -> None:
        self.assist.prelabel_cursor = iid

    @property
    def segmenting(self) -> bool:
        """Whether a click-to-segment run is in progress."""
        return self.assist.segmenting

    @property
    def efem_running(self) -> bool:
        """Whether an EFEM run on the whole scan is in progress."""
        return self.assist.efem_running

    # ================================================================== tools and instances (rooms/instances.py)
    def set_tool(self, tool: str) -> None:
        """`InstanceRoom.set_tool`."""
        self.instances.set_tool(tool)

    def set_active(self, instance_id: int) -> None:
        """`InstanceRoom.set_active`."""
        self.instances.set_active(instance_id)

    def cycle_active(self, step: int = 1) -> int:
        """`InstanceRoom.cycle_active`."""
        return self.instances.cycle_active(step)

    def resize_brush(self, factor: float) -> float:
        """`InstanceRoom.resize_brush`."""
        return self.instances.resize_brush(factor)

    def choose_category(self, category: str) -> None:
        """`InstanceRoom.choose_category`."""
        self.instances.choose_category(category)

    def type_text(self, field: Literal["name", "category"], value: str) -> None:
        """`InstanceRoom.type_text`."""
        self.instances.type_text(field, value)

    def flush_typing(self, *, refresh: bool = True) -> int:
        """`InstanceRoom.flush_typing`."""
        return self.instances.flush_typing(refresh=refresh)

    def fields_typing(self) -> frozenset[str]:
        """`InstanceRoom.fields_typing`."""
        return self.instances.fields_typing()

    def new_instance(self, *, category: str = "object", name: str | None = None, client: str = "") -> int:
        """`InstanceRoom.new_instance`."""
        return self.instances.new_instance(category=category, name=name, client=client)

    def update_active(self, **changes: Any) -> None:
        """`InstanceRoom.update_active`."""
        self.instances.update_active(**changes)

    def toggle_active(self, what: Literal["visible", "locked"]) -> None:
        """`InstanceRoom.toggle_active`."""
        self.instances.toggle_active(what)

    def update_instance(self, instance_id: int, **changes: Any) -> None:
        """`InstanceRoom.update_instance`."""
        self.instances.update_instance(instance_id, **changes)

    def delete_instance(self, instance_id: int) -> None:
        """`InstanceRoom.delete_instance`."""
        self.instances.delete_instance(instance_id)

    def merge(self, sources: list[int], into: int) -> None:
        """`InstanceRoom.merge`."""
        self.instances.merge(sources, into)

    def undo(self, *, client: str = "") -> list[Delta]:
        """`InstanceRoom.undo`."""
        return self.instances.undo(client=client)

    def redo(self, *, client: str = "") -> list[Delta]:
        """`InstanceRoom.redo`."""
        return self.instances.redo(client=client)

    def require_active(self) -> int:
        """`InstanceRoom.require_active`."""
        return self.instances.require_active()

    # ================================================================== painting (rooms/paint.py)
    def paint(self, idx: np.ndarray, *, erase: bool = False, group: str = "", client: str = "") -> Delta | None:
        """`PaintRoom.paint`."""
        return self.painting.paint(idx, erase=erase, group=group, client=client)

    def edit_source(self, source: str) -> AbstractContextManager[None]:
        """`PaintRoom.edit_source`."""
        return self.painting.edit_source(source)

    def paint_stroke(self, points: np.ndarray, *, erase: bool = False, client: str = "") -> int:
        """`PaintRoom.paint_stroke`."""
        return self.painting.paint_stroke(points, erase=erase, client=client)

    def dab(self, vertex: int, position: np.ndarray, *, erase: bool, client: str = "") -> Delta | None:
        """`PaintRoom.dab`."""
        return self.painting.dab(vertex, position, erase=erase, client=client)

    def grow(self, seed: int, *, client: str = "") -> Delta | None:
        """`PaintRoom.grow`."""
        return self.painting.grow(seed, client=client)

    def fill(self, seed: int, *, client: str = "") -> Delta | None:
        """`PaintRoom.fill`."""
        return self.painting.fill(seed, client=client)

    def pick_instance(self, vertex: int) -> int:
        """`PaintRoom.pick_instance`."""
        return self.painting.pick_instance(vertex)

    def apply_tool(self, hit: Hit) -> None:
        """`PaintRoom.apply_tool`."""
        self.painting.apply_tool(hit)

    def click(self, origin: np.ndarray, direction: np.ndarray, *, client: str = "") -> int | None:
        """`PaintRoom.click`."""
        return self.painting.click(origin, direction, client=client)

    def stroke_start(self, key: int, position: np.ndarray, *, client: str = "") -> None:
        """`PaintRoom.stroke_start`."""
        self.painting.stroke_start(key, position, client=client)

    def stroke_to(self, key: int, camera_position: np.ndarray, target: np.ndarray, *, end: bool = False,
                  client: str = "") -> None:
        """`PaintRoom.stroke_to`."""
        self.painting.stroke_to(key, camera_position, target, end=end, client=client)

    # ================================================================== the brush cursor (rooms/cursor.py)
    def move_cursor(self, position: np.ndarray, vertex: int) -> BrushCursor:
        """`CursorRoom.move_cursor`."""
        return self.cursor_room.move_cursor(position, vertex)

    def refresh_cursor(self) -> BrushCursor | None:
        """`CursorRoom.refresh_cursor`."""
        return self.cursor_room.refresh_cursor()

    # ================================================================== box and lasso (rooms/box_lasso.py)
    def box(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float,
            screen_min: tuple[float, float], screen_max: tuple[float, float], client: str = "") -> Delta | None:
        """`BoxLassoRoom.box`."""
        return self.box_lasso.box(position=position, wxyz=wxyz, fov=fov, aspect=aspect, screen_min=screen_min,
                                  screen_max=screen_max, client=client)

    def lasso(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float, polygon: np.ndarray,
              client: str = "") -> Delta | None:
        """`BoxLassoRoom.lasso`."""
        return self.box_lasso.lasso(position=position, wxyz=wxyz, fov=fov, aspect=aspect, polygon=polygon,
                                    client=client)

    def add_lasso_point(self, screen_pos: Sequence[float] | Sequence[Sequence[float]], *,
                        ray_origin: Sequence[float] | np.ndarray, ray_direction: Sequence[float] | np.ndarray,
                        camera: LassoCamera) -> int:
        """`BoxLassoRoom.add_lasso_point`."""
        return self.box_lasso.add_lasso_point(screen_pos, ray_origin=ray_origin, ray_direction=ray_direction,
                                              camera=camera)

    def apply_lasso(self, *, client: str = "") -> Delta | None:
        """`BoxLassoRoom.apply_lasso`."""
        return self.box_lasso.apply_lasso(client=client)

    def clear_lasso(self) -> None:
        """`BoxLassoRoom.clear_lasso`."""
        self.box_lasso.clear_lasso()

    # ================================================================== files (rooms/files.py)
    def safe_path(self, name: str, *, what: str) -> Path:
        """`FileRoom.safe_path`."""
        return self.files.safe_path(name, what=what)

    def export(self, fmt: Literal["ply", "npz", "scannet"], *, directory: str | None = None) -> list[Path]:
        """`FileRoom.export`."""
        return self.files.export(fmt, directory=directory)

    def import_labels(self, path: str) -> Delta | None:
        """`FileRoom.import_labels`."""
        return self.files.import_labels(path)

    # ================================================================== EFEM assistance (rooms/assist.py)
    def import_efem(self, path: str) -> list[int]:
        """`AssistRoom.import_efem`."""
        return self.assist.import_efem(path)

    def add_prelabels(self, data: LabelData, *, source: str) -> list[int]:
        """`AssistRoom.add_prelabels`."""
        return self.assist.add_prelabels(data, source=source)

    def review_prelabel(self, instance_id: int, action: Literal["accept", "reject", "merge"], *,
                        group: str = "") -> None:
        """`AssistRoom.review_prelabel`."""
        self.assist.review_prelabel(instance_id, action, group=group)

    def prelabel_cut(self, default: float = 0.5) -> float:
        """`AssistRoom.prelabel_cut`."""
        return self.assist.prelabel_cut(default)

    def review_prelabels(self, cut: float, action: Literal["accept", "reject"]) -> list[int]:
        """`AssistRoom.review_prelabels`."""
        return self.assist.review_prelabels(cut, action)

    def run_efem(self, *, preset: str | None = None, proposals: int | None = None, seed: int = 0,
                 wait: bool = False) -> list[int] | None:
        """`AssistRoom.run_efem`."""
        return self.assist.run_efem(preset=preset, proposals=proposals, seed=seed, wait=wait)

    def cancel_efem(self) -> bool:
        """`AssistRoom.cancel_efem`."""
        return self.assist.cancel_efem()

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """`AssistRoom.segment_at`."""
        return self.assist.segment_at(vertex, wait=wait)

    def set_preview(self, idx: np.ndarray | None) -> None:
        """`AssistRoom.set_preview`."""
        self.assist.set_preview(idx)

    def accept_segment(self) -> Delta | None:
        """`AssistRoom.accept_segment`."""
        return self.assist.accept_segment()

    def discard_segment(self) -> None:
        """`AssistRoom.discard_segment`."""
        self.assist.discard_segment()
