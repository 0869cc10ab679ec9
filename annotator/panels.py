"""The annotator's GUI panels: the viser handles (`Panels`) and what writes a moment's state into them.

Callbacks are wired in `annotator.wiring`; the text and options shown are computed in `annotator.panel_views`. The
GUI is shared (`server.gui`): every connected browser sees and drives the same controls.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence, Union, get_args

from annotator.io import EXPORT_FRAMES
from annotator.panel_views import NO_OPTIONS, PanelView
from annotator.tools import Control, Tool, ToolSettings, all_controls, help_markdown, shown_settings
from efem_viz.em.config import PRESETS, FreeSpaceMode
from efem_viz.serve.table import option_for

if TYPE_CHECKING:
    from viser import (
        GuiApi,
        GuiButtonHandle,
        GuiCheckboxHandle,
        GuiDropdownHandle,
        GuiMarkdownHandle,
        GuiNumberHandle,
        GuiRgbHandle,
        GuiSliderHandle,
        GuiTextHandle,
    )
    from viser._gui_handles import GuiProgressBarHandle  # not re-exported by viser 1.1

    ControlHandle = Union[GuiSliderHandle[float], GuiDropdownHandle[str], GuiCheckboxHandle]
    """The handle of a tool setting's control (`annotator.tools.Control.kind`)."""


def _add_control(gui: GuiApi, c: Control, settings: ToolSettings) -> ControlHandle:
    """Create a setting control; a setting with a `ToolSettings` field starts at its value."""
    initial = settings.shown_initial(c)
    if c.kind == "slider":
        return gui.add_slider(c.label, min=c.min, max=c.max, step=c.step, initial_value=float(initial), hint=c.hint)
    if c.kind == "dropdown":
        return gui.add_dropdown(c.label, c.options, initial_value=str(initial), hint=c.hint)
    return gui.add_checkbox(c.label, bool(initial), hint=c.hint)


class Panels:
    """All GUI handles of the annotator, grouped as the folders show them. Names start with `gui_`."""

    # ---- Tools
    gui_tool: GuiDropdownHandle[str]
    gui_tool_help: GuiMarkdownHandle
    """The active tool's hotkey and help line."""
    gui_controls: dict[str, ControlHandle]
    """The tools' setting controls by setting name (`annotator.tools.Control`)."""
    gui_tool_buttons: dict[str, GuiButtonHandle]
    """The tools' buttons by command key (`annotator.tools.ToolCommand`)."""
    gui_seg_progress: GuiProgressBarHandle
    """Click-to-segment's progress (EM steps done), shown while it runs."""
    gui_tools_progress: GuiProgressBarHandle
    """The tools' structures built after opening a scan (`ScanGeometry.warm_up`), shown until all are ready."""
    gui_tools_status: GuiMarkdownHandle
    """What the warm-up builds now and what already works."""
    # ---- Instances
    gui_active: GuiDropdownHandle[str]
    gui_name: GuiTextHandle
    gui_category: GuiTextHandle
    gui_color: GuiRgbHandle
    gui_new: GuiButtonHandle
    gui_labels_only: GuiCheckboxHandle
    gui_visible: GuiCheckboxHandle
    gui_locked: GuiCheckboxHandle
    gui_merge_into: GuiDropdownHandle[str]
    gui_merge: GuiButtonHandle
    gui_delete: GuiButtonHandle
    gui_progress: GuiProgressBarHandle
    gui_table: GuiMarkdownHandle
    # ---- History
    gui_undo: GuiButtonHandle
    gui_redo: GuiButtonHandle
    gui_history: GuiMarkdownHandle
    # ---- Files
    gui_status: GuiMarkdownHandle
    gui_export_frame: GuiDropdownHandle[str]
    gui_export_ply: GuiButtonHandle
    gui_export_npz: GuiButtonHandle
    gui_export_scannet: GuiButtonHandle
    gui_import_path: GuiTextHandle
    gui_import: GuiButtonHandle
    # ---- EFEM assist
    gui_efem_run: GuiButtonHandle
    """Run EFEM on the open scan (its instances become pre-labels)."""
    gui_efem_preset: GuiDropdownHandle[str]
    gui_efem_proposals: GuiNumberHandle[int]
    gui_efem_free_space: GuiDropdownHandle[str]
    gui_efem_cancel: GuiButtonHandle
    gui_efem_progress: GuiProgressBarHandle
    gui_efem_status: GuiMarkdownHandle
    """What the EFEM run is doing (at the bottom of the folder, below every button)."""
    gui_efem_path: GuiTextHandle
    gui_efem_import: GuiButtonHandle
    gui_prelabel: GuiDropdownHandle[str]
    gui_prelabel_prev: GuiButtonHandle
    gui_prelabel_next: GuiButtonHandle
    gui_accept: GuiButtonHandle
    gui_reject: GuiButtonHandle
    gui_accept_merge: GuiButtonHandle
    gui_prelabel_cut: GuiSliderHandle[float]
    gui_accept_above: GuiButtonHandle
    gui_reject_below: GuiButtonHandle
    gui_prior: GuiDropdownHandle[str]
    gui_seg_accept: GuiButtonHandle
    gui_seg_cancel: GuiButtonHandle
    # ---- Help
    gui_help: GuiMarkdownHandle

    def __init__(self, gui: GuiApi, tools: Sequence[Tool], settings: ToolSettings, *,
                 efem_result: str, priors: tuple[str, ...], prior: str, preset: str = "real") -> None:
        """Create the folders and their handles (Tools, Instances, EFEM assist, History, Files, Instance table, Edit
        history, Help): every folder with buttons comes before the text that grows.

        Args:
            gui: the server's GUI.
            tools: the tool table (toolbar order).
            settings: the tool settings the controls start from.
            efem_result: the EFEM result path shown at start ("" for none).
            priors: the Segment tool's priors; `prior` is selected.
            preset: the EFEM run's preset shown at start (the one that fits the scan).
        """
        with gui.add_folder("Tools"):
            self.gui_tool = gui.add_dropdown("Tool", tuple(t.name for t in tools), initial_value=settings.tool,
                                             hint="Ctrl/Cmd+drag paints; Ctrl/Cmd+click applies the tool")
            self.gui_tool_help = gui.add_markdown("")
            self.gui_controls = {c.setting: _add_control(gui, c, settings) for c in all_controls(tools)}
            self.gui_tool_buttons = {
                cmd.key: gui.add_button(f"{cmd.label} ({cmd.hotkey})" if cmd.hotkey else cmd.label,
                                        disabled=cmd.disabled, hint=cmd.hint)
                for t in tools for cmd in t.commands}
            self.gui_seg_progress = gui.add_progress_bar(0.0, visible=False)
            # below every tool button: the words grow and go while a person clicks
            self.gui_tools_progress = gui.add_progress_bar(0.0, visible=False)
            self.gui_tools_status = gui.add_markdown("")
        with gui.add_folder("Instances"):
            self.gui_active = gui.add_dropdown("Active", NO_OPTIONS)
            self.gui_name = gui.add_text("Name", "")
            self.gui_category = gui.add_text("Category", settings.category,
                                             hint="the active instance's category; new instances (N) take "
                                                  "the one chosen last")
            self.gui_color = gui.add_rgb("Colour", (255, 0, 0))
            self.gui_new = gui.add_button("New instance (N)")
            self.gui_labels_only = gui.add_checkbox("Labels only", False,
                                                    hint="dim unlabelled vertices, so what is labelled stands out")
            self.gui_visible = gui.add_checkbox("Visible", True)
            self.gui_locked = gui.add_checkbox("Locked", False)
            self.gui_merge_into = gui.add_dropdown("Merge active into", NO_OPTIONS)
            self.gui_merge = gui.add_button("Merge")
            self.gui_delete = gui.add_button("Delete active", color="red")
            self.gui_progress = gui.add_progress_bar(0.0)
        with gui.add_folder("EFEM assist", expand_by_default=False):
            self.gui_efem_run = gui.add_button(
                "Run EFEM on this scan",
                hint="its instances become pre-labels to review (the settings and the prior below)")
            self.gui_efem_cancel = gui.add_button("Cancel EFEM run", disabled=True)
            # Cancel, the run's progress and its words right under Run, the run's settings after them: in view where
            # Run is clicked on a small window (below the settings they fell below the fold); they show while a run goes
            self.gui_efem_progress = gui.add_progress_bar(0.0, visible=False)
            self.gui_efem_status = gui.add_markdown("")
            self.gui_efem_preset = gui.add_dropdown("Run preset", PRESETS, initial_value=preset,
                                                    hint="'real' for single-view captures, 'fast' for a quick look")
            self.gui_efem_proposals = gui.add_number(
                "Proposals", 0, min=0, max=2000, step=10,
                hint="0: the preset's (real 120, fast 80); more finds more, slower")
            self.gui_efem_free_space = gui.add_dropdown(
                "Free space", get_args(FreeSpaceMode), initial_value="auto",
                hint="remove fits the scan's cameras saw through: auto = the preset's (on for 'real'); "
                     "'on' adds it for a fused scan with several cameras; 'off' keeps every fit")
            self.gui_efem_path = gui.add_text("EFEM result", efem_result)
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
            self.gui_prior = gui.add_dropdown("Prior for Segment tool", priors, initial_value=prior)
            self.gui_seg_accept = gui.add_button("Accept segment preview", disabled=True)
            self.gui_seg_cancel = gui.add_button("Discard segment preview", disabled=True)
        with gui.add_folder("History"):
            self.gui_undo = gui.add_button("Undo (Ctrl+Z)")
            self.gui_redo = gui.add_button("Redo (Ctrl+Y)")
        with gui.add_folder("Files", expand_by_default=False):
            self.gui_export_frame = gui.add_dropdown(
                "Export frame", EXPORT_FRAMES, initial_value="scene",
                hint="original: a scan brought in by import-scan is written back on its file's own coordinates and "
                     "units (labels always follow the file's vertex order)")
            self.gui_export_ply = gui.add_button("Export PLY")
            self.gui_export_npz = gui.add_button("Export NPZ")
            self.gui_export_scannet = gui.add_button("Export ScanNet JSON")
            self.gui_import_path = gui.add_text("Import labels from", "", hint="path inside the scan or output folder")
            self.gui_import = gui.add_button("Import labels (undoable)")
            self.gui_status = gui.add_markdown("")  # below its buttons: they never move
        # Text that grows (the instance table, the edit history) sits below every button, so that nothing above a
        # button changes height while a person is clicking it (Accept, Reject, Next, Undo...).
        with gui.add_folder("Instance table"):
            self.gui_table = gui.add_markdown("")
        with gui.add_folder("Edit history"):
            self.gui_history = gui.add_markdown("")
        with gui.add_folder("Help", expand_by_default=False):
            self.gui_help = gui.add_markdown(help_markdown(tools))

    # ---- what the app shows (call these with the app's callbacks silenced)
    def show_tool(self, tool: Tool, tools: Sequence[Tool]) -> None:
        """Show a tool's controls, buttons and help line; hide the other tools' controls and buttons."""
        shown = shown_settings(tool)
        for name, h in self.gui_controls.items():
            h.visible = name in shown
        mine = {cmd.key for cmd in tool.commands}
        for key, button in self.gui_tool_buttons.items():
            button.visible = key in mine
        self.gui_tool_help.content = f"**{tool.hotkey}** {tool.label}: {tool.help}"
        self.gui_help.content = help_markdown(tools, tool.name)

    def show(self, v: PanelView, status: str, *, typing: frozenset[str] = frozenset()) -> None:
        """Counts, progress, the instance list and the active instance's fields (`annotator.panel_views`); the
        text fields in `typing` keep what the person is typing (committed later, then shown as stored)."""
        self.gui_active.options = v.options
        self.gui_merge_into.options = v.options
        self.gui_active.value = option_for(v.options, v.active_id)
        current = str(self.gui_prelabel.value).split(":", 1)[0]
        self.gui_prelabel.options = v.prelabel_options
        if current.isdigit() and current in {o.split(":", 1)[0] for o in v.prelabel_options}:
            self.gui_prelabel.value = option_for(v.prelabel_options, int(current))  # keep the one under review
        if v.active is not None:
            if "name" not in typing:
                self.gui_name.value = v.active.name
            if "category" not in typing:
                self.gui_category.value = v.active.category
            self.gui_color.value, self.gui_visible.value = v.active.color, v.active.visible
            self.gui_locked.value = v.active.locked
        self.gui_progress.value = round(100.0 * v.progress, 2)
        self.gui_table.content, self.gui_history.content = v.table, v.history
        self.gui_status.content = status

    def enable_lasso(self, n_points: int) -> None:
        """The lasso's buttons: Apply needs 3 outline points, Clear one (absent from a table without the lasso)."""
        for key, disabled in (("lasso_apply", n_points < 3), ("lasso_clear", n_points == 0)):
            if key in self.gui_tool_buttons:
                self.gui_tool_buttons[key].disabled = disabled

    def show_warm_up(self, stage: str, done: int, total: int) -> None:
        """The tools' structures being built after the scan opened (big scans: seconds): what is built now and
        what already works; hidden once every one is ready (`ScanGeometry.warm_up`'s stages)."""
        ready = done >= total
        self.gui_tools_progress.visible = not ready
        self.gui_tools_progress.value = round(100.0 * done / max(total, 1), 1)
        if ready:
            self.gui_tools_status.content = ""
            return
        works = ("" if done == 0 else " The brush works already" + (
            " (picking by vertices); lasso visibility waits for the ray caster." if stage == "ray caster" else "."))
        self.gui_tools_status.content = f"Preparing the tools ({done + 1} of {total}): {stage} …{works}"

    def show_efem_run(self, text: str | None, percent: float | None) -> None:
        """An EFEM run on the scan: its words and progress, Run / Cancel enabled to match (None: it ended)."""
        running = text is not None
        self.gui_efem_status.content = text or ""
        if percent is not None:
            self.gui_efem_progress.value = percent
        self.gui_efem_progress.visible = running
        self.gui_efem_run.disabled = running
        self.gui_efem_cancel.disabled = not running

    def enable_segment(self, *, has_preview: bool, running: bool) -> None:
        """Accept needs a segment preview; Discard a preview or a run to cancel (the Tools and EFEM assist ones)."""
        self.gui_seg_accept.disabled = not has_preview
        self.gui_seg_cancel.disabled = not has_preview
        if "segment_accept" in self.gui_tool_buttons:
            self.gui_tool_buttons["segment_accept"].disabled = not has_preview
        if "segment_discard" in self.gui_tool_buttons:
            self.gui_tool_buttons["segment_discard"].disabled = not (has_preview or running)
