"""GUI events → annotator actions: connects every control, button, palette command and hotkey of the `Panels` to
one session or app action.

Every client value is read through `efem_viz.serve.inputs` (clamped to the control's declared range, checked
against its options, bounded text), never used raw. A callback does nothing while the app sets a control itself
(`AnnotatorControls.quiet`), and its errors reach the client that acted (`AnnotatorControls.run_reporting`).
`AnnotatorControls` types what the events call, so this module does not import the app.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Literal, Protocol, Union

from annotator.tools import APP_KEYS, BRUSH_STEP, ToolCommand, all_controls
from efem_viz.serve.inputs import ClientValueError, read_bool, read_choice, read_number, read_rgb, read_text
from efem_viz.serve.table import option_id

if TYPE_CHECKING:
    from viser import ClientHandle, CommandEvent, GuiApi, GuiEvent, GuiInputHandle

    from annotator.panels import ControlHandle, Panels
    from annotator.session import AnnotatorSession

MAX_NAME = 200
"""Longest instance name / category accepted from a client."""

Event = Union["GuiEvent[Any]", "CommandEvent"]
"""What a GUI control or a palette command (hotkey) delivers."""
Callback = Callable[[Event], None]
"""A viser GUI or command callback."""


class AnnotatorControls(Protocol):
    """What the GUI events call: the app's own actions and its session (`annotator.app.AnnotatorApp`)."""

    @property
    def session(self) -> AnnotatorSession: ...
    @property
    def panels(self) -> Panels: ...

    def quiet(self) -> bool: ...
    def run_reporting(self, fn: Callable[[], object], client: ClientHandle | None = None, *,
                      typing: bool = False) -> object: ...
    def write_back(self, handle: GuiInputHandle[Any], value: object) -> None: ...
    def refuse(self, exc: ClientValueError, client: ClientHandle | None, handle: GuiInputHandle[Any],
               old: object) -> None: ...
    def show_tool(self) -> None: ...
    def set_tool(self, tool: str) -> None: ...
    def set_labels_only(self, on: bool) -> None: ...
    def step_prelabel(self, step: int, *, client: ClientHandle | None = None) -> int: ...
    def run_efem(self, *, wait: bool = False) -> list[int] | None: ...
    def run_tool_hotkey(self, key: str) -> object: ...
    def resize_brush(self, factor: float) -> float: ...
    def toggle_cheat_sheet(self, client: ClientHandle | None) -> bool: ...
    def reset_view(self, client: ClientHandle | None = None) -> None: ...


def wire(app: AnnotatorControls, gui: GuiApi) -> None:
    """Connect the panels, the tools' commands and the app's hotkeys to their actions."""
    _wire_settings(app)
    _wire_buttons(app)
    _wire_tool_commands(app, gui)
    _wire_app_keys(app, gui)


def _guarded(app: AnnotatorControls, fn: Callable[[], object]) -> Callback:
    """A GUI callback running `fn` for the client that acted (errors reported to it; nothing while the app sets a
    control itself)."""
    def cb(event: Event) -> None:
        if not app.quiet():
            app.run_reporting(fn, event.client)

    return cb


def _typed(app: AnnotatorControls, field: Literal["name", "category"], handle: GuiInputHandle[Any]) -> Callback:
    """A keystroke in a text field: buffered (`AnnotatorSession.type_text`), committed once when the field is left
    alone or the person does anything else; not an action itself, so it does not commit what is being typed."""
    def cb(event: Event) -> None:
        if app.quiet():
            return  # the app set the field itself
        app.run_reporting(lambda: app.session.instances.type_text(field, read_text(handle, max_len=MAX_NAME)),
                          event.client, typing=True)

    return cb


def _for_client(app: AnnotatorControls, fn: Callable[[ClientHandle | None], object]) -> Callback:
    """A GUI callback running `fn(client)` for the client that acted, errors reported to it."""
    def cb(event: Event) -> None:
        app.run_reporting(lambda: fn(event.client), event.client)

    return cb


def _wire_settings(app: AnnotatorControls) -> None:
    """The tool dropdown and the setting controls: every change re-reads them all into the settings."""
    s, p = app.session.toolbox.settings, app.panels
    controls = {c.setting: c for c in all_controls(app.session.toolbox.tools)}

    def read_one(name: str, handle: ControlHandle, client: ClientHandle | None) -> None:
        c = controls[name]
        try:
            if c.kind == "slider":
                value: float | str | bool = read_number(handle, write_back=app.write_back) / c.scale
            elif c.kind == "dropdown":
                value = read_choice(handle)
            else:
                value = read_bool(handle)
        except ClientValueError as exc:  # keep this setting; show it again where the bad value was
            old = s.value(name)
            app.refuse(exc, client, handle, round(float(old) * c.scale, 6) if c.kind == "slider" else old)
            return
        s.assign(name, value)

    def read_settings(event: Event) -> None:
        if app.quiet():
            return
        try:
            s.tool = read_choice(p.gui_tool)
        except ClientValueError as exc:
            app.refuse(exc, event.client, p.gui_tool, s.tool)
        for name, handle in p.gui_controls.items():
            read_one(name, handle, event.client)
        app.show_tool()

    p.gui_tool.on_update(read_settings)
    for h in p.gui_controls.values():
        h.on_update(read_settings)  # pyright: ignore[reportArgumentType]  # the handles' event type differs


def _wire_buttons(app: AnnotatorControls) -> None:
    """The panels' buttons and fields → session actions."""
    ses, p, wb = app.session, app.panels, app.write_back

    def on(fn: Callable[[], object]) -> Callback:
        return _guarded(app, fn)

    def prelabel() -> int:
        return option_id(read_choice(p.gui_prelabel))

    p.gui_active.on_update(on(lambda: ses.instances.set_active(option_id(read_choice(p.gui_active)))))
    p.gui_name.on_update(_typed(app, "name", p.gui_name))
    p.gui_category.on_update(_typed(app, "category", p.gui_category))
    p.gui_color.on_update(on(lambda: ses.instances.update_active(color=read_rgb(p.gui_color, write_back=wb))))
    p.gui_visible.on_update(on(lambda: ses.instances.update_active(visible=read_bool(p.gui_visible))))
    p.gui_labels_only.on_update(on(lambda: app.set_labels_only(read_bool(p.gui_labels_only))))
    p.gui_locked.on_update(on(lambda: ses.instances.update_active(locked=read_bool(p.gui_locked))))
    p.gui_new.on_click(on(lambda: ses.instances.new_instance(category=ses.toolbox.settings.category)))
    p.gui_merge.on_click(on(lambda: ses.instances.merge([ses.toolbox.settings.active_id],
                                                        option_id(read_choice(p.gui_merge_into)))))
    p.gui_delete.on_click(on(lambda: ses.instances.delete_instance(ses.toolbox.settings.active_id)))
    p.gui_undo.on_click(on(ses.instances.undo))
    p.gui_redo.on_click(on(ses.instances.redo))
    for fmt, button in (("ply", p.gui_export_ply), ("npz", p.gui_export_npz), ("scannet", p.gui_export_scannet)):
        button.on_click(on(lambda fmt=fmt: ses.files.export(fmt, frame=read_choice(p.gui_export_frame))))
    p.gui_import.on_click(on(lambda: ses.files.import_labels(read_text(p.gui_import_path))))
    def import_efem() -> None:
        ses.assist.import_efem(read_text(p.gui_efem_path))
        p.gui_prelabel_cut.value = ses.assist.prelabel_cut(float(p.gui_prelabel_cut.value))  # shows the best ones

    p.gui_efem_import.on_click(on(import_efem))
    p.gui_efem_run.on_click(on(lambda: app.run_efem()))
    p.gui_efem_cancel.on_click(on(ses.assist.cancel_efem))
    p.gui_accept.on_click(on(lambda: ses.assist.review_prelabel(prelabel(), "accept")))
    p.gui_reject.on_click(on(lambda: ses.assist.review_prelabel(prelabel(), "reject")))
    p.gui_accept_merge.on_click(on(lambda: ses.assist.review_prelabel(prelabel(), "merge")))
    p.gui_accept_above.on_click(on(lambda: ses.assist.review_prelabels(read_number(p.gui_prelabel_cut, write_back=wb),
                                                                "accept")))
    p.gui_reject_below.on_click(on(lambda: ses.assist.review_prelabels(read_number(p.gui_prelabel_cut, write_back=wb),
                                                                "reject")))
    p.gui_prelabel_next.on_click(_for_client(app, lambda client: app.step_prelabel(+1, client=client)))
    p.gui_prelabel_prev.on_click(_for_client(app, lambda client: app.step_prelabel(-1, client=client)))
    def choose_prior() -> None:  # the Run preset follows the prior: the chair prior runs "chairs" on a scan
        ses.toolbox.settings.prior = read_choice(p.gui_prior)
        app.write_back(p.gui_efem_preset, ses.assist.suggested_preset())

    p.gui_prior.on_update(on(choose_prior))
    ses.toolbox.settings.prior = read_choice(p.gui_prior)
    p.gui_seg_accept.on_click(on(ses.assist.accept_segment))
    p.gui_seg_cancel.on_click(on(ses.assist.discard_segment))


def _wire_tool_commands(app: AnnotatorControls, gui: GuiApi) -> None:
    """The tools' palette entries, buttons and command hotkeys."""
    command_keys: dict[str, list[str]] = {}
    """Command hotkeys → the labels of the commands (of different tools) that use them."""
    for t in app.session.toolbox.tools:
        gui.add_command(f"Tool: {t.label}", hotkey=t.hotkey).on_trigger(  # type: ignore[arg-type]
            _guarded(app, lambda name=t.name: app.set_tool(name)))
        for cmd in t.commands:
            def run(cmd: ToolCommand = cmd) -> object:
                return cmd.run(app.session)

            app.panels.gui_tool_buttons[cmd.key].on_click(_guarded(app, run))
            if cmd.hotkey:
                command_keys.setdefault(cmd.hotkey, []).append(cmd.label)
    for key, labels in command_keys.items():  # a command hotkey acts for the active tool
        gui.add_command(" / ".join(labels), hotkey=key).on_trigger(  # type: ignore[arg-type]
            _for_client(app, lambda _client, key=key: app.run_tool_hotkey(key)))


def _wire_app_keys(app: AnnotatorControls, gui: GuiApi) -> None:
    """The app's own hotkeys: the table `annotator.tools.APP_KEYS`, each action bound here."""
    ses = app.session
    actions: dict[str, Callback] = {
        "new_instance": _guarded(app, lambda: ses.instances.new_instance(category=ses.toolbox.settings.category)),
        "next_instance": _guarded(app, lambda: ses.instances.cycle_active(+1)),
        "previous_instance": _guarded(app, lambda: ses.instances.cycle_active(-1)),
        "toggle_visible": _guarded(app, lambda: ses.instances.toggle_active("visible")),
        "toggle_locked": _guarded(app, lambda: ses.instances.toggle_active("locked")),
        "brush_smaller": _guarded(app, lambda: app.resize_brush(1.0 / BRUSH_STEP)),
        "brush_larger": _guarded(app, lambda: app.resize_brush(BRUSH_STEP)),
        "undo": _guarded(app, ses.instances.undo),
        "redo": _guarded(app, ses.instances.redo),
        "cheat_sheet": _for_client(app, app.toggle_cheat_sheet),
        "reset_view": _for_client(app, app.reset_view),
    }
    for k in APP_KEYS:
        for key, modifier in k.bindings:
            gui.add_command(k.label, hotkey=key, modifier=modifier).on_trigger(  # type: ignore[arg-type]
                actions[k.action])
