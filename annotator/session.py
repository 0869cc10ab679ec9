"""The annotator's headless session: every labelling action on typed data, no viser, no GUI handle.

`AnnotatorSession` opens one scan and its label store (`annotator.journal.LabelStore`: journal first, autosaved
checkpoint, recovery) and does what the annotator does: paint and erase (dabs, strokes), region grow, fill, box
and lasso select, instances (new, update, delete, merge, pick, cycle), undo/redo, import, export, EFEM pre-labels
and their review, and click-to-segment with the shape prior (preview, accept, discard). It is the tools' host
(`annotator.tools.ToolHost`): a tool's functions get the session. `annotator.app.AnnotatorApp` is the thin viser
layer on top: it builds the GUI, translates events into session calls and draws what the session reports through
its hooks (`on_change`, `on_cursor`, `on_lasso`, `on_preview`, `on_segment`, `notify`).

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

import contextlib
import dataclasses
import logging
import os
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, Sequence

import numpy as np

from annotator import selection as sel
from annotator.io import (
    MAX_SCAN_POINTS,
    LabelData,
    LabelIOError,
    load_labels,
    load_scan,
    resolve_inside,
    save_labels_npz,
    save_labels_ply,
    save_scannet,
)
from annotator.journal import LabelStore, remove_stale_temp_files, scan_fingerprint
from annotator.labels import Delta, InstanceInfo, prelabel_note, unreviewed_prelabels
from annotator.lasso import LassoCamera, LassoOutline
from annotator.tools import DEFAULT_TOOLS, RADIUS, Hit, Tool, ToolSettings, all_controls, check_tools, shown_settings
from efem_viz.colors import instance_color
from efem_viz.data.io import RESULT_SUFFIX

log = logging.getLogger(__name__)

__all__ = ["AnnotatorSession", "BrushCursor", "Stroke"]


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


@dataclass
class Stroke:
    """A drag stroke in progress (one undo group)."""

    group: str
    last: np.ndarray
    """(3,) float32, the last brush position, world frame."""
    normal: np.ndarray
    erase: bool
    source: str = ""
    """Label of the tool that paints the stroke (history)."""


def _nothing(*_args: object) -> None:
    """The default hook: a session without a GUI draws nothing."""


class AnnotatorSession:
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
    ) -> None:
        self.tools: tuple[Tool, ...] = tuple(tools)
        """The tool table the toolbar, hotkeys, help and gestures read."""
        self.tool_of = check_tools(self.tools)
        self.scan_path = Path(scan_path).resolve()
        self.scene = load_scan(self.scan_path, max_points=max_points)
        self.n = self.scene.num_points
        self.out_dir = _writable_dir(out_dir)
        self.stem = self.scan_path.stem
        self.roots = [self.scan_path.parent, self.out_dir]
        self.work_dir = self.out_dir / f"{self.stem}.annotate"
        self.store = self._open_store(labels_path, autosave_delay=autosave_delay,
                                      accept_scan_mismatch=accept_scan_mismatch)
        # We hold the scan's journal lock now: temp files of an interrupted write of ours are stale.
        for folder in {self.out_dir, self.work_dir}:
            remove_stale_temp_files(folder, self.stem)
        self.geom = sel.ScanGeometry(self.scene.points, self.scene.normals, faces=self.scene.faces)
        self.settings = ToolSettings(tool=self.tools[0].name,
                                     radius=max(0.005, 0.02 * float(np.linalg.norm(np.ptp(self.scene.points, axis=0)))))
        ls = self.store.labelset
        if ls.instances:
            self.settings.active_id = max(ls.instances)
            self.settings.category = ls.instances[self.settings.active_id].category or "object"
        self.preview: np.ndarray | None = None
        """(N,) bool mask drawn highlighted (click-to-segment preview), or None."""
        self.pending_segment: np.ndarray | None = None
        """(K,) int32 vertices of the previewed segment, or None."""
        self.cursor: BrushCursor | None = None
        """The brush cursor (None until the brush first touches the scan)."""
        self.lasso_outline = LassoOutline()
        """The lasso tool's outline (screen points of one view)."""
        self.strokes: dict[int, Stroke] = {}
        """Drag strokes in progress, by client id."""
        self.prelabel_cursor: int | None = None
        """The pre-label Next / Previous went to last (None: not used yet)."""
        self._segment_lock = threading.Lock()
        self._segment_cancel: threading.Event | None = None
        self._cursor_lock = threading.Lock()
        self._tls = threading.local()
        # Hooks the GUI sets (a headless session leaves them doing nothing).
        self.on_change: Callable[[], None] = _nothing
        """The instance table or the active instance changed (redraw the panel)."""
        self.on_cursor: Callable[[], None] = _nothing
        """The brush cursor moved or changed (redraw it)."""
        self.on_lasso: Callable[[], None] = _nothing
        """The lasso outline changed."""
        self.on_preview: Callable[[np.ndarray], object] = _nothing
        """The segment preview changed: (K,) int64 vertices whose highlight changed."""
        self.on_segment: Callable[[float | None], None] = _nothing
        """Click-to-segment progress in percent (None: the run ended, or the preview changed)."""
        self.notify: Callable[[str, str], None] = lambda title, body: log.info("%s: %s", title, body)
        """Tell the user something (title, body)."""
        self.report: Callable[[Callable[[], Any]], Any] = _log_errors
        """Runs background work (the segment thread) so that its errors reach the user."""

    def _open_store(self, labels_path: str | Path | None, *, autosave_delay: float,
                    accept_scan_mismatch: bool) -> LabelStore:
        initial: LabelData | None = None
        if labels_path is not None:
            initial = load_labels(labels_path, self.n)
        elif self.scene.instance is not None and self.scene.has_gt:
            cats = dict(self.scene.categories)
            initial = LabelData(
                self.scene.instance.copy(),
                [
                    InstanceInfo(int(i), f"{cats.get(int(i), 'object')} {int(i)}", category=cats.get(int(i), "object"),
                                 color=instance_color(int(i)))
                    for i in self.scene.instance_ids()
                ],
            )
        journal_path = self.work_dir / f"{self.stem}.journal"
        if labels_path is not None and journal_path.exists():
            log.warning(
                "%s already has a journal: resuming it and ignoring --labels %s (use Import in the GUI to load "
                "them as an undoable edit)", self.work_dir, labels_path,
            )
        return LabelStore(
            self.n,
            journal_path=journal_path,
            label_path=self.work_dir / f"{self.stem}.labels.npz",
            scan_id={
                "name": self.scan_path.name,
                "num_vertices": self.n,
                "content_hash": scan_fingerprint(self.scene.points, self.scene.faces),
            },
            initial_labels=None if initial is None else initial.labels,
            initial_instances=None if initial is None else initial.instances,
            autosave_delay=autosave_delay,
            accept_scan_mismatch=accept_scan_mismatch,
        )

    def close(self) -> None:
        """Flush the checkpoint and release the journal (idempotent)."""
        self.store.close()

    # ================================================================== tools and instances
    @property
    def tool(self) -> Tool:
        """The active tool's table entry."""
        return self.tool_of[self.settings.tool]

    def set_tool(self, tool: str) -> None:
        """Make a tool of the table active."""
        if tool not in self.tool_of:
            raise ValueError(f"unknown tool {tool!r}; tools: {tuple(self.tool_of)}")
        self.settings.tool = tool
        self.refresh_cursor()

    def set_active(self, instance_id: int) -> None:
        """Make an instance the one brushes paint."""
        self.store.labelset.info(instance_id)  # KeyError when unknown
        self.settings.active_id = int(instance_id)
        self.on_change()

    def cycle_active(self, step: int = 1) -> int:
        """Make the next (`step` = 1) or previous (-1) instance by id active, wrapping around; returns its id.

        Raises:
            ValueError: there is no instance yet.
        """
        ids = sorted(self.store.labelset.instances)
        if not ids:
            raise ValueError("no instances yet: N creates one")
        current = self.settings.active_id
        if current in ids:
            nxt = ids[(ids.index(current) + step) % len(ids)]
        else:  # none active (or it was deleted): start at the first (last going back)
            nxt = ids[0] if step > 0 else ids[-1]
        self.set_active(nxt)
        return nxt

    def resize_brush(self, factor: float) -> float:
        """Multiply the brush radius by `factor` (the `[` / `]` keys), by at least one step of its slider and within
        the slider's range. Returns the radius in metres."""
        control = next((c for c in all_controls(self.tools) if c.setting == "radius"), RADIUS)
        shown = self.settings.radius * control.scale
        target = shown * float(factor)
        snapped = round(round(target / control.step) * control.step, 6)
        if factor > 1.0:
            snapped = max(snapped, shown + control.step)
        elif factor < 1.0:
            snapped = min(snapped, shown - control.step)
        snapped = round(min(max(snapped, control.min), control.max), 6)
        self.settings.radius = snapped / control.scale
        self.refresh_cursor()
        return self.settings.radius

    def choose_category(self, category: str) -> None:
        """The user typed a category: the active instance takes it, and so do new instances from now on."""
        category = category.strip()
        if not category:
            return
        self.settings.category = category
        self.update_active(category=category)

    def new_instance(self, *, category: str = "object", name: str | None = None, client: str = "") -> int:
        """Create an instance and make it active; returns its id."""
        d = self.store.do(lambda ls: ls.create_instance(category=category, name=name), client=client)
        assert d is not None
        iid = next(iter(d.table_after))
        self.settings.active_id = int(iid)
        self.on_change()
        return int(iid)

    def update_active(self, **changes: Any) -> None:
        """Change the active instance (nothing when none is active)."""
        iid = self.settings.active_id
        if iid <= 0:
            return
        self.store.do(lambda ls: ls.update_instance(iid, **changes))

    def toggle_active(self, what: Literal["visible", "locked"]) -> None:
        """Hide / show or lock / unlock the active instance."""
        info = self.store.labelset.info(self.settings.active_id)
        self.update_active(**{what: not getattr(info, what)})

    def update_instance(self, instance_id: int, **changes: Any) -> None:
        """Rename / recategorise / recolour / hide / lock an instance (undoable)."""
        self.store.do(lambda ls: ls.update_instance(instance_id, **changes))

    def delete_instance(self, instance_id: int) -> None:
        """Delete an instance (its vertices become unlabelled; undoable)."""
        self.store.do(lambda ls: ls.delete_instance(instance_id))

    def merge(self, sources: list[int], into: int) -> None:
        """Merge instances into one, which becomes active (undoable)."""
        self.store.do(lambda ls: ls.merge(sources, into))
        self.settings.active_id = int(into)
        self.on_change()

    def undo(self, *, client: str = "") -> list[Delta]:
        """Undo the last edit (a whole stroke or group); returns the deltas undone."""
        return self.store.undo(client=client)

    def redo(self, *, client: str = "") -> list[Delta]:
        """Redo the last undone edit; returns the deltas redone."""
        return self.store.redo(client=client)

    def require_active(self) -> int:
        """The active instance id.

        Raises:
            ValueError: none is active.
        """
        iid = self.settings.active_id
        if iid <= 0 or iid not in self.store.labelset.instances:
            raise ValueError("no active instance: create one first (N)")
        return iid

    # ================================================================== painting
    def paint(self, idx: np.ndarray, *, erase: bool = False, group: str = "", client: str = "") -> Delta | None:
        """Paint vertices `idx` with the active instance (or erase them); one journalled edit.

        Inside a gesture the edit's label names the tool ("paint 1,234 → mug 1 (Region grow)"), as the history
        panel and the journal show it; a paint that relabels vertices of other instances says how many ("paint
        1,234 → mug 1, 56 taken from other instances (Brush)": *Only unlabelled vertices* keeps them).
        """
        source = getattr(self._tls, "source", "")

        def tagged(d: Delta) -> Delta:
            label = d.label
            taken = 0 if erase else int(np.count_nonzero(d.before > 0))
            if taken:
                label += f", {taken:,} taken from other instances"
            if source:
                label += f" ({source})"
            return d if label == d.label else dataclasses.replace(d, label=label)

        if erase:
            return self.store.do(lambda ls: tagged(ls.erase(idx)), client=client, group=group)
        iid = self.require_active()
        return self.store.do(
            lambda ls: tagged(ls.paint(idx, iid, overwrite=not self.settings.only_unlabelled)), client=client,
            group=group,
        )

    @contextlib.contextmanager
    def edit_source(self, source: str) -> Iterator[None]:
        """Edits made in this thread inside the block are labelled with `source` (a tool or gesture name)."""
        prev = getattr(self._tls, "source", "")
        self._tls.source = source
        try:
            yield
        finally:
            self._tls.source = prev

    def _brush_normal(self, vertex: int) -> tuple[np.ndarray | None, float | None]:
        lim = self.settings.brush_max_angle_deg
        if lim >= 180:
            return None, None
        return self.geom.normals[vertex], lim

    def _brush_at(self, position: np.ndarray, vertex: int, start: np.ndarray | None = None) -> np.ndarray:
        """Vertices under a dab at `position` (or along the segment from `start`), with the normal limit."""
        nrm, lim = self._brush_normal(vertex)
        if start is None:
            return sel.brush(self.geom, position, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
        return sel.brush_segment(self.geom, start, position, self.settings.radius, normal=nrm,
                                 max_normal_angle_deg=lim)

    def paint_stroke(self, points: np.ndarray, *, erase: bool = False, client: str = "") -> int:
        """Paint a whole stroke through surface points (what a drag does): returns vertices changed.

        Args:
            points: (S, 3) brush positions on the surface, world frame.
            erase: erase instead of painting the active instance.
        """
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        group = uuid.uuid4().hex[:12]
        changed = 0
        prev = None
        for p in pts:
            v = int(self.geom.tree.query(p)[1])
            self.move_cursor(p, v)
            d = self.paint(self._brush_at(p, v, prev), erase=erase, group=group, client=client)
            changed += 0 if d is None else d.num_vertices
            prev = p
        return changed

    def dab(self, vertex: int, position: np.ndarray, *, erase: bool, client: str = "") -> Delta | None:
        """One brush (or erase) dab of the current radius at a surface point.

        Args:
            vertex: the scan vertex at the point (its normal limits the brush when a normal limit is set).
            position: (3,) float, the point on the surface, world frame.
            erase: erase instead of painting the active instance.
        """
        self.move_cursor(position, int(vertex))
        return self.paint(self._brush_at(position, int(vertex)), erase=erase, client=client)

    def grow(self, seed: int, *, client: str = "") -> Delta | None:
        """Region grow from a vertex with the current settings and paint the result."""
        ls = self.store.labelset
        allowed = ~np.isin(ls.labels, ls.protected_ids())
        if self.settings.only_unlabelled:
            allowed &= ls.labels == 0
        if self.settings.grow_min_height > 0:
            allowed &= self.scene.points[:, 2] >= self.settings.grow_min_height
        idx = sel.region_grow(self.geom, seed, max_angle_deg=self.settings.grow_angle_deg,
                              max_distance=self.settings.grow_distance, allowed=allowed)
        return self.paint(idx, client=client)

    def fill(self, seed: int, *, client: str = "") -> Delta | None:
        """Bucket fill: the connected region sharing the seed's label becomes the active instance."""
        idx = sel.fill_same_label(self.geom, seed, self.store.labels)
        if self.settings.grow_min_height > 0:
            idx = idx[self.scene.points[idx, 2] >= self.settings.grow_min_height]
        return self.paint(idx, client=client)

    def pick_instance(self, vertex: int) -> int:
        """Make the instance under a vertex active; returns its id (0 = unlabelled, nothing changes)."""
        iid = int(self.store.labels[vertex])
        if iid > 0:
            self.set_active(iid)
        return iid

    def apply_tool(self, hit: Hit) -> None:
        """The active tool at a surface point (`Tool.apply_at`; nothing for a tool without one)."""
        tool = self.tool
        if tool.apply_at is not None:
            with self.edit_source(tool.label):
                tool.apply_at(self, hit)

    def click(self, origin: np.ndarray, direction: np.ndarray, *, client: str = "") -> int | None:
        """Apply the active tool at the surface point hit by a ray; returns the hit vertex (None = miss)."""
        hit = sel.pick(self.geom, origin, direction)
        if hit is None:
            return None
        v, pos = hit
        self.apply_tool(Hit(int(v), np.asarray(pos), client))
        return v

    def stroke_start(self, key: int, position: np.ndarray, *, client: str = "") -> None:
        """A Ctrl/Cmd+drag starts at a surface point: a stroke tool paints its first dab, other tools act once.

        Args:
            key: the dragging client's id (strokes of several clients may run at once).
            position: (3,) float, the grabbed surface point, world frame.
        """
        tool = self.tool
        start = np.asarray(position, np.float32)
        v = int(self.geom.tree.query(start)[1])
        if not tool.stroke:
            self.apply_tool(Hit(v, start, client))
            return
        p = self.scene.points[v] if self.geom.is_mesh is False else start
        stroke = Stroke(group=uuid.uuid4().hex[:12], last=np.asarray(p, np.float32), normal=self.geom.normals[v],
                        erase=tool.erase, source=tool.label)
        self.move_cursor(stroke.last, v)
        self.strokes[key] = stroke
        with self.edit_source(stroke.source):
            self.paint(self._brush_at(stroke.last, v), erase=stroke.erase, group=stroke.group, client=client)

    def stroke_to(self, key: int, camera_position: np.ndarray, target: np.ndarray, *, end: bool = False,
                  client: str = "") -> None:
        """Continue a client's stroke to the surface point seen from the camera through `target` (world).

        Args:
            key: the dragging client's id.
            camera_position: (3,) float, the camera, world frame.
            target: (3,) float, a point on the ray (viser's drag `end_position`), world frame.
            end: the drag ends here.
        """
        stroke = self.strokes.get(key)
        if stroke is None:
            return
        if end:
            self.strokes.pop(key, None)
        cam = np.asarray(camera_position, np.float64)
        hit = sel.pick(self.geom, cam, np.asarray(target, np.float64) - cam)
        if hit is None:
            return
        v, pos = hit
        self.move_cursor(pos, v)
        idx = self._brush_at(pos, v, stroke.last)
        stroke.last = np.asarray(pos, np.float32)
        with self.edit_source(stroke.source):
            self.paint(idx, erase=stroke.erase, group=stroke.group, client=client)

    # ---- brush cursor
    def move_cursor(self, position: np.ndarray, vertex: int) -> BrushCursor:
        """Put the brush cursor (a ring of the brush radius) at a surface point.

        Args:
            position: (3,) float, the point on the surface, world frame.
            vertex: the scan vertex there (its normal orients the ring).
        """
        with self._cursor_lock:
            cur = self.cursor = BrushCursor(np.asarray(position, np.float64).reshape(3).copy(),
                                            np.asarray(self.geom.normals[int(vertex)], np.float64).reshape(3).copy(),
                                            self.settings.radius, "radius" in shown_settings(self.tool))
        self.on_cursor()
        return cur

    def refresh_cursor(self) -> BrushCursor | None:
        """The cursor with the current radius and tool (after a radius or tool change); None before the first."""
        with self._cursor_lock:
            if self.cursor is None:
                return None
            self.cursor = dataclasses.replace(self.cursor, radius=self.settings.radius,
                                              visible="radius" in shown_settings(self.tool))
        self.on_cursor()
        return self.cursor

    # ================================================================== box and lasso
    def box(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float,
            screen_min: tuple[float, float], screen_max: tuple[float, float], client: str = "") -> Delta | None:
        """Box select with a camera, painted with the active instance (erased with the erase tool)."""
        idx = sel.box_select(self.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect,
                             screen_min=screen_min, screen_max=screen_max,
                             facing="front" if self.settings.box_facing == "front" else "all")
        with self.edit_source("box select"):
            return self.paint(idx, erase=self.tool.erase, client=client)

    def lasso(self, *, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float, polygon: np.ndarray,
              client: str = "") -> Delta | None:
        """Lasso select with a camera: vertices inside a screen outline, painted with the active instance (erased
        with the erase tool); `Box select: front/all` decides whether hidden sides are taken too."""
        idx = sel.lasso_select(self.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect, polygon=polygon,
                               facing="front" if self.settings.box_facing == "front" else "all")
        with self.edit_source("lasso"):
            return self.paint(idx, erase=self.tool.erase, client=client)

    def add_lasso_point(self, screen_pos: Sequence[float] | Sequence[Sequence[float]], *,
                        ray_origin: Sequence[float] | np.ndarray, ray_direction: Sequence[float] | np.ndarray,
                        camera: LassoCamera) -> int:
        """Lasso tool: add a clicked screen point to the outline (the first point's camera is used); returns the
        number of outline points (see `annotator.lasso.LassoOutline.add`).

        Raises:
            ValueError: the outline is full, or `screen_pos` is not one finite (u, v).
        """
        n = self.lasso_outline.add(screen_pos, ray_origin=ray_origin, ray_direction=ray_direction, camera=camera)
        self.on_lasso()
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
        self.on_lasso()

    # ================================================================== files
    def safe_path(self, name: str, *, what: str) -> Path:
        """A path to write: it must resolve inside the output folder chosen at start (relative = below it)."""
        p = resolve_inside(name, [self.out_dir], what=what)
        if p == self.scan_path:
            raise LabelIOError(f"refusing to write {what} over the source scan {p}")
        return p

    def export(self, fmt: Literal["ply", "npz", "scannet"], *, directory: str | None = None) -> list[Path]:
        """Write the labels to `<out>/<stem>.labels.ply|.labels.npz` or ScanNet JSON; returns the paths.

        Args:
            fmt: "ply", "npz" or "scannet".
            directory: a folder inside the output folder (relative paths are taken below it); default: the
                output folder. Anything resolving elsewhere (`..`, the scan's folder, symlinks out) is refused.
        """
        d = self.safe_path(directory, what="export directory") if directory else self.out_dir
        labels, table = self.store.snapshot()
        if fmt == "ply":
            out = [save_labels_ply(self.scene, labels, table, self.safe_path(str(d / f"{self.stem}.labels.ply"),
                                                                              what="export file"))]
        elif fmt == "npz":
            out = [save_labels_npz(labels, table, self.safe_path(str(d / f"{self.stem}.labels.npz"), what="export file"),
                                   scan_name=self.stem)]
        elif fmt == "scannet":
            out = list(save_scannet(labels, table, d, self.stem))
        else:
            raise ValueError(f"unknown export format {fmt!r}; use ply, npz or scannet")
        self.notify("Exported", ", ".join(p.name for p in out))
        log.info("exported %s", [str(p) for p in out])
        return out

    def import_labels(self, path: str) -> Delta | None:
        """Replace all labels by a file's (undoable). Only files inside the scan/output folders are read."""
        p = resolve_inside(path, self.roots, what="label file")
        data = load_labels(p, self.n)
        return self.store.do(lambda ls: ls.replace_all(data.labels, data.instances, label=f"import {p.name}"))

    # ================================================================== EFEM assist: pre-labels
    def import_efem(self, path: str) -> list[int]:
        """Import an EFEM result as unreviewed pre-label instances on unlabelled vertices; returns their ids."""
        p = resolve_inside(path, self.roots, what="EFEM result")
        data = load_labels(p, self.n)
        if not p.name.endswith(RESULT_SUFFIX):
            raise LabelIOError(f"{p.name} is not an EFEM result (*{RESULT_SUFFIX})")
        return self.add_prelabels(data, source=p.name)

    def add_prelabels(self, data: LabelData, *, source: str) -> list[int]:
        """Add proposals (labels + rows) as new unreviewed instances, painted only where nothing is labelled."""
        new_ids: list[int] = []
        group = uuid.uuid4().hex[:12]
        conf = data.confidence or {}
        order = sorted((r for r in data.instances if (data.labels == r.id).any()),
                       key=lambda r: -conf.get(r.id, 0.0))
        for row in order:
            note = prelabel_note(source, conf.get(row.id))
            d = self.store.do(lambda ls, row=row, note=note: ls.create_instance(category=row.category,
                                                                                name=f"{row.category} (EFEM)"),
                              group=group)
            assert d is not None
            iid = int(next(iter(d.table_after)))
            self.store.do(lambda ls, iid=iid, note=note: ls.update_instance(iid, note=note), group=group)
            idx = np.flatnonzero(data.labels == row.id)
            self.store.do(lambda ls, iid=iid, idx=idx: ls.paint(idx, iid, overwrite=False), group=group)
            new_ids.append(iid)
        self.on_change()
        return new_ids

    def review_prelabel(self, instance_id: int, action: Literal["accept", "reject", "merge"], *,
                        group: str = "") -> None:
        """Accept (keep as a real instance), reject (delete) or merge (into the active instance) a pre-label.

        Args:
            instance_id: the pre-label.
            action: what to do with it.
            group: undo group (reviews of one group undo together).
        """
        info = self.store.labelset.info(instance_id)
        if action == "accept":
            self.store.do(lambda ls: ls.update_instance(instance_id, note=info.note.replace("unreviewed", "accepted"),
                                                        name=info.name.replace(" (EFEM)", "")), group=group)
        elif action == "reject":
            self.store.do(lambda ls: ls.delete_instance(instance_id), group=group)
        elif action == "merge":
            target = self.require_active()
            if target == instance_id:
                raise ValueError("choose another active instance to merge this pre-label into")
            self.store.do(lambda ls: ls.merge([instance_id], target), group=group)
        else:
            raise ValueError(f"unknown review action {action!r}")
        self.on_change()

    def prelabel_cut(self, default: float = 0.5) -> float:
        """The pre-label cut that suits the unreviewed pre-labels: `default`, lowered to the best one's confidence
        when every one is below it (issue 37: a real frame's pre-labels all under 0.5 made "Accept all ≥ cut"
        accept nothing)."""
        table = self.store.labelset.instances
        conf = [float(table[k].confidence) for k in unreviewed_prelabels(table)]
        if not conf:
            return float(default)
        return float(min(default, np.floor(max(conf) * 100.0) / 100.0))

    def review_prelabels(self, cut: float, action: Literal["accept", "reject"]) -> list[int]:
        """Bulk review: accept every unreviewed pre-label with confidence ≥ `cut`, or reject every one below it;
        one undo step. Returns the instance ids reviewed."""
        if action not in ("accept", "reject"):
            raise ValueError(f"unknown bulk review action {action!r}")
        table = self.store.labelset.instances
        ids = [k for k in unreviewed_prelabels(table)
               if (table[k].confidence >= cut) == (action == "accept")]
        group = uuid.uuid4().hex[:12]
        for iid in ids:
            self.review_prelabel(iid, action, group=group)
        self.on_change()
        self.notify("Pre-labels", f"{'accepted' if action == 'accept' else 'rejected'} {len(ids)} pre-label(s) "
                    f"with confidence {'≥' if action == 'accept' else '<'} {cut:.2f} (one undo step)")
        return ids

    # ================================================================== EFEM assist: click to segment
    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment: run EFEM seeded near a vertex with the chosen prior (`settings.prior`) and preview the
        mask.

        The solver runs in a background thread (edits stay responsive); the mask is highlighted when it is ready
        and becomes labels only through `accept_segment`.

        Args:
            vertex: the clicked vertex.
            wait: run in the calling thread and return the mask (tests, scripts).

        Returns:
            With `wait`, (K,) int32 vertex indices of the proposed mask (also kept in `pending_segment`); else None.
        """
        prior_name = self.settings.prior
        with self._segment_lock:
            if self._segment_cancel is not None:
                raise ValueError("still segmenting the last click: wait for its preview, or Esc cancels it")
            cancel = self._segment_cancel = threading.Event()
        self.on_segment(0.0)
        if wait:
            return self._segment_job(int(vertex), prior_name, cancel)
        self.notify("Segmenting", f"EFEM with prior {prior_name!r} around vertex {vertex}... (Esc cancels)")
        threading.Thread(target=lambda: self.report(lambda: self._segment_job(int(vertex), prior_name, cancel)),
                         name="annotator-segment", daemon=True).start()
        return None

    def _segment_job(self, vertex: int, prior_name: str, cancel: threading.Event) -> np.ndarray | None:
        from annotator import assist
        from efem_viz.em.solver import EMCancelled

        def on_step(info: Any) -> None:
            self.on_segment(round(100.0 * (info.step + 1) / max(info.num_steps, 1), 1))

        t0 = time.perf_counter()
        try:
            mask_idx = assist.segment_at_point(self.scene, vertex, prior_name=prior_name, on_step=on_step,
                                               cancel=cancel)
        except EMCancelled:
            self.notify("Segmenting cancelled", f"the segmentation around vertex {vertex} was stopped")
            return None
        finally:
            with self._segment_lock:
                self._segment_cancel = None
            self.on_segment(None)
        self.set_preview(mask_idx)
        if len(mask_idx) == 0:
            self.notify("No object found", f"EFEM with prior {prior_name!r} accepted no proposal around vertex "
                        f"{vertex} ({time.perf_counter() - t0:.1f} s): click nearer the object's centre, or "
                        "label it with the brush / region grow")
        else:
            self.notify("Segment preview", f"{len(mask_idx):,} vertices in {time.perf_counter() - t0:.1f} s: "
                        "Enter (Accept segment) paints it as a new instance, Esc discards it")
        return mask_idx

    @property
    def segmenting(self) -> bool:
        """Whether a click-to-segment run is in progress."""
        with self._segment_lock:
            return self._segment_cancel is not None

    def set_preview(self, idx: np.ndarray | None) -> None:
        """Highlight a proposed mask (None clears it) without touching the labels."""
        old = self.preview
        if idx is None or len(idx) == 0:
            self.preview, self.pending_segment = None, None
        else:
            preview = np.zeros(self.n, bool)
            preview[idx] = True
            self.preview = preview
            self.pending_segment = np.asarray(idx, np.int32)
        touched = np.zeros(0, np.int64)
        for m in (old, self.preview):
            if m is not None:
                touched = np.union1d(touched, np.flatnonzero(m))
        self.on_preview(touched)
        self.on_segment(None)

    def accept_segment(self) -> Delta | None:
        """Paint the previewed segment as a new instance (category from the prior name)."""
        if self.pending_segment is None:
            raise ValueError("no segment preview to accept: Ctrl+click with the segment tool first")
        idx = self.pending_segment
        self.set_preview(None)
        self.new_instance(category=self.settings.prior or "object")
        return self.paint(idx)

    def discard_segment(self) -> None:
        """Drop the segment preview; while a segmentation runs, cancel it (Esc)."""
        with self._segment_lock:
            running = self._segment_cancel
        if running is not None:
            running.set()
            return
        self.set_preview(None)


def _writable_dir(out_dir: str | Path | None) -> Path:
    """The output folder, created when missing.

    Raises:
        LabelIOError: it is a file, cannot be created, or is read-only.
    """
    out = Path(out_dir).resolve() if out_dir is not None else Path.cwd().resolve()
    if out.exists() and not out.is_dir():
        raise LabelIOError(f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabelIOError(f"cannot create the output folder {out} ({exc}); choose one with --out") from exc
    # Mode bits too: a read-only data folder (r-x) is still writable for root, and must not be written.
    if not os.access(out, os.W_OK) or not (out.stat().st_mode & 0o222):
        raise LabelIOError(f"the output folder {out} is read-only; choose another with --out")
    return out


def _log_errors(fn: Callable[[], Any]) -> Any:
    """The default `report`: run `fn`, log what fails."""
    try:
        return fn()
    except Exception:  # noqa: BLE001 - a background job of a headless session: log it
        log.exception("annotator job failed")
        return None
