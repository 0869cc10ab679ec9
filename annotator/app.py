"""The annotator's viser layer: draws the scan in spatial chunks, turns GUI/scene events into label edits.

Thin by design: callbacks read GUI values into `ToolSettings`, call the pure tools (`annotator.selection`) and
the label store (`annotator.journal.LabelStore`, one lock, journal first), and the store's listener redraws the
touched chunks (`draw_chunks`). Every action the GUI offers is also a public method (`paint_stroke`, `click`,
`box`, `new_instance`, `undo`, ...) so tests and scripts drive the same code paths without a browser.

Interaction (see docs/ANNOTATOR.md). The tools are the entries of a table (`annotator.tools.DEFAULT_TOOLS`, or
the `tools=` given): the Tool dropdown, the hotkeys, the help, the controls shown and what each gesture does are
read from it; this module has no per-tool branches.
* Ctrl/Cmd + left-drag on the scan: a stroke with a stroke tool (brush, erase); one stroke = one undo step. Other
  tools act once where the drag starts.
* Ctrl/Cmd + click: the active tool at the clicked point (`Tool.apply_at`, or `Tool.on_click` for the lasso).
* Shift + drag a rectangle: box select, painted with the active instance (erased with an erasing tool).
* Hotkeys (also in the Ctrl/Cmd+K palette): each tool's, and the app's own (`annotator.tools.APP_KEYS`: N new
  instance, Tab / Shift+Tab next / previous instance, H hide/show, L lock/unlock, [ / ] brush size, Ctrl+Z undo,
  Ctrl+Y redo, R reset view, ? the cheat sheet). They are viser palette commands, which the browser matches on
  the key typed. None is one of W/A/S/D/Q/E: viser's client flies the camera with those.
* Camera: every client starts on the fitted view; R puts it back; a camera that leaves the scan (viser's W/A/S/D
  keys after a pause) is put back by `efem_viz.serve.camera.CameraGuard`. A click that misses the scan says so.
* Errors: a refused action (bad input) and a failing one (a bug) both reach the user who acted as a notification
  (`_run_reporting`), not only the log.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Literal, Sequence

import numpy as np

from annotator import selection as sel
from annotator.io import (
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
from annotator.labels import Delta, InstanceInfo, LabelSet, prelabel_note, unreviewed_prelabels
from annotator.lasso import LassoCamera, LassoOutline
from annotator.render import Chunks, build_chunks, color_lut, compose_colors, ring_segments, splat_proxy
from annotator.tools import (
    APP_KEYS,
    BRUSH_STEP,
    DEFAULT_TOOLS,
    RADIUS,
    TOOLS,
    Control,
    Hit,
    Tool,
    all_controls,
    cheat_sheet_markdown,
    check_tools,
    help_markdown,
    shown_settings,
)
from efem_viz.geometry.transforms import xyz_tuple
from efem_viz.serve.camera import CameraGuard, View, fly_to_view
from efem_viz.serve.guard import start_server
from efem_viz.serve.table import cell as _md
from efem_viz.serve.table import option_for as _option_for
from efem_viz.serve.table import option_id as _id_of
from efem_viz.serve.table import step_row
from efem_viz.serve.table import swatch as _swatch
from efem_viz.serve.inputs import (
    ClientValueError,
    read_bool,
    read_choice,
    read_number,
    read_rgb,
    read_text,
)
from efem_viz.data.io import RESULT_SUFFIX
from efem_viz.prior.config import DEFAULT_PRIOR

if TYPE_CHECKING:
    from viser import ClientHandle, GuiButtonHandle, GuiInputHandle, SceneClickEvent
    from viser._gui_handles import GuiModalHandle  # not re-exported by viser 1.1
    from viser._messages import LiteralColor  # the colour names `add_notification` accepts

log = logging.getLogger(__name__)

__all__ = ["TOOLS", "AnnotatorApp", "ToolSettings"]

MAX_NAME = 200
"""Longest instance name / category accepted from a client."""
NO_OPTIONS: tuple[str, ...] = ("(none)",)
"""Dropdown options while a list is empty (typed `str` so that the handles accept real options later)."""


@dataclass
class ToolSettings:
    """What the tool controls say; read from the GUI, never read by compute code directly."""

    tool: str = "brush"
    """Name of the active tool (an entry of the app's tool table, `annotator.tools`)."""
    category: str = "object"
    """Category of new instances (N, *New instance*): the one the user chose last (typed into *Category*), or of
    the scan's labels when it has some."""
    radius: float = 0.01
    """Brush radius, metres."""
    brush_max_angle_deg: float = 180.0
    """Brush paints only vertices whose normal is within this angle of the hit normal (180 = no limit)."""
    grow_angle_deg: float = 20.0
    """Region grow: maximum normal change across one edge, degrees."""
    grow_distance: float = 0.15
    """Region grow: maximum distance from the seed, metres."""
    grow_min_height: float = 0.0
    """Region grow and fill never enter points lower than this above z = 0 (the table plane of imported
    tabletop scans), metres; 0 = off."""
    only_unlabelled: bool = False
    """Paint/grow/box change only unlabelled vertices."""
    labels_only: bool = False
    """The labels-only view: unlabelled vertices drawn in a faint grey (`annotator.render.compose_colors`)."""
    box_facing: str = "front"
    """Box select: "front" (vertices facing the camera) or "all"."""
    active_id: int = 0
    """Active instance id (0 = none yet)."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Settings of added tools' controls that have no field here (`annotator.tools.Control.setting` → value)."""


@dataclass
class Stats:
    """Counters for the benchmark and the status line."""

    bytes_sent: int = 0
    """Colour payload bytes sent to clients since start (3 bytes per point of each redrawn chunk)."""
    chunks_sent: int = 0
    last_edit_bytes: int = 0
    last_edit_ms: float = 0.0
    edits: int = 0
    history: list[str] = field(default_factory=list)


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


CURSOR_COLOR = (255, 150, 0)
"""Colour of the brush cursor's ring."""
CURSOR_THICKNESS_PX = 2.5
"""Line width of the brush cursor's ring, screen pixels."""


@dataclass
class _Stroke:
    group: str
    last: np.ndarray
    normal: np.ndarray
    erase: bool
    source: str = ""
    """Label of the tool that paints the stroke (history)."""


class AnnotatorApp:
    """The annotator server for one scan.

    Args:
        scan_path: the scan (PLY/OBJ/OFF/GLB/NPZ scene, or an RGB-D frame .npz). Never written.
        labels_path: labels to start a *new* session from (ignored with a warning when the output directory
            already holds a journal for this scan: the session resumes instead).
        out_dir: where the journal, checkpoint and exports go (default: the current working directory). The
            journal and checkpoint live in `<out>/<stem>.annotate/`; read-only folders are refused.
        host: bind address (127.0.0.1 by default: local only). Every bind needs the access token (`url`).
        port: TCP port (0 = any free port).
        max_points: refuse scans with more vertices.
        autosave_delay: seconds between an edit and the checkpoint rewrite (the journal is always immediate).
        chunk_size: points per drawn chunk.
        efem_result: an `<scene>.efem.npz` to import as pre-labels at start (optional).
        accept_scan_mismatch: resume a journal written for other geometry with the same vertex count.
        token: the server's access token (None = a fresh random one; see `efem_viz.serve.guard`).
        tools: the tool table (`annotator.tools.Tool` entries, toolbar order; default `DEFAULT_TOOLS`). The first
            one is active at start.

    Raises:
        LabelIOError: the scan or labels cannot be read; JournalError: the journal belongs to another scan.
    """

    def __init__(
        self,
        scan_path: str | Path,
        *,
        labels_path: str | Path | None = None,
        out_dir: str | Path | None = None,
        host: str = "127.0.0.1",
        port: int = 8081,
        max_points: int = 2_000_000,
        autosave_delay: float = 0.5,
        chunk_size: int = 16384,
        accept_scan_mismatch: bool = False,
        token: str | None = None,
        tools: Sequence[Tool] = DEFAULT_TOOLS,
    ) -> None:
        t0 = time.perf_counter()
        self.tools: tuple[Tool, ...] = tuple(tools)
        """The tool table the toolbar, hotkeys, help and gestures read."""
        self._tool_of = check_tools(self.tools)
        self.scan_path = Path(scan_path).resolve()
        self.scene = load_scan(self.scan_path, max_points=max_points)
        self.n = self.scene.num_points
        self.out_dir = Path(out_dir).resolve() if out_dir is not None else Path.cwd().resolve()
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise LabelIOError(f"--out {self.out_dir} exists and is not a directory")
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise LabelIOError(f"cannot create the output folder {self.out_dir} ({exc}); choose one with --out") from exc
        # Mode bits too: a read-only data folder (r-x) is still writable for root, and must not be written.
        if not os.access(self.out_dir, os.W_OK) or not (self.out_dir.stat().st_mode & 0o222):
            raise LabelIOError(f"the output folder {self.out_dir} is read-only; choose another with --out")
        self.stem = self.scan_path.stem
        self.roots = [self.scan_path.parent, self.out_dir]
        self.work_dir = self.out_dir / f"{self.stem}.annotate"
        initial: LabelData | None = None
        if labels_path is not None:
            initial = load_labels(labels_path, self.n)
        elif self.scene.instance is not None and self.scene.has_gt:
            cats = dict(self.scene.categories)
            initial = LabelData(
                self.scene.instance.copy(),
                [
                    InstanceInfo(int(i), f"{cats.get(int(i), 'object')} {int(i)}", category=cats.get(int(i), "object"),
                                 color=_color(int(i)))
                    for i in self.scene.instance_ids()
                ],
            )
        journal_path = self.work_dir / f"{self.stem}.journal"
        if labels_path is not None and journal_path.exists():
            log.warning(
                "%s already has a journal: resuming it and ignoring --labels %s (use Import in the GUI to load "
                "them as an undoable edit)", self.work_dir, labels_path,
            )
        self.store = LabelStore(
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
        # We hold the scan's journal lock now: temp files of an interrupted write of ours are stale.
        for folder in {self.out_dir, self.work_dir}:
            remove_stale_temp_files(folder, self.stem)
        self.geom = sel.ScanGeometry(self.scene.points, self.scene.normals, faces=self.scene.faces)
        self.chunks: Chunks = build_chunks(self.scene.points, max_chunk=chunk_size)
        self.settings = ToolSettings(tool=self.tools[0].name,
                                     radius=max(0.005, 0.02 * float(np.linalg.norm(np.ptp(self.scene.points, axis=0)))))
        self.stats = Stats()
        self.preview: np.ndarray | None = None
        """(N,) bool mask drawn highlighted (click-to-segment preview), or None."""
        self.pending_segment: np.ndarray | None = None
        self._segment_lock = threading.Lock()
        self._segment_cancel: threading.Event | None = None
        """Set to cancel the click-to-segment run in progress (None: none runs)."""
        self._prelabel_cursor: int | None = None
        """The pre-label Next / Previous went to last (None: not used yet)."""
        self._strokes: dict[int, _Stroke] = {}
        self.cursor: BrushCursor | None = None
        """The brush cursor (None until the brush first touches the scan)."""
        self._cursor_handle: Any = None
        self._cursor_lock = threading.Lock()
        self.lasso_outline = LassoOutline()
        """The lasso tool's outline (screen points of one view)."""
        self._lasso_handle: Any = None
        self.cheat_sheets: dict[int, GuiModalHandle] = {}
        """The open `?` cheat-sheet overlays, by client id (under `_sheet_lock`: keys and buttons run on viser's
        worker threads)."""
        self._sheet_lock = threading.Lock()
        self._edits: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._tls = threading.local()
        self._draw_lock = threading.Lock()
        self._closed = threading.Event()
        ls = self.store.labelset
        if ls.instances:
            self.settings.active_id = max(ls.instances)
            self.settings.category = ls.instances[self.settings.active_id].category or "object"

        try:
            self.server, self.access = start_server(host=host, port=port, token=token)
        except BaseException:
            self.store.close()
            raise
        try:
            self.server.gui.configure_theme(control_width="large")
            self._draw_scan()
            self._build_gui()
        except BaseException:
            self.server.stop()
            self.store.close()
            raise
        self.store.listeners.append(self._on_labels_changed)
        self.store.problem_listeners.append(self._on_store_problem)
        self.server.on_client_connect(self._greet)
        self.server.on_client_disconnect(self._forget_client)
        self._worker = threading.Thread(target=self._edit_loop, name="annotator-edits", daemon=True)
        self._worker.start()
        self._warmup = threading.Thread(target=self.geom.warm_up, name="annotator-warmup", daemon=True)
        self._warmup.start()
        self.open_s = time.perf_counter() - t0
        log.info("opened %s: %d vertices, %d chunks, %.2f s", self.scan_path.name, self.n, self.chunks.count, self.open_s)

    # ================================================================== drawing
    @property
    def url(self) -> str:
        """The URL to open, with the access token (the machine's address for a 0.0.0.0 bind; the real port)."""
        return self.access.url

    @property
    def local_url(self) -> str:
        """The URL from this machine (127.0.0.1 for loopback and 0.0.0.0 binds), with the token."""
        return self.access.local_url

    def _draw_scan(self) -> None:
        pts = self.scene.points
        centre = pts.mean(axis=0)
        extent = float(np.linalg.norm(np.ptp(pts, axis=0)))
        spacing = self.geom.spacing
        self.point_size = float(max(spacing * 1.6, extent * 5e-4))
        if self.scene.is_mesh:
            assert self.scene.faces is not None
            self.surface = self.server.scene.add_mesh_simple(
                "/scan/surface", pts, self.scene.faces, color=(205, 205, 205), side="double"
            )
        else:
            verts, faces = splat_proxy(pts, self.scene.normals, size=2.5 * spacing, max_splats=150_000)
            # An invisible proxy surface: it receives the drag gestures that point clouds do not.
            self.surface = self.server.scene.add_mesh_simple(
                "/scan/surface", verts, faces, color=(200, 200, 200), opacity=0.0, side="double"
            )
        self.surface.on_drag("left", modifier="cmd/ctrl")(self._on_drag)
        self.chunk_handles = []
        labels = self.store.labels
        lut, show = color_lut(self.store.labelset.instances, int(labels.max(initial=0)))
        for c in range(self.chunks.count):
            m = self.chunks.members(c)
            h = self.server.scene.add_point_cloud(
                f"/scan/labels/chunk_{c:04d}",
                points=pts[m],
                colors=compose_colors(self.scene.colors[m], labels[m], lut, show,
                                      dim_unlabelled=self.settings.labels_only),
                point_size=self.point_size,
                point_shape="circle",
            )
            self.chunk_handles.append(h)
        self.server.scene.on_click(modifier="cmd/ctrl")(self._on_scene_click)
        self.server.scene.on_rect_select(modifier="shift")(self._on_rect)
        self.home_view = View(look_at=xyz_tuple(centre),
                              position=xyz_tuple(centre + np.array([0.0, -1.0, 0.8]) * extent * 0.8))
        """The fitted view: where every client starts, and where R (reset view) puts the camera."""
        self.camera_guard = CameraGuard(self.server, self.home_view, pts.min(axis=0), pts.max(axis=0),
                                        hint="R (reset view) brings it back any time.")
        """Puts a camera that left the scan back on `home_view` (see `efem_viz.serve.camera`)."""

    def draw_chunks(self, chunk_ids: np.ndarray) -> int:
        """Recompute and send the colours of some chunks; returns the payload bytes sent."""
        with self._draw_lock:
            labels = self.store.labels
            lut, show = color_lut(self.store.labelset.instances, int(labels.max(initial=0)))
            sent = 0
            for c in np.asarray(chunk_ids, np.int64):
                m = self.chunks.members(int(c))
                hl = None if self.preview is None else self.preview[m]
                cols = compose_colors(self.scene.colors[m], labels[m], lut, show, highlight=hl,
                                      dim_unlabelled=self.settings.labels_only)
                self.chunk_handles[int(c)].colors = cols
                sent += cols.nbytes
            self.stats.bytes_sent += sent
            self.stats.chunks_sent += len(chunk_ids)
            return sent

    def _on_labels_changed(self, d: Delta, how: str) -> None:
        t0 = time.perf_counter()
        touched = self.chunks.touched(d.idx)
        if d.table_after:
            # Colour / visibility changes recolour every chunk holding those instances.
            ids = np.array([k for k in d.table_after], np.int32)
            visual = [
                k for k in ids
                if (d.table_before.get(int(k)) is None) != (d.table_after.get(int(k)) is None)
                or (d.table_before.get(int(k)) and d.table_after.get(int(k))
                    and (d.table_before[int(k)].color != d.table_after[int(k)].color  # type: ignore[union-attr]
                         or d.table_before[int(k)].visible != d.table_after[int(k)].visible  # type: ignore[union-attr]
                         or d.table_before[int(k)].unreviewed != d.table_after[int(k)].unreviewed))  # type: ignore[union-attr]
            ]
            if visual:
                mask = np.isin(self.store.labels, np.array(visual, np.int32))
                touched = np.union1d(touched, self.chunks.touched(np.flatnonzero(mask)))
        sent = self.draw_chunks(touched)
        self.stats.last_edit_bytes = sent
        self.stats.last_edit_ms = 1000 * (time.perf_counter() - t0)
        self.stats.edits += 1
        self.stats.history = ([f"{how}: {d.label}"] + self.stats.history)[:8]
        self._refresh_panel()

    # ================================================================== GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        s = self.settings
        with gui.add_folder("Tools"):
            self.gui_tool = gui.add_dropdown("Tool", tuple(t.name for t in self.tools), initial_value=s.tool,
                                             hint="Ctrl/Cmd+drag paints; Ctrl/Cmd+click applies the tool")
            self.gui_tool_help = gui.add_markdown("")
            """The active tool's hotkey and help line."""
            self.gui_controls: dict[str, GuiInputHandle[Any]] = {
                c.setting: self._add_control(c) for c in all_controls(self.tools)
            }
            """The tools' setting controls by setting name (`annotator.tools.Control`)."""
            self.gui_tool_buttons: dict[str, GuiButtonHandle] = {}
            """The tools' buttons by command key (`annotator.tools.ToolCommand`)."""
            for t in self.tools:
                for cmd in t.commands:
                    label = f"{cmd.label} ({cmd.hotkey})" if cmd.hotkey else cmd.label
                    self.gui_tool_buttons[cmd.key] = gui.add_button(label, disabled=cmd.disabled, hint=cmd.hint)
            self.gui_seg_progress = gui.add_progress_bar(0.0, visible=False)
            """Click-to-segment's progress (EM steps done), shown while it runs."""
        with gui.add_folder("Instances"):
            self.gui_active = gui.add_dropdown("Active", self._instance_options() or NO_OPTIONS)
            self.gui_name = gui.add_text("Name", "")
            self.gui_category = gui.add_text("Category", self.settings.category,
                                             hint="the active instance's category; new instances (N) take the "
                                                  "one chosen last")
            self.gui_color = gui.add_rgb("Colour", (255, 0, 0))
            self.gui_new = gui.add_button("New instance (N)")
            self.gui_labels_only = gui.add_checkbox("Labels only", False,
                                                    hint="dim unlabelled vertices, so what is labelled stands out")
            self.gui_visible = gui.add_checkbox("Visible", True)
            self.gui_locked = gui.add_checkbox("Locked", False)
            self.gui_merge_into = gui.add_dropdown("Merge active into", self._instance_options() or NO_OPTIONS)
            self.gui_merge = gui.add_button("Merge")
            self.gui_delete = gui.add_button("Delete active", color="red")
            self.gui_progress = gui.add_progress_bar(0.0)
            self.gui_table = gui.add_markdown("")
        with gui.add_folder("History"):
            self.gui_undo = gui.add_button("Undo (Ctrl+Z)")
            self.gui_redo = gui.add_button("Redo (Ctrl+Y)")
            self.gui_history = gui.add_markdown("")
        with gui.add_folder("Files", expand_by_default=False):
            self.gui_status = gui.add_markdown("")
            self.gui_export_ply = gui.add_button("Export PLY")
            self.gui_export_npz = gui.add_button("Export NPZ")
            self.gui_export_scannet = gui.add_button("Export ScanNet JSON")
            self.gui_import_path = gui.add_text("Import labels from", "", hint="path inside the scan or output folder")
            self.gui_import = gui.add_button("Import labels (undoable)")
        with gui.add_folder("EFEM assist", expand_by_default=False):
            default_efem = self.scan_path.with_name(self.stem + RESULT_SUFFIX)
            self.gui_efem_path = gui.add_text("EFEM result", default_efem.name if default_efem.exists() else "")
            self.gui_efem_import = gui.add_button("Import EFEM pre-labels")
            self.gui_prelabel = gui.add_dropdown("Pre-label", NO_OPTIONS,
                                                 hint="unreviewed pre-labels, most confident first (drawn pale)")
            self.gui_prelabel_prev = gui.add_button("◀ Previous pre-label", hint="select it and fly to it")
            self.gui_prelabel_next = gui.add_button("Next pre-label ▶", hint="select it and fly to it")
            self.gui_accept = gui.add_button("Accept")
            self.gui_reject = gui.add_button("Reject")
            self.gui_accept_merge = gui.add_button("Merge into active")
            self.gui_prelabel_cut = gui.add_slider("Pre-label cut", min=0.0, max=1.0, step=0.01, initial_value=0.5,
                                                   hint="confidence that the bulk buttons below split at")
            self.gui_accept_above = gui.add_button("Accept all ≥ cut")
            self.gui_reject_below = gui.add_button("Reject all < cut", color="red")
            from annotator.assist import available_priors

            priors = tuple(available_priors()) or (DEFAULT_PRIOR,)
            self.gui_prior = gui.add_dropdown("Prior for Segment tool", priors,
                                              initial_value=DEFAULT_PRIOR if DEFAULT_PRIOR in priors else priors[0])
            self.gui_seg_accept = gui.add_button("Accept segment preview", disabled=True)
            self.gui_seg_cancel = gui.add_button("Discard segment preview", disabled=True)

        # ---- callbacks: read values into settings, call the action methods. Client values pass the checks of
        # efem_viz.serve.inputs (clamped to the declared slider range, dropdown options only, bounded text).
        wb = self._gui_write_back

        controls = {c.setting: c for c in all_controls(self.tools)}

        def read_settings(event: Any = None) -> None:
            if getattr(self._tls, 'syncing', False):
                return
            try:
                s.tool = read_choice(self.gui_tool)
            except ClientValueError as exc:
                self._refuse(exc, event, self.gui_tool, s.tool)
            for name, handle in self.gui_controls.items():
                c = controls[name]
                try:
                    if c.kind == "slider":
                        value: Any = read_number(handle, write_back=wb) / c.scale
                    elif c.kind == "dropdown":
                        value = read_choice(handle)
                    else:
                        value = read_bool(handle)
                except ClientValueError as exc:  # keep this setting; show it again where the bad value was
                    old = self._setting(name)
                    self._refuse(exc, event, handle, round(old * c.scale, 6) if c.kind == "slider" else old)
                    continue
                self._set_setting(name, value)
            self._show_tool()

        self.gui_tool.on_update(read_settings)
        for h in self.gui_controls.values():
            h.on_update(read_settings)

        def guarded(fn: Callable[..., Any]) -> Callable[[Any], None]:
            def cb(event: Any) -> None:
                if getattr(self._tls, 'syncing', False):
                    return
                self._run_reporting(lambda: fn(), getattr(event, "client", None))

            return cb

        def text(h: Any) -> str:
            return read_text(h, max_len=MAX_NAME)

        self.gui_active.on_update(guarded(lambda: self.set_active(_id_of(read_choice(self.gui_active)))))
        self.gui_name.on_update(guarded(lambda: self._update_active(name=text(self.gui_name))))
        self.gui_category.on_update(guarded(lambda: self.choose_category(text(self.gui_category))))
        self.gui_color.on_update(guarded(lambda: self._update_active(color=read_rgb(self.gui_color, write_back=wb))))
        self.gui_visible.on_update(guarded(lambda: self._update_active(visible=read_bool(self.gui_visible))))
        self.gui_labels_only.on_update(guarded(lambda: self.set_labels_only(read_bool(self.gui_labels_only))))
        self.gui_locked.on_update(guarded(lambda: self._update_active(locked=read_bool(self.gui_locked))))
        self.gui_new.on_click(guarded(lambda: self.new_instance(category=self.settings.category)))
        self.gui_merge.on_click(
            guarded(lambda: self.merge([self.settings.active_id], _id_of(read_choice(self.gui_merge_into)))))
        self.gui_delete.on_click(guarded(lambda: self.delete_instance(self.settings.active_id)))
        self.gui_undo.on_click(guarded(lambda: self.undo()))
        self.gui_redo.on_click(guarded(lambda: self.redo()))
        self.gui_export_ply.on_click(guarded(lambda: self.export("ply")))
        self.gui_export_npz.on_click(guarded(lambda: self.export("npz")))
        self.gui_export_scannet.on_click(guarded(lambda: self.export("scannet")))
        self.gui_import.on_click(guarded(lambda: self.import_labels(read_text(self.gui_import_path))))
        self.gui_efem_import.on_click(guarded(lambda: self.import_efem(read_text(self.gui_efem_path))))
        self.gui_accept.on_click(
            guarded(lambda: self.review_prelabel(_id_of(read_choice(self.gui_prelabel)), "accept")))
        self.gui_reject.on_click(
            guarded(lambda: self.review_prelabel(_id_of(read_choice(self.gui_prelabel)), "reject")))
        self.gui_accept_merge.on_click(
            guarded(lambda: self.review_prelabel(_id_of(read_choice(self.gui_prelabel)), "merge")))
        self.gui_accept_above.on_click(guarded(lambda: self.review_prelabels(
            read_number(self.gui_prelabel_cut, write_back=wb), "accept")))
        self.gui_reject_below.on_click(guarded(lambda: self.review_prelabels(
            read_number(self.gui_prelabel_cut, write_back=wb), "reject")))
        self.gui_prelabel_next.on_click(
            lambda event: self._run_reporting(lambda: self.step_prelabel(+1, client=event.client), event.client))
        self.gui_prelabel_prev.on_click(
            lambda event: self._run_reporting(lambda: self.step_prelabel(-1, client=event.client), event.client))
        self.gui_seg_accept.on_click(guarded(lambda: self.accept_segment()))
        self.gui_seg_cancel.on_click(guarded(lambda: self.discard_segment()))
        command_keys: dict[str, list[str]] = {}
        """Command hotkeys → the labels of the commands (of different tools) that use them."""
        for t in self.tools:  # the tools' buttons and hotkeys
            gui.add_command(f"Tool: {t.label}", hotkey=t.hotkey).on_trigger(  # type: ignore[arg-type]
                guarded(lambda name=t.name: self.set_tool(name)))
            for cmd in t.commands:
                def run(cmd: Any = cmd) -> object:
                    return cmd.run(self)

                self.gui_tool_buttons[cmd.key].on_click(guarded(run))
                if cmd.hotkey:
                    command_keys.setdefault(cmd.hotkey, []).append(cmd.label)
        for key, labels in command_keys.items():  # a command hotkey acts for the active tool
            gui.add_command(" / ".join(labels), hotkey=key).on_trigger(  # type: ignore[arg-type]
                lambda event, key=key: self._run_reporting(lambda: self.run_tool_hotkey(key), event.client))

        # ---- the app's own hotkeys: the table annotator.tools.APP_KEYS, each action bound to a method here
        actions: dict[str, Callable[[Any], None]] = {
            "new_instance": guarded(
                lambda: self.new_instance(category=self.settings.category)),
            "next_instance": guarded(lambda: self.cycle_active(+1)),
            "previous_instance": guarded(lambda: self.cycle_active(-1)),
            "toggle_visible": guarded(lambda: self._toggle_active("visible")),
            "toggle_locked": guarded(lambda: self._toggle_active("locked")),
            "brush_smaller": guarded(lambda: self.resize_brush(1.0 / BRUSH_STEP)),
            "brush_larger": guarded(lambda: self.resize_brush(BRUSH_STEP)),
            "undo": guarded(lambda: self.undo()),
            "redo": guarded(lambda: self.redo()),
            "cheat_sheet": lambda event: self._run_reporting(lambda: self.toggle_cheat_sheet(event.client),
                                                             event.client),
            "reset_view": lambda event: self._run_reporting(lambda: self.reset_view(event.client), event.client),
        }
        for k in APP_KEYS:
            for key, modifier in k.bindings:
                gui.add_command(k.label, hotkey=key, modifier=modifier).on_trigger(  # type: ignore[arg-type]
                    actions[k.action])
        with gui.add_folder("Help", expand_by_default=False):
            self.gui_help = gui.add_markdown(help_markdown(self.tools))
        self._show_tool()
        self._refresh_panel()

    # ---- tool table → GUI
    @property
    def tool(self) -> Tool:
        """The active tool's entry."""
        return self._tool_of[self.settings.tool]

    def _add_control(self, c: Control) -> GuiInputHandle[Any]:
        """Create a setting control; a setting with a `ToolSettings` field starts at its value."""
        gui = self.server.gui
        initial: Any = c.initial
        if hasattr(self.settings, c.setting):
            initial = getattr(self.settings, c.setting)
            if c.kind == "slider":
                digits = max(0, -int(np.floor(np.log10(c.step)))) if c.step < 1 else 0
                initial = round(float(initial) * c.scale, digits)
        else:
            self.settings.extra.setdefault(c.setting, initial / c.scale if c.kind == "slider" else initial)
        if c.kind == "slider":
            return gui.add_slider(c.label, min=c.min, max=c.max, step=c.step, initial_value=initial, hint=c.hint)
        if c.kind == "dropdown":
            return gui.add_dropdown(c.label, c.options, initial_value=str(initial), hint=c.hint)
        return gui.add_checkbox(c.label, bool(initial), hint=c.hint)

    def _setting(self, name: str) -> Any:
        return getattr(self.settings, name) if hasattr(self.settings, name) else self.settings.extra[name]

    def _set_setting(self, name: str, value: Any) -> None:
        if hasattr(self.settings, name):
            setattr(self.settings, name, value)
        else:
            self.settings.extra[name] = value

    def _refuse(self, exc: ClientValueError, event: Any, handle: Any, old: Any) -> None:
        """A client value no control can produce: say so to that client and show the kept value again."""
        log.warning("refused: %s", exc)
        self.notify("Not done", str(exc), client=getattr(event, "client", None), color="red")
        self._gui_write_back(handle, old)

    def _show_tool(self) -> None:
        """Show the active tool's controls, buttons and help line; hide the other tools' controls and buttons."""
        t = self.tool
        shown = shown_settings(t)
        for name, h in self.gui_controls.items():
            h.visible = name in shown
        mine = {cmd.key for cmd in t.commands}
        for key, button in self.gui_tool_buttons.items():
            button.visible = key in mine
        self.gui_tool_help.content = f"**{t.hotkey}** {t.label}: {t.help}"
        self.gui_help.content = help_markdown(self.tools, t.name)
        self._draw_cursor()

    def _gui_write_back(self, handle: Any, value: Any) -> None:
        """Show the value actually used (a clamped client value) in every client, without re-reading it."""
        prev = getattr(self._tls, "syncing", False)
        self._tls.syncing = True
        try:
            handle.value = value
        finally:
            self._tls.syncing = prev

    def _instance_options(self) -> tuple[str, ...]:
        ls = self.store.labelset
        return tuple(f"{k}: {v.name}" for k, v in ls.instances.items())

    def _refresh_panel(self) -> None:
        """Push counts, progress, the instance list and the active instance's fields to the GUI."""
        if not hasattr(self, "gui_table"):
            return
        with self.store.lock:
            ls: LabelSet = self.store.labelset
            table = ls.instances
            counts = ls.counts()
            progress = ls.progress()
            n_undo, n_redo = _undo_steps(ls.undo_stack), _undo_steps(ls.redo_stack)
        opts = tuple(f"{k}: {v.name}" for k, v in table.items()) or NO_OPTIONS
        self._tls.syncing = True
        try:
            if self.settings.active_id not in table:
                self.settings.active_id = max(table) if table else 0
            self.gui_active.options = opts
            self.gui_merge_into.options = opts
            self.gui_active.value = _option_for(opts, self.settings.active_id)
            pre = tuple(f"{k}: {table[k].name} · {table[k].confidence:.2f}"
                        for k in unreviewed_prelabels(table)) or NO_OPTIONS
            current = str(self.gui_prelabel.value).split(":", 1)[0]
            self.gui_prelabel.options = pre
            if current.isdigit() and current in {o.split(":", 1)[0] for o in pre}:  # keep the one under review
                self.gui_prelabel.value = _option_for(pre, int(current))
            info = table.get(self.settings.active_id)
            if info is not None:
                self.gui_name.value = info.name
                self.gui_category.value = info.category
                self.gui_color.value = info.color
                self.gui_visible.value = info.visible
                self.gui_locked.value = info.locked
            self.gui_progress.value = round(100.0 * progress, 2)
            rows = ["| id | name | category | vertices | flags |", "|---:|---|---|---:|---|"]
            for k, v in table.items():
                flags = ("hidden " if not v.visible else "") + ("locked " if v.locked else "")
                if v.unreviewed:
                    flags += f"pre-label {v.confidence:.2f}"
                mark = " ◀" if k == self.settings.active_id else ""
                rows.append(f"| {k} {_swatch(v.color)}{mark} | {_md(v.name)} | {_md(v.category)} | "
                            f"{counts.get(k, 0):,} | {flags} |")
            per_cat: dict[str, list[tuple[int, tuple[int, int, int]]]] = {}
            for k, v in table.items():
                per_cat.setdefault(v.category, []).append((counts.get(k, 0), v.color))
            cats = " · ".join(f"{''.join(_swatch(col) for _, col in n)} {_md(c)}: {len(n)} "
                              f"({sum(c_ for c_, _ in n):,} vertices)" for c, n in per_cat.items())
            self.gui_table.content = (
                f"**{100 * progress:.1f}%** of {self.n:,} vertices labelled"
                + (f"\n\nper category: {cats}" if cats else "") + "\n\n" + "\n".join(rows)
            )
            self.gui_history.content = (
                f"{n_undo} undoable, {n_redo} redoable\n\n" + "\n".join(f"- {h}" for h in self.stats.history)
            )
            self.gui_status.content = self._status_markdown()
        finally:
            self._tls.syncing = False

    def _status_markdown(self) -> str:
        """Autosave state for the panel: problems first (an autosave failure, what a recovery could not restore)."""
        parts: list[str] = []
        if self.store.problem:
            parts.append(f"**⚠ {self.store.problem}**")
        if self.store.journal.broken:
            parts.append(f"**⚠ {self.store.journal.broken}**")
        rec = self.store.recovery
        if rec is not None:
            mark = ("Recovered" if rec.verified_complete else "**⚠ Recovered with losses**" if not rec.complete
                    else "**⚠ Recovered, not everything verifiable**")
            parts.append(f"{mark} at start:  \n" + "  \n".join(rec.summary().splitlines()))
        parts.append(
            f"Autosave: `{self.store.label_path.name}` + journal in `{self.work_dir}`  \n"
            f"last edit: {self.stats.last_edit_bytes / 1024:.0f} KiB sent, {self.stats.last_edit_ms:.0f} ms"
        )
        return "\n\n".join(parts)

    def _on_store_problem(self, msg: str | None) -> None:
        """An autosave failed (msg) or works again (None): tell every client, not only the terminal."""
        if msg:
            self.notify("Autosave failed", msg, color="red")
        else:
            self.notify("Autosave works again", "the checkpoint is up to date", color="green")
        self._refresh_panel()

    def _greet(self, client: Any) -> None:
        """A newly connected client: its camera is watched (`camera_guard`), and it hears about a recovery or a
        standing autosave problem."""
        self.camera_guard.attach(client)
        rec = self.store.recovery
        if rec is not None:
            title = ("Session recovered" if rec.verified_complete else "Session recovered with losses"
                     if not rec.complete else "Session recovered, not everything verifiable")
            self.notify(title, rec.summary(), client=client, color="yellow" if rec.complete else "red")
        if self.store.problem:
            self.notify("Autosave failed", self.store.problem, client=client, color="red")

    def _forget_client(self, client: ClientHandle) -> None:
        """A client left: drop what the app kept for it (its cheat-sheet overlay)."""
        with self._sheet_lock:
            self.cheat_sheets.pop(client.client_id, None)
        self.camera_guard.forget(client)

    def _run_reporting(self, fn: Callable[[], Any], client: Any = None) -> Any:
        """Run an action for a client (a GUI callback, a hotkey, a scene gesture); errors become a notification to
        that client (all clients when None), never a crash and never only a log line.

        A refused action (bad input: ValueError, KeyError, OSError) says why ("Not done"); anything else is a bug
        and is logged with its traceback and shown as "Error" with its type and message.

        Returns:
            What `fn` returned, or None after an error.
        """
        try:
            return fn()
        except (ValueError, KeyError, OSError) as exc:
            msg = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
            log.warning("refused: %s", msg)
            self.notify("Not done", msg, client=client, color="red")
            return None
        except Exception as exc:  # noqa: BLE001 - a bug in a tool: the user must hear of it, the server stays up
            log.exception("action failed")
            self.notify("Error", f"that did not work: {type(exc).__name__}: {exc} (the server log has the details)",
                        client=client, color="red")
            return None

    def notify(self, title: str, body: str, *, client: Any = None, color: LiteralColor | None = None) -> None:
        """Show a notification to one client (or all)."""
        targets = [client] if client is not None else list(self.server.get_clients().values())
        for c in targets:
            try:
                c.add_notification(title, body, auto_close_seconds=6.0, color=color)
            except Exception:  # a disconnected client must not break the action
                log.debug("notification to %r failed", c, exc_info=True)

    # ================================================================== actions (GUI callbacks call these)
    def set_tool(self, tool: str) -> None:
        """Make a tool of the table active (its controls and help are shown)."""
        if tool not in self._tool_of:
            raise ValueError(f"unknown tool {tool!r}; tools: {tuple(self._tool_of)}")
        self.settings.tool = tool
        self._tls.syncing = True
        try:
            self.gui_tool.value = tool
        finally:
            self._tls.syncing = False
        self._show_tool()

    def set_active(self, instance_id: int) -> None:
        """Make an instance the one brushes paint."""
        self.store.labelset.info(instance_id)  # KeyError when unknown
        self.settings.active_id = int(instance_id)
        self._refresh_panel()

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
        the slider's range; the slider shows the new value. Returns the radius in metres."""
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
        handle = self.gui_controls.get("radius")
        if handle is not None:
            self._gui_write_back(handle, snapped)
        self._draw_cursor()
        return self.settings.radius

    def run_tool_hotkey(self, key: str) -> object:
        """A command hotkey (Enter, Esc): run the active tool's command with that key; nothing when it has none
        (the key may be meant for something else in the page)."""
        for cmd in self.tool.commands:
            if cmd.hotkey is not None and cmd.hotkey.upper() == key.upper():
                return cmd.run(self)
        return None

    def reset_view(self, client: ClientHandle | None = None) -> None:
        """Put a client's camera (every client's when None) back on the fitted view of the scan (R)."""
        self.camera_guard.reset(client)

    def toggle_cheat_sheet(self, client: ClientHandle | None) -> bool:
        """Open the keyboard cheat sheet (`?`) over one client's view, or close it when open; True when open now.

        Args:
            client: the client that pressed the key (None: every connected client).
        """
        targets = [client] if client is not None else list(self.server.get_clients().values())
        opened = False
        for c in targets:
            with self._sheet_lock:
                modal = self.cheat_sheets.pop(c.client_id, None)
                if modal is not None:
                    modal.close()
                    continue
                modal = c.gui.add_modal("Keyboard shortcuts")
                with modal:
                    c.gui.add_markdown(cheat_sheet_markdown(self.tools))
                    close = c.gui.add_button("Close (?)")
                self.cheat_sheets[c.client_id] = modal
                opened = True

            def on_close(_event: Any, c: ClientHandle = c, modal: GuiModalHandle = modal) -> None:
                with self._sheet_lock:
                    if self.cheat_sheets.get(c.client_id) is modal:
                        del self.cheat_sheets[c.client_id]
                        modal.close()

            close.on_click(on_close)
        return opened

    def set_labels_only(self, on: bool) -> None:
        """The labels-only view (unlabelled vertices dimmed) on or off; every chunk is redrawn."""
        self.settings.labels_only = bool(on)
        self._gui_write_back(self.gui_labels_only, self.settings.labels_only)
        self.draw_chunks(np.arange(self.chunks.count))

    def choose_category(self, category: str) -> None:
        """The user typed a category: the active instance takes it, and so do new instances from now on."""
        category = category.strip()
        if not category:
            return
        self.settings.category = category
        self._update_active(category=category)

    def new_instance(self, *, category: str = "object", name: str | None = None, client: str = "") -> int:
        """Create an instance and make it active; returns its id."""
        d = self.store.do(lambda ls: ls.create_instance(category=category, name=name), client=client)
        assert d is not None
        iid = next(iter(d.table_after))
        self.settings.active_id = int(iid)
        self._refresh_panel()
        return int(iid)

    def _update_active(self, **changes: Any) -> None:
        iid = self.settings.active_id
        if iid <= 0:
            return
        self.store.do(lambda ls: ls.update_instance(iid, **changes))

    def _toggle_active(self, what: str) -> None:
        info = self.store.labelset.info(self.settings.active_id)
        self._update_active(**{what: not getattr(info, what)})

    def update_instance(self, instance_id: int, **changes: Any) -> None:
        """Rename / recategorise / recolour / hide / lock an instance (undoable)."""
        self.store.do(lambda ls: ls.update_instance(instance_id, **changes))

    def delete_instance(self, instance_id: int) -> None:
        self.store.do(lambda ls: ls.delete_instance(instance_id))

    def merge(self, sources: list[int], into: int) -> None:
        self.store.do(lambda ls: ls.merge(sources, into))
        self.settings.active_id = int(into)
        self._refresh_panel()

    def undo(self, *, client: str = "") -> list[Delta]:
        return self.store.undo(client=client)

    def redo(self, *, client: str = "") -> list[Delta]:
        return self.store.redo(client=client)

    def _require_active(self) -> int:
        iid = self.settings.active_id
        if iid <= 0 or iid not in self.store.labelset.instances:
            raise ValueError("no active instance: create one first (N)")
        return iid

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
        iid = self._require_active()
        return self.store.do(
            lambda ls: tagged(ls.paint(idx, iid, overwrite=not self.settings.only_unlabelled)), client=client,
            group=group,
        )

    @contextlib.contextmanager
    def _edit_source(self, source: str) -> Iterator[None]:
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
            nrm, lim = self._brush_normal(v)
            if prev is None:
                idx = sel.brush(self.geom, p, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
            else:
                idx = sel.brush_segment(self.geom, prev, p, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
            d = self.paint(idx, erase=erase, group=group, client=client)
            changed += 0 if d is None else d.num_vertices
            prev = p
        return changed

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

    def click(self, origin: np.ndarray, direction: np.ndarray, *, client: str = "") -> int | None:
        """Apply the active tool at the surface point hit by a ray; returns the hit vertex (None = miss)."""
        hit = sel.pick(self.geom, origin, direction)
        if hit is None:
            return None
        v, pos = hit
        tool = self.tool
        if tool.apply_at is not None:
            with self._edit_source(tool.label):
                tool.apply_at(self, Hit(int(v), np.asarray(pos), client))
        return v

    def dab(self, vertex: int, position: np.ndarray, *, erase: bool, client: str = "") -> Delta | None:
        """One brush (or erase) dab of the current radius at a surface point.

        Args:
            vertex: the scan vertex at the point (its normal limits the brush when a normal limit is set).
            position: (3,) float, the point on the surface, world frame.
            erase: erase instead of painting the active instance.
        """
        nrm, lim = self._brush_normal(int(vertex))
        self.move_cursor(position, int(vertex))
        idx = sel.brush(self.geom, position, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
        return self.paint(idx, erase=erase, client=client)

    # ---- brush cursor
    def move_cursor(self, position: np.ndarray, vertex: int) -> BrushCursor:
        """Put the brush cursor (a ring of the brush radius) at a surface point and draw it.

        Args:
            position: (3,) float, the point on the surface, world frame.
            vertex: the scan vertex there (its normal orients the ring).
        """
        with self._cursor_lock:
            self.cursor = BrushCursor(np.asarray(position, np.float64).reshape(3).copy(),
                                      np.asarray(self.geom.normals[int(vertex)], np.float64).reshape(3).copy(),
                                      self.settings.radius, self._cursor_visible())
        self._draw_cursor()
        assert self.cursor is not None
        return self.cursor

    def _cursor_visible(self) -> bool:
        """The cursor shows while the active tool has a brush radius among its controls (brush, erase)."""
        return "radius" in shown_settings(self.tool)

    def _draw_cursor(self) -> None:
        """Redraw the brush cursor at its position with the current radius (hidden for tools without one)."""
        with self._cursor_lock:
            cur = self.cursor
            if cur is None:
                return
            cur = dataclasses.replace(cur, radius=self.settings.radius, visible=self._cursor_visible())
            self.cursor = cur
            try:
                self._cursor_handle = self.server.scene.add_line_segments(
                    "/annotator/brush_cursor", ring_segments(cur.position, cur.normal, cur.radius),
                    colors=CURSOR_COLOR, thickness=CURSOR_THICKNESS_PX, thickness_units="screen",
                    visible=cur.visible)
            except ValueError:  # a degenerate radius: keep the last ring
                log.debug("brush cursor not drawn", exc_info=True)

    def box(
        self,
        *,
        position: np.ndarray,
        wxyz: np.ndarray,
        fov: float,
        aspect: float,
        screen_min: tuple[float, float],
        screen_max: tuple[float, float],
        client: str = "",
    ) -> Delta | None:
        """Box select with a camera, painted with the active instance (erased with the erase tool)."""
        idx = sel.box_select(self.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect,
                             screen_min=screen_min, screen_max=screen_max,
                             facing="front" if self.settings.box_facing == "front" else "all")
        with self._edit_source("box select"):
            return self.paint(idx, erase=self.tool.erase, client=client)

    def lasso(
        self,
        *,
        position: np.ndarray,
        wxyz: np.ndarray,
        fov: float,
        aspect: float,
        polygon: np.ndarray,
        client: str = "",
    ) -> Delta | None:
        """Lasso select with a camera: vertices inside a screen outline, painted with the active instance (erased
        with the erase tool); `Box select: front/all` decides whether hidden sides are taken too."""
        idx = sel.lasso_select(self.geom, position=position, wxyz=wxyz, fov=fov, aspect=aspect, polygon=polygon,
                               facing="front" if self.settings.box_facing == "front" else "all")
        with self._edit_source("lasso"):
            return self.paint(idx, erase=self.tool.erase, client=client)

    def add_lasso_point(self, event: SceneClickEvent) -> int:
        """Lasso tool: a Ctrl/Cmd+click adds a screen point to the outline (the camera of the first point is used).

        Args:
            event: the click as viser delivers it (`screen_pos` is one (u, v) pair; its client's camera is read).

        Returns:
            The number of outline points so far.

        Raises:
            ClientValueError: the outline already has `annotator.lasso.MAX_LASSO_POINTS` points, or the click has no
                usable screen position.
        """
        cam = event.client.camera
        camera = LassoCamera(np.asarray(cam.position, np.float64), np.asarray(cam.wxyz, np.float64), float(cam.fov),
                             float(cam.aspect))
        try:
            n = self.lasso_outline.add(event.screen_pos, ray_origin=event.ray_origin,
                                       ray_direction=event.ray_direction, camera=camera)
        except ValueError as exc:
            raise ClientValueError(str(exc)) from None
        self._draw_lasso()
        return n

    def apply_lasso(self, *, client: str = "") -> Delta | None:
        """Select inside the outline drawn with the lasso tool, then clear it."""
        camera, polygon = self.lasso_outline.polygon()
        self.clear_lasso()
        return self.lasso(position=camera.position, wxyz=camera.wxyz, fov=camera.fov, aspect=camera.aspect,
                          polygon=polygon, client=client)

    def clear_lasso(self) -> None:
        self.lasso_outline.clear()
        self._draw_lasso()

    def _draw_lasso(self) -> None:
        n = len(self.lasso_outline)
        seg = self.lasso_outline.segments()
        if seg is not None:
            self._lasso_handle = self.server.scene.add_line_segments("/annotator/lasso", seg, colors=(255, 200, 0),
                                                                     thickness=2.0, thickness_units="screen")
        elif self._lasso_handle is not None:
            with contextlib.suppress(Exception):
                self._lasso_handle.remove()
            self._lasso_handle = None
        buttons = getattr(self, "gui_tool_buttons", {})  # the lasso's buttons (absent from a table without it)
        for key, disabled in (("lasso_apply", n < 3), ("lasso_clear", n == 0)):
            if key in buttons:
                buttons[key].disabled = disabled

    # ---- files
    def _safe_path(self, name: str, *, what: str) -> Path:
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
        d = self._safe_path(directory, what="export directory") if directory else self.out_dir
        labels, table = self.store.snapshot()
        if fmt == "ply":
            out = [save_labels_ply(self.scene, labels, table, self._safe_path(str(d / f"{self.stem}.labels.ply"),
                                                                               what="export file"))]
        elif fmt == "npz":
            out = [save_labels_npz(labels, table, self._safe_path(str(d / f"{self.stem}.labels.npz"), what="export file"),
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

    # ---- EFEM assist
    def import_efem(self, path: str, *, threshold: float = 0.0) -> list[int]:
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
        self._refresh_panel()
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
            target = self._require_active()
            if target == instance_id:
                raise ValueError("choose another active instance to merge this pre-label into")
            self.store.do(lambda ls: ls.merge([instance_id], target), group=group)
        else:
            raise ValueError(f"unknown review action {action!r}")
        self._refresh_panel()

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
        self._refresh_panel()
        self.notify("Pre-labels", f"{'accepted' if action == 'accept' else 'rejected'} {len(ids)} pre-label(s) "
                    f"with confidence {'≥' if action == 'accept' else '<'} {cut:.2f} (one undo step)")
        return ids

    def step_prelabel(self, step: int, *, client: ClientHandle | None = None) -> int:
        """Select the next (`step` = 1) or previous (-1) unreviewed pre-label in the dropdown's order (most
        confident first, wrapping around; the first press goes to the first / last one) and fly the client's camera
        to it; returns its id.

        Raises:
            ValueError: no unreviewed pre-label is left.
        """
        ids = unreviewed_prelabels(self.store.labelset.instances)
        if not ids:
            raise ValueError("no unreviewed pre-labels: import an EFEM result first")
        current = str(self.gui_prelabel.value).split(":", 1)[0]
        started = self._prelabel_cursor is not None
        iid = step_row(ids, int(current) if started and current.isdigit() else None, step)
        self._prelabel_cursor = iid
        self._gui_write_back(self.gui_prelabel, _option_for(tuple(self.gui_prelabel.options), iid))
        self.fly_to(np.flatnonzero(self.store.labels == iid), client)
        return iid

    def fly_to(self, idx: np.ndarray, client: ClientHandle | None = None) -> None:
        """Point a client's camera (every client's when None) at some vertices: their box, seen from the fitted
        view's direction, filling about half the view."""
        idx = np.asarray(idx, np.int64)
        if idx.size == 0:
            return
        pts = self.scene.points[idx]
        scan_diag = float(np.linalg.norm(np.ptp(self.scene.points, axis=0))) or 1.0
        self.camera_guard.place(fly_to_view(pts.min(axis=0), pts.max(axis=0), home=self.home_view,
                                            scene_diagonal=scan_diag), client)

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment: run EFEM seeded near a vertex with the chosen prior and preview the mask.

        The solver runs in a background thread (edits stay responsive); the mask is highlighted when it is ready
        and becomes labels only through `accept_segment`.

        Args:
            vertex: the clicked vertex.
            wait: run in the calling thread and return the mask (tests, scripts).

        Returns:
            With `wait`, (K,) int32 vertex indices of the proposed mask (also kept in `pending_segment`); else None.
        """
        from annotator import assist
        from efem_viz.em.solver import EMCancelled

        prior_name = read_choice(self.gui_prior)
        with self._segment_lock:
            if self._segment_cancel is not None:
                raise ValueError("still segmenting the last click: wait for its preview, or Esc cancels it")
            cancel = self._segment_cancel = threading.Event()
        self.gui_seg_progress.value = 0.0
        self.gui_seg_progress.visible = True
        self._enable_segment_buttons()

        def on_step(info: Any) -> None:
            self.gui_seg_progress.value = round(100.0 * (info.step + 1) / max(info.num_steps, 1), 1)

        def job() -> np.ndarray | None:
            t0 = time.perf_counter()
            try:
                mask_idx = assist.segment_at_point(self.scene, int(vertex), prior_name=prior_name, on_step=on_step,
                                                   cancel=cancel)
            except EMCancelled:
                self.notify("Segmenting cancelled", f"the segmentation around vertex {vertex} was stopped")
                return None
            finally:
                with self._segment_lock:
                    self._segment_cancel = None
                self.gui_seg_progress.visible = False
                self._enable_segment_buttons()
            self.set_preview(mask_idx)
            if len(mask_idx) == 0:
                self.notify("No object found", f"EFEM with prior {prior_name!r} accepted no proposal around vertex "
                            f"{vertex} ({time.perf_counter() - t0:.1f} s): click nearer the object's centre, or "
                            "label it with the brush / region grow")
            else:
                self.notify("Segment preview", f"{len(mask_idx):,} vertices in {time.perf_counter() - t0:.1f} s: "
                            "Enter (Accept segment) paints it as a new instance, Esc discards it")
            return mask_idx

        if wait:
            return job()
        self.notify("Segmenting", f"EFEM with prior {prior_name!r} around vertex {vertex}... (Esc cancels)")
        threading.Thread(target=lambda: self._run_reporting(job), name="annotator-segment", daemon=True).start()
        return None

    @property
    def segmenting(self) -> bool:
        """Whether a click-to-segment run is in progress."""
        with self._segment_lock:
            return self._segment_cancel is not None

    def _enable_segment_buttons(self) -> None:
        """Accept needs a preview; Discard a preview or a run to cancel (both the Tools and EFEM assist ones)."""
        has = self.pending_segment is not None
        self.gui_seg_accept.disabled = not has
        self.gui_seg_cancel.disabled = not has
        buttons = getattr(self, "gui_tool_buttons", {})
        if "segment_accept" in buttons:
            buttons["segment_accept"].disabled = not has
        if "segment_discard" in buttons:
            buttons["segment_discard"].disabled = not (has or self.segmenting)

    def set_preview(self, idx: np.ndarray | None) -> None:
        """Highlight a proposed mask (None clears it) without touching the labels."""
        old = self.preview
        if idx is None or len(idx) == 0:
            self.preview, self.pending_segment = None, None
        else:
            preview = np.zeros(self.n, bool)
            self.preview = preview
            preview[idx] = True
            self.pending_segment = np.asarray(idx, np.int32)
        touched = np.zeros(0, np.int64)
        for m in (old, self.preview):
            if m is not None:
                touched = np.union1d(touched, self.chunks.touched(np.flatnonzero(m)))
        self.draw_chunks(touched)
        self._enable_segment_buttons()

    def accept_segment(self) -> Delta | None:
        """Paint the previewed segment as a new instance (category from the prior name)."""
        if self.pending_segment is None:
            raise ValueError("no segment preview to accept: Ctrl+click with the segment tool first")
        idx = self.pending_segment
        self.set_preview(None)
        self.new_instance(category=read_choice(self.gui_prior) or "object")
        return self.paint(idx)

    def discard_segment(self) -> None:
        """Drop the segment preview; while a segmentation runs, cancel it (Esc)."""
        with self._segment_lock:
            running = self._segment_cancel
        if running is not None:
            running.set()
            return
        self.set_preview(None)

    # ================================================================== viser events
    def _on_scene_click(self, event: Any) -> None:
        self._edits.put(("click", event))

    def _on_rect(self, event: Any) -> None:
        self._edits.put(("rect", event))

    async def _on_drag(self, event: Any) -> None:
        # async: phases arrive in order; the work itself runs on the edit thread.
        self._edits.put(("drag", event))

    def _edit_loop(self) -> None:
        while not self._closed.is_set():
            try:
                kind, event = self._edits.get(timeout=0.5)
            except queue.Empty:
                continue
            if kind == "stop":
                break
            # Coalesce a backlog of drag updates of one client: the segment from the last point covers them.
            if kind == "drag" and event.phase == "update":
                while True:
                    try:
                        k2, e2 = self._edits.queue[0]
                    except IndexError:
                        break
                    if k2 == "drag" and e2.phase == "update" and e2.client_id == event.client_id:
                        self._edits.get_nowait()
                        self._edits.task_done()
                        event = e2
                    else:
                        break
            client = getattr(event, "client", None)
            try:
                self._run_reporting(lambda: self.handle_event(kind, event), client)
            except Exception:  # never let one bad event kill the edit thread
                log.exception("event %s failed", kind)
            finally:
                self._edits.task_done()

    def handle_event(self, kind: str, event: Any) -> None:
        """Process one viser event (click, rect or drag); runs on the edit thread (tests may call it directly).

        Raises:
            ClientValueError: the event carries non-finite or malformed coordinates (a scripted client).
        """
        _check_event(kind, event)
        cid = f"client{getattr(event, 'client_id', '?')}"
        on_click = self.tool.on_click
        if kind == "click" and on_click is not None:
            with self._edit_source(self.tool.label):
                on_click(self, event)
        elif kind == "click":
            v = self.click(np.asarray(event.ray_origin), np.asarray(event.ray_direction), client=cid)
            if v is None and self.tool.apply_at is not None:
                self.notify("Missed the scan", MISSED_SCAN, client=getattr(event, "client", None), color="yellow")
        elif kind == "rect":
            cam = event.client.camera
            self.box(position=np.asarray(cam.position), wxyz=np.asarray(cam.wxyz), fov=float(cam.fov),
                     aspect=float(cam.aspect), screen_min=tuple(event.screen_min), screen_max=tuple(event.screen_max),
                     client=cid)
        elif kind == "drag":
            self._drag(event, cid)
        self.server.flush()

    def _drag(self, event: Any, cid: str) -> None:
        tool = self.tool
        key = int(event.client_id)
        if event.phase == "start":
            start = np.asarray(event.start_position, np.float32)
            v = int(self.geom.tree.query(start)[1])
            if not tool.stroke:
                # Other tools act once at the grabbed point (a tool without `apply_at` ignores drags).
                if tool.apply_at is not None:
                    with self._edit_source(tool.label):
                        tool.apply_at(self, Hit(v, start, cid))
                return
            p = self.scene.points[v] if self.geom.is_mesh is False else start
            stroke = _Stroke(group=uuid.uuid4().hex[:12], last=np.asarray(p, np.float32), normal=self.geom.normals[v],
                             erase=tool.erase, source=tool.label)
            self.move_cursor(stroke.last, v)
            self._strokes[key] = stroke
            nrm, lim = self._brush_normal(v)
            idx = sel.brush(self.geom, stroke.last, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
            with self._edit_source(stroke.source):
                self.paint(idx, erase=stroke.erase, group=stroke.group, client=cid)
            return
        stroke = self._strokes.get(key)
        if stroke is None:
            return
        if event.phase == "end":
            self._strokes.pop(key, None)
        cam_pos = np.asarray(event.client.camera.position, np.float64)
        end = np.asarray(event.end_position, np.float64)
        hit = sel.pick(self.geom, cam_pos, end - cam_pos)
        if hit is None:
            return
        v, pos = hit
        self.move_cursor(pos, v)
        nrm, lim = self._brush_normal(v)
        idx = sel.brush_segment(self.geom, stroke.last, pos, self.settings.radius, normal=nrm, max_normal_angle_deg=lim)
        stroke.last = np.asarray(pos, np.float32)
        with self._edit_source(stroke.source):
            self.paint(idx, erase=stroke.erase, group=stroke.group, client=cid)

    def wait_idle(self, timeout: float = 10.0) -> None:
        """Block until queued viser events are processed (tests)."""
        t_end = time.time() + timeout
        while self._edits.unfinished_tasks and time.time() < t_end:
            time.sleep(0.01)

    def close(self) -> None:
        """Stop the server, flush the checkpoint, release the journal (idempotent)."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._edits.put(("stop", None))
        try:
            self.server.stop()
        finally:
            self.store.close()
            # A Ctrl+C right after start must not exit while open3d builds its ray-casting scene in the warm-up
            # thread (open3d then reports leaks and the process exits with status 1).
            self._warmup.join(timeout=60)
            self._worker.join(timeout=10)


MISSED_SCAN = ("Nothing of the scan is under the cursor, so the tool did nothing: Ctrl/Cmd+click on the scan. If "
               "the scan is out of sight or tiny, R (reset view) fits it to the view.")
"""What a Ctrl/Cmd+click that misses the scan tells the user."""


def _undo_steps(stack: list[Delta]) -> int:
    """Undo steps on a stack: adjacent deltas of one stroke group count once (what one Ctrl+Z undoes)."""
    steps = 0
    prev = None
    for d in stack:
        if not d.group or d.group != prev:
            steps += 1
        prev = d.group
    return steps


def _finite(value: Any, n: int, what: str) -> None:
    try:
        a = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ClientValueError(f"{what}: expected {n} numbers") from None
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ClientValueError(f"{what}: expected {n} finite numbers")


def _check_event(kind: str, event: Any) -> None:
    """Refuse scene events whose coordinates no browser produces (NaN, inf, wrong length)."""
    if kind == "click":
        _finite(event.ray_origin, 3, "click ray origin")
        _finite(event.ray_direction, 3, "click ray direction")
        _finite(event.screen_pos, 2, "click screen position")
    elif kind == "rect":
        _finite(event.screen_min, 2, "box corner")
        _finite(event.screen_max, 2, "box corner")
        cam = event.client.camera
        _finite(cam.position, 3, "camera position")
        _finite(cam.wxyz, 4, "camera orientation")
        _finite((cam.fov, cam.aspect), 2, "camera fov/aspect")
        if not (0.0 < float(cam.fov) < np.pi and float(cam.aspect) > 0.0):
            raise ClientValueError("camera fov/aspect out of range")
    elif kind == "drag":
        _finite(event.start_position, 3, "drag start")
        if event.phase != "start":
            _finite(event.end_position, 3, "drag position")
            _finite(event.client.camera.position, 3, "camera position")


def _color(i: int) -> tuple[int, int, int]:
    from efem_viz.colors import instance_color

    return instance_color(i)
