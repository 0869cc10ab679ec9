"""Draw the viewer session's state into the GUI panels (text, plots, dropdowns, enabled buttons).

The `show_*` functions read a `ViewerSession` and write `Panels` handles; the scene nodes are drawn by
`viewer/nodes.py`. `ViewerApp` calls them after each session action. `gui_set` sets a control's value without
re-entering the app's own callback (`ViewerApp.gui_set`). No viser import at run time.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Protocol, TypeVar

import numpy as np

from efem_viz.serve.table import NO_ROW, option_for
from efem_viz.viewer.legend import category_summary, instance_table_markdown, legend_html, result_summary_markdown
from efem_viz.viewer.panels import (
    MASK_BAND_RANGE,
    NO_PROPOSAL,
    Panels,
    active_figure,
    pr_figure,
    set_figure,
    set_slider_marks,
)
from efem_viz.viewer.texts import (
    deaths_markdown,
    gt_markdown,
    inspect_markdown,
    md_escape,
    parse_pid,
    proposal_options,
    scene_info_markdown,
    step_markdown,
)
from efem_viz.viewer.trace_queries import deaths, phase_marks
from efem_viz.terminal import count

if TYPE_CHECKING:
    from viser import GuiInputHandle

    from efem_viz.em.solver import StepInfo
    from efem_viz.viewer.session import Inspection, StepView, ViewerSession

logger = logging.getLogger(__name__)

ValueT = TypeVar("ValueT")


class GuiSet(Protocol):
    """Sets a control's value without re-entering the app's callback (`ViewerApp.gui_set`)."""

    def __call__(self, handle: GuiInputHandle[ValueT], value: ValueT, /) -> None: ...


def show_scene_info(p: Panels, session: ViewerSession) -> None:
    """The Scene tab's description of the open scene (and of its saved result)."""
    s = session.state
    if s.scene is not None and s.scene_name is not None:
        p.gui_info.content = scene_info_markdown(s.scene, s.entry(s.scene_name))


def show_running(p: Panels, running: bool) -> None:
    """Run/Load/Cancel buttons and the progress bar while a run is (not) in progress."""
    p.gui_run.disabled = running
    p.gui_load.disabled = running
    p.gui_cancel.disabled = not running
    p.gui_progress.visible = running
    if running:
        p.gui_progress.value = 0.0
        p.gui_progress.animated = True


def show_run_progress(p: Panels, info: StepInfo) -> None:
    """The progress bar and line of a running EM (`info`: the solver's step info)."""
    done, total = int(info.step) + 1, max(int(info.num_steps), 1)
    p.gui_progress.value = float(np.clip(100.0 * done / total, 0.0, 100.0))
    p.gui_run_info.content = f"step {done}/{total} · {info.status()}"


def show_no_result(p: Panels, session: ViewerSession, gui_set: GuiSet) -> None:
    """The panels of an open scene without a result."""
    p.gui_mask_band.disabled = True
    p.gui_step.disabled = True
    p.gui_play.disabled = True
    p.gui_active_plot.visible = False
    p.gui_pr_plot.visible = False
    p.gui_step_info.content = "_No trace: run EFEM or load a saved trace._"
    for h in (p.gui_inspect_info, p.gui_dead_info, p.gui_result_info, p.gui_legend):
        h.content = ""
    show_instance_table(p, session, gui_set)
    p.gui_gt_info.content = ""
    p.gui_run_info.content = ""
    gui_set(p.gui_proposal, NO_PROPOSAL)
    p.gui_proposal.options = (NO_PROPOSAL,)


def show_result(p: Panels, session: ViewerSession, gui_set: GuiSet) -> None:
    """The timeline, threshold, mask band and run line of a newly shown result."""
    s = session.state
    result = s.require_result()
    T = s.num_steps
    marks = phase_marks(np.asarray(result.trace.phase))
    p.gui_step.max = max(T - 1, 1)
    set_slider_marks(p.gui_step, [(m.step, m.label) for m in marks])
    p.gui_step.disabled = T == 0
    p.gui_play.disabled = T == 0
    gui_set(p.gui_step, s.step)
    gui_set(p.gui_proposal, NO_PROPOSAL)
    p.gui_threshold.max = session.results.threshold_max(result)  # the top hides every instance
    gui_set(p.gui_threshold, s.threshold)
    p.gui_mask_band.disabled = len(result.instances) == 0
    gui_set(p.gui_mask_band, float(np.clip(result.config.output.out_tau, *MASK_BAND_RANGE)))
    counts = md_escape(category_summary(result.instances.category))
    p.gui_run_info.content = (
        f"**Result**: {s.result_source} · {T} steps · {count(len(result.instances.ids), 'instance')}"
        + (f" ({counts})" if counts else "")
    )
    p.gui_active_plot.visible = True
    gui_set(p.gui_color, "instances")


def show_step(p: Panels, session: ViewerSession, v: StepView, gui_set: GuiSet) -> None:
    """The step line, the active-count plot, the proposal dropdown and the dead list at step `v.step`."""
    trace = session.state.require_result().trace
    t = v.step
    phase = int(np.asarray(trace.phase)[t]) if len(trace.phase) else 0
    sched = np.asarray(trace.schedule)[t] if len(trace.schedule) else np.zeros(4)
    active = np.asarray(trace.active_count)
    p.gui_step_info.content = step_markdown(t, int(trace.num_steps), phase=phase, alive=len(v.ids),
                                            initial=int(active[0]) if active.size else 0, schedule=sched)
    set_figure(p.gui_active_plot, active_figure(
        active, [(m.step, m.label) for m in phase_marks(np.asarray(trace.phase))], t
    ))
    sel = session.state.selected
    options = proposal_options(v.ids, v.scores, selected=sel)
    p.gui_proposal.options = options
    gui_set(p.gui_proposal, next((o for o in options if parse_pid(o) == sel), NO_PROPOSAL))
    p.gui_dead_info.content = deaths_markdown(deaths(trace), t)


def show_selected_proposal(p: Panels, pid: int, gui_set: GuiSet) -> None:
    """Show proposal `pid` in the proposal dropdown (added when the step's options lack it)."""
    opts = p.gui_proposal.options
    cur = next((o for o in opts if parse_pid(o) == int(pid)), None)
    if cur is None:
        cur = f"#{int(pid)}"
        p.gui_proposal.options = tuple(opts) + (cur,)
    gui_set(p.gui_proposal, cur)


def show_inspection(p: Panels, session: ViewerSession, ins: Inspection, gui_set: GuiSet) -> None:
    """The inspector's text and the colour dropdown on "proposal weights"."""
    gui_set(p.gui_color, "proposal weights")
    p.gui_inspect_info.content = inspect_markdown(ins.pid, ins.step, ins.view,
                                                  instances=session.state.require_result().instances)


def show_threshold(p: Panels, session: ViewerSession, gui_set: GuiSet) -> None:
    """The result summary, legend, ground-truth panel and instance table at the session's threshold."""
    s = session.state
    if s.result is None:
        return
    keep = session.results.kept_mask()
    inst = s.result.instances
    p.gui_result_info.content = result_summary_markdown(
        inst, keep, threshold=s.threshold, out_tau=s.result.config.output.out_tau,
        hidden_by_hand=int((keep & ~session.results.shown_mask()).sum()),
    )
    p.gui_legend.content = legend_html(inst, session.results.shown_mask())
    show_gt(p, session)
    show_instance_table(p, session, gui_set)


def show_instance_table(p: Panels, session: ViewerSession, gui_set: GuiSet) -> None:
    """The instance table, its dropdown (options and choice), *Visible* box and buttons."""
    s = session.state
    buttons = (p.gui_instance_visible, p.gui_fly_to, p.gui_instance_prev, p.gui_instance_next)
    opts = session.instances.table_options()
    if not opts:
        p.gui_instance.options = (NO_ROW,)
        gui_set(p.gui_instance, NO_ROW)
        p.gui_instance_table.content = "_No final instances._" if s.result is not None else ""
        for h in buttons:
            h.disabled = True
        return
    if tuple(p.gui_instance.options) != opts:
        p.gui_instance.options = opts
    gui_set(p.gui_instance, option_for(opts, s.table_row) if s.table_row is not None else opts[0])
    gui_set(p.gui_instance_visible, s.table_row not in s.hidden)
    for h in buttons:
        h.disabled = False
    metrics = session.results.gt_metrics_or_none() if s.scene is not None and s.scene.has_gt else None
    p.gui_instance_table.content = instance_table_markdown(s.require_result().instances, threshold=s.threshold,
                                                           hidden=s.hidden, metrics=metrics, selected=s.table_row)


def show_gt(p: Panels, session: ViewerSession) -> None:
    """The ground-truth comparison (AP line, PR curve) at the session's threshold."""
    s = session.state
    if s.scene is None or not s.scene.has_gt or s.result is None:
        p.gui_gt_info.content = "_No ground truth in this scene._" if s.scene is not None else ""
        p.gui_pr_plot.visible = False
        return
    try:
        metrics = session.results.gt_metrics()
    except Exception as exc:  # noqa: BLE001 - evaluation problems must not break the threshold view
        logger.exception("ground-truth evaluation failed")
        p.gui_gt_info.content = f"_Ground-truth evaluation failed: {exc}_"
        p.gui_pr_plot.visible = False
        return
    p.gui_gt_info.content = gt_markdown(len(s.scene.instance_ids()), s.threshold, metrics)
    set_figure(p.gui_pr_plot, pr_figure(metrics.curves, point=metrics.point))
    p.gui_pr_plot.visible = True
