"""GUI panels of the viewer (viser handles only; callbacks are wired in `app.py`).

The GUI is shared (`server.gui`): every connected browser sees and drives the same controls, so a presenter and
an audience, or two people debugging together, always look at the same scene, step and selection.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Sequence, cast, get_args

import numpy as np

from efem_viz.em import config as em_config
from efem_viz.serve.table import NO_ROW
from efem_viz.viewer.state import (
    COLOR_MODES,
    DEFAULT_CONFIDENCE_CUT,
    MASK_BAND_RANGE,
    NO_PROPOSAL,
    VIEW_MODES,
)

if TYPE_CHECKING:
    import plotly.graph_objects as go
    from viser import (
        GuiApi,
        GuiButtonHandle,
        GuiCheckboxHandle,
        GuiDropdownHandle,
        GuiHtmlHandle,
        GuiMarkdownHandle,
        GuiNumberHandle,
        GuiPlotlyHandle,
        GuiSliderHandle,
        GuiTextHandle,
    )
    from viser._gui_handles import GuiProgressBarHandle  # not re-exported by viser 1.1

PRESETS: tuple[str, ...] = ("fast", *(p for p in em_config.PRESETS if p != "fast"))
DISPLAYS: tuple[str, ...] = ("points", "mesh")


@dataclass
class Panels:
    """All GUI handles of the viewer, grouped as the tabs show them. Names start with `gui_`."""

    gui_status: GuiMarkdownHandle
    """Status line above the tabs (errors start with a warning sign)."""
    # ---- Scene tab
    gui_scene: GuiDropdownHandle[str]
    gui_display: GuiDropdownHandle[str]
    gui_color: GuiDropdownHandle[str]
    """Options are the keys of `COLOR_MODES`."""
    gui_color_key: GuiHtmlHandle
    """The key of the point colours (`efem_viz.viewer.legend.color_key_html`)."""
    gui_point_size: GuiSliderHandle[float]
    """Millimetres."""
    gui_reset_view: GuiButtonHandle
    """Puts the clicking browser's camera back on the view that fits the scene."""
    gui_info: GuiMarkdownHandle
    # ---- Run tab
    gui_preset: GuiDropdownHandle[str]
    gui_proposals: GuiNumberHandle[int]
    gui_seed: GuiNumberHandle[int]
    gui_precision: GuiDropdownHandle[str]
    gui_free_space: GuiDropdownHandle[str]
    gui_run: GuiButtonHandle
    gui_cancel: GuiButtonHandle
    gui_load: GuiButtonHandle
    gui_progress: GuiProgressBarHandle
    gui_run_info: GuiMarkdownHandle
    # ---- Timeline tab
    gui_view_mode: GuiDropdownHandle[str]
    """Options are the keys of `VIEW_MODES`."""
    gui_step: GuiSliderHandle[int]
    gui_play: GuiButtonHandle
    gui_speed: GuiSliderHandle[float]
    """Steps per second."""
    gui_step_info: GuiMarkdownHandle
    gui_active_plot: GuiPlotlyHandle
    # ---- Proposals tab
    gui_show_shapes: GuiCheckboxHandle
    gui_show_samples: GuiCheckboxHandle
    gui_max_shapes: GuiSliderHandle[int]
    gui_proposal: GuiDropdownHandle[str]
    """Options are `NO_PROPOSAL` and "#<id>  (score …)" / "#<id>  (dead)"."""
    gui_inspect_info: GuiMarkdownHandle
    gui_dead_info: GuiMarkdownHandle
    # ---- Results tab
    gui_threshold: GuiSliderHandle[float]
    gui_mask_band: GuiSliderHandle[float]
    gui_show_meshes: GuiCheckboxHandle
    gui_show_obbs: GuiCheckboxHandle
    gui_show_axes: GuiCheckboxHandle
    gui_result_info: GuiMarkdownHandle
    """Instances kept by the threshold, with counts per category, and how many the threshold hides."""
    gui_instance: GuiDropdownHandle[str]
    """The instance table's row chooser: options "<id>: <category> · <confidence>" (`texts.instance_options`),
    or `NO_ROW`."""
    gui_instance_visible: GuiCheckboxHandle
    """Shows / hides the chosen instance (a view: metrics and exports follow the threshold)."""
    gui_fly_to: GuiButtonHandle
    """Flies the clicking browser's camera to the chosen instance."""
    gui_instance_prev: GuiButtonHandle
    """Chooses the previous row and flies to it."""
    gui_instance_next: GuiButtonHandle
    """Chooses the next row and flies to it."""
    gui_instance_table: GuiMarkdownHandle
    """One row per instance (`legend.instance_table_markdown`)."""
    gui_legend: GuiHtmlHandle
    """One line per shown instance: colour swatch, id, category, confidence."""
    gui_gt_info: GuiMarkdownHandle
    gui_pr_plot: GuiPlotlyHandle
    # ---- Export tab
    gui_out_dir: GuiTextHandle
    gui_export_results: GuiButtonHandle
    gui_export_static: GuiButtonHandle
    gui_export_cancel: GuiButtonHandle
    """Stops a static-demo export (enabled while one runs)."""
    gui_export_progress: GuiProgressBarHandle
    """The static demo's recording (EM steps done), shown while it runs."""
    gui_export_info: GuiMarkdownHandle


def build_panels(gui: GuiApi, *, scene_names: list[str], out_dir: str) -> Panels:
    """Create every control under `gui` (a `viser.GuiApi`), grouped in tabs (one function per tab, in tab order).

    Args:
        gui: `server.gui`.
        scene_names: dropdown options of the scene browser.
        out_dir: the output root (exports from the GUI stay inside it).
    """
    tabs = gui.add_tab_group()
    handles: dict[str, Any] = {}
    with tabs.add_tab("Scene"):
        handles |= _scene_tab(gui, scene_names=scene_names)
    with tabs.add_tab("Run"):
        handles |= _run_tab(gui)
    with tabs.add_tab("Timeline"):
        handles |= _timeline_tab(gui)
    with tabs.add_tab("Proposals"):
        handles |= _proposals_tab(gui)
    with tabs.add_tab("Results"):
        handles |= _results_tab(gui)
    with tabs.add_tab("Export"):
        handles |= _export_tab(gui, out_dir=out_dir)
    # below the tabs: a status line that changes length never moves a tab or a button
    status = gui.add_markdown("")
    return Panels(gui_status=status, **handles)


def _scene_tab(gui: GuiApi, *, scene_names: list[str]) -> dict[str, Any]:
    """The Scene tab's controls (`Panels` field → handle): scene browser, display, colours, point size, view."""
    opts = tuple(scene_names) if scene_names else ("(no scenes)",)
    scene = gui.add_dropdown("Scene", opts, initial_value=opts[0], hint="scenes inside the paths given")
    display = gui.add_dropdown("Display", DISPLAYS, initial_value="points")
    color = gui.add_dropdown("Colour", tuple(COLOR_MODES), initial_value="scene colours")
    color_key = gui.add_html("")
    point_size = gui.add_slider("Point size (mm)", 0.5, 20.0, 0.5, 4.0)
    reset_view = gui.add_button("Reset view", hint="fit the scene in this browser's view")
    info = gui.add_markdown("")
    return dict(gui_scene=scene, gui_display=display, gui_color=color, gui_color_key=color_key,
                gui_point_size=point_size, gui_reset_view=reset_view, gui_info=info)


def _run_tab(gui: GuiApi) -> dict[str, Any]:
    """The Run tab's controls: the solve's settings, Run / Cancel / Load, the progress bar and line."""
    preset = gui.add_dropdown("Preset", PRESETS, initial_value="fast")
    proposals = gui.add_number("Proposals", em_config.preset("fast").proposals.n_init[0], min=1,
                               max=em_config.MAX_PROPOSALS,
                               step=1, hint="the preset's number until you change it")
    seed = gui.add_number("Seed", 0, min=0, max=2**31 - 1, step=1)
    run = gui.add_button("Run EFEM", hint="run EM on this scene in the background")
    cancel = gui.add_button("Cancel", disabled=True, color="red")
    load = gui.add_button("Load saved trace", hint="<scene>.efem.npz next to the scene file")
    # below the buttons: Tab from Seed goes to Run EFEM, not into a dropdown that opens over it
    precision = gui.add_dropdown("Precision", em_config.SOLVE_PRECISIONS,
                                 initial_value=em_config.SolveSettings().matmul_dtype,
                                 hint="bfloat16: the decoder's matrix products in bf16 (faster on a CPU with "
                                      "AVX-512 BF16 or AMX, slower without); auto: bfloat16 on such a CPU, float32 "
                                      "elsewhere; float32: the method as published")
    free_space = gui.add_dropdown("Free space", get_args(em_config.FreeSpaceMode), initial_value="auto",
                                  hint="check fits against what the scene's recorded cameras saw empty: auto (the "
                                       "preset's: on for real), on (also a fused scan, against all its cameras) "
                                       "or off")
    progress = gui.add_progress_bar(0.0, visible=False)
    run_info = gui.add_markdown("")
    return dict(gui_preset=preset, gui_proposals=proposals, gui_seed=seed, gui_precision=precision,
                gui_free_space=free_space, gui_run=run, gui_cancel=cancel, gui_load=load, gui_progress=progress,
                gui_run_info=run_info)


def _timeline_tab(gui: GuiApi) -> dict[str, Any]:
    """The Timeline tab's controls: step or result view, the step slider, Play and speed, the active-count plot."""
    import plotly.graph_objects as go

    view_mode = gui.add_dropdown("Show", tuple(VIEW_MODES), initial_value=next(iter(VIEW_MODES)),
                                 hint="one EM step (its decoded shapes and samples) or the final instances")
    step = gui.add_slider("Step", 0, 1, 1, 0, disabled=True)
    play = gui.add_button("Play", disabled=True)
    speed = gui.add_slider("Speed (steps/s)", 0.5, 10.0, 0.5, 2.0)
    step_info = gui.add_markdown("")
    active_plot = gui.add_plotly(go.Figure(), aspect=1.6, visible=False)
    return dict(gui_view_mode=view_mode, gui_step=step, gui_play=play, gui_speed=speed, gui_step_info=step_info,
                gui_active_plot=active_plot)


def _proposals_tab(gui: GuiApi) -> dict[str, Any]:
    """The Proposals tab's controls: which step layers show, how many shapes, the inspected proposal."""
    show_shapes = gui.add_checkbox("Decoded shapes", True)
    show_samples = gui.add_checkbox("Sampled points", True)
    max_shapes = gui.add_slider("Max shapes drawn", 0, 64, 1, 8, hint="top-N by stationary score")
    proposal = gui.add_dropdown("Inspect", (NO_PROPOSAL,), initial_value=NO_PROPOSAL)
    inspect_info = gui.add_markdown("")
    dead_info = gui.add_markdown("")
    return dict(gui_show_shapes=show_shapes, gui_show_samples=show_samples, gui_max_shapes=max_shapes,
                gui_proposal=proposal, gui_inspect_info=inspect_info, gui_dead_info=dead_info)


def _results_tab(gui: GuiApi) -> dict[str, Any]:
    """The Results tab's controls: confidence cut, mask band, result layers, the instance table, legend, ground
    truth and the PR curve."""
    import plotly.graph_objects as go

    threshold = gui.add_slider("Confidence ≥", 0.0, 1.0, 0.01, DEFAULT_CONFIDENCE_CUT,
                               hint="instances below this confidence are hidden (a view: nothing is re-run)")
    mask_band = gui.add_slider(
        "Mask band τ_out", MASK_BAND_RANGE[0], MASK_BAND_RANGE[1], 0.005, 0.04, disabled=True,
        hint="output masks take the points whose decoded |SDF| is below this (canonical units); re-derived from "
             "the stored latents, no re-run")
    show_meshes = gui.add_checkbox("Meshes", True)
    show_obbs = gui.add_checkbox("Boxes (OBB)", True)
    show_axes = gui.add_checkbox("Pose axes", False)
    result_info = gui.add_markdown("")
    with gui.add_folder("Instance table"):
        instance = gui.add_dropdown("Instance", (NO_ROW,), initial_value=NO_ROW,
                                    hint="a row of the table below, most confident first")
        instance_visible = gui.add_checkbox("Visible", True, disabled=True,
                                            hint="show or hide the chosen instance (metrics and exports follow "
                                                 "the confidence threshold only)")
        fly_to = gui.add_button("Fly to", disabled=True, hint="point this browser's camera at the instance")
        instance_prev = gui.add_button("◀ Previous", disabled=True, hint="choose the row above and fly to it")
        instance_next = gui.add_button("Next ▶", disabled=True, hint="choose the row below and fly to it")
        instance_table = gui.add_markdown("")
    legend = gui.add_html("")
    gt_info = gui.add_markdown("")
    pr_plot = gui.add_plotly(go.Figure(), aspect=1.3, visible=False)
    return dict(gui_threshold=threshold, gui_mask_band=mask_band, gui_show_meshes=show_meshes,
                gui_show_obbs=show_obbs, gui_show_axes=show_axes, gui_result_info=result_info,
                gui_instance=instance, gui_instance_visible=instance_visible, gui_fly_to=fly_to,
                gui_instance_prev=instance_prev, gui_instance_next=instance_next, gui_instance_table=instance_table,
                gui_legend=legend, gui_gt_info=gt_info, gui_pr_plot=pr_plot)


def _export_tab(gui: GuiApi, *, out_dir: str) -> dict[str, Any]:
    """The Export tab's controls: the output folder (inside `out_dir`), the two buttons, where they wrote."""
    out = gui.add_text("Output folder", out_dir, hint=f"inside {out_dir} (the output folder chosen at start)")
    export_results = gui.add_button("Export results", hint="ScanNet layout + coloured PLY")
    export_static = gui.add_button("Export static demo", hint="<output folder>/static/<scene>/index.html")
    export_cancel = gui.add_button("Cancel export", disabled=True, hint="stops the static demo; nothing is written")
    export_progress = gui.add_progress_bar(0.0, visible=False)  # below every button: it comes and goes
    export_info = gui.add_markdown("")
    return dict(gui_out_dir=out, gui_export_results=export_results, gui_export_static=export_static,
                gui_export_cancel=export_cancel, gui_export_progress=export_progress, gui_export_info=export_info)


class PlotlyJSON:
    """A Plotly figure given as its JSON dict; viser's plot handle only calls `to_json()` on what it is given.

    Building `plotly.graph_objects.Figure` objects costs 10-40 ms each (validation); the timeline plot is redrawn
    on every step change, so the figures here are plain dicts (≈0.1 ms).
    """

    def __init__(self, spec: dict[str, object]) -> None:
        self.spec = spec

    def to_json(self) -> str:
        return json.dumps(self.spec, separators=(",", ":"))


def set_slider_marks(handle: GuiSliderHandle[int], marks: Sequence[tuple[int, str]]) -> None:
    """Replace the labelled marks under a slider (the timeline's phase marks), in every client.

    viser 1.1 takes `marks=` only in `add_slider`; its handle has no public `marks` property (assigning one only
    sets a Python attribute that never reaches a browser). The marks live in the handle's `_marks` prop, which
    the handle sends on assignment like any other prop.

    Args:
        handle: the slider.
        marks: (value, label) pairs; empty = no marks.
    """
    from viser._messages import GuiSliderMark

    handle._marks = tuple(GuiSliderMark(value=float(v), label=str(lab)) for v, lab in marks) or None


def slider_marks(handle: GuiSliderHandle[int]) -> tuple[tuple[int, str], ...]:
    """The (value, label) marks a slider shows (what `set_slider_marks` set)."""
    return tuple((int(m.value), str(m.label)) for m in (handle._marks or ()))


def set_figure(handle: GuiPlotlyHandle, figure: PlotlyJSON) -> None:
    """Show `figure` in a plot handle. The handle is typed for `go.Figure` but calls only `to_json()` on it,
    which `PlotlyJSON` provides (the cast says so to the type checker; nothing is converted)."""
    handle.figure = cast("go.Figure", figure)


def active_figure(active_count: np.ndarray, marks: list[tuple[int, str]], step: int) -> PlotlyJSON:
    """Plot of the active proposals after each step, with phase/review marks and the current step.

    Args:
        active_count: (T+1,) int, proposals active before step 0 and after each step (x = -1 is the initial pool).
        marks: (step, label) timeline marks.
        step: current step (highlighted in red).
    """
    ac = np.asarray(active_count).reshape(-1)
    x = (np.arange(ac.shape[0]) - 1).tolist()
    data: list[dict[str, object]] = [
        {"type": "scatter", "x": x, "y": ac.tolist(), "mode": "lines+markers", "name": "active", "line": {"width": 2}}
    ]
    if 0 <= step + 1 < ac.shape[0]:
        data.append(
            {"type": "scatter", "x": [step], "y": [int(ac[step + 1])], "mode": "markers", "name": "now",
             "marker": {"size": 12, "color": "red"}}
        )
    shapes = [
        {"type": "line", "x0": s, "x1": s, "yref": "paper", "y0": 0, "y1": 1,
         "line": {"dash": "dot", "color": "grey", "width": 1}}
        for s, _ in marks
    ]
    annotations = [
        {"x": s, "y": 1.0, "yref": "paper", "text": lab, "showarrow": False, "yshift": 8, "font": {"size": 10}}
        for s, lab in marks
    ]
    layout = {
        "margin": {"l": 40, "r": 10, "t": 24, "b": 36},
        "showlegend": False,
        "xaxis": {"title": {"text": "step"}},
        "yaxis": {"title": {"text": "active proposals"}, "rangemode": "tozero"},
        "shapes": shapes,
        "annotations": annotations,
    }
    return PlotlyJSON({"data": data, "layout": layout})


def pr_figure(curves: list[tuple[str, np.ndarray, np.ndarray]], *,
              point: tuple[float, float] | None = None) -> PlotlyJSON:
    """Precision-recall curves.

    Args:
        curves: (label, recall (P,), precision (P,)) per curve.
        point: (recall, precision) of the shown predictions at IoU 0.5, marked in red.
    """
    data: list[dict[str, object]] = [
        {"type": "scatter", "x": np.asarray(rec, float).tolist(), "y": np.asarray(prec, float).tolist(),
         "mode": "lines", "name": label}
        for label, rec, prec in curves
    ]
    if point is not None:
        data.append(
            {"type": "scatter", "x": [point[0]], "y": [point[1]], "mode": "markers", "name": "threshold",
             "marker": {"size": 11, "color": "red"}}
        )
    layout = {
        "margin": {"l": 40, "r": 10, "t": 44, "b": 36},
        "xaxis": {"range": [0, 1.02], "title": {"text": "recall"}},
        "yaxis": {"range": [0, 1.02], "title": {"text": "precision"}},
        # above the plot: the default horizontal legend sits under the x axis and covers its title
        "legend": {"orientation": "h", "x": 0, "xanchor": "left", "y": 1.02, "yanchor": "bottom",
                   "font": {"size": 10}},
    }
    return PlotlyJSON({"data": data, "layout": layout})
