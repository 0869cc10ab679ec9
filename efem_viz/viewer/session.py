"""The viewer's headless session: every viewer action on typed data, no viser, no GUI handle.

`ViewerSession` owns the viewer's state (`ViewerState`) and does what the viewer does: open a scene of the
discovered list, load a saved result or run EFEM (progress callback, cancel), step through the EM iterations,
set the confidence threshold and the mask band, inspect a proposal, the instance table's actions, and the exports
(results, static demo; both keep their path confinement). It computes what the GUI draws (`StepView`,
`Inspection`, `PointColors`) and never draws it: `efem_viz.viewer.app.ViewerApp` is the thin viser layer on top
(builds the panels, translates GUI events into session calls, draws the session's state).

A script or a notebook drives it directly (`examples/viewer_session.py`)::

    session = ViewerSession(["sample_scenes"])
    session.open_scene("syn_z_1")
    session.load_result()
    session.set_threshold(0.3)
    print(session.shown_mask())

Threading: the methods are safe to call from several threads; `lock` (re-entrant) guards the state, and the app
holds it while it draws. `run()` and `load_result()` are synchronous: the app calls them from its worker threads.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Hashable
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

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
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.prior.registry import PriorSet
from efem_viz.serve.outputs import default_output_dir
from efem_viz.serve.table import option_id, step_row
from efem_viz.viewer import state as st
from efem_viz.viewer.legend import instance_options
from efem_viz.viewer.nodes import decode_shape, proposal_samples
from efem_viz.viewer.panels import COLOR_MODES, MASK_BAND_RANGE, VIEW_MODES
from efem_viz.viewer.scenes import SceneEntry, discover_scenes, is_inside, trace_path_for
from efem_viz.viewer.state import DEFAULT_CONFIDENCE_CUT, ViewerState
from efem_viz.viewer.texts import safe_name
from efem_viz.viewer.trace_queries import alive_table, is_dead_at, proposal_center, top_n

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.masks import InstanceDistances
    from efem_viz.em.results import EMResult
    from efem_viz.em.solver import StepInfo
    from efem_viz.em.trace import ProposalView
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

StatusListener = Callable[[str, bool], None]
"""Called with (text, is_error) whenever the session's status line changes."""
ProgressCallback = Callable[["StepInfo"], None]
"""Called after each EM step with the solver's step info (`step`, `num_steps`, `phase`, `active`, `elapsed_s`)."""


class StepView(NamedTuple):
    """What the timeline shows at one step."""

    step: int
    """The EM step (clamped to the trace)."""
    ids: np.ndarray
    """(A,) int: proposals alive at the step."""
    scores: np.ndarray
    """(A,) float: their stationary scores."""
    drawn: np.ndarray
    """(D,) int: the proposals whose samples and decoded shapes are drawn (top `max_shapes` by score)."""


class Inspection(NamedTuple):
    """The Fig. S9 views of one inspected proposal at one step, ready to draw."""

    pid: int
    step: int
    view: ProposalView
    """The replayed `ProposalView` (weights, sampled points, decoded mesh when a prior was there, alive flag)."""
    crop_points: np.ndarray
    """(C, 3) float32, world frame: scene points inside the proposal's error ball."""
    crop_colors: np.ndarray
    """(C, 3) uint8: their weights as a heat map."""
    sampled_points: np.ndarray
    """(S, 3) float32, world frame."""
    sample_color: np.ndarray
    """(3,) uint8: the proposal's colour (red once terminated)."""
    center: np.ndarray
    """(3,) float, world frame: the error ball's centre."""
    radius: float
    """The error ball's radius (m)."""
    weights: np.ndarray
    """(N,) float32: per-point weights over the whole scene."""


class PointColors(NamedTuple):
    """The scene points' colours for the current colour mode."""

    colors: np.ndarray
    """(N, 3) uint8."""
    key: Hashable
    """A cache key: equal keys mean equal colours (the nodes skip resending them)."""
    shown: str
    """The colouring in effect ("rgb", "instances", "gt_match" or "weights"): its key is shown under the control."""
    boxes: np.ndarray | None
    """(K, 3) uint8 box colours of the final instances (TP/FP in the ground-truth view), or None: their own."""


class FlyTarget(NamedTuple):
    """Where to point a camera for one final instance."""

    pid: int
    lo: np.ndarray
    """(3,) world-frame minimum of the instance's points (of its box when it has none)."""
    hi: np.ndarray
    """(3,) world-frame maximum."""
    scene_diagonal: float
    below_threshold: bool
    """The instance is below the confidence threshold (not drawn)."""
    confidence: float


class ViewerSession:
    """The viewer without its GUI: state and every action.

    Args:
        paths: scene files and/or folders; only scene files inside them are listed and opened.
        prior: a `ShapePrior`, or None to load `prior_name` lazily when first needed (decoding, runs).
        prior_name: the prior's spec (`efem_viz.prior.registry.PriorSet`).
        run_priors: specs of more priors for runs started here (a joint solve over the prior and these).
        out_dir: the output root (exports confined to it by the app); default `view/` in the user's data folder.
        results: folders of saved results searched after each scene's own folder; with no `paths`, the scenes
            are the scene files in these folders.
        max_points: refuse scenes with more points than this.
    """

    def __init__(
        self,
        paths: Sequence[str | Path] = (),
        *,
        prior: ShapePriorLike | None = None,
        prior_name: str = DEFAULT_PRIOR,
        run_priors: Sequence[str] = (),
        out_dir: str | Path | None = None,
        results: Sequence[str | Path] = (),
        max_points: int = DEFAULT_MAX_POINTS,
    ) -> None:
        self.max_points = int(max_points)
        """Scenes with more points are refused."""
        self.state = ViewerState()
        scene_paths = list(paths) if paths else (list(results) if results else [DEFAULT_SCENE_DIR])
        self.state.entries = discover_scenes(scene_paths, result_dirs=list(results))
        self.roots = [Path(p).expanduser().resolve() for p in [*scene_paths, *results]]
        """The given paths: nothing outside them is read."""
        self.out_root = Path(out_dir if out_dir is not None else default_output_dir("view")).expanduser().resolve()
        """The output root (fixed at start)."""
        self.priors = PriorSet(prior_name, prior=prior, extra=run_priors)
        """This viewer's priors, each loaded once (`efem_viz.prior.registry.PriorSet`)."""
        self.lock = threading.RLock()
        """Guards the state (re-entrant: the app holds it while it draws)."""
        self.cancel_event = threading.Event()
        """Set to stop a running EM at its next step."""
        self.on_status: StatusListener | None = None
        """Told every status change (the app shows it in the GUI)."""
        self.generation = 0
        """Bumped on every scene/result change so stale worker results are dropped."""
        self.mask_version = 0
        """Bumped whenever the shown masks change within one result (colour caches key on it)."""
        self.no_shapes_generation = -1
        """The generation whose shapes could not be decoded (no prior): not retried on every step."""
        self.inspect_weights: np.ndarray | None = None
        """(N,) float32 weights of the inspected proposal (the "proposal weights" colouring)."""
        self.last_run_source = ""
        """The source line of the last finished run ("run (preset, seed, time)")."""
        self._view_cache: dict[tuple[int, int], ProposalView] = {}
        self._gt_cache: dict[tuple[int, float], GTMetrics] = {}
        self._mask_dist: tuple[int, InstanceDistances] | None = None
        """(generation, InstanceDistances) of the shown result: masks at any τ_out without a re-run."""

    # ================================================================== status
    def set_status(self, text: str, *, error: bool = False) -> None:
        """Record a status line (and the error, when it is one) and tell `on_status`."""
        with self.lock:
            self.state.status = text
            self.state.error = text if error else None
        if error:
            logger.warning("%s", text)
        if self.on_status is not None:
            self.on_status(text, error)

    def prior(self) -> ShapePriorLike:
        """The shape prior (loaded on first use). Raises RuntimeError with the reason when unavailable."""
        return self.priors.primary()

    def allowed(self, path: Path) -> bool:
        """May the viewer read `path`? Inside a given folder, a given file, or the saved result of a given file."""
        if is_inside(path, self.roots):
            return True
        rp = path.resolve()
        return any(r.is_file() and rp == trace_path_for(r) for r in self.roots)

    # ================================================================== 1. scenes
    def read_scene(self, name: str) -> tuple[SceneEntry, Scene] | None:
        """Load a scene of the list (no state change). None, with the status saying why, when it cannot."""
        from efem_viz.data.io import holds_predictions, load_scene

        try:
            entry = self.state.entry(name)
        except KeyError as exc:
            self.set_status(str(exc), error=True)
            return None
        if not is_inside(entry.path, self.roots):  # never read outside the given paths
            self.set_status(f"refusing to open {entry.path}: outside the given paths", error=True)
            return None
        self.set_status(f"Loading {entry.name} …")
        try:
            scene = load_scene(entry.path, max_points=self.max_points)
            if holds_predictions(entry.path) and scene.instance is not None:
                scene = scene.with_labels(None, {})  # a segment output's labels are its predictions: no ground truth
        except Exception as exc:  # noqa: BLE001 - SceneError, OSError, parser errors: show, stay up
            self.set_status(f"Could not open {entry.path.name}: {exc}", error=True)
            return None
        return entry, scene

    def show_scene(self, entry: SceneEntry, scene: Scene) -> None:
        """Make `scene` the open scene (no result yet; a run of the previous scene is cancelled)."""
        with self.lock:
            s = self.state
            s.playing = False
            if s.running:
                self.cancel_event.set()  # the run belongs to the previous scene
            self.generation += 1
            self._view_cache.clear()
            self.inspect_weights = None
            s.scene_name, s.scene, s.result, s.result_source = entry.name, scene, None, ""
            s.step, s.selected, s.color_mode, s.view_mode = 0, None, "rgb", "result"
            if scene.is_mesh and s.display == "points":
                s.display = "mesh"
            elif not scene.is_mesh:
                s.display = "points"

    def open_scene(self, name: str) -> Scene | None:
        """Open a scene of the list (`state.entries`). Returns it, or None (status says why; the previous scene
        stays). Its saved result is not loaded: call `load_result()`."""
        got = self.read_scene(name)
        if got is None:
            return None
        self.show_scene(*got)
        self.set_status(f"Opened {got[0].name} ({got[1].num_points:,} points).")
        return got[1]

    def saved_result_path(self) -> Path | None:
        """The open scene's saved result when one exists and may be read, else None."""
        s = self.state
        if s.scene_name is None:
            return None
        p = s.entry(s.scene_name).trace_path
        return p if p.is_file() and self.allowed(p) else None

    def set_display(self, display: str) -> None:
        """'points' or 'mesh'."""
        if display not in ("points", "mesh"):
            raise ValueError(f"display must be 'points' or 'mesh', got {display!r}")
        self.state.display = display  # type: ignore[assignment]

    def set_color_mode(self, mode: str) -> None:
        """'rgb', 'instances', 'gt_match' or 'weights' (the instance colourings show the result view)."""
        if mode not in COLOR_MODES.values():
            raise ValueError(f"unknown colour mode {mode!r}; expected one of {sorted(COLOR_MODES.values())}")
        self.state.color_mode = mode  # type: ignore[assignment]

    def set_view_mode(self, mode: str) -> None:
        """"step" or "result"."""
        if mode not in VIEW_MODES.values():
            raise ValueError(f"unknown view mode {mode!r}; expected one of {sorted(VIEW_MODES.values())}")
        self.state.view_mode = mode  # type: ignore[assignment]

    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None:
        """Show or hide the final instances' meshes, boxes and axes."""
        s = self.state
        s.show_meshes, s.show_obbs, s.show_axes = bool(meshes), bool(obbs), bool(axes)

    def recolored(self) -> bool:
        """Whether the points carry other colours than the scene's (the mesh display then overlays them)."""
        s = self.state
        if s.color_mode == "weights":
            return True
        return s.color_mode != "rgb" and s.view_mode == "result"

    # ================================================================== 2. results: load / run
    def read_result(self, path: str | Path | None = None) -> tuple[EMResult, str] | None:
        """Read `<scene>.efem.npz` (or `path`, inside the given paths) of the open scene (no state change).
        Returns (result, source name), or None with the status saying why."""
        from efem_viz.em import EMResult

        s = self.state
        if s.scene is None or s.scene_name is None:
            self.set_status("Open a scene first.", error=True)
            return None
        p = Path(path) if path is not None else s.entry(s.scene_name).trace_path
        if not self.allowed(p):
            self.set_status(f"refusing to read {p}: outside the given paths", error=True)
            return None
        if not p.is_file():
            self.set_status(f"No saved trace at {p.name}; run EFEM first.", error=True)
            return None
        try:
            return EMResult.load(p), str(p.name)
        except Exception as exc:  # noqa: BLE001 - corrupt file: show, stay up
            logger.exception("loading %s failed", p)
            self.set_status(f"Could not load {p.name}: {exc}", error=True)
            return None

    def load_result(self, path: str | Path | None = None) -> EMResult | None:
        """Read and show the open scene's saved result (or `path`). None when it cannot (status says why)."""
        got = self.read_result(path)
        if got is None:
            return None
        try:
            self.set_result(got[0], source=got[1])
        except Exception as exc:  # noqa: BLE001 - another scene's result: show, stay up
            self.set_status(f"Could not load {got[1]}: {exc}", error=True)
            return None
        return got[0]

    def threshold_max(self, result: EMResult) -> float:
        """The top of the threshold slider: just above the most confident instance (it hides every instance)."""
        conf = np.asarray(result.instances.confidence, float)
        hi = float(conf.max()) if conf.size else 1.0
        return float(np.ceil(hi * 100.0 + 1e-6) / 100.0 + 0.01)

    def set_result(self, result: EMResult, *, source: str) -> None:
        """Show an EMResult: the last step, no proposal inspected, its final instances in instance colours.

        Raises:
            ValueError: the result belongs to another scene.
        """
        with self.lock:
            s = self.state
            s.playing = False
            self.generation += 1
            self._view_cache.clear()
            self.inspect_weights = None
            if s.scene is not None and hasattr(result, "bind"):
                result.bind(s.scene)  # raises ValueError when the result belongs to another scene
            s.result, s.result_source, s.selected = result, source, None
            s.hidden, s.table_row = set(), None  # another result: other instances
            s.step = max(int(result.trace.num_steps) - 1, 0)
            conf = np.asarray(result.instances.confidence, float)
            best = float(conf.max()) if conf.size else 0.0
            cut_note = ""
            if s.threshold_by_user and conf.size and s.threshold <= best:  # a person's cut that still shows some
                cut_note = f" Your confidence cut {s.threshold:.2f} is kept."
            else:
                if s.threshold_by_user and conf.size:
                    cut_note = (f" Your confidence cut {s.threshold:.2f} would hide every instance (best "
                                f"{best:.2f}): this result opens at {self.default_threshold(result):.2f}.")
                s.threshold, s.threshold_by_user = self.default_threshold(result), False
            s.threshold = float(np.clip(s.threshold, 0.0, self.threshold_max(result)))
            self._mask_dist = None
            s.color_mode = "instances"
        warn = "; ".join(getattr(result, "warnings", ()))  # e.g. the free-space check was off: never silently
        self.set_status(f"Loaded result: {source}.{cut_note}" + (f" Warning: {warn}" if warn else ""),
                        error=bool(warn))

    def begin_run(self) -> int | None:
        """Mark a run as started (`state.running`). Returns its ticket (the scene generation), or None (status
        says why) when a run is in progress or no scene is open."""
        with self.lock:
            if self.state.running:
                self.set_status("A run is already in progress.", error=True)
                return None
            if self.state.scene is None:
                self.set_status("Open a scene first.", error=True)
                return None
            self.state.running = True
            self.cancel_event.clear()
            return self.generation

    def run(self, *, preset: str = "fast", proposals: int | None = None, seed: int = 0,
            on_step: ProgressCallback | None = None, show: bool = True,
            generation: int | None = None, matmul_dtype: str = "float32") -> EMResult | None:
        """Run EFEM on the open scene (synchronously; `cancel_run()` from another thread stops it).

        Args:
            preset: an `efem_viz.em.preset` name.
            proposals: the initial proposal count (None: the preset's).
            seed: the run's seed.
            matmul_dtype: `EMConfig.matmul_dtype` ("float32" or "bfloat16").
            on_step: called after each EM step with the solver's step info.
            show: show the result when done (unless the scene changed meanwhile).
            generation: the ticket of a `begin_run()` already called (None: begin here).

        Returns:
            The result, or None when cancelled, failed (status says why) or another run is in progress.
        """
        from efem_viz.em import EMCancelled, preset as make_preset, run_em

        if generation is None:
            generation = self.begin_run()
            if generation is None:
                return None
        t0 = time.perf_counter()
        try:
            scene = self.state.require_scene()
            cfg = make_preset(preset)
            if proposals is not None:
                cfg = cfg.with_proposals(int(proposals))
            cfg = cfg.replace(matmul_dtype=matmul_dtype)
            self.set_status(f"Running EFEM ({preset}, {cfg.n_init[0]} proposals, seed {seed}"
                            f"{', bf16' if matmul_dtype == 'bfloat16' else ''}) …")
            prior = self.prior()
            priors = self.priors.run_priors()
            if priors is None:
                result = run_em(scene, prior, cfg, seed=int(seed), on_step=on_step, cancel=self.cancel_event)
            else:
                result = run_em(scene, cfg=cfg, priors=priors, seed=int(seed), on_step=on_step,
                                cancel=self.cancel_event)
        except EMCancelled:
            self.set_status("Run cancelled.")
            return None
        except Exception as exc:  # noqa: BLE001
            self.set_status(f"EFEM run failed: {exc}", error=True)
            return None
        finally:
            with self.lock:
                self.state.running = False
        if generation != self.generation:
            logger.info("scene changed during the run; result dropped")
            return None
        self.last_run_source = f"run ({preset}, seed {seed}, {time.perf_counter() - t0:.1f} s)"
        if show:
            self.set_result(result, source=self.last_run_source)
        return result

    def cancel_run(self) -> None:
        """Ask a running EM to stop at its next step."""
        self.cancel_event.set()
        self.set_status("Cancelling …")

    # ================================================================== 3. timeline
    def step_view(self, step: int | None = None) -> StepView | None:
        """The proposals of a step (default: the current one), clamped to the trace; None without a result."""
        s = self.state
        if s.result is None:
            return None
        t = int(np.clip(s.step if step is None else step, 0, max(s.num_steps - 1, 0)))
        ids, scores = alive_table(s.result.trace, t)
        return StepView(t, ids, scores, top_n(ids, scores, s.max_shapes))

    def set_step(self, step: int) -> StepView | None:
        """Go to EM step `step` (clamped). Returns what the step shows, or None without a result."""
        with self.lock:
            v = self.step_view(step)
            if v is not None:
                self.state.step = v.step
            return v

    def next_step(self) -> StepView | None:
        """One step on (playback); None at the end or without a result (playback then stops)."""
        with self.lock:
            s = self.state
            if s.result is None or s.step + 1 >= s.num_steps:
                s.playing = False
                return None
            return self.set_step(s.step + 1)

    def set_max_shapes(self, n: int) -> None:
        """Draw decoded shapes for at most `n` live proposals."""
        self.state.max_shapes = max(int(n), 0)

    def set_proposal_layers(self, *, shapes: bool | None = None, samples: bool | None = None) -> None:
        """Show or hide the step's decoded shapes and samples."""
        if shapes is not None:
            self.state.show_shapes = bool(shapes)
        if samples is not None:
            self.state.show_samples = bool(samples)

    def samples(self, drawn: np.ndarray, step: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) float32 world points and (M, 3) uint8 colours of the drawn proposals' samples at a step."""
        s = self.state
        t = s.step if step is None else int(step)
        return proposal_samples(s.require_result().trace, t, drawn, s.require_scene().points)

    def decode_shape(self, pid: int, step: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(vertices, faces) of proposal `pid`'s decoded shape at `step`, from its stored latent.

        Raises:
            RuntimeError: no prior to decode with.
        """
        from efem_viz.em.replay import prior_latent

        trace = self.state.require_result().trace
        prior, latent = prior_latent(trace, pid, step, self.priors.for_run(trace))
        return decode_shape(prior, latent, resolution=trace.config.mesh_resolution)

    def is_dead_at(self, pid: int, step: int) -> bool:
        """Whether proposal `pid` has been eliminated by `step`."""
        return is_dead_at(self.state.require_result().trace, pid, step)

    # ================================================================== 4. proposals
    def select_proposal(self, pid: int | None) -> bool:
        """Choose the inspected proposal (None clears). Returns whether one is to be inspected (then call
        `inspect()`); clearing leaves the weights colouring for the instance (or scene) colours."""
        with self.lock:
            s = self.state
            s.selected = None if pid is None else int(pid)
            if pid is None or s.result is None:
                if s.color_mode == "weights":
                    s.color_mode = "instances" if s.result is not None else "rgb"
                return False
            return True

    def proposal_view(self, pid: int, step: int, prior: ShapePriorLike | None) -> ProposalView:
        """The replayed view of proposal `pid` at `step` (cached; with its decoded mesh when `prior` is given)."""
        key = (int(pid), int(step))
        v = self._view_cache.get(key)
        if v is None or (prior is not None and getattr(v, "mesh", None) is None):
            v = self.state.require_result().replay.view(int(pid), int(step), prior, mesh=prior is not None)
            self._view_cache[key] = v
            if len(self._view_cache) > 256:
                self._view_cache.pop(next(iter(self._view_cache)))
        return v

    def inspect(self, pid: int, step: int | None = None) -> Inspection:
        """The Fig. S9 views of proposal `pid` at `step` (default: the current step).

        Raises:
            ValueError: the proposal cannot be replayed at that step.
        """
        s = self.state
        t = s.step if step is None else int(step)
        try:
            prior = self.priors.for_trace(s.require_result().trace, pid)
        except RuntimeError as exc:
            prior = None  # the first step of an episode still has weights (the crop); later steps need the prior
            logger.info("inspecting without a prior: %s", exc)
        view = self.proposal_view(pid, t, prior)
        scene, result = s.require_scene(), s.require_result()
        w = np.asarray(view.weights, np.float32).reshape(-1)
        r_err = float(result.trace.prop_r_err[pid])
        center = proposal_center(result.trace, pid, t)
        near = np.flatnonzero(np.linalg.norm(scene.points - center[None], axis=1) <= r_err)
        col = instance_colors([pid])[0] if view.alive else DEAD_COLOR  # red once terminated (paper Fig. S9)
        return Inspection(pid=int(pid), step=t, view=view, crop_points=scene.points[near],
                          crop_colors=heatmap(w[near], vmin=0.0, vmax=1.0),
                          sampled_points=np.asarray(view.sampled_points, np.float32).reshape(-1, 3),
                          sample_color=col, center=center, radius=r_err,
                          weights=w)

    def show_inspection(self, ins: Inspection) -> bool:
        """Record a finished inspection (weights colouring). False when it is stale (another proposal, step or
        result meanwhile)."""
        with self.lock:
            s = self.state
            if s.selected != ins.pid or s.step != ins.step or s.result is None:
                return False
            self.inspect_weights = ins.weights
            s.color_mode = "weights"
            return True

    # ================================================================== 5./6. results and ground truth
    def set_threshold(self, threshold: float, *, by_user: bool = True) -> None:
        """Filter the final instances by confidence (a view, no re-run). `by_user=False` for the app's own
        redraws: only a person's cut is carried over to the next result (`set_result`)."""
        self.state.threshold = float(threshold)
        if by_user:
            self.state.threshold_by_user = True

    @staticmethod
    def suggested_preset(scene: "Scene") -> str:
        """The Run preset that fits a scene: "real" for a single-view capture (`import-rgbd` provenance or a
        recorded camera), else "fast" (issue 37: a real scan was run with the synthetic `fast` settings)."""
        from efem_viz.geometry.camera import Camera

        prov = dict(getattr(scene, "provenance", None) or {})
        camera, problem = Camera.parse(prov)
        return "real" if prov.get("source") == "rgbd" or camera is not None or problem is not None else "fast"

    def default_threshold(self, result: EMResult) -> float:
        """The cut a result opens with: `DEFAULT_CONFIDENCE_CUT`, lowered to its best instance's confidence when
        that is below (issue 37: a real frame whose best instance is 0.11 opened with every instance hidden)."""
        conf = np.asarray(result.instances.confidence, float)
        if not conf.size:
            return DEFAULT_CONFIDENCE_CUT
        return float(min(DEFAULT_CONFIDENCE_CUT, np.floor(float(conf.max()) * 100.0) / 100.0))

    def set_mask_band(self, tau_out: float) -> bool:
        """Re-derive the output masks at SDF band `tau_out` (clamped to `MASK_BAND_RANGE`) from the stored
        latents (no re-run). Colours, metrics and exports follow; the result's config records the band.

        Returns:
            False (status says why) when there is no result or no prior to decode with.
        """
        with self.lock:
            s = self.state
            if s.result is None or s.scene is None:
                return False
            tau = float(np.clip(tau_out, *MASK_BAND_RANGE))
            if abs(tau - s.result.config.out_tau) < 1e-9:
                return True
            try:
                if self._mask_dist is None or self._mask_dist[0] != self.generation:
                    from efem_viz.em.masks import instance_distances

                    self.set_status("Decoding the instances' final shapes for the mask band …")
                    self._mask_dist = (self.generation,
                                       instance_distances(s.result, s.scene, self.priors.for_run(s.result.trace)))
                masks = self._mask_dist[1].masks(tau, s.result.config.gamma_out)
            except (RuntimeError, ValueError) as exc:
                self.set_status(f"Mask band unavailable: {exc}", error=True)
                return False
            inst = dataclasses.replace(s.result.instances, masks=masks)
            s.result = dataclasses.replace(s.result, instances=inst, config=s.result.config.replace(tau_out=tau))
            self._gt_cache.clear()
            self.mask_version += 1
            self.set_status(f"Masks re-derived at τ_out = {tau:g} from the stored latents; nothing was re-run.")
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

    def gt_metrics(self) -> GTMetrics:
        """Ground-truth metrics of the result at the current threshold (cached per threshold).

        Raises:
            RuntimeError: no scene or result; ValueError: the scene has no ground truth.
        """
        s = self.state
        key = (self.generation, round(float(s.threshold), 6))
        cached = self._gt_cache.get(key)
        if cached is None:
            cached = gt_metrics(s.require_result().instances, s.require_scene(), s.threshold)
            if len(self._gt_cache) > 64:
                self._gt_cache.clear()
            self._gt_cache[key] = cached
        return cached

    def gt_metrics_or_none(self) -> GTMetrics | None:
        """`gt_metrics()`, or None when they cannot be computed."""
        try:
            return self.gt_metrics()
        except Exception:  # noqa: BLE001 - shown in the ground-truth panel
            return None

    def point_colors(self, result_box_colors: np.ndarray | None = None) -> PointColors | None:
        """The scene points' colours for the colour mode and view (None without a scene).

        Args:
            result_box_colors: (K, 3) uint8 the final instances' own box colours (the TP/FP view recolours a copy).
        """
        s = self.state
        if s.scene is None:
            return None
        base = s.scene.colors
        mode = s.color_mode
        if mode in ("instances", "gt_match") and s.view_mode != "result":
            return PointColors(base, ("rgb", id(base)), "rgb", None)  # one EM step on screen: no final instances
        if (mode == "gt_match" and s.result is not None and s.scene.has_gt
                and self.gt_metrics_or_none() is not None):
            return self._gt_point_colors(base, result_box_colors)
        if mode in ("instances", "gt_match") and s.result is not None:
            keep = self.shown_mask()
            return PointColors(instance_point_colors(base, s.result.instances, keep),
                               ("inst", self.generation, self.mask_version, keep.tobytes()), "instances", None)
        if mode == "weights" and s.selected is not None and self.inspect_weights is not None:
            return PointColors(weights_colors(base, self.inspect_weights),
                               ("w", self.generation, s.selected, s.step), "weights", None)
        return PointColors(base, ("rgb", id(base)), "rgb", None)

    def _gt_point_colors(self, base: np.ndarray, result_box_colors: np.ndarray | None) -> PointColors:
        """TP/FP/FN colours of the points and boxes (instances hidden in the table: grey)."""
        m = self.gt_metrics()
        kept = np.flatnonzero(self.kept_mask())  # the metrics index the kept instances
        drawn = self.shown_mask()
        off = {j for j, k in enumerate(kept) if not drawn[k]}
        gt_instance = self.state.require_scene().instance
        assert gt_instance is not None  # has_gt
        cols = gt_match_colors(base, m.masks, gt_instance, tp=[j for j in m.tp if j not in off],
                               fp=[j for j in m.fp if j not in off], fn=m.fn)
        boxes = None
        if result_box_colors is not None:
            boxes = np.array(result_box_colors, np.uint8, copy=True)
            for ks, colour in ((m.tp, TP_COLOR), (m.fp, FP_COLOR)):
                for k in ks:
                    if int(k) < kept.size and kept[int(k)] < len(boxes):
                        boxes[kept[int(k)]] = colour
        key = ("gt", self.generation, self.mask_version, drawn.tobytes())
        return PointColors(cols, key, "gt_match", boxes)

    # ---------------------------------------------------------------- the instance table
    def instance_index(self, pid: int | None) -> int:
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

    def table_options(self) -> tuple[str, ...]:
        """The instance table's rows (most confident first) as dropdown options; keeps `state.table_row` on one
        of them (the first when none or a stale one is chosen). Empty without instances."""
        s = self.state
        if s.result is None or len(s.result.instances) == 0:
            return ()
        opts = instance_options(s.result.instances)
        if s.table_row is not None and s.table_row not in {option_id(o) for o in opts}:
            s.table_row = None
        if s.table_row is None:  # the dropdown shows the first row: that is the one chosen
            s.table_row = option_id(opts[0])
        return opts

    def choose_instance(self, pid: int | None) -> None:
        """Choose a row of the instance table (None: none). Raises ValueError for an unknown id."""
        with self.lock:
            if pid is not None:
                self.instance_index(pid)
            self.state.table_row = None if pid is None else int(pid)

    def set_instance_visible(self, pid: int | None, visible: bool) -> None:
        """Show or hide one final instance (a view like the threshold). Raises ValueError for an unknown id."""
        with self.lock:
            self.instance_index(pid)
            assert pid is not None
            s = self.state
            s.table_row = int(pid)
            if visible:
                s.hidden.discard(int(pid))
            else:
                s.hidden.add(int(pid))

    def fly_target(self, pid: int | None) -> FlyTarget:
        """Choose instance `pid` in the table and say where a camera should look at it (the status line says so
        when it is below the threshold).

        Raises:
            ValueError: no such instance.
        """
        with self.lock:
            k = self.instance_index(pid)
            s = self.state
            inst, scene = s.require_result().instances, s.require_scene()
            mask = np.asarray(inst.masks[k], np.int64)
            pts = scene.points[mask] if mask.size else np.asarray(inst.obb(k).corners, np.float64)
            lo_s, hi_s = scene.bounds
            s.table_row = int(inst.ids[k])
            target = FlyTarget(pid=int(inst.ids[k]), lo=pts.min(axis=0), hi=pts.max(axis=0),
                               scene_diagonal=float(np.linalg.norm(np.subtract(hi_s, lo_s))),
                               below_threshold=not bool(inst.kept(s.threshold)[k]),
                               confidence=float(inst.confidence[k]))
        if target.below_threshold:
            self.set_status(f"Instance #{target.pid} (confidence {target.confidence:.2f}) is below the "
                            f"confidence threshold {s.threshold:.2f}: lower it to see the instance.")
        return target

    def next_instance(self, step: int) -> int:
        """The proposal id of the next (`step` = 1) or previous (-1) row of the instance table (most confident
        first, wrapping around).

        Raises:
            ValueError: no result or no instance.
        """
        with self.lock:
            res = self.state.result
            if res is None or len(res.instances) == 0:
                raise ValueError("no instances: load or run a result first")
            ids = [option_id(o) for o in instance_options(res.instances)]
            return step_row(ids, self.state.table_row, step)

    # ================================================================== 7. export
    def export_results(self, out_dir: str | Path, *, root: Path | None = None) -> Path | None:
        """Write the thresholded result (ScanNet layout + coloured PLY) under `out_dir`.

        Args:
            out_dir: the export folder.
            root: when given, every folder and file written must resolve inside it (links followed), checked
                before anything is written.

        Returns:
            The folder written, or None (status says why) without a result.
        """
        from efem_viz.viewer.export import export_results

        s = self.state
        if s.result is None or s.scene is None:
            self.set_status("Nothing to export: load or run a result first.", error=True)
            return None
        out = export_results(s.result, s.scene, Path(out_dir), threshold=s.threshold, root=root)
        self.set_status(f"Exported results to {out}.")
        return out

    def static_target(self, folder: Path | None = None) -> Path | None:
        """The static demo's folder: `<folder or output root>/static/<scene>/` (None without a scene)."""
        scene = self.state.scene
        if scene is None:
            return None
        return (folder if folder is not None else self.out_root) / "static" / safe_name(scene.name)

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None) -> Path | None:
        """Write the static demo page `<out_dir>/index.html` (final result + playback of the steps).

        Args:
            out_dir: the page's folder; None = `<output root>/static/<scene>/`.
            root: as in `export_results`.
        """
        from efem_viz.viewer.export import export_static_demo

        s = self.state
        if s.result is None or s.scene is None:
            self.set_status("Nothing to export: load or run a result first.", error=True)
            return None
        target = Path(out_dir) if out_dir is not None else self.static_target()
        assert target is not None
        try:
            prior = self.priors.for_run(s.result.trace)
        except RuntimeError as exc:
            prior = None
            logger.info("static demo without decoded shapes: %s", exc)
        self.set_status(f"Exporting the static demo of {s.scene.name} …")
        out = export_static_demo(s.scene, s.result, target, threshold=s.threshold, prior=prior, root=root)
        self.set_status(f"Exported static demo to {out}.")
        return out
