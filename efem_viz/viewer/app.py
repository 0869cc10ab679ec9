"""The EFEM viewer: a thin viser layer over the scene, EM, trace and evaluation code.

Threading: GUI callbacks run on viser's threads. They read handle values into `ViewerState` and either redraw
directly (cheap: colours, visibility) or submit heavy work (loading, EM, decoding shapes, exports) to worker
threads. One re-entrant lock guards the state and the scene nodes; the workers take it only to publish results.

Sharing: one state, one scene and one GUI for all browsers (`server.gui` / `server.scene`): every client sees the
same scene, step, threshold and selection. Errors are shown in the status line and as a notification to every
connected client; the server stays up.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Sequence

import numpy as np

from efem_viz.colors import (
    DEAD_COLOR,
    FP_COLOR,
    TP_COLOR,
    gt_match_colors,
    heatmap,
    instance_colors,
    instance_point_colors,
    weights_colors,
)
from efem_viz.data.scene import DEFAULT_MAX_POINTS
from efem_viz.eval.comparison import GTMetrics, gt_metrics
from efem_viz.viewer import state as st
from efem_viz.viewer.scenes import discover_scenes, is_inside, trace_path_for
from efem_viz.viewer.trace_queries import alive_table, deaths, is_dead_at, phase_marks, proposal_center, top_n
from efem_viz.serve.inputs import (
    ClientValueError,
    read_bool,
    read_choice,
    read_int,
    read_number,
    read_text,
    resolve_inside_root,
)
from efem_viz.viewer.legend import (
    category_summary,
    color_key_html,
    instance_options,
    instance_table_markdown,
    legend_html,
    result_summary_markdown,
)
from efem_viz.serve.camera import CameraGuard, fitted_view, fly_to_view
from efem_viz.serve.table import NO_ROW, option_for, option_id, step_row
from efem_viz.serve.outputs import default_output_dir
from efem_viz.viewer.nodes import VIEW_DIRECTION, SceneNodes, decode_shape, proposal_samples
from efem_viz.viewer.panels import (
    COLOR_MODES,
    MASK_BAND_RANGE,
    VIEW_MODES,
    NO_PROPOSAL,
    active_figure,
    build_panels,
    pr_figure,
    set_figure,
    set_slider_marks,
)
from efem_viz.viewer.state import ViewerState
from efem_viz.viewer.texts import (
    deaths_markdown,
    gt_markdown,
    inspect_markdown,
    md_escape,
    parse_pid,
    proposal_options,
    safe_name,
    scene_info_markdown,
    step_markdown,
)
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.prior.registry import PriorSet

if TYPE_CHECKING:
    from efem_viz.prior.config import ShapePriorLike

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
BUNDLED_SCENE_DIR = Path(__file__).resolve().parents[1] / "sample_scenes"
"""The sample scenes an installed efem-viz carries (`efem_viz/sample_scenes/`, copied from the checkout's
`sample_scenes/` when the wheel is built: setup.py)."""
CHECKOUT_SCENE_DIR = REPO_ROOT / "sample_scenes"
"""The sample scenes of a source checkout."""


def default_scene_dir() -> Path:
    """Where `efem-viz view` without arguments finds its demo: the bundled samples of an install, else the
    checkout's `sample_scenes/` (which may be missing: the caller says so)."""
    return BUNDLED_SCENE_DIR if BUNDLED_SCENE_DIR.is_dir() else CHECKOUT_SCENE_DIR


DEFAULT_SCENE_DIR = default_scene_dir()
"""`default_scene_dir()` at import."""


class ViewerApp:
    """The viewer application (server, state, panels, nodes, workers).

    Args:
        paths: scene files and/or folders; the browser lists only scene files inside them.
        host: interface to bind (default loopback only).
        port: port (0 = a free random port; a busy port is replaced by the next free one, see `url`).
        prior: a `ShapePrior`, or None to load `prior_name` lazily when first needed (decoding, runs).
        prior_name: the prior's spec (`efem_viz.prior.registry.PriorSet`: a name under efem_viz/weights/, "sphere"
            or a .pt path).
        run_priors: specs of more priors for runs started here (a joint solve over the prior and these).
        open_first: open the first scene at start (and its saved trace when present).
        out_dir: the output root: every export from the GUI goes into this folder or below it (a folder typed
            into the GUI must resolve inside it); the static demo defaults to `<out_dir>/static/<scene>/`.
            Default: `view/` in the user's data folder (`efem_viz.serve.outputs`), never the working directory.
        token: the server's access token (None = a fresh random one; see `efem_viz.serve.guard`).
        results: folders of saved results (`<scene>.efem.npz`, e.g. `efem-viz segment --out DIR`), searched after
            each scene's own folder; with no `paths`, the scenes are the scene files in these folders (segment's
            `<scene>.seg.ply`).
        max_points: refuse scenes with more points than this.

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
    ) -> None:
        from efem_viz.serve.guard import start_server

        self.max_points = int(max_points)
        """Scenes with more points are refused (shown as an error; the server stays up)."""

        self.state = ViewerState()
        scene_paths = list(paths) if paths else (list(results) if results else [DEFAULT_SCENE_DIR])
        self.state.entries = discover_scenes(scene_paths, result_dirs=list(results))
        self._roots = [Path(p).expanduser().resolve() for p in [*scene_paths, *results]]
        self.out_root = Path(out_dir if out_dir is not None else default_output_dir("view")).expanduser().resolve()
        """Exports from the GUI stay inside this folder (fixed at start)."""
        self.priors = PriorSet(prior_name, prior=prior, extra=run_priors)
        """This viewer's priors (`efem_viz.prior.registry.PriorSet`): the prior, the extra run priors (a joint solve
        over the prior and these) and the priors that saved multi-prior runs name, each loaded once."""
        self._lock = threading.RLock()
        self._quiet = False
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-work")
        self._decoder = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-decode")
        self._runner = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-run")
        """EM runs have their own thread: opening another scene or a trace does not wait for a run."""
        self._pending: set[Future[Any]] = set()
        self._pending_lock = threading.Lock()
        self._cancel = threading.Event()
        self._play_stop = threading.Event()
        self._play_thread: threading.Thread | None = None
        self._view_cache: dict[tuple[int, int], Any] = {}
        self._gt_cache: dict[tuple[int, float], GTMetrics] = {}
        self._no_shapes_generation = -1
        self._inspect_weights: np.ndarray | None = None
        self._mask_dist: tuple[int, Any] | None = None
        """(generation, InstanceDistances) of the shown result: masks at any τ_out without a re-run."""
        self._mask_version = 0
        """Bumped whenever the shown masks change within one result (colour caches key on it)."""
        self._generation = 0
        """Bumped on every scene/result change so stale worker results are dropped."""

        self.server, self.access = start_server(host=host, port=port, token=token)
        self.server.gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        self.server.scene.set_up_direction("+z")
        unit = (np.full(3, -0.5), np.full(3, 0.5))  # until a scene opens
        self.camera_guard = CameraGuard(self.server, fitted_view(*unit, direction=VIEW_DIRECTION), *unit,
                                        hint="Reset view (Scene tab) brings it back any time.")
        """Fits every browser's camera to the open scene and puts back a camera that left it
        (`efem_viz.serve.camera`)."""
        self.nodes = SceneNodes(self.server.scene)
        self.nodes.on_shape_click = self._on_shape_click
        self.panels = build_panels(
            self.server.gui, scene_names=[e.name for e in self.state.entries], out_dir=str(self.out_root)
        )
        self._wire()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self.camera_guard.forget)
        if open_first and self.state.entries:
            for e in self.state.entries:  # the first scene that opens (a bad file only shows its error)
                if self.open_scene(e.name):
                    break
        elif not self.state.entries:
            self._set_status("No scene files found in the given paths.", error=True)

    # ================================================================== lifecycle
    @property
    def url(self) -> str:
        """The URL to open, with the access token (the machine's address for a 0.0.0.0 bind; the real port)."""
        return self.access.url

    @property
    def local_url(self) -> str:
        """The URL from this machine (127.0.0.1 for loopback and 0.0.0.0 binds), with the token."""
        return self.access.local_url

    def stop(self) -> None:
        """Stop playback, cancel a run, shut the workers and the server down."""
        self.pause()
        self._cancel.set()  # a running EM stops at its next step
        self._generation += 1  # running decode/inspect jobs drop their results
        for pool in (self._runner, self._worker, self._decoder):
            pool.shutdown(wait=True, cancel_futures=True)
        self.server.stop()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every submitted job (loads, runs, decodes) has finished. Returns False on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            with self._pending_lock:
                pending = [f for f in self._pending if not f.done()]
                self._pending = set(pending)
            if not pending:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)

    def _submit(self, pool: ThreadPoolExecutor, fn: Callable[..., Any], *args: Any, **kw: Any) -> Future[Any]:
        def guarded() -> Any:
            try:
                return fn(*args, **kw)
            except ClientValueError as exc:  # a refused value or path: one line, no traceback
                self._set_status(str(exc), error=True)
                raise
            except Exception as exc:  # noqa: BLE001 - shown in the GUI, server stays up
                logger.exception("viewer job %s failed", getattr(fn, "__name__", fn))
                self._set_status(f"{getattr(fn, '__name__', 'job')} failed: {exc}", error=True)
                raise

        fut = pool.submit(guarded)
        with self._pending_lock:
            self._pending.add(fut)
        return fut

    # ================================================================== status
    def _set_status(self, text: str, *, error: bool = False) -> None:
        with self._lock:
            self.state.status = text
            self.state.error = text if error else None
            icon = "⚠️ " if error else ""
            self.panels.gui_status.content = f"{icon}{text}" if text else ""
        if error:
            logger.warning("%s", text)
            for client in list(self.server.get_clients().values()):
                try:
                    client.add_notification("efem-viz", text, color="red", auto_close_seconds=8.0)
                except Exception:  # noqa: BLE001 - a client may disconnect meanwhile
                    pass

    def _on_connect(self, client: Any) -> None:
        self.camera_guard.attach(client)
        if self.state.error:
            client.add_notification("efem-viz", self.state.error, color="red", auto_close_seconds=8.0)

    # ================================================================== wiring (callbacks stay thin)
    def _wire(self) -> None:
        """Connect the controls to the actions. Every client value is read through `efem_viz.serve.inputs`
        (clamped to the control's declared range, checked against its options), never used raw."""
        p = self.panels
        wb = self._gui_set  # shows a clamped value in every client without re-entering the callback

        def guard(fn: Callable[[], object]) -> Callable[[Any], None]:
            def cb(_event: Any) -> None:
                with self._lock:  # our own programmatic updates set _quiet while holding the lock
                    if self._quiet:
                        return
                try:
                    fn()
                except ClientValueError as exc:  # a value no control can produce: one line, no traceback
                    self._set_status(str(exc), error=True)
                except Exception as exc:  # noqa: BLE001
                    logger.exception("callback failed")
                    self._set_status(f"error: {exc}", error=True)

            return cb

        p.gui_scene.on_update(guard(lambda: self._submit(self._worker, self.open_scene, read_choice(p.gui_scene))))
        p.gui_display.on_update(guard(lambda: self.set_display(read_choice(p.gui_display))))
        p.gui_color.on_update(guard(lambda: self.set_color_mode(COLOR_MODES[read_choice(p.gui_color)])))
        p.gui_point_size.on_update(
            guard(lambda: self.set_point_size(read_number(p.gui_point_size, write_back=wb) / 1000.0)))
        p.gui_run.on_click(
            guard(lambda: self.start_run(preset=read_choice(p.gui_preset),
                                         proposals=read_int(p.gui_proposals, write_back=wb),
                                         seed=read_int(p.gui_seed, write_back=wb)))
        )
        p.gui_cancel.on_click(guard(self.cancel_run))
        p.gui_load.on_click(guard(lambda: self._submit(self._worker, self.load_trace)))
        p.gui_view_mode.on_update(guard(lambda: self.set_view_mode(VIEW_MODES[read_choice(p.gui_view_mode)])))
        p.gui_step.on_update(guard(lambda: self.set_step(read_int(p.gui_step))))
        p.gui_play.on_click(guard(self.toggle_play))
        p.gui_speed.on_update(guard(lambda: setattr(self.state, "speed", read_number(p.gui_speed, write_back=wb))))
        p.gui_show_shapes.on_update(guard(lambda: self.set_proposal_layers(shapes=read_bool(p.gui_show_shapes))))
        p.gui_show_samples.on_update(guard(lambda: self.set_proposal_layers(samples=read_bool(p.gui_show_samples))))
        p.gui_max_shapes.on_update(guard(lambda: self.set_max_shapes(read_int(p.gui_max_shapes, write_back=wb))))
        p.gui_proposal.on_update(guard(lambda: self.select_proposal(parse_pid(read_choice(p.gui_proposal)))))
        p.gui_threshold.on_update(guard(lambda: self.set_threshold(read_number(p.gui_threshold))))
        p.gui_mask_band.on_update(
            guard(lambda: self._submit(self._worker, self.set_mask_band, read_number(p.gui_mask_band))))
        for h in (p.gui_show_meshes, p.gui_show_obbs, p.gui_show_axes):
            h.on_update(
                guard(
                    lambda: self.set_result_layers(
                        meshes=read_bool(p.gui_show_meshes), obbs=read_bool(p.gui_show_obbs),
                        axes=read_bool(p.gui_show_axes)
                    )
                )
            )
        p.gui_instance.on_update(guard(lambda: self.choose_instance(_row_id(read_choice(p.gui_instance)))))
        p.gui_instance_visible.on_update(
            guard(lambda: self.set_instance_visible(self.state.table_row, read_bool(p.gui_instance_visible))))
        p.gui_fly_to.on_click(
            lambda event: guard(lambda: self.fly_to_instance(self.state.table_row, client=event.client))(event))
        p.gui_instance_prev.on_click(lambda event: guard(lambda: self.step_instance(-1, client=event.client))(event))
        p.gui_instance_next.on_click(lambda event: guard(lambda: self.step_instance(+1, client=event.client))(event))
        p.gui_reset_view.on_click(lambda event: self.reset_view(event.client))
        p.gui_export_results.on_click(guard(lambda: self.export_from_gui("results")))
        p.gui_export_static.on_click(guard(lambda: self.export_from_gui("static")))

    def gui_out_folder(self) -> Path:
        """The folder in the GUI's "Output folder" field, resolved inside the output root chosen at start.

        Raises:
            ClientValueError: the field names a place outside the output root (`..`, another absolute path, a
                symlink pointing out), or is not a usable path.
        """
        return resolve_inside_root(read_text(self.panels.gui_out_dir), self.out_root, what="output folder")

    def export_from_gui(self, kind: Literal["results", "static"]) -> Future[Any] | None:
        """The Export buttons: results into the GUI's output folder, the static demo into
        `<output folder>/static/<scene>/`; both confined to the output root. Returns the job's Future.

        Raises:
            ClientValueError: the output folder field is outside the output root.
        """
        folder = self.gui_out_folder()
        if kind == "results":
            return self._submit(self._worker, self.export_results, folder, root=self.out_root)
        scene = self.state.scene
        target = folder / "static" / safe_name(scene.name) if scene is not None else None
        return self._submit(self._worker, self.export_static, target, root=self.out_root)

    def _gui_set(self, handle: Any, value: Any) -> None:
        """Set a GUI value without re-entering our own callback."""
        with self._lock:
            prev, self._quiet = self._quiet, True
            try:
                handle.value = value
            finally:
                self._quiet = prev

    def _allowed(self, path: Path) -> bool:
        """May the viewer read `path`? Inside a given folder, a given file, or the saved result of a given file."""
        if is_inside(path, self._roots):
            return True
        rp = path.resolve()
        return any(r.is_file() and rp == trace_path_for(r) for r in self._roots)

    # ================================================================== prior
    def prior(self) -> ShapePriorLike:
        """The shape prior (loaded on first use). Raises RuntimeError with the reason when unavailable."""
        return self.priors.primary()

    # ================================================================== 1. scenes
    def open_scene(self, name: str) -> bool:
        """Load a scene from the browser list, draw it, and load its saved trace when present.

        Returns:
            True on success; on failure the error is shown in the GUI and the previous scene stays.
        """
        from efem_viz.data.io import holds_predictions, load_scene

        try:
            entry = self.state.entry(name)
        except KeyError as exc:
            self._set_status(str(exc), error=True)
            return False
        if not is_inside(entry.path, self._roots):  # never read outside the given paths
            self._set_status(f"refusing to open {entry.path}: outside the given paths", error=True)
            return False
        self._set_status(f"Loading {entry.name} …")
        try:
            scene = load_scene(entry.path, max_points=self.max_points)
            if holds_predictions(entry.path) and scene.instance is not None:
                scene = scene.with_labels(None, {})  # a segment output's labels are its predictions: no ground truth
        except Exception as exc:  # noqa: BLE001 - SceneError, OSError, parser errors: show, stay up
            self._set_status(f"Could not open {entry.path.name}: {exc}", error=True)
            if self.state.scene_name is not None:
                self._gui_set(self.panels.gui_scene, self.state.scene_name)
            return False
        with self._lock:
            self.pause()
            if self.state.running:
                self._cancel.set()  # the run belongs to the previous scene
            self._generation += 1
            self._view_cache.clear()
            self._inspect_weights = None
            s = self.state
            s.scene_name, s.scene, s.result, s.result_source = entry.name, scene, None, ""
            s.step, s.selected, s.color_mode = 0, None, "rgb"
            self._set_view_mode("result")
            if scene.is_mesh and s.display == "points":
                s.display = "mesh"
            elif not scene.is_mesh:
                s.display = "points"
            self.nodes.draw_scene(scene, display=s.display)
            s.point_size = self.nodes.point_size
            self._gui_set(self.panels.gui_scene, entry.name)
            self._gui_set(self.panels.gui_display, s.display)
            self._gui_set(self.panels.gui_color, "scene colours")
            self._gui_set(self.panels.gui_point_size, float(np.clip(round(s.point_size * 2000) / 2, 0.5, 20.0)))
            self.panels.gui_info.content = scene_info_markdown(scene, entry)
            self._frame_cameras(scene)
            self._draw_no_result()
            self._set_status(f"Opened {entry.name} ({scene.num_points:,} points).")
        if entry.trace_path.is_file() and self._allowed(entry.trace_path):
            self.load_trace()
        return True

    def _frame_cameras(self, scene: Any) -> None:
        """Point the initial camera (new clients, "Reset view") and every connected camera at the scene."""
        lo, hi = scene.bounds
        self.camera_guard.set_scene(fitted_view(lo, hi, direction=VIEW_DIRECTION), lo, hi)

    def reset_view(self, client: Any = None) -> None:
        """Put one browser's camera (every browser's when None) on the view that fits the open scene."""
        self.camera_guard.reset(client)

    def set_display(self, display: str) -> None:
        """'points' or 'mesh'."""
        if display not in ("points", "mesh"):
            raise ValueError(f"display must be 'points' or 'mesh', got {display!r}")
        with self._lock:
            self.state.display = display  # type: ignore[assignment]
            self.nodes.set_display(display, recolored=self._recolored())

    def set_point_size(self, size_m: float) -> None:
        with self._lock:
            self.state.point_size = float(size_m)
            if self.nodes.points is not None:
                self.nodes.points.point_size = float(size_m)

    def set_color_mode(self, mode: str) -> None:
        """How the scene points are coloured: 'rgb', 'instances', 'gt_match' or 'weights'."""
        if mode not in COLOR_MODES.values():
            raise ValueError(f"unknown colour mode {mode!r}; expected one of {sorted(COLOR_MODES.values())}")
        with self._lock:
            self.state.color_mode = mode  # type: ignore[assignment]
            label = next(k for k, v in COLOR_MODES.items() if v == mode)
            self._gui_set(self.panels.gui_color, label)
            if mode in ("instances", "gt_match"):
                self._show_result_view()  # colours of the final instances: show the result
            self.draw_point_colors()
            self.nodes.set_display(self.state.display, recolored=self._recolored())
            self._show_results()

    # ================================================================== 2. results: load / run
    def load_trace(self, path: str | Path | None = None) -> bool:
        """Load `<scene>.efem.npz` (or `path`, which must lie inside the given paths) for the open scene."""
        from efem_viz.em import EMResult

        s = self.state
        if s.scene is None or s.scene_name is None:
            self._set_status("Open a scene first.", error=True)
            return False
        p = Path(path) if path is not None else s.entry(s.scene_name).trace_path
        if not self._allowed(p):
            self._set_status(f"refusing to read {p}: outside the given paths", error=True)
            return False
        if not p.is_file():
            self._set_status(f"No saved trace at {p.name}; run EFEM first.", error=True)
            return False
        try:
            result = EMResult.load(p)
            self.set_result(result, source=str(p.name))
            scene = s.scene
            if scene is not None:
                self.panels.gui_info.content = scene_info_markdown(scene, s.entry(s.scene_name))
        except Exception as exc:  # noqa: BLE001 - corrupt file, other scene's result: show, stay up
            logger.exception("loading %s failed", p)
            self._set_status(f"Could not load {p.name}: {exc}", error=True)
            return False
        return True

    def start_run(self, *, preset: str = "fast", proposals: int | None = None, seed: int = 0) -> Future[Any] | None:
        """Run EFEM on the open scene in the worker thread (progress bar, cancel). Returns the job's Future."""
        with self._lock:
            if self.state.running:
                self._set_status("A run is already in progress.", error=True)
                return None
            if self.state.scene is None:
                self._set_status("Open a scene first.", error=True)
                return None
            self.state.running = True
            self._cancel.clear()
            p = self.panels
            p.gui_run.disabled = True
            p.gui_load.disabled = True
            p.gui_cancel.disabled = False
            p.gui_progress.value = 0.0
            p.gui_progress.visible = True
            p.gui_progress.animated = True
        return self._submit(self._runner, self._run_job, preset, proposals, seed, self._generation)

    def _run_job(self, preset: str, proposals: int | None, seed: int, generation: int) -> Any:
        from efem_viz.em import EMCancelled, preset as make_preset, run_em

        t0 = time.perf_counter()
        try:
            scene = self.state.require_scene()
            cfg = make_preset(preset)
            if proposals is not None:
                cfg = cfg.with_proposals(int(proposals))
            self._set_status(f"Running EFEM ({preset}, {cfg.n_init[0]} proposals, seed {seed}) …")
            prior = self.prior()
            priors = self.priors.run_priors()

            def on_step(info: Any) -> None:
                frac = 100.0 * (int(info.step) + 1) / max(int(info.num_steps), 1)
                self.panels.gui_progress.value = float(np.clip(frac, 0.0, 100.0))
                self.panels.gui_run_info.content = (
                    f"step {int(info.step) + 1}/{int(info.num_steps)} · phase {int(info.phase)} · "
                    f"{int(info.active)} active · {float(info.elapsed_s):.1f} s"
                )

            if priors is None:
                result = run_em(scene, prior, cfg, seed=int(seed), on_step=on_step, cancel=self._cancel)
            else:
                result = run_em(scene, cfg=cfg, priors=priors, seed=int(seed), on_step=on_step, cancel=self._cancel)
        except EMCancelled:
            self._set_status("Run cancelled.")
            return None
        except Exception as exc:  # noqa: BLE001
            self._set_status(f"EFEM run failed: {exc}", error=True)
            return None
        finally:
            with self._lock:
                self.state.running = False
                p = self.panels
                p.gui_run.disabled = False
                p.gui_load.disabled = False
                p.gui_cancel.disabled = True
                p.gui_progress.visible = False
        if generation != self._generation:
            logger.info("scene changed during the run; result dropped")
            return None
        self.set_result(result, source=f"run ({preset}, seed {seed}, {time.perf_counter() - t0:.1f} s)")
        return result

    def cancel_run(self) -> None:
        """Ask a running EM to stop at its next step."""
        self._cancel.set()
        self._set_status("Cancelling …")

    def set_result(self, result: Any, *, source: str) -> None:
        """Show an EMResult: timeline, proposals at the last step, final instances and ground truth."""
        with self._lock:
            self.pause()
            self._generation += 1
            self._view_cache.clear()
            self._inspect_weights = None
            s = self.state
            trace = result.trace
            if s.scene is not None and hasattr(result, "bind"):
                result.bind(s.scene)  # raises ValueError when the result belongs to another scene
            s.result, s.result_source, s.selected = result, source, None
            s.hidden, s.table_row = set(), None  # another result: other instances
            T = int(trace.num_steps)
            s.step = max(T - 1, 0)
            p = self.panels
            marks = phase_marks(np.asarray(trace.phase))
            p.gui_step.max = max(T - 1, 1)
            set_slider_marks(p.gui_step, [(m.step, m.label) for m in marks])
            p.gui_step.disabled = T == 0
            p.gui_play.disabled = T == 0
            self._gui_set(p.gui_step, s.step)
            self._gui_set(p.gui_proposal, NO_PROPOSAL)
            self.nodes.clear_inspector()
            # Remove old per-step shapes and draw the final instances once.
            for key in list(self.nodes.shapes):
                h = self.nodes.shapes.pop(key)
                try:
                    h.remove()
                except Exception:  # noqa: BLE001
                    pass
            self.nodes.draw_results(result.instances)
            conf = np.asarray(result.instances.confidence, float)
            hi = float(conf.max()) if conf.size else 1.0
            p.gui_threshold.max = float(np.ceil(hi * 100.0 + 1e-6) / 100.0 + 0.01)  # the top hides every instance
            s.threshold = float(np.clip(s.threshold, 0.0, p.gui_threshold.max))
            self._gui_set(p.gui_threshold, s.threshold)
            self._mask_dist = None
            p.gui_mask_band.disabled = len(result.instances) == 0
            self._gui_set(p.gui_mask_band, float(np.clip(result.config.out_tau, *MASK_BAND_RANGE)))
            counts = md_escape(category_summary(result.instances.category))
            p.gui_run_info.content = (
                f"**Result**: {source} · {T} steps · {len(result.instances.ids)} instances"
                + (f" ({counts})" if counts else "")
            )
            p.gui_active_plot.visible = True
            s.color_mode = "instances"
            self._gui_set(p.gui_color, "instances")
            self.set_step(s.step, view_mode="result")
            self.set_threshold(s.threshold)
            self._set_status(f"Loaded result: {source}.")

    def _draw_no_result(self) -> None:
        p = self.panels
        p.gui_mask_band.disabled = True
        p.gui_step.disabled = True
        p.gui_play.disabled = True
        p.gui_active_plot.visible = False
        p.gui_pr_plot.visible = False
        p.gui_step_info.content = "_No trace: run EFEM or load a saved trace._"
        p.gui_inspect_info.content = ""
        p.gui_dead_info.content = ""
        p.gui_result_info.content = ""
        p.gui_legend.content = ""
        self._update_instance_table()
        p.gui_gt_info.content = ""
        p.gui_run_info.content = ""
        self._gui_set(p.gui_proposal, NO_PROPOSAL)
        p.gui_proposal.options = (NO_PROPOSAL,)

    # ================================================================== 3. timeline
    def set_view_mode(self, mode: str) -> None:
        """Show one EM step ("step": its decoded shapes and samples, no final instances) or the final instances
        ("result": meshes, boxes, labels and their colours, no step layers)."""
        if mode not in VIEW_MODES.values():
            raise ValueError(f"unknown view mode {mode!r}; expected one of {sorted(VIEW_MODES.values())}")
        with self._lock:
            self._set_view_mode(mode)  # type: ignore[arg-type]
            if self.state.result is not None:
                self.set_step(self.state.step, view_mode=self.state.view_mode)
                self._show_results()
                self.draw_point_colors()
                self.nodes.set_display(self.state.display, recolored=self._recolored())

    def _show_result_view(self) -> None:
        """Switch to the result view when a step is shown (the step's layers step aside)."""
        if self.state.view_mode != "result" and self.state.result is not None:
            self.set_step(self.state.step, view_mode="result")

    def _set_view_mode(self, mode: st.ViewMode) -> None:
        """Record the mode and show it in the Show dropdown (no redraw)."""
        self.state.view_mode = mode
        self._gui_set(self.panels.gui_view_mode, next(k for k, v in VIEW_MODES.items() if v == mode))

    def _recolored(self) -> bool:
        """Whether the points carry other colours than the scene's (the mesh display then overlays them)."""
        s = self.state
        if s.color_mode == "weights":
            return True
        return s.color_mode != "rgb" and s.view_mode == "result"

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
            T = s.num_steps
            t = int(np.clip(step, 0, max(T - 1, 0)))
            s.step = t
            self._gui_set(self.panels.gui_step, t)
            trace = s.result.trace
            ids, scores = alive_table(trace, t)
            drawn = top_n(ids, scores, s.max_shapes)
            self._draw_samples(trace, t, drawn)
            self._draw_shapes(t, drawn)
            self._update_step_panels(trace, t, ids, scores)
            if s.selected is not None:
                self._request_inspect(s.selected, t)
            if view_mode != was:  # the other layers step aside
                self._show_results()
                self.draw_point_colors()
                self.nodes.set_display(s.display, recolored=self._recolored())

    def _draw_samples(self, trace: Any, t: int, drawn: np.ndarray) -> None:
        s = self.state
        if not s.show_samples or drawn.size == 0 or s.view_mode != "step":
            self.nodes.hide_samples()
            return
        pts, cols = proposal_samples(trace, t, drawn, s.require_scene().points)
        if not len(pts):
            self.nodes.hide_samples()
            return
        self.nodes.draw_samples(pts, cols)

    def _draw_shapes(self, t: int, drawn: np.ndarray) -> None:
        s = self.state
        keys = [(int(pid), t) for pid in drawn] if s.show_shapes and s.view_mode == "step" else []
        self.nodes.show_shapes(keys)
        missing = [k for k in keys if not self.nodes.has_shape(*k)]
        if missing and self._no_shapes_generation != self._generation:
            self._submit(self._decoder, self._decode_shapes, missing, self._generation)

    def _decode_shapes(self, keys: list[tuple[int, int]], generation: int) -> None:
        """Worker: decode the shapes of (proposal, step) pairs from their stored latents and send each once."""
        from efem_viz.em.replay import prior_latent

        for pid, t in keys:
            with self._lock:
                if generation != self._generation or self.state.step != t or self.nodes.has_shape(pid, t):
                    continue  # the user moved on (decoded again when asked) or it is already there
                trace = self.state.require_result().trace
            try:
                prior, latent = prior_latent(trace, pid, t, self.priors.for_run(trace))
            except RuntimeError as exc:
                self._no_shapes_generation = generation  # say it once, do not retry on every step
                self._set_status(f"Decoded shapes unavailable: {exc}", error=True)
                return
            shape = decode_shape(prior, latent, resolution=trace.config.mesh_resolution)
            with self._lock:
                if generation != self._generation:
                    return
                if shape is not None:
                    self.nodes.add_shape(pid, t, *shape, dead=is_dead_at(trace, pid, t))
                if self.state.step == t and self.state.show_shapes and self.state.view_mode == "step":
                    ids, scores = alive_table(trace, t)
                    drawn = top_n(ids, scores, self.state.max_shapes)
                    self.nodes.show_shapes([(int(p_), t) for p_ in drawn])

    def _view(self, pid: int, t: int, prior: ShapePriorLike | None) -> Any:
        key = (int(pid), int(t))
        v = self._view_cache.get(key)
        if v is None or (prior is not None and getattr(v, "mesh", None) is None):
            v = self.state.require_result().replay.view(int(pid), int(t), prior, mesh=prior is not None)
            self._view_cache[key] = v
            if len(self._view_cache) > 256:
                self._view_cache.pop(next(iter(self._view_cache)))
        return v

    def _update_step_panels(self, trace: Any, t: int, ids: np.ndarray, scores: np.ndarray) -> None:
        p = self.panels
        phase = int(np.asarray(trace.phase)[t]) if len(trace.phase) else 0
        sched = np.asarray(trace.schedule)[t] if len(trace.schedule) else np.zeros(4)
        active = np.asarray(trace.active_count)
        p.gui_step_info.content = step_markdown(t, int(trace.num_steps), phase=phase, alive=len(ids),
                                                initial=int(active[0]) if active.size else 0, schedule=sched)
        set_figure(p.gui_active_plot, active_figure(
            active, [(m.step, m.label) for m in phase_marks(np.asarray(trace.phase))], t
        ))
        options = proposal_options(ids, scores, selected=self.state.selected)
        p.gui_proposal.options = options
        sel = self.state.selected
        current = next((o for o in options if parse_pid(o) == sel), NO_PROPOSAL)
        self._gui_set(p.gui_proposal, current)
        p.gui_dead_info.content = deaths_markdown(deaths(trace), t)

    def play(self) -> None:
        """Start playback from the current step (from 0 when at the end)."""
        with self._lock:
            if self.state.result is None or self.state.playing:
                return
            if self.state.step >= self.state.num_steps - 1:
                self.set_step(0)
            self.state.playing = True
            self.panels.gui_play.label = "Pause"
            self._play_stop.clear()
            self._play_thread = threading.Thread(target=self._play_loop, name="efem-viewer-play", daemon=True)
            self._play_thread.start()

    def pause(self) -> None:
        with self._lock:
            self.state.playing = False
            self._play_stop.set()
            self.panels.gui_play.label = "Play"

    def toggle_play(self) -> None:
        if self.state.playing:
            self.pause()
        else:
            self.play()

    def _play_loop(self) -> None:
        while not self._play_stop.wait(1.0 / max(self.state.speed, 0.1)):
            with self._lock:
                if not self.state.playing or self.state.result is None:
                    return
                nxt = self.state.step + 1
                if nxt >= self.state.num_steps:
                    self.pause()
                    return
                self.set_step(nxt)

    # ================================================================== 4. proposals
    def set_max_shapes(self, n: int) -> None:
        with self._lock:
            self.state.max_shapes = max(int(n), 0)
            self.set_step(self.state.step)

    def set_proposal_layers(self, *, shapes: bool | None = None, samples: bool | None = None) -> None:
        with self._lock:
            if shapes is not None:
                self.state.show_shapes = bool(shapes)
            if samples is not None:
                self.state.show_samples = bool(samples)
            self.set_step(self.state.step)

    def select_proposal(self, pid: int | None) -> Future[Any] | None:
        """Inspect one proposal (None clears): Fig. S9 views computed in the worker, drawn when ready."""
        with self._lock:
            s = self.state
            s.selected = None if pid is None else int(pid)
            if pid is None or s.result is None:
                self.nodes.clear_inspector()
                self.panels.gui_inspect_info.content = ""
                if s.color_mode == "weights":
                    self.set_color_mode("instances" if s.result is not None else "rgb")
                self._gui_set(self.panels.gui_proposal, NO_PROPOSAL)
                return None
            opts = self.panels.gui_proposal.options
            cur = next((o for o in opts if parse_pid(o) == int(pid)), None)
            if cur is None:
                cur = f"#{int(pid)}"
                self.panels.gui_proposal.options = tuple(opts) + (cur,)
            self._gui_set(self.panels.gui_proposal, cur)
            return self._request_inspect(int(pid), s.step)

    def _on_shape_click(self, pid: int) -> None:
        try:
            self.select_proposal(pid)
        except Exception as exc:  # noqa: BLE001
            self._set_status(f"error: {exc}", error=True)

    def _request_inspect(self, pid: int, t: int) -> Future[Any]:
        return self._submit(self._decoder, self._inspect_job, pid, t, self._generation)

    def _inspect_job(self, pid: int, t: int, generation: int) -> None:
        try:
            prior = self.priors.for_trace(self.state.require_result().trace, pid)
        except RuntimeError as exc:
            prior = None  # the first step of an episode still has weights (the crop); later steps need the prior
            logger.info("inspecting without a prior: %s", exc)
        try:
            view = self._view(pid, t, prior)
        except ValueError as exc:
            self._set_status(f"Cannot inspect #{pid} at step {t}: {exc}", error=True)
            return
        with self._lock:
            s = self.state
            if generation != self._generation or s.selected != pid or s.step != t:
                return
            self._draw_inspector(pid, t, view)

    def _draw_inspector(self, pid: int, t: int, view: Any) -> None:
        s = self.state
        scene, result = s.require_scene(), s.require_result()
        w = np.asarray(view.weights, np.float32).reshape(-1)
        r_err = float(result.trace.prop_r_err[pid])
        center = proposal_center(result.trace, pid, t)
        near = np.flatnonzero(np.linalg.norm(scene.points - center[None], axis=1) <= r_err)
        crop_cols = heatmap(w[near], vmin=0.0, vmax=1.0)
        mesh = getattr(view, "mesh", None)
        col = instance_colors([pid])[0] if view.alive else DEAD_COLOR  # red once terminated (paper Fig. S9)
        self.nodes.draw_inspector(
            crop_points=scene.points[near],
            crop_colors=crop_cols,
            sampled_points=np.asarray(view.sampled_points, np.float32).reshape(-1, 3),
            sample_color=col,
            mesh_vertices=None if mesh is None else np.asarray(mesh.vertices),
            mesh_faces=None if mesh is None else np.asarray(mesh.faces),
            center=center,
            radius=r_err,
            label=f"#{pid} t={t}",
        )
        self._inspect_weights = w
        if s.color_mode != "weights":
            s.color_mode = "weights"
            self._gui_set(self.panels.gui_color, "proposal weights")
        self.draw_point_colors()
        self.nodes.set_display(s.display, recolored=True)
        self._show_results()
        self.panels.gui_inspect_info.content = inspect_markdown(pid, t, view, instances=result.instances)

    # ================================================================== 5./6. results and ground truth
    def set_threshold(self, threshold: float) -> None:
        """Filter the final instances by confidence (visibility + colours only, no re-run)."""
        with self._lock:
            s = self.state
            s.threshold = float(threshold)
            self._gui_set(self.panels.gui_threshold, s.threshold)
            if s.result is None:
                return
            self._show_result_view()  # the threshold filters the final instances: show them
            keep = self.kept_mask()
            self._show_results()
            self.draw_point_colors()
            inst = s.result.instances
            self.panels.gui_result_info.content = result_summary_markdown(
                inst, keep, threshold=s.threshold, out_tau=s.result.config.out_tau,
                hidden_by_hand=int((keep & ~self.shown_mask()).sum()),
            )
            self.panels.gui_legend.content = legend_html(inst, self.shown_mask())
            self._update_gt_panel(keep)
            self._update_instance_table()

    def set_mask_band(self, tau_out: float) -> bool:
        """Re-derive the output masks at SDF band `tau_out` from the stored latents (no re-run).

        Colours, ground-truth metrics and exports follow; the result's config records the band. Returns False
        (status line says why) when there is no result or no prior to decode with.
        """
        with self._lock:
            s = self.state
            if s.result is None or s.scene is None:
                return False
            tau = float(np.clip(tau_out, *MASK_BAND_RANGE))
            self._gui_set(self.panels.gui_mask_band, tau)
            if abs(tau - s.result.config.out_tau) < 1e-9:
                return True
            try:
                if self._mask_dist is None or self._mask_dist[0] != self._generation:
                    from efem_viz.em.masks import instance_distances

                    self._set_status("Decoding the instances' final shapes for the mask band …")
                    self._mask_dist = (self._generation,
                                       instance_distances(s.result, s.scene, self.priors.for_run(s.result.trace)))
                dist = self._mask_dist[1]
                masks = dist.masks(tau, s.result.config.gamma_out)
            except (RuntimeError, ValueError) as exc:
                self._set_status(f"Mask band unavailable: {exc}", error=True)
                return False
            inst = dataclasses.replace(s.result.instances, masks=masks)
            s.result = dataclasses.replace(s.result, instances=inst, config=s.result.config.replace(tau_out=tau))
            self._gt_cache.clear()
            self._mask_version += 1
            self.set_threshold(s.threshold)
            self._set_status(f"Masks re-derived at τ_out = {tau:g} from the stored latents; nothing was re-run.")
            return True

    def kept_mask(self) -> np.ndarray:
        """(K,) bool: final instances at or above the threshold (what the metrics and exports take)."""
        res = self.state.result
        if res is None:
            return np.zeros(0, bool)
        return res.instances.kept(self.state.threshold)

    def shown_mask(self) -> np.ndarray:
        """(K,) bool: final instances drawn: at or above the threshold and not hidden in the instance table."""
        res = self.state.result
        if res is None:
            return np.zeros(0, bool)
        return st.shown_mask(res.instances, self.state.threshold, self.state.hidden)

    # ---------------------------------------------------------------- the instance table
    def _instance_index(self, pid: int | None) -> int:
        """Position in the result's instances of proposal id `pid`.

        Raises:
            ValueError: no result, no instance chosen, or no instance with that id.
        """
        res = self.state.result
        if res is None:
            raise ValueError("no result: load or run one first")
        if pid is None:
            raise ValueError("no instance chosen: pick one in the Instance dropdown")
        hit = np.flatnonzero(np.asarray(res.instances.ids).reshape(-1) == int(pid))
        if hit.size == 0:
            raise ValueError(f"the result has no instance #{int(pid)}")
        return int(hit[0])

    def choose_instance(self, pid: int | None) -> None:
        """Choose a row of the instance table (None: none); its *Visible* box and mark follow."""
        with self._lock:
            if pid is not None:
                self._instance_index(pid)
            self.state.table_row = None if pid is None else int(pid)
            self._update_instance_table()

    def set_instance_visible(self, pid: int | None, visible: bool) -> None:
        """Show or hide one final instance (its mesh, box, label and point colours); a view like the threshold.

        Raises:
            ValueError: no such instance.
        """
        with self._lock:
            self._instance_index(pid)
            assert pid is not None
            s = self.state
            s.table_row = int(pid)
            if visible:
                s.hidden.discard(int(pid))
            else:
                s.hidden.add(int(pid))
            self.set_threshold(s.threshold)  # redraw layers, colours, summary, legend and table

    def fly_to_instance(self, pid: int | None, *, client: Any = None) -> None:
        """Point one browser's camera (every browser's when None) at an instance: the box of its points (of its
        box when it has none), seen from the fitted view's direction (`efem_viz.serve.camera.fly_to_view`).

        Raises:
            ValueError: no such instance.
        """
        with self._lock:
            k = self._instance_index(pid)
            s = self.state
            inst, scene = s.require_result().instances, s.require_scene()
            mask = np.asarray(inst.masks[k], np.int64)
            pts = scene.points[mask] if mask.size else np.asarray(inst.obb(k).corners, np.float64)
            lo_s, hi_s = scene.bounds
            view = fly_to_view(pts.min(axis=0), pts.max(axis=0), home=self.camera_guard.view,
                               scene_diagonal=float(np.linalg.norm(np.subtract(hi_s, lo_s))))
            row_id = int(inst.ids[k])
            s.table_row = row_id
            self._update_instance_table()
            below = not bool(inst.kept(s.threshold)[k])
        self.camera_guard.place(view, client)
        if below:
            self._set_status(f"Instance #{row_id} (confidence {float(inst.confidence[k]):.2f}) is below the "
                             f"confidence threshold {s.threshold:.2f}: lower it to see the instance.")

    def step_instance(self, step: int, *, client: Any = None) -> int:
        """Choose the next (`step` = 1) or previous (-1) row of the instance table (most confident first, wrapping
        around) and fly to it; returns its proposal id.

        Raises:
            ValueError: no result or no instance.
        """
        with self._lock:
            res = self.state.result
            if res is None or len(res.instances) == 0:
                raise ValueError("no instances: load or run a result first")
            ids = [option_id(o) for o in instance_options(res.instances)]
            pid = step_row(ids, self.state.table_row, step)
        self.fly_to_instance(pid, client=client)
        return pid

    def _update_instance_table(self) -> None:
        """Redraw the instance table, its dropdown (options and choice), *Visible* box and buttons."""
        s = self.state
        p = self.panels
        inst = None if s.result is None else s.result.instances
        if inst is None or len(inst) == 0:
            p.gui_instance.options = (NO_ROW,)
            self._gui_set(p.gui_instance, NO_ROW)
            p.gui_instance_table.content = "_No final instances._" if inst is not None else ""
            for h in (p.gui_instance_visible, p.gui_fly_to, p.gui_instance_prev, p.gui_instance_next):
                h.disabled = True
            return
        opts = instance_options(inst)
        if tuple(p.gui_instance.options) != opts:
            p.gui_instance.options = opts
        if s.table_row is not None and s.table_row not in {option_id(o) for o in opts}:
            s.table_row = None
        self._gui_set(p.gui_instance, option_for(opts, s.table_row) if s.table_row is not None else opts[0])
        if s.table_row is None:  # the dropdown shows the first row: that is the one chosen
            s.table_row = option_id(opts[0])
        self._gui_set(p.gui_instance_visible, s.table_row not in s.hidden)
        for h in (p.gui_instance_visible, p.gui_fly_to, p.gui_instance_prev, p.gui_instance_next):
            h.disabled = False
        metrics = self._gt_metrics_or_none() if s.scene is not None and s.scene.has_gt else None
        p.gui_instance_table.content = instance_table_markdown(inst, threshold=s.threshold, hidden=s.hidden,
                                                               metrics=metrics, selected=s.table_row)

    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None:
        with self._lock:
            s = self.state
            s.show_meshes, s.show_obbs, s.show_axes = bool(meshes), bool(obbs), bool(axes)
            self._show_result_view()
            self._show_results()

    def _show_results(self) -> None:
        """Result layers per the toggles and the threshold; meshes step aside while the points carry a weight heat
        map or the TP/FP/FN colours (they would hide them)."""
        s = self.state
        keep = self.shown_mask()
        if s.view_mode != "result":  # one EM step on screen: no final instance over it
            keep = np.zeros_like(keep)
        self.nodes.show_results(
            keep,
            show_meshes=s.show_meshes and s.color_mode in ("rgb", "instances"),
            show_obbs=s.show_obbs,
            show_axes=s.show_axes,
        )

    def _update_gt_panel(self, keep: np.ndarray) -> None:
        s = self.state
        p = self.panels
        if s.scene is None or not s.scene.has_gt or s.result is None:
            p.gui_gt_info.content = "_No ground truth in this scene._" if s.scene is not None else ""
            p.gui_pr_plot.visible = False
            return
        try:
            metrics = self._gt_metrics()
        except Exception as exc:  # noqa: BLE001 - evaluation problems must not break the threshold view
            logger.exception("ground-truth evaluation failed")
            p.gui_gt_info.content = f"_Ground-truth evaluation failed: {exc}_"
            p.gui_pr_plot.visible = False
            return
        p.gui_gt_info.content = gt_markdown(len(s.scene.instance_ids()), s.threshold, metrics)
        set_figure(p.gui_pr_plot, pr_figure(metrics.curves, point=metrics.point))
        p.gui_pr_plot.visible = True

    def _gt_metrics(self) -> GTMetrics:
        """Ground-truth metrics of the current result at the current threshold (cached per threshold)."""
        s = self.state
        key = (self._generation, round(float(s.threshold), 6))
        cached = self._gt_cache.get(key)
        if cached is None:
            cached = gt_metrics(s.require_result().instances, s.require_scene(), s.threshold)
            if len(self._gt_cache) > 64:
                self._gt_cache.clear()
            self._gt_cache[key] = cached
        return cached

    def _gt_metrics_or_none(self) -> GTMetrics | None:
        try:
            return self._gt_metrics()
        except Exception:  # noqa: BLE001 - shown in the ground-truth panel
            return None

    def draw_point_colors(self) -> None:
        """Recolour the scene points for the current colour mode (sends only (N,3) uint8)."""
        s = self.state
        if s.scene is None:
            return
        base = s.scene.colors
        mode = s.color_mode
        cols: np.ndarray
        key: Any
        shown = "rgb"  # the colouring in effect: its key is shown under the Colour control
        boxes: np.ndarray | None = None
        if mode in ("instances", "gt_match") and s.view_mode != "result":
            cols, key = base, ("rgb", id(base))  # one EM step on screen: no final instance colours
        elif mode == "instances" and s.result is not None:
            keep = self.shown_mask()
            cols = instance_point_colors(base, s.result.instances, keep)
            key = ("inst", self._generation, self._mask_version, keep.tobytes())
            shown = "instances"
        elif mode == "gt_match" and s.result is not None and s.scene.has_gt and self._gt_metrics_or_none() is not None:
            m = self._gt_metrics()
            kept = np.flatnonzero(self.kept_mask())  # the metrics index the kept instances
            drawn = self.shown_mask()
            off = {j for j, k in enumerate(kept) if not drawn[k]}  # hidden in the instance table: grey
            gt_instance = s.require_scene().instance
            assert gt_instance is not None  # has_gt
            cols = gt_match_colors(base, m.masks, gt_instance, tp=[j for j in m.tp if j not in off],
                                   fp=[j for j in m.fp if j not in off], fn=m.fn)
            key = ("gt", self._generation, self._mask_version, drawn.tobytes())
            shown = "gt_match"
            boxes = np.array(self.nodes.results.colors, np.uint8, copy=True)
            for ks, colour in ((m.tp, TP_COLOR), (m.fp, FP_COLOR)):
                for k in ks:
                    if int(k) < kept.size and kept[int(k)] < len(boxes):
                        boxes[kept[int(k)]] = colour
        elif mode in ("instances", "gt_match") and s.result is not None:
            keep = self.shown_mask()
            cols = instance_point_colors(base, s.result.instances, keep)
            key = ("inst", self._generation, self._mask_version, keep.tobytes())
            shown = "instances"
        elif mode == "weights" and s.selected is not None and self._inspect_weights is not None:
            cols = weights_colors(base, self._inspect_weights)
            key = ("w", self._generation, s.selected, s.step)
            shown = "weights"
        else:
            cols, key = base, ("rgb", id(base))
        self.nodes.set_point_colors(cols, key=key)
        self.nodes.set_box_colors(boxes)
        self.panels.gui_color_key.content = color_key_html(shown)

    # ================================================================== 7. export
    def export_results(self, out_dir: str | Path, *, root: Path | None = None) -> Path | None:
        """Write the thresholded result: ScanNet layout + coloured PLY under `out_dir` (a Python caller's choice;
        the GUI button goes through `export_from_gui`, confined to the output root).

        Args:
            out_dir: the export folder.
            root: when given, every folder and file written must resolve inside it (links followed), checked
                before anything is written.
        """
        from efem_viz.viewer.export import export_results

        s = self.state
        if s.result is None or s.scene is None:
            self._set_status("Nothing to export: load or run a result first.", error=True)
            return None
        out = export_results(s.result, s.scene, Path(out_dir), threshold=s.threshold, root=root)
        self.panels.gui_export_info.content = f"Results written to `{out}`"
        self._set_status(f"Exported results to {out}.")
        return out

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None) -> Path | None:
        """Write the static demo page `<out_dir>/index.html` (final result + playback of the steps).

        Args:
            out_dir: the page's folder (a Python caller's choice); None = `<output root>/static/<scene>/`, never
                the installed package or the checkout. The GUI button goes through `export_from_gui`.
            root: as in `export_results`.
        """
        from efem_viz.viewer.export import export_static_demo

        s = self.state
        if s.result is None or s.scene is None:
            self._set_status("Nothing to export: load or run a result first.", error=True)
            return None
        target = Path(out_dir) if out_dir is not None else self.out_root / "static" / safe_name(s.scene.name)
        try:
            prior = self.priors.for_run(s.result.trace)
        except RuntimeError as exc:
            prior = None
            logger.info("static demo without decoded shapes: %s", exc)
        self._set_status(f"Exporting the static demo of {s.scene.name} …")
        out = export_static_demo(s.scene, s.result, target, threshold=s.threshold, prior=prior, root=root)
        self.panels.gui_export_info.content = f"Static demo written to `{out}`"
        self._set_status(f"Exported static demo to {out}.")
        return out


def _row_id(option: str) -> int | None:
    """The proposal id of an instance-table option (None for `NO_ROW`)."""
    return None if option == NO_ROW else option_id(option)
