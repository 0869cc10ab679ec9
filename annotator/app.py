"""The annotator's viser layer over the headless session: builds the GUI, turns GUI/scene events into session calls,
draws the scan through `annotator.scan_view.ScanView`.

Thin by design: every action (paint, grow, fill, box, lasso, pre-labels, click-to-segment, undo, export) is done by
`annotator.session.AnnotatorSession` (`self.session`), which is also the tools' host; callbacks read GUI values into
its `ToolSettings` and call it, and the label store's listener redraws the touched chunks (`ScanView.draw_delta`). The
app's action methods are the session's, so tests and scripts drive the same code paths without a browser.

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

import logging
import queue
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence, cast

import numpy as np

from annotator.labels import Delta, unreviewed_prelabels
from annotator.cheat_sheet import CheatSheets
from annotator.events import MISSED_SCAN, check_event, coalesce_drag_updates
from annotator.panel_views import NO_OPTIONS, panel_view, status_markdown
from annotator.session import AnnotatorSession, BrushCursor, Stroke
from annotator.scan_view import DISPLAY_POINTS, ScanView
from annotator.tools import (
    APP_KEYS,
    BRUSH_STEP,
    DEFAULT_TOOLS,
    RADIUS,
    TOOLS,
    Control,
    Tool,
    ToolSettings,
    all_controls,
    help_markdown,
    lasso_click,
    shown_settings,
)
from efem_viz.serve.guard import start_server
from efem_viz.serve.table import option_for as _option_for
from efem_viz.serve.table import option_id as _id_of
from efem_viz.serve.table import step_row
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
    from viser._messages import LiteralColor  # the colour names `add_notification` accepts

log = logging.getLogger(__name__)

__all__ = ["TOOLS", "AnnotatorApp", "ToolSettings"]

MAX_NAME = 200
"""Longest instance name / category accepted from a client."""

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
        display_points: display budget: a scan with more vertices is drawn from a subset of this many (every tool
            still labels all of them; see `annotator.scan_view`).
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
        display_points: int = DISPLAY_POINTS,
        accept_scan_mismatch: bool = False,
        token: str | None = None,
        tools: Sequence[Tool] = DEFAULT_TOOLS,
    ) -> None:
        t0 = time.perf_counter()
        self.session = AnnotatorSession(scan_path, labels_path=labels_path, out_dir=out_dir, max_points=max_points,
                                        autosave_delay=autosave_delay, accept_scan_mismatch=accept_scan_mismatch,
                                        tools=tools)
        """Every action and the state it acts on (`annotator.session`); this class draws it."""
        ses = self.session
        self.tools, self.scan_path, self.out_dir, self.stem = ses.tools, ses.scan_path, ses.out_dir, ses.stem
        self.work_dir = ses.work_dir
        self.scene, self.n, self.store, self.geom, self.settings = ses.scene, ses.n, ses.store, ses.geom, ses.settings
        self.lasso_outline = ses.lasso_outline
        # The actions the GUI offers, for tests and scripts that drive the app (the session does them).
        self.new_instance, self.update_instance, self.delete_instance = (ses.new_instance, ses.update_instance,
                                                                         ses.delete_instance)
        self.merge, self.undo, self.redo, self.cycle_active = ses.merge, ses.undo, ses.redo, ses.cycle_active
        self.set_active, self.choose_category, self.pick_instance = ses.set_active, ses.choose_category, ses.pick_instance
        self.paint, self.paint_stroke, self.dab, self.grow, self.fill = (ses.paint, ses.paint_stroke, ses.dab,
                                                                         ses.grow, ses.fill)
        self.click, self.box, self.lasso, self.move_cursor = ses.click, ses.box, ses.lasso, ses.move_cursor
        self.apply_lasso, self.clear_lasso = ses.apply_lasso, ses.clear_lasso
        self.export, self.import_labels, self.import_efem = ses.export, ses.import_labels, ses.import_efem
        self.add_prelabels, self.review_prelabel, self.review_prelabels = (ses.add_prelabels, ses.review_prelabel,
                                                                           ses.review_prelabels)
        self.set_preview, self.accept_segment, self.discard_segment = (ses.set_preview, ses.accept_segment,
                                                                       ses.discard_segment)
        self._sheets = CheatSheets(self.tools)
        self.cheat_sheets = self._sheets.open
        """The open `?` cheat-sheet overlays, by client id."""
        self._edits: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._tls = threading.local()
        self._closed = threading.Event()

        try:
            self.server, self.access = start_server(host=host, port=port, token=token)
        except BaseException:
            ses.close()
            raise
        try:
            self.server.gui.configure_theme(control_width="large")
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
        ses.on_segment, ses.report = self._show_segmenting, self._run_reporting
        ses.notify = lambda title, body: self.notify(title, body)  # late-bound: tests replace `notify`
        self.store.listeners.append(self._on_labels_changed)
        self.store.problem_listeners.append(self._on_store_problem)
        self.server.on_client_connect(self._greet)
        self.server.on_client_disconnect(self._forget_client)
        self._worker = threading.Thread(target=self._edit_loop, name="annotator-edits", daemon=True)
        self._worker.start()
        self._warmup = threading.Thread(target=self.geom.warm_up, name="annotator-warmup", daemon=True)
        self._warmup.start()
        self.open_s = time.perf_counter() - t0
        log.info("opened %s: %d vertices (%d drawn), %d chunks, %.2f s", self.scan_path.name, self.n,
                 len(self.view.display), self.view.chunks.count, self.open_s)

    # ================================================================== drawing
    @property
    def url(self) -> str:
        """The URL to open, with the access token (the machine's address for a 0.0.0.0 bind; the real port)."""
        return self.access.url

    @property
    def local_url(self) -> str:
        """The URL from this machine (127.0.0.1 for loopback and 0.0.0.0 binds), with the token."""
        return self.access.local_url

    def _on_labels_changed(self, d: Delta, how: str) -> None:
        t0 = time.perf_counter()
        sent = self.view.draw_delta(d)
        st = self.view.stats
        st.last_edit_bytes, st.last_edit_ms, st.edits = sent, 1000 * (time.perf_counter() - t0), st.edits + 1
        st.history = ([f"{how}: {d.label}"] + st.history)[:8]
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
        self._build_assist_folder()
        with gui.add_folder("Help", expand_by_default=False):
            self.gui_help = gui.add_markdown(help_markdown(self.tools))

        # ---- callbacks: read values into settings, call the action methods. Client values pass the checks of
        # efem_viz.serve.inputs (clamped to the declared slider range, dropdown options only, bounded text).
        self._wire_settings()
        self._wire_buttons()
        self._wire_tool_commands()
        self._wire_app_keys()
        self._show_tool()
        self._refresh_panel()

    def _build_assist_folder(self) -> None:
        """The EFEM assist folder: pre-label import and review, the Segment tool's prior and preview buttons."""
        gui = self.server.gui
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

    def _guarded(self, fn: Callable[[], Any]) -> Callable[[Any], None]:
        """A GUI callback running `fn` for the client that acted (errors reported to it; nothing while the app
        sets a control itself)."""
        def cb(event: Any) -> None:
            if getattr(self._tls, 'syncing', False):
                return
            self._run_reporting(lambda: fn(), getattr(event, "client", None))

        return cb

    def _wire_settings(self) -> None:
        """The tool dropdown and the setting controls: every change re-reads them all into `settings`."""
        s = self.settings
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
                    old = s.value(name)
                    self._refuse(exc, event, handle, round(old * c.scale, 6) if c.kind == "slider" else old)
                    continue
                s.assign(name, value)
            self._show_tool()

        self.gui_tool.on_update(read_settings)
        for h in self.gui_controls.values():
            h.on_update(read_settings)


    def _wire_buttons(self) -> None:
        """The panels' buttons and fields → session actions."""
        wb = self._gui_write_back
        guarded = self._guarded

        def text(h: Any) -> str:
            return read_text(h, max_len=MAX_NAME)

        self.gui_active.on_update(guarded(lambda: self.set_active(_id_of(read_choice(self.gui_active)))))
        self.gui_name.on_update(guarded(lambda: self.session.update_active(name=text(self.gui_name))))
        self.gui_category.on_update(guarded(lambda: self.choose_category(text(self.gui_category))))
        self.gui_color.on_update(guarded(lambda: self.session.update_active(color=read_rgb(self.gui_color, write_back=wb))))
        self.gui_visible.on_update(guarded(lambda: self.session.update_active(visible=read_bool(self.gui_visible))))
        self.gui_labels_only.on_update(guarded(lambda: self.set_labels_only(read_bool(self.gui_labels_only))))
        self.gui_locked.on_update(guarded(lambda: self.session.update_active(locked=read_bool(self.gui_locked))))
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
        self.gui_prior.on_update(guarded(lambda: setattr(self.settings, "prior", read_choice(self.gui_prior))))
        self.settings.prior = read_choice(self.gui_prior)
        self.gui_seg_accept.on_click(guarded(lambda: self.accept_segment()))
        self.gui_seg_cancel.on_click(guarded(lambda: self.discard_segment()))
    def _wire_tool_commands(self) -> None:
        """The tools' palette entries, buttons and command hotkeys."""
        gui = self.server.gui
        guarded = self._guarded
        command_keys: dict[str, list[str]] = {}
        """Command hotkeys → the labels of the commands (of different tools) that use them."""
        for t in self.tools:  # the tools' buttons and hotkeys
            gui.add_command(f"Tool: {t.label}", hotkey=t.hotkey).on_trigger(  # type: ignore[arg-type]
                guarded(lambda name=t.name: self.set_tool(name)))
            for cmd in t.commands:
                def run(cmd: Any = cmd) -> object:
                    return cmd.run(self.session)

                self.gui_tool_buttons[cmd.key].on_click(guarded(run))
                if cmd.hotkey:
                    command_keys.setdefault(cmd.hotkey, []).append(cmd.label)
        for key, labels in command_keys.items():  # a command hotkey acts for the active tool
            gui.add_command(" / ".join(labels), hotkey=key).on_trigger(  # type: ignore[arg-type]
                lambda event, key=key: self._run_reporting(lambda: self.run_tool_hotkey(key), event.client))


    def _wire_app_keys(self) -> None:
        """The app's own hotkeys: the table `annotator.tools.APP_KEYS`, each action bound to a method here."""
        gui = self.server.gui
        guarded = self._guarded
        actions: dict[str, Callable[[Any], None]] = {
            "new_instance": guarded(
                lambda: self.new_instance(category=self.settings.category)),
            "next_instance": guarded(lambda: self.cycle_active(+1)),
            "previous_instance": guarded(lambda: self.cycle_active(-1)),
            "toggle_visible": guarded(lambda: self.session.toggle_active("visible")),
            "toggle_locked": guarded(lambda: self.session.toggle_active("locked")),
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

    # ---- tool table → GUI
    @property
    def tool(self) -> Tool:
        """The active tool's entry."""
        return self.session.tool

    def _add_control(self, c: Control) -> GuiInputHandle[Any]:
        """Create a setting control; a setting with a `ToolSettings` field starts at its value."""
        gui, initial = self.server.gui, self.settings.shown_initial(c)
        if c.kind == "slider":
            return gui.add_slider(c.label, min=c.min, max=c.max, step=c.step, initial_value=cast(float, initial),
                                  hint=c.hint)
        if c.kind == "dropdown":
            return gui.add_dropdown(c.label, c.options, initial_value=str(initial), hint=c.hint)
        return gui.add_checkbox(c.label, bool(initial), hint=c.hint)

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
        self.session.refresh_cursor()

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
        """Push counts, progress, the instance list and the active instance's fields to the GUI
        (`annotator.panel_views.panel_view`)."""
        if not hasattr(self, "gui_table"):
            return
        v = panel_view(self.store, self.settings.active_id, history=self.view.stats.history)
        self._tls.syncing = True
        try:
            self.settings.active_id = v.active_id
            self.gui_active.options = v.options
            self.gui_merge_into.options = v.options
            self.gui_active.value = _option_for(v.options, v.active_id)
            current = str(self.gui_prelabel.value).split(":", 1)[0]
            self.gui_prelabel.options = v.prelabel_options
            if current.isdigit() and current in {o.split(":", 1)[0] for o in v.prelabel_options}:
                self.gui_prelabel.value = _option_for(v.prelabel_options, int(current))  # keep the one under review
            if v.active is not None:
                self.gui_name.value, self.gui_category.value = v.active.name, v.active.category
                self.gui_color.value, self.gui_visible.value = v.active.color, v.active.visible
                self.gui_locked.value = v.active.locked
            self.gui_progress.value = round(100.0 * v.progress, 2)
            self.gui_table.content, self.gui_history.content = v.table, v.history
            self.gui_status.content = status_markdown(self.store, self.work_dir,
                                                      last_edit_bytes=self.view.stats.last_edit_bytes,
                                                      last_edit_ms=self.view.stats.last_edit_ms)
        finally:
            self._tls.syncing = False

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
        self.view.camera_guard.attach(client)
        rec = self.store.recovery
        if rec is not None:
            title = ("Session recovered" if rec.verified_complete else "Session recovered with losses"
                     if not rec.complete else "Session recovered, not everything verifiable")
            self.notify(title, rec.summary(), client=client, color="yellow" if rec.complete else "red")
        if self.store.problem:
            self.notify("Autosave failed", self.store.problem, client=client, color="red")

    def _forget_client(self, client: ClientHandle) -> None:
        """A client left: drop what the app kept for it (its cheat-sheet overlay)."""
        self._sheets.forget(client.client_id)
        self.view.camera_guard.forget(client)

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
        self.session.set_tool(tool)
        self._tls.syncing = True
        try:
            self.gui_tool.value = tool
        finally:
            self._tls.syncing = False
        self._show_tool()

    @property
    def cursor(self) -> BrushCursor | None:
        """The brush cursor (`AnnotatorSession.cursor`)."""
        return self.session.cursor

    @property
    def preview(self) -> np.ndarray | None:
        """(N,) bool, the segment preview drawn highlighted (`AnnotatorSession.preview`)."""
        return self.session.preview

    @property
    def pending_segment(self) -> np.ndarray | None:
        """(K,) int32, the previewed segment's vertices (`AnnotatorSession.pending_segment`)."""
        return self.session.pending_segment

    @property
    def segmenting(self) -> bool:
        """Whether a click-to-segment run is in progress."""
        return self.session.segmenting

    @property
    def _strokes(self) -> dict[int, Stroke]:
        return self.session.strokes

    def resize_brush(self, factor: float) -> float:
        """Multiply the brush radius by `factor` (the `[` / `]` keys, `AnnotatorSession.resize_brush`); the slider
        shows the new value. Returns the radius in metres."""
        radius = self.session.resize_brush(factor)
        control = next((c for c in all_controls(self.tools) if c.setting == "radius"), RADIUS)
        handle = self.gui_controls.get("radius")
        if handle is not None:
            self._gui_write_back(handle, round(radius * control.scale, 6))
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
        self.settings.labels_only = bool(on)
        self._gui_write_back(self.gui_labels_only, self.settings.labels_only)
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
        n = len(self.lasso_outline)
        buttons = getattr(self, "gui_tool_buttons", {})  # the lasso's buttons (absent from a table without it)
        for key, disabled in (("lasso_apply", n < 3), ("lasso_clear", n == 0)):
            if key in buttons:
                buttons[key].disabled = disabled

    # ---- files
    # ---- EFEM assist
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
        started = self.session.prelabel_cursor is not None
        iid = step_row(ids, int(current) if started and current.isdigit() else None, step)
        self.session.prelabel_cursor = iid
        self._gui_write_back(self.gui_prelabel, _option_for(tuple(self.gui_prelabel.options), iid))
        self.view.fly_to(np.flatnonzero(self.store.labels == iid), client)
        return iid

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment with the prior the dropdown shows (`AnnotatorSession.segment_at`)."""
        self.settings.prior = read_choice(self.gui_prior)
        return self.session.segment_at(vertex, wait=wait)

    def _show_segmenting(self, percent: float | None) -> None:
        """The segment run's progress (None: it ended, or the preview changed) and the segment buttons."""
        if percent is not None:
            self.gui_seg_progress.value = percent
            self.gui_seg_progress.visible = True
        elif not self.session.segmenting:
            self.gui_seg_progress.visible = False
        self._enable_segment_buttons()

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
            if kind == "drag" and event.phase == "update":
                event = coalesce_drag_updates(self._edits, event)
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
        check_event(kind, event)
        cid = f"client{getattr(event, 'client_id', '?')}"
        on_click = self.tool.on_click
        if kind == "click" and on_click is not None:
            with self.session.edit_source(self.tool.label):
                on_click(self.session, event)
        elif kind == "click":
            v = self.click(np.asarray(event.ray_origin), np.asarray(event.ray_direction), client=cid)
            if v is None and self.tool.apply_at is not None:
                self.notify("Missed the scan", MISSED_SCAN, client=getattr(event, "client", None), color="yellow")
        elif kind == "rect":
            cam = event.client.camera
            self.box(position=np.asarray(cam.position), wxyz=np.asarray(cam.wxyz), fov=float(cam.fov),
                     aspect=float(cam.aspect), screen_min=tuple(event.screen_min), screen_max=tuple(event.screen_max),
                     client=cid)
        elif kind == "drag" and event.phase == "start":
            self.session.stroke_start(int(event.client_id), np.asarray(event.start_position), client=cid)
        elif kind == "drag":
            self.session.stroke_to(int(event.client_id), np.asarray(event.client.camera.position),
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
            self.server.stop()
        finally:
            self.session.close()
            # A Ctrl+C right after start must not exit while open3d builds its ray-casting scene in the warm-up
            # thread (open3d then reports leaks and the process exits with status 1).
            self._warmup.join(timeout=60)
            self._worker.join(timeout=10)
