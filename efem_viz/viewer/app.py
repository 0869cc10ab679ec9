"""The EFEM viewer: a thin viser layer over the scene, EM, trace and evaluation code.

The viewer's state and actions live in `efem_viz.viewer.session.ViewerSession` (headless, no viser); this module
builds the GUI, translates GUI events into session calls and draws the session's state.

Threading: GUI callbacks (viser's threads) read handle values, call the session and redraw directly (cheap:
colours, visibility) or submit heavy work (loading, EM, decoding shapes, exports) to worker threads. One
re-entrant lock (the session's) guards the state and the scene nodes; the workers take it to publish results.

Sharing: one state, one scene and one GUI for all browsers (`server.gui` / `server.scene`): every client sees the
same scene, step, threshold and selection. Errors are shown in the status line and as a notification to every
connected client; the server stays up.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence, TypeVar

import numpy as np

from efem_viz.data.scene import DEFAULT_MAX_POINTS
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.prior.registry import PriorSet
from efem_viz.serve.camera import fitted_view, framing
from efem_viz.serve.guard import ServedApp
from efem_viz.viewer import panel_views as pv, scene_views as sv, state as st
from efem_viz.viewer.browsers import Browsers, start_viewer_server
from efem_viz.viewer.wiring import wire
from efem_viz.viewer.export_tab import ExportTab
from efem_viz.viewer.instance_table import InstanceTable
from efem_viz.viewer.jobs import Jobs
from efem_viz.viewer.legend import color_key_html
from efem_viz.viewer.nodes import VIEW_DIRECTION, SceneNodes
from efem_viz.viewer.parts.runs import RunSettings
from efem_viz.viewer.panels import COLOR_MODES, MASK_BAND_RANGE, NO_PROPOSAL, VIEW_MODES, build_panels
from efem_viz.viewer.playback import Playback
from efem_viz.viewer.run_panel import RunPanel
from efem_viz.viewer.session import DEFAULT_SCENE_DIR, ViewerSession, default_scene_dir  # noqa: F401 - re-export
from efem_viz.viewer.state import ViewerState

if TYPE_CHECKING:
    from typing_extensions import TypeVarTuple, Unpack  # typing has them from Python 3.11 only
    from viser import ClientHandle, GuiInputHandle
    from efem_viz.em.results import EMResult
    from efem_viz.eval.comparison import GTMetrics
    from efem_viz.prior.config import ShapePriorLike

    Ts = TypeVarTuple("Ts")

logger = logging.getLogger(__name__)

T = TypeVar("T")


class ViewerApp(ServedApp):
    """The viewer application: a viser server, its panels and scene nodes over a `ViewerSession` (which holds the
    state and does every action; this class builds the GUI, runs the heavy actions in worker threads and draws).

    Args:
        paths, prior, prior_name, run_priors, results, max_points: the session's (`ViewerSession`): the scenes
            listed (only scene files inside `paths`), the priors, saved-result folders, the size limit.
        host: interface to bind (default loopback only).
        port: port (0 = a free random port; a busy port is replaced by the next free one, see `url`).
        open_first: open a scene at start: the first with a saved result (and that result), else the first.
        out_dir: the output root: every export from the GUI goes into this folder or below it (a folder typed
            into the GUI must resolve inside it); the static demo defaults to `<out_dir>/static/<scene>/`.
            Default: `view/` in the user's data folder (`efem_viz.serve.outputs`), never the working directory.
        token: the server's access token (None = a fresh random one; see `efem_viz.serve.guard`).

    Raises:
        GuardUnavailableError: the access guard cannot be attached to this viser (nothing is served).
    """

    def __init__(
        self,
        paths: Sequence[str | Path] = (),
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        prior: ShapePriorLike | None = None,
        prior_name: str = DEFAULT_PRIOR,
        run_priors: Sequence[str] = (),
        open_first: bool = True,
        out_dir: str | Path | None = None,
        token: str | None = None,
        results: Sequence[str | Path] = (),
        max_points: int = DEFAULT_MAX_POINTS,
        device: str = "cpu",
    ) -> None:
        self.session = ViewerSession(paths, prior=prior, prior_name=prior_name, run_priors=run_priors,
                                     out_dir=out_dir, results=results, max_points=max_points, device=device)
        """The headless viewer under this GUI: state and actions."""
        self._lock = self.session.lock
        self._quiet = False
        self.jobs = Jobs(on_error=lambda text: self.session.set_status(text, error=True))
        """Worker threads (`efem_viz.viewer.jobs`): loads and exports, decoding, EM runs."""
        self._worker, self._decoder, self._runner = self.jobs.worker, self.jobs.decoder, self.jobs.runner
        self._submit = self.jobs.submit

        self.server, self.access, self.camera_guard = start_viewer_server(host=host, port=port, token=token)
        """The server, how to reach it (`url`) and the guard that fits every browser's camera to the open scene
        (`efem_viz.viewer.browsers`)."""
        self.nodes = SceneNodes(self.server.scene)
        self.nodes.on_shape_click = self._on_shape_click
        self.panels = build_panels(
            self.server.gui, scene_names=[e.name for e in self.state.entries], out_dir=str(self.out_root)
        )
        self.run_panel = RunPanel(self.session, self.panels, self.jobs,
                                  show_result=lambda result, source, mode: self.set_result(result, source=source,
                                                                                           view_mode=mode))
        """The Run button's job, its progress and result (`efem_viz.viewer.run_panel`)."""
        self.playback = Playback(self.session, self.panels.gui_play, self.set_step)
        """Play/Pause and the timer that steps through the timeline (`efem_viz.viewer.playback`)."""
        self.export_tab = ExportTab(self.session, self.panels, self.jobs)
        """The Export tab's actions (`efem_viz.viewer.export_tab`)."""
        self.instance_table = InstanceTable(
            self.session, self.panels, gui_set=self.gui_set, camera_guard=self.camera_guard,
            redraw_results=lambda: self.set_threshold(self.state.threshold, by_user=False))
        """The instance table's GUI actions (`efem_viz.viewer.instance_table`)."""
        self.browsers = Browsers(self.server, self.panels, lock=self._lock, state=self.state,
                                 camera_guard=self.camera_guard)
        """The status line, error notifications and a new client's greeting (`efem_viz.viewer.browsers`)."""
        self.session.on_status = self.browsers.show_status
        wire(self)
        self.server.on_client_connect(self.browsers.connect)
        self.server.on_client_disconnect(self.camera_guard.forget)
        if open_first and self.state.entries:
            # the first scene that opens (a bad file only shows its error), one with a saved result before the
            # others: a person opening a folder of scans and results sees a result at once
            for e in sorted(self.state.entries, key=lambda e: not e.trace_path.is_file()):
                if self.open_scene(e.name):
                    break
        elif not self.state.entries:
            self.session.set_status("No scene files found in the given paths.", error=True)

    # ================================================================== the session's parts
    @property
    def state(self) -> ViewerState:
        """The session's state (`ViewerState`)."""
        return self.session.state

    @property
    def priors(self) -> PriorSet:
        """This viewer's priors (`efem_viz.prior.registry.PriorSet`), each loaded once."""
        return self.session.priors

    @property
    def out_root(self) -> Path:
        """Exports from the GUI stay inside this folder (fixed at start)."""
        return self.session.out_root

    def prior(self) -> ShapePriorLike:
        """The shape prior (loaded on first use). Raises RuntimeError with the reason when unavailable."""
        return self.session.prior()

    # ================================================================== lifecycle
    def stop(self) -> None:
        """Stop playback, cancel a run and a static-demo export, shut the workers and the server down."""
        self.playback.pause()
        self.session.cancel_event.set()  # a running EM stops at its next step
        self.session.export.cancel_export()  # a static demo stops at its next step, unwritten
        self.session.generation += 1  # running decode/inspect jobs drop their results
        self.jobs.shutdown()
        self.server.stop()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every submitted job (loads, runs, decodes) has finished. Returns False on timeout."""
        return self.jobs.wait_idle(timeout)

    # ================================================================== GUI events (`viewer/wiring.py`)
    def quiet(self) -> bool:
        """Whether the app is setting a control itself (its callback then does nothing)."""
        with self._lock:  # our own programmatic updates set _quiet while holding the lock
            return self._quiet

    def report_error(self, text: str) -> None:
        self.session.set_status(text, error=True)

    def submit_work(self, fn: Callable[[Unpack[Ts]], T], *args: Unpack[Ts]) -> Future[T]:
        """Run an action in the worker thread (loads, mask bands, exports)."""
        return self._submit(self._worker, fn, *args)

    def gui_set(self, handle: GuiInputHandle[T], value: T) -> None:
        """Set a GUI value without re-entering our own callback."""
        with self._lock:
            prev, self._quiet = self._quiet, True
            try:
                handle.value = value
            finally:
                self._quiet = prev

    def choose_preset(self, name: str) -> None:
        """The Run tab's preset is now `name`: the Proposals field shows that preset's number of proposals,
        unless a person has edited the field (their number is kept)."""
        from efem_viz.em.config import preset

        if not self.state.proposals_by_user:
            self.gui_set(self.panels.gui_proposals, int(preset(name).proposals.n_init[0]))

    # ================================================================== 1. scenes
    def open_scene(self, name: str) -> bool:
        """Load a scene from the browser list, draw it, and load its saved trace when present.

        Returns:
            True on success; on failure the error is shown in the GUI and the previous scene stays.
        """
        got = self.session.scenes.read_scene(name)
        if got is None:
            if self.state.scene_name is not None:
                self.gui_set(self.panels.gui_scene, self.state.scene_name)
            return False
        entry, scene = got
        with self._lock:
            self.playback.pause()
            self.session.scenes.show_scene(entry, scene)
            s = self.state
            self._set_view_mode("result")
            self.nodes.draw_scene(scene, display=s.display)
            s.point_size = self.nodes.point_size
            self.gui_set(self.panels.gui_scene, entry.name)
            self.gui_set(self.panels.gui_display, s.display)
            self.gui_set(self.panels.gui_color, "scene colours")
            self.gui_set(self.panels.gui_preset, self.session.results.suggested_preset(scene))
            self.choose_preset(self.session.results.suggested_preset(scene))
            self.gui_set(self.panels.gui_point_size, float(np.clip(round(s.point_size * 2000) / 2, 0.5, 20.0)))
            pv.show_scene_info(self.panels, self.session)
            lo, hi = scene.bounds  # the initial camera (new clients, "Reset view") and every connected one
            flo, fhi, sample = framing(scene.points)
            self.camera_guard.set_scene(
                fitted_view(flo, fhi, direction=VIEW_DIRECTION, points=sample), lo, hi,
                fit=lambda aspect: fitted_view(flo, fhi, direction=VIEW_DIRECTION, points=sample, aspect=aspect))
            self._draw_no_result()
            self.session.set_status(f"Opened {entry.name} ({scene.num_points:,} points).")
        if self.session.scenes.saved_result_path() is not None:
            self.load_trace()
        return True

    def reset_view(self, client: ClientHandle | None = None) -> None:
        """Put one browser's camera (every browser's when None) on the view that fits the open scene."""
        self.camera_guard.reset(client)

    def set_display(self, display: str) -> None:
        """'points' or 'mesh'."""
        with self._lock:
            self.session.scenes.set_display(display)
            self.nodes.set_display(display, recolored=self.session.scenes.recolored())

    def set_point_size(self, size_m: float) -> None:
        with self._lock:
            self.state.point_size = float(size_m)
            if self.nodes.points is not None:
                self.nodes.points.point_size = float(size_m)

    def set_color_mode(self, mode: str) -> None:
        """How the scene points are coloured: 'rgb', 'instances', 'gt_match' or 'weights'."""
        with self._lock:
            self.session.scenes.set_color_mode(mode)
            label = next(k for k, v in COLOR_MODES.items() if v == mode)
            self.gui_set(self.panels.gui_color, label)
            if mode in ("instances", "gt_match"):
                self._show_result_view()  # colours of the final instances: show the result
            self._redraw_layers()

    # ================================================================== 2. results: load / run
    def load_trace(self, path: str | Path | None = None) -> bool:
        """Load `<scene>.efem.npz` (or `path`, which must lie inside the given paths) for the open scene."""
        got = self.session.results.read_result(path)
        if got is None:
            return False
        result, name = got
        try:
            self.set_result(result, source=name)
            pv.show_scene_info(self.panels, self.session)
        except Exception as exc:  # noqa: BLE001 - another scene's result: show, stay up
            logger.exception("loading %s failed", name)
            self.session.set_status(f"Could not load {name}: {exc}", error=True)
            return False
        return True

    def start_run(self, settings: RunSettings | None = None, **knobs: Any) -> Future[EMResult | None] | None:
        """`RunPanel.start_run`: EFEM on the open scene in the runner thread with
        `RunSettings.of(settings, **knobs)`."""
        return self.run_panel.start_run(settings, **knobs)

    def set_result(self, result: EMResult, *, source: str, view_mode: st.ViewMode = "result") -> None:
        """Show an EMResult: timeline, proposals at the last step, final instances and ground truth; in the result
        view (the final instances) or the step view (the proposals at the last step: a run as it goes)."""
        with self._lock:
            self.playback.pause()
            self.session.results.set_result(result, source=source)
            pv.show_result(self.panels, self.session, self.gui_set)
            self.nodes.clear_inspector()
            self.nodes.remove_shapes()  # old per-step shapes; the final instances are drawn once
            self.nodes.draw_results(result.instances)
            self.set_step(self.state.step, view_mode=view_mode)
            # the status line is the session's; a run as it goes stays on its proposals (the step view)
            self.set_threshold(self.state.threshold, by_user=False, show_instances=view_mode == "result")

    def _draw_no_result(self) -> None:
        pv.show_no_result(self.panels, self.session, self.gui_set)

    # ================================================================== 3. timeline
    def set_view_mode(self, mode: str) -> None:
        """Show one EM step ("step": its decoded shapes and samples, no final instances) or the final instances
        ("result": meshes, boxes, labels and their colours, no step layers)."""
        with self._lock:
            self.session.scenes.set_view_mode(mode)
            self._set_view_mode(self.state.view_mode)
            if self.state.result is not None:
                self.set_step(self.state.step, view_mode=self.state.view_mode)
                self._redraw_layers()

    def _show_result_view(self) -> None:
        """Switch to the result view when a step is shown (the step's layers step aside)."""
        if self.state.view_mode != "result" and self.state.result is not None:
            self.set_step(self.state.step, view_mode="result")

    def _set_view_mode(self, mode: st.ViewMode) -> None:
        """Record the mode and show it in the Show dropdown (no redraw)."""
        self.session.scenes.set_view_mode(mode)
        self.gui_set(self.panels.gui_view_mode, next(k for k, v in VIEW_MODES.items() if v == mode))

    def set_step(self, step: int, *, view_mode: st.ViewMode = "step") -> None:
        """Show EM step `step`: proposals alive then (samples now, decoded shapes as they arrive), the dead list,
        the inspected proposal's views and the active-count plot marker. Cheap; decoding runs in the worker.

        Args:
            step: the EM step (clamped to the trace).
            view_mode: "step" (the default: moving the timeline shows that step only) or "result" (update the
                timeline and panels but keep showing the final instances).
        """
        with self._lock:
            s = self.state
            if s.result is None:
                return
            was = s.view_mode
            if view_mode != was:
                self._set_view_mode(view_mode)
            v = self.session.timeline.set_step(step)
            assert v is not None
            self.gui_set(self.panels.gui_step, v.step)
            missing = sv.draw_step(self.nodes, self.session, v)
            if missing and self.session.no_shapes_generation != self.session.generation:
                self._submit(self._decoder, sv.decode_shapes, self.nodes, self.session, missing,
                             self.session.generation)
            pv.show_step(self.panels, self.session, v, self.gui_set)
            if s.selected is not None:
                self._request_inspect(s.selected, v.step)
            if view_mode != was:  # the other layers step aside
                self._redraw_layers()

    # ================================================================== 4. proposals
    def set_max_shapes(self, n: int) -> None:
        with self._lock:
            self.session.timeline.set_max_shapes(n)
            self.set_step(self.state.step)

    def set_proposal_layers(self, *, shapes: bool | None = None, samples: bool | None = None) -> None:
        with self._lock:
            self.session.timeline.set_proposal_layers(shapes=shapes, samples=samples)
            self.set_step(self.state.step)

    def select_proposal(self, pid: int | None) -> Future[None] | None:
        """Inspect one proposal (None clears): Fig. S9 views computed in the worker, drawn when ready."""
        with self._lock:
            s = self.state
            was_weights = s.color_mode == "weights"
            if not self.session.inspection.select_proposal(pid):
                self.nodes.clear_inspector()
                self.panels.gui_inspect_info.content = ""
                if was_weights:
                    self.set_color_mode(s.color_mode)
                self.gui_set(self.panels.gui_proposal, NO_PROPOSAL)
                return None
            assert pid is not None
            pv.show_selected_proposal(self.panels, pid, self.gui_set)
            return self._request_inspect(int(pid), s.step)

    def _on_shape_click(self, pid: int) -> None:
        try:
            self.select_proposal(pid)
        except Exception as exc:  # noqa: BLE001
            self.session.set_status(f"error: {exc}", error=True)

    def _request_inspect(self, pid: int, t: int) -> Future[None]:
        return self._submit(self._decoder, self._inspect_job, pid, t, self.session.generation)

    def _inspect_job(self, pid: int, t: int, generation: int) -> None:
        try:
            ins = self.session.inspection.inspect(pid, t)
        except ValueError as exc:
            self.session.set_status(f"Cannot inspect #{pid} at step {t}: {exc}", error=True)
            return
        with self._lock:
            if generation != self.session.generation or not self.session.inspection.show_inspection(ins):
                return
            sv.draw_inspection(self.nodes, ins)
            pv.show_inspection(self.panels, self.session, ins, self.gui_set)
            self._redraw_layers()

    # ================================================================== 5./6. results and ground truth
    def set_threshold(self, threshold: float, *, by_user: bool = True, show_instances: bool = True) -> None:
        """Filter the final instances by confidence (visibility + colours only, no re-run); `by_user=False` for
        redraws (only a person's cut carries over to the next result); `show_instances=False` keeps the view mode
        (else the result view is shown, where the cut acts)."""
        with self._lock:
            s = self.state
            self.session.results.set_threshold(threshold, by_user=by_user)
            self.gui_set(self.panels.gui_threshold, s.threshold)
            if s.result is None:
                return
            if show_instances:
                self._show_result_view()  # the threshold filters the final instances: show them
            sv.show_results(self.nodes, self.session)
            self.draw_point_colors()
            pv.show_threshold(self.panels, self.session, self.gui_set)

    def set_mask_band(self, tau_out: float) -> bool:
        """Re-derive the output masks at SDF band `tau_out` from the stored latents (no re-run).

        Colours, ground-truth metrics and exports follow; the result's config records the band. Returns False
        (status line says why) when there is no result or no prior to decode with.
        """
        with self._lock:
            s = self.state
            if s.result is None or s.scene is None:
                return False
            self.gui_set(self.panels.gui_mask_band, float(np.clip(tau_out, *MASK_BAND_RANGE)))
            before = self.session.mask_version
            if not self.session.results.set_mask_band(tau_out):
                return False
            if self.session.mask_version != before:
                self.set_threshold(s.threshold, by_user=False)
            return True

    # ---------------------------------------------------------------- the instance table
    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None:
        with self._lock:
            self.session.scenes.set_result_layers(meshes=meshes, obbs=obbs, axes=axes)
            self._show_result_view()
            sv.show_results(self.nodes, self.session)

    def _redraw_layers(self) -> None:
        """Result layers, point colours and the mesh display's overlay after a mode change."""
        sv.show_results(self.nodes, self.session)
        self.draw_point_colors()
        self.nodes.set_display(self.state.display, recolored=self.session.scenes.recolored())

    def _gt_metrics(self) -> GTMetrics:
        """Ground-truth metrics of the current result at the current threshold (`ViewerSession.gt_metrics`)."""
        return self.session.results.gt_metrics()

    def draw_point_colors(self) -> None:
        """Recolour the scene points for the current colour mode (sends only (N,3) uint8)."""
        shown = sv.draw_point_colors(self.nodes, self.session)
        if shown is not None:
            self.panels.gui_color_key.content = color_key_html(shown)

    # ================================================================== 7. export