"""The annotator's viser layer over the headless session: builds the GUI, turns GUI/scene events into session calls,
draws the scan through `annotator.scan_view.ScanView`.

Thin by design: every action (paint, grow, fill, box, lasso, pre-labels, click-to-segment, undo, export) is done by
`annotator.session.AnnotatorSession` (`self.session`), which is also the tools' host; callbacks read GUI values into
its `ToolSettings` and call it, and the label store's listener redraws the touched chunks (`ScanView.draw_delta`). Tests
and scripts drive the same code paths through `app.session` without a browser (the app copies none of its
names).

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
  (`run_reporting`), not only the log.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence, TypeVar

import numpy as np

from annotator.io import MAX_SCAN_POINTS
from annotator.labels import Delta, unreviewed_prelabels
from annotator.cheat_sheet import CheatSheets
from annotator.scene_events import MISSED_SCAN, check_event, coalesce_drag_updates
from annotator.panel_views import panel_view, status_markdown
from annotator.panels import Panels
from annotator.wiring import wire
from annotator.session import AnnotatorSession
from annotator.scan_view import DISPLAY_POINTS, ScanView
from annotator.tools import DEFAULT_TOOLS, RADIUS, TOOLS, Tool, ToolSettings, all_controls, lasso_click
from efem_viz.serve.guard import ServedApp, saved_token, start_server
from efem_viz.serve.table import option_for as _option_for
from efem_viz.serve.table import step_row
from efem_viz.serve.inputs import ClientValueError, read_choice, read_int
from efem_viz.data.io import RESULT_SUFFIX
from efem_viz.em.config import suggested_preset
from efem_viz.prior.config import DEFAULT_PRIOR

if TYPE_CHECKING:
    from viser import (ClientHandle, GuiInputHandle, MeshHandle, SceneClickEvent, SceneNodeDragEvent,
                       SceneRectSelectEvent)
    from viser._messages import LiteralColor  # the colour names `add_notification` accepts

log = logging.getLogger(__name__)

__all__ = ["TOOLS", "AnnotatorApp", "ToolSettings"]

T = TypeVar("T")


class AnnotatorApp(ServedApp):
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
        display_points: display budget: a scan with more vertices is drawn from a subset of this many (every tool
            still labels all of them; see `annotator.scan_view`).
        efem_result: an `<scene>.efem.npz` to import as pre-labels at start (optional).
        accept_scan_mismatch: resume a journal written for other geometry with the same vertex count.
        token: the server's access token (None = a fresh random one; see `efem_viz.serve.guard`).
        tools: the tool table (`annotator.tools.Tool` entries, toolbar order; default `DEFAULT_TOOLS`). The first
            one is active at start.
        on_stage: called with what the opening does next (reading, journal, normals, server, drawing): a big
            scan takes seconds before its URL, and the CLI prints each stage.

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
        max_points: int = MAX_SCAN_POINTS,
        autosave_delay: float = 0.5,
        chunk_size: int = 16384,
        display_points: int = DISPLAY_POINTS,
        accept_scan_mismatch: bool = False,
        token: str | None = None,
        tools: Sequence[Tool] = DEFAULT_TOOLS,
        on_stage: Callable[[str], None] | None = None,
    ) -> None:
        t0 = time.perf_counter()
        stage = on_stage or (lambda _what: None)
        if display_points < 1:  # before the scan is read and its journal created
            raise ValueError(f"the display budget must be at least 1 point, got {display_points}")
        self.session = AnnotatorSession(scan_path, labels_path=labels_path, out_dir=out_dir, max_points=max_points,
                                        autosave_delay=autosave_delay, accept_scan_mismatch=accept_scan_mismatch,
                                        tools=tools, on_stage=on_stage)
        """Every action and the state it acts on (`annotator.session`); this class draws it."""
        ses = self.session
        self._sheets = CheatSheets(self.session.toolbox.tools)
        self.cheat_sheets = self._sheets.open
        """The open `?` cheat-sheet overlays, by client id."""
        self._edits: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._tls = threading.local()
        self._closed = threading.Event()

        try:
            self.token_kept = False
            """True when the token (and so the URL) is the one this scan's folder kept from an earlier run."""
            if token is None:  # the scan's folder keeps it: a tab left open reconnects after a restart
                token, self.token_kept = saved_token(ses.scan.work_dir)
            stage("starting the server")
            self.server, self.access = start_server(host=host, port=port, token=token)
        except BaseException:
            ses.close()
            raise
        try:
            self.server.gui.configure_theme(control_width="large")
            stage("preparing the drawing")
            self.view = ScanView(self.server, ses, chunk_size=chunk_size, display_points=display_points)
            """The scan as drawn: chunks, surface, overlays, camera (`annotator.scan_view`)."""
            self.view.surface.on_drag("left", modifier="cmd/ctrl")(self._on_drag)
            self.server.scene.on_click(modifier="cmd/ctrl")(self._on_scene_click)
            self.server.scene.on_rect_select(modifier="shift")(self._on_rect)
            self._build_gui()
        except BaseException:
            self.server.stop()
            ses.close()
            raise
        ses.on_change, ses.on_cursor, ses.on_lasso = self._refresh_panel, self.view.draw_cursor, self._draw_lasso
        ses.on_preview = self.view.draw_preview
        ses.on_segment, ses.report = self._show_segmenting, self.run_reporting
        ses.on_efem = self._show_efem_run
        ses.notify = lambda title, body: self.notify(title, body)  # late-bound: tests replace `notify`
        self.session.scan.store.listeners.append(self._on_labels_changed)
        self.session.scan.store.problem_listeners.append(self._on_store_problem)
        self.server.on_client_connect(self._greet)
        self.server.on_client_disconnect(self._forget_client)
        self._worker = threading.Thread(target=self._edit_loop, name="annotator-edits", daemon=True)
        self._worker.start()
        ses.scan.start_warm_up(self._show_warm_up)
        self.open_s = time.perf_counter() - t0
        log.info("opened %s: %d vertices (%d drawn), %d chunks, %.2f s", self.session.scan.scan_path.name,
                 self.session.scan.n, len(self.view.display), self.view.chunks.count, self.open_s)

    # ================================================================== drawing
    def _on_labels_changed(self, d: Delta, how: str) -> None:
        t0 = time.perf_counter()
        sent = self.view.draw_delta(d)
        st = self.view.stats
        st.last_edit_bytes, st.last_edit_ms, st.edits = sent, 1000 * (time.perf_counter() - t0), st.edits + 1
        self._refresh_panel()

    # ================================================================== GUI
    def _build_gui(self) -> None:
        from efem_viz.prior.registry import available_priors

        default_efem = self.session.scan.scan_path.with_name(self.session.scan.stem + RESULT_SUFFIX)
        priors = tuple(available_priors()) or (DEFAULT_PRIOR,)
        self.panels = Panels(self.server.gui, self.session.toolbox.tools, self.session.toolbox.settings,
                             efem_result=default_efem.name if default_efem.exists() else "", priors=priors,
                             prior=DEFAULT_PRIOR if DEFAULT_PRIOR in priors else priors[0],
                             preset=suggested_preset(self.session.scan.scene))
        """The GUI handles (`annotator.panels`)."""
        wire(self, self.server.gui)
        self.show_tool()
        self._refresh_panel()  # fills the instance lists (`panel_view`)

    # ---- tool table → GUI
    @property
    def tool(self) -> Tool:
        """The active tool's entry."""
        return self.session.toolbox.tool

    def refuse(self, exc: ClientValueError, client: ClientHandle | None, handle: GuiInputHandle[Any],
               old: object) -> None:
        """A client value no control can produce: say so to that client and show the kept value again."""
        log.warning("refused: %s", exc)
        self.notify("Not done", str(exc), client=client, color="red")
        self.write_back(handle, old)

    def quiet(self) -> bool:
        """True while the app itself sets controls (their callbacks then do nothing)."""
        return bool(getattr(self._tls, "syncing", False))

    def show_tool(self) -> None:
        """Show the active tool's controls, buttons and help line (`Panels.show_tool`)."""
        self.panels.show_tool(self.tool, self.session.toolbox.tools)
        self.session.brush.refresh_cursor()

    def write_back(self, handle: GuiInputHandle[Any], value: object) -> None:
        """Show the value actually used (a clamped client value) in every client, without re-reading it."""
        prev = getattr(self._tls, "syncing", False)
        self._tls.syncing = True
        try:
            handle.value = value
        finally:
            self._tls.syncing = prev

    def _refresh_panel(self) -> None:
        """Push counts, progress, the instance list and the active instance's fields to the GUI
        (`annotator.panel_views.panel_view`, `Panels.show`)."""
        if not hasattr(self, "panels"):
            return
        if getattr(self._tls, "defer_panel", False):
            self._tls.panel_due = True  # an action is about to read its control: refresh after it
            return
        st = self.view.stats
        v = panel_view(self.session.scan.store, self.session.toolbox.settings.active_id)
        status = status_markdown(self.session.scan.store, self.session.scan.work_dir,
                                 last_edit_bytes=st.last_edit_bytes, last_edit_ms=st.last_edit_ms)
        self._tls.syncing = True
        try:
            self.session.toolbox.settings.active_id = v.active_id
            self.panels.show(v, status, typing=self.session.instances.fields_typing())
        finally:
            self._tls.syncing = False

    def _on_store_problem(self, msg: str | None) -> None:
        """An autosave failed (msg) or works again (None): tell every client, not only the terminal."""
        if msg:
            self.notify("Autosave failed", msg, color="red")
        else:
            self.notify("Autosave works again", "the checkpoint is up to date", color="green")
        self._refresh_panel()

    def _greet(self, client: ClientHandle) -> None:
        """A newly connected client: its camera is watched (`camera_guard`), and it hears about a recovery or a
        standing autosave problem."""
        self.view.camera_guard.attach(client)
        rec = self.session.scan.store.recovery
        if rec is not None:
            title = ("Session recovered" if rec.verified_complete else "Session recovered with losses"
                     if not rec.complete else "Session recovered, not everything verifiable")
            self.notify(title, rec.summary(), client=client, color="yellow" if rec.complete else "red")
        if self.session.scan.store.problem:
            self.notify("Autosave failed", self.session.scan.store.problem, client=client, color="red")
        if self.session.instances.restored_typing:
            self.notify("Typed value restored", self.session.instances.restored_typing, client=client, color="yellow")

    def _forget_client(self, client: ClientHandle) -> None:
        """A client left: drop what the app kept for it (its cheat-sheet overlay)."""
        self._sheets.forget(client.client_id)
        self.view.camera_guard.forget(client)

    def run_reporting(self, fn: Callable[[], T], client: ClientHandle | None = None, *,
                      typing: bool = False) -> T | None:
        """Run an action for a client (a GUI callback, a hotkey, a scene gesture); errors become a notification to
        that client (all clients when None), never a crash and never only a log line.

        Every action but a keystroke in a text field (`typing`) first commits what was typed in the Name and
        Category fields (`AnnotatorSession.flush_typing`): doing anything else is leaving the field.

        A refused action (bad input: ValueError, KeyError, OSError) says why ("Not done"); anything else is a bug
        and is logged with its traceback and shown as "Error" with its type and message.

        Returns:
            What `fn` returned, or None after an error.
        """
        typed = 0
        try:
            if not typing:
                self._tls.defer_panel = True  # the action reads its own control before the panels are redrawn
                try:
                    typed = self.session.instances.flush_typing(refresh=False)
                finally:
                    self._tls.defer_panel = False
                typed = typed or bool(getattr(self._tls, "panel_due", False))
                self._tls.panel_due = False
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
        finally:
            if typed:
                self._refresh_panel()  # the typed fields now show what is stored

    def notify(self, title: str, body: str, *, client: ClientHandle | None = None,
               color: LiteralColor | None = None) -> None:
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
        self.session.instances.set_tool(tool)
        self._tls.syncing = True
        try:
            self.panels.gui_tool.value = tool
        finally:
            self._tls.syncing = False
        self.show_tool()

    def resize_brush(self, factor: float) -> float:
        """Multiply the brush radius by `factor` (the `[` / `]` keys, `AnnotatorSession.resize_brush`); the slider
        shows the new value. Returns the radius in metres."""
        radius = self.session.instances.resize_brush(factor)
        control = next((c for c in all_controls(self.session.toolbox.tools) if c.setting == "radius"), RADIUS)
        handle = self.panels.gui_controls.get("radius")
        if handle is not None:
            self.write_back(handle, round(radius * control.scale, 6))
        return radius

    def run_tool_hotkey(self, key: str) -> object:
        """A command hotkey (Enter, Esc): run the active tool's command with that key; nothing when it has none
        (the key may be meant for something else in the page)."""
        for cmd in self.tool.commands:
            if cmd.hotkey is not None and cmd.hotkey.upper() == key.upper():
                return cmd.run(self.session)
        return None

    def reset_view(self, client: ClientHandle | None = None) -> None:
        """Put a client's camera (every client's when None) back on the fitted view of the scan (R)."""
        self.view.camera_guard.reset(client)

    def toggle_cheat_sheet(self, client: ClientHandle | None) -> bool:
        """Open the keyboard cheat sheet (`?`) over one client's view, or close it when open; True when open now.

        Args:
            client: the client that pressed the key (None: every connected client).
        """
        return self._sheets.toggle([client] if client is not None else list(self.server.get_clients().values()))

    def set_labels_only(self, on: bool) -> None:
        """The labels-only view (unlabelled vertices dimmed) on or off; every chunk is redrawn."""
        self.session.toolbox.settings.labels_only = bool(on)
        self.write_back(self.panels.gui_labels_only, self.session.toolbox.settings.labels_only)
        self.view.redraw()

    def add_lasso_point(self, event: SceneClickEvent) -> int:
        """Lasso tool: a Ctrl/Cmd+click adds a screen point to the outline (`annotator.tools.lasso_click`).

        Raises:
            ClientValueError: the outline is full, or the click has no usable screen position.
        """
        try:
            return lasso_click(self.session, event)
        except ValueError as exc:
            raise ClientValueError(str(exc)) from None

    def _draw_lasso(self) -> None:
        self.view.draw_lasso()
        self.panels.enable_lasso(len(self.session.box_lasso.lasso_outline))

    # ---- files
    # ---- EFEM assist
    def step_prelabel(self, step: int, *, client: ClientHandle | None = None) -> int:
        """Select the next (`step` = 1) or previous (-1) unreviewed pre-label in the dropdown's order (most
        confident first, wrapping around; the first press goes to the first / last one) and fly the client's camera
        to it; returns its id.

        Raises:
            ValueError: no unreviewed pre-label is left.
        """
        ids = unreviewed_prelabels(self.session.scan.store.labelset.instances)
        if not ids:
            raise ValueError("no unreviewed pre-labels: import an EFEM result first")
        current = str(self.panels.gui_prelabel.value).split(":", 1)[0]
        started = self.session.assist.prelabel_cursor is not None
        iid = step_row(ids, int(current) if started and current.isdigit() else None, step)
        self.session.assist.prelabel_cursor = iid
        self.write_back(self.panels.gui_prelabel, _option_for(tuple(self.panels.gui_prelabel.options), iid))
        self.view.fly_to(np.flatnonzero(self.session.scan.store.labels == iid), client)
        return iid

    def run_efem(self, *, wait: bool = False) -> list[int] | None:
        """EFEM on the whole scan with the preset, proposal count, free-space mode and prior the EFEM assist folder
        shows (`AnnotatorSession.run_efem`); every value read is checked."""
        p = self.panels
        self.session.toolbox.settings.prior = read_choice(p.gui_prior)
        return self.session.assist.run_efem(preset=read_choice(p.gui_efem_preset),  # proposals 0: the preset's count
                                     proposals=read_int(p.gui_efem_proposals, write_back=self.write_back) or None,
                                     free_space=read_choice(p.gui_efem_free_space), wait=wait)

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment with the prior the dropdown shows (`AnnotatorSession.segment_at`)."""
        self.session.toolbox.settings.prior = read_choice(self.panels.gui_prior)
        return self.session.assist.segment_at(vertex, wait=wait)

    def _show_segmenting(self, percent: float | None) -> None:
        """The segment run's progress (None: it ended, or the preview changed) and the segment buttons."""
        if percent is not None:
            self.panels.gui_seg_progress.value = percent
            self.panels.gui_seg_progress.visible = True
        elif not self.session.assist.segmenting:
            self.panels.gui_seg_progress.visible = False
        self._enable_segment_buttons()

    def _show_warm_up(self, stage: str, done: int, total: int) -> None:
        """The tools' warm-up on the panel (`Panels.show_warm_up`; nothing once the app is closing)."""
        if not self._closed.is_set():
            self.panels.show_warm_up(stage, done, total)

    def _show_efem_run(self, text: str | None, percent: float | None) -> None:
        """An EFEM run on the scan on the panel (`Panels.show_efem_run`); when it ends, the pre-label cut moves to
        where "Accept all ≥ cut" accepts the best of the new pre-labels."""
        if self._closed.is_set():
            return
        self.panels.show_efem_run(text, percent)
        if text is None:
            cut = self.panels.gui_prelabel_cut
            cut.value = self.session.assist.prelabel_cut(float(cut.value))
            if self.session.assist.last_run_path is not None:  # the saved run, ready to import again
                self.panels.gui_efem_path.value = str(self.session.assist.last_run_path)

    def _enable_segment_buttons(self) -> None:
        ses = self.session
        self.panels.enable_segment(has_preview=ses.assist.pending_segment is not None, running=ses.assist.segmenting)

    # ================================================================== viser events
    def _on_scene_click(self, event: SceneClickEvent) -> None:
        self._edits.put(("click", event))

    def _on_rect(self, event: SceneRectSelectEvent) -> None:
        self._edits.put(("rect", event))

    async def _on_drag(self, event: SceneNodeDragEvent[MeshHandle]) -> None:
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
            if kind == "drag" and event.phase == "update":
                event = coalesce_drag_updates(self._edits, event)
            client = getattr(event, "client", None)
            try:
                self.run_reporting(lambda: self.handle_event(kind, event), client)
            except Exception:  # never let one bad event kill the edit thread
                log.exception("event %s failed", kind)
            finally:
                self._edits.task_done()

    def handle_event(self, kind: str, event: Any) -> None:
        """Process one viser event (click, rect or drag); runs on the edit thread (tests may call it directly).

        Raises:
            ClientValueError: the event carries non-finite or malformed coordinates (a scripted client).
        """
        check_event(kind, event)
        cid = f"client{getattr(event, 'client_id', '?')}"
        on_click = self.tool.on_click
        if kind == "click" and on_click is not None:
            with self.session.painting.edit_source(self.tool.label):
                on_click(self.session, event)
        elif kind == "click":
            v = self.session.painting.click(np.asarray(event.ray_origin), np.asarray(event.ray_direction), client=cid)
            if v is None and self.tool.apply_at is not None:
                self.notify("Missed the scan", MISSED_SCAN, client=getattr(event, "client", None), color="yellow")
        elif kind == "rect":
            cam = event.client.camera
            self.session.box_lasso.box(position=np.asarray(cam.position), wxyz=np.asarray(cam.wxyz), fov=float(cam.fov),
                     aspect=float(cam.aspect), screen_min=tuple(event.screen_min), screen_max=tuple(event.screen_max),
                     client=cid)
        elif kind == "drag" and event.phase == "start":
            self.session.painting.stroke_start(int(event.client_id), np.asarray(event.start_position), client=cid)
        elif kind == "drag":
            self.session.painting.stroke_to(int(event.client_id), np.asarray(event.client.camera.position),
                                   np.asarray(event.end_position), end=event.phase == "end", client=cid)
        self.server.flush()

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
            self.session.assist.join_jobs()  # an EFEM job stops at its next step, before the journal closes
            self.server.stop()
        finally:
            self.session.close()
            self.session.scan.stop_warm_up()  # a Ctrl+C right after start: the warm-up stops
            self._worker.join(timeout=10)
