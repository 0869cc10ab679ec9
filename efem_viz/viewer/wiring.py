"""GUI events → viewer actions: connects every control of the `Panels` to one `ViewerApp` method.

Every client value is read through `efem_viz.serve.inputs` (clamped to the control's declared range, checked
against its options), never used raw. A callback does nothing while the app sets a control itself (`quiet`), and
an error in it is shown in the status line (the server stays up). `ViewerControls` types what the events call, so
this module does not import the app. No viser import at run time.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol, TypeVar, cast

from efem_viz.serve.inputs import ClientValueError, read_bool, read_choice, read_int, read_number
from efem_viz.serve.table import NO_ROW, option_id
from efem_viz.viewer.panels import COLOR_MODES, VIEW_MODES
from efem_viz.viewer.parts.runs import RunSettings
from efem_viz.viewer.texts import parse_pid

if TYPE_CHECKING:
    from typing_extensions import TypeVarTuple, Unpack  # typing has them from Python 3.11 only
    from viser import ClientHandle, GuiInputHandle

    from efem_viz.em.config import FreeSpaceMode, PresetName, SolvePrecision
    from efem_viz.viewer.export_tab import ExportTab
    from efem_viz.viewer.instance_table import InstanceTable
    from efem_viz.viewer.panels import Panels
    from efem_viz.viewer.playback import Playback
    from efem_viz.viewer.session import ViewerSession
    from efem_viz.viewer.state import ViewerState, ViewMode

logger = logging.getLogger(__name__)

T = TypeVar("T")
ValueT = TypeVar("ValueT")
if TYPE_CHECKING:
    Ts = TypeVarTuple("Ts")


class ViewerControls(Protocol):
    """The viewer actions the GUI events call (`efem_viz.viewer.app.ViewerApp`): its own, and its parts'."""

    panels: Panels
    session: ViewerSession
    playback: Playback
    instance_table: InstanceTable
    export_tab: ExportTab

    @property
    def state(self) -> ViewerState: ...
    def quiet(self) -> bool: ...
    def report_error(self, text: str) -> None: ...
    def gui_set(self, handle: GuiInputHandle[ValueT], value: ValueT) -> None: ...
    def submit_work(self, fn: Callable[[Unpack[Ts]], T], *args: Unpack[Ts]) -> Future[T]: ...
    def open_scene(self, name: str) -> bool: ...
    def choose_preset(self, name: str) -> None: ...
    def load_trace(self, path: str | Path | None = None) -> bool: ...
    def set_display(self, display: str) -> None: ...
    def set_color_mode(self, mode: str) -> None: ...
    def set_point_size(self, size_m: float) -> None: ...
    def start_run(self, settings: RunSettings | None = ..., **knobs: Any) -> object: ...
    def set_view_mode(self, mode: str) -> None: ...
    def set_step(self, step: int, *, view_mode: ViewMode = ...) -> None: ...
    def set_proposal_layers(self, *, shapes: bool | None = ..., samples: bool | None = ...) -> None: ...
    def set_max_shapes(self, n: int) -> None: ...
    def select_proposal(self, pid: int | None) -> object: ...
    def set_threshold(self, threshold: float, *, by_user: bool = True) -> None: ...
    def set_mask_band(self, tau_out: float) -> bool: ...
    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None: ...
    def reset_view(self, client: ClientHandle | None = ...) -> None: ...


def row_id(option: str) -> int | None:
    """The proposal id of an instance-table option (None for `NO_ROW`)."""
    return None if option == NO_ROW else option_id(option)


def guarded(app: ViewerControls, fn: Callable[[], object]) -> Callable[[object], None]:
    """A callback running `fn` unless the app is setting a control itself; errors go to the status line.

    The callback takes any event (`viser.GuiEvent` of any control) and ignores it."""
    def cb(_event: object) -> None:
        if app.quiet():
            return
        try:
            fn()
        except ClientValueError as exc:  # a value no control can produce: one line, no traceback
            app.report_error(str(exc))
        except Exception as exc:  # noqa: BLE001
            logger.exception("callback failed")
            app.report_error(f"error: {exc}")

    return cb


def wire(app: ViewerControls) -> None:
    """Connect the controls of `app.panels` to the app's actions."""
    p = app.panels
    wb = app.gui_set  # shows a clamped value in every client without re-entering the callback

    def guard(fn: Callable[[], object]) -> Callable[[object], None]:
        return guarded(app, fn)

    def layers() -> None:
        app.set_result_layers(meshes=read_bool(p.gui_show_meshes), obbs=read_bool(p.gui_show_obbs),
                              axes=read_bool(p.gui_show_axes))

    p.gui_scene.on_update(guard(lambda: app.submit_work(app.open_scene, read_choice(p.gui_scene))))
    p.gui_display.on_update(guard(lambda: app.set_display(read_choice(p.gui_display))))
    p.gui_color.on_update(guard(lambda: app.set_color_mode(COLOR_MODES[read_choice(p.gui_color)])))
    p.gui_point_size.on_update(
        guard(lambda: app.set_point_size(read_number(p.gui_point_size, write_back=wb) / 1000.0)))
    p.gui_run.on_click(
        guard(lambda: app.start_run(RunSettings(preset=cast("PresetName", read_choice(p.gui_preset)),
                                                proposals=read_int(p.gui_proposals, write_back=wb),
                                                seed=read_int(p.gui_seed, write_back=wb),
                                                matmul_dtype=cast("SolvePrecision", read_choice(p.gui_precision)),
                                                free_space=cast("FreeSpaceMode", read_choice(p.gui_free_space)))))
    )
    p.gui_preset.on_update(guard(lambda: app.choose_preset(read_choice(p.gui_preset))))
    p.gui_proposals.on_update(guard(lambda: setattr(app.state, "proposals_by_user", True)))
    p.gui_cancel.on_click(guard(app.session.runs.cancel_run))
    p.gui_load.on_click(guard(lambda: app.submit_work(app.load_trace)))
    p.gui_view_mode.on_update(guard(lambda: app.set_view_mode(VIEW_MODES[read_choice(p.gui_view_mode)])))
    p.gui_step.on_update(guard(lambda: app.set_step(read_int(p.gui_step))))
    p.gui_play.on_click(guard(app.playback.toggle))
    p.gui_speed.on_update(guard(lambda: setattr(app.state, "speed", read_number(p.gui_speed, write_back=wb))))
    p.gui_show_shapes.on_update(guard(lambda: app.set_proposal_layers(shapes=read_bool(p.gui_show_shapes))))
    p.gui_show_samples.on_update(guard(lambda: app.set_proposal_layers(samples=read_bool(p.gui_show_samples))))
    p.gui_max_shapes.on_update(guard(lambda: app.set_max_shapes(read_int(p.gui_max_shapes, write_back=wb))))
    p.gui_proposal.on_update(guard(lambda: app.select_proposal(parse_pid(read_choice(p.gui_proposal)))))
    p.gui_threshold.on_update(guard(lambda: app.set_threshold(read_number(p.gui_threshold))))
    p.gui_mask_band.on_update(guard(lambda: app.submit_work(app.set_mask_band, read_number(p.gui_mask_band))))
    for h in (p.gui_show_meshes, p.gui_show_obbs, p.gui_show_axes):
        h.on_update(guard(layers))
    table = app.instance_table
    p.gui_instance.on_update(guard(lambda: table.choose_instance(row_id(read_choice(p.gui_instance)))))
    p.gui_instance_visible.on_update(
        guard(lambda: table.set_instance_visible(app.state.table_row, read_bool(p.gui_instance_visible))))
    p.gui_fly_to.on_click(
        lambda event: guard(lambda: table.fly_to_instance(app.state.table_row, client=event.client))(event))
    p.gui_instance_prev.on_click(lambda event: guard(lambda: table.step_instance(-1, client=event.client))(event))
    p.gui_instance_next.on_click(lambda event: guard(lambda: table.step_instance(+1, client=event.client))(event))
    p.gui_reset_view.on_click(lambda event: app.reset_view(event.client))
    p.gui_export_results.on_click(guard(lambda: app.export_tab.export_from_gui("results")))
    p.gui_export_static.on_click(guard(lambda: app.export_tab.export_from_gui("static")))
    p.gui_export_cancel.on_click(guard(lambda: app.export_tab.cancel()))
