"""The viewer's headless session: every viewer action on typed data, no viser, no GUI handle.

`ViewerSession` owns the viewer's state (`ViewerState`) and does what the viewer does: open a scene of the
discovered list, load a saved result or run EFEM (progress callback, cancel), step through the EM iterations,
set the confidence threshold and the mask band, inspect a proposal, the instance table's actions, and the exports
(results, static demo; both keep their path confinement). It computes what the GUI draws (`StepView`,
`Inspection`, `PointColors`) and never draws it: `efem_viz.viewer.app.ViewerApp` is the thin viser layer on top
(builds the panels, translates GUI events into session calls, draws the session's state).

The session is a facade over its rooms (`efem_viz.viewer.rooms`, one job each; docs/INTERFACES.md): it is the
rooms' shared core (`rooms.core.ViewerCore`: state, lock, status, priors, generation) and forwards each action to
the room that does it (`session.scenes`, `.results`, `.runs`, `.timeline`, `.inspection`, `.instances`, `.export`).
Neither it nor anything it imports loads viser or a drawing module (`tests/test_layering.py`).

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

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from efem_viz.data.scene import DEFAULT_MAX_POINTS
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.viewer.rooms.core import (
    BUNDLED_SCENE_DIR,
    CHECKOUT_SCENE_DIR,
    DEFAULT_SCENE_DIR,
    REPO_ROOT,
    StatusListener,
    ViewerCore,
    default_scene_dir,
)
from efem_viz.viewer.rooms.export import ExportRoom
from efem_viz.viewer.rooms.inspect import Inspection, InspectRoom
from efem_viz.viewer.rooms.instances import FlyTarget, InstanceRoom
from efem_viz.viewer.rooms.results import PointColors, ResultRoom
from efem_viz.viewer.rooms.runs import ProgressCallback, RunRoom, RunSettings
from efem_viz.viewer.rooms.scenes import SceneRoom
from efem_viz.viewer.rooms.timeline import StepView, TimelineRoom

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult
    from efem_viz.em.trace import ProposalView
    from efem_viz.eval.comparison import GTMetrics
    from efem_viz.prior.config import ShapePriorLike
    from efem_viz.viewer.scenes import SceneEntry

__all__ = [
    "BUNDLED_SCENE_DIR", "CHECKOUT_SCENE_DIR", "DEFAULT_SCENE_DIR", "REPO_ROOT", "FlyTarget", "Inspection",
    "PointColors", "ProgressCallback", "RunSettings", "StatusListener", "StepView", "ViewerSession", "default_scene_dir",
]


class ViewerSession(ViewerCore):
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
        device: str = "cpu",
    ) -> None:
        super().__init__(paths, prior=prior, prior_name=prior_name, run_priors=run_priors, out_dir=out_dir,
                         results=results, max_points=max_points, device=device)
        self.scenes = SceneRoom(self)
        """Opening scenes and the display choices."""
        self.results = ResultRoom(self)
        """The shown result: cut, mask band, ground truth, point colours."""
        self.runs = RunRoom(self, self.results)
        """EFEM runs (start, progress, cancel)."""
        self.timeline = TimelineRoom(self)
        """Stepping through the EM iterations."""
        self.inspection = InspectRoom(self)
        """The inspected proposal (Fig. S9 views)."""
        self.instances = InstanceRoom(self, self.results)
        """The instance table."""
        self.export = ExportRoom(self)
        """Result and static-demo exports."""

    @property
    def last_run_source(self) -> str:
        """The source line of the last finished run ("run (preset, seed, time)")."""
        return self.runs.last_run_source

    # ================================================================== 1. scenes (rooms/scenes.py)
    def read_scene(self, name: str) -> tuple[SceneEntry, Scene] | None:
        """`SceneRoom.read_scene`."""
        return self.scenes.read_scene(name)

    def show_scene(self, entry: SceneEntry, scene: Scene) -> None:
        """`SceneRoom.show_scene`."""
        self.scenes.show_scene(entry, scene)

    def open_scene(self, name: str) -> Scene | None:
        """`SceneRoom.open_scene`."""
        return self.scenes.open_scene(name)

    def saved_result_path(self) -> Path | None:
        """`SceneRoom.saved_result_path`."""
        return self.scenes.saved_result_path()

    def set_display(self, display: str) -> None:
        """`SceneRoom.set_display`."""
        self.scenes.set_display(display)

    def set_color_mode(self, mode: str) -> None:
        """`SceneRoom.set_color_mode`."""
        self.scenes.set_color_mode(mode)

    def set_view_mode(self, mode: str) -> None:
        """`SceneRoom.set_view_mode`."""
        self.scenes.set_view_mode(mode)

    def set_result_layers(self, *, meshes: bool, obbs: bool, axes: bool) -> None:
        """`SceneRoom.set_result_layers`."""
        self.scenes.set_result_layers(meshes=meshes, obbs=obbs, axes=axes)

    def recolored(self) -> bool:
        """`SceneRoom.recolored`."""
        return self.scenes.recolored()

    # ================================================================== 2. results and ground truth (rooms/results.py)
    def read_result(self, path: str | Path | None = None) -> tuple[EMResult, str] | None:
        """`ResultRoom.read_result`."""
        return self.results.read_result(path)

    def load_result(self, path: str | Path | None = None) -> EMResult | None:
        """`ResultRoom.load_result`."""
        return self.results.load_result(path)

    def threshold_max(self, result: EMResult) -> float:
        """`ResultRoom.threshold_max`."""
        return self.results.threshold_max(result)

    def set_result(self, result: EMResult, *, source: str) -> None:
        """`ResultRoom.set_result`."""
        self.results.set_result(result, source=source)

    def set_threshold(self, threshold: float, *, by_user: bool = True) -> None:
        """`ResultRoom.set_threshold`."""
        self.results.set_threshold(threshold, by_user=by_user)

    @staticmethod
    def suggested_preset(scene: "Scene") -> str:
        """`ResultRoom.suggested_preset`."""
        return ResultRoom.suggested_preset(scene)

    def default_threshold(self, result: EMResult) -> float:
        """`ResultRoom.default_threshold`."""
        return self.results.default_threshold(result)

    def set_mask_band(self, tau_out: float) -> bool:
        """`ResultRoom.set_mask_band`."""
        return self.results.set_mask_band(tau_out)

    def kept_mask(self) -> np.ndarray:
        """`ResultRoom.kept_mask`."""
        return self.results.kept_mask()

    def shown_mask(self) -> np.ndarray:
        """`ResultRoom.shown_mask`."""
        return self.results.shown_mask()

    def gt_metrics(self) -> GTMetrics:
        """`ResultRoom.gt_metrics`."""
        return self.results.gt_metrics()

    def gt_metrics_or_none(self) -> GTMetrics | None:
        """`ResultRoom.gt_metrics_or_none`."""
        return self.results.gt_metrics_or_none()

    def point_colors(self, result_box_colors: np.ndarray | None = None) -> PointColors | None:
        """`ResultRoom.point_colors`."""
        return self.results.point_colors(result_box_colors)

    # ================================================================== 3. runs (rooms/runs.py)
    def begin_run(self) -> int | None:
        """`RunRoom.begin_run`."""
        return self.runs.begin_run()

    def run(self, settings: RunSettings | None = None, *, on_step: ProgressCallback | None = None,
            show: bool = True, generation: int | None = None, **knobs: Any) -> EMResult | None:
        """`RunRoom.run` with `settings`, or `RunSettings` fields as keywords (`run(preset="fast", seed=3)`)."""
        return self.runs.run(RunSettings.of(settings, **knobs), on_step=on_step, show=show, generation=generation)

    def cancel_run(self) -> None:
        """`RunRoom.cancel_run`."""
        self.runs.cancel_run()

    # ================================================================== 4. timeline (rooms/timeline.py)
    def step_view(self, step: int | None = None) -> StepView | None:
        """`TimelineRoom.step_view`."""
        return self.timeline.step_view(step)

    def set_step(self, step: int) -> StepView | None:
        """`TimelineRoom.set_step`."""
        return self.timeline.set_step(step)

    def next_step(self) -> StepView | None:
        """`TimelineRoom.next_step`."""
        return self.timeline.next_step()

    def set_max_shapes(self, n: int) -> None:
        """`TimelineRoom.set_max_shapes`."""
        self.timeline.set_max_shapes(n)

    def set_proposal_layers(self, *, shapes: bool | None = None, samples: bool | None = None) -> None:
        """`TimelineRoom.set_proposal_layers`."""
        self.timeline.set_proposal_layers(shapes=shapes, samples=samples)

    def samples(self, drawn: np.ndarray, step: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`TimelineRoom.samples`."""
        return self.timeline.samples(drawn, step)

    def decode_shape(self, pid: int, step: int) -> tuple[np.ndarray, np.ndarray] | None:
        """`TimelineRoom.decode_shape`."""
        return self.timeline.decode_shape(pid, step)

    def is_dead_at(self, pid: int, step: int) -> bool:
        """`TimelineRoom.is_dead_at`."""
        return self.timeline.is_dead_at(pid, step)

    # ================================================================== 5. proposal inspection (rooms/inspect.py)
    def select_proposal(self, pid: int | None) -> bool:
        """`InspectRoom.select_proposal`."""
        return self.inspection.select_proposal(pid)

    def proposal_view(self, pid: int, step: int, prior: ShapePriorLike | None) -> ProposalView:
        """`InspectRoom.proposal_view`."""
        return self.inspection.proposal_view(pid, step, prior)

    def inspect(self, pid: int, step: int | None = None) -> Inspection:
        """`InspectRoom.inspect`."""
        return self.inspection.inspect(pid, step)

    def show_inspection(self, ins: Inspection) -> bool:
        """`InspectRoom.show_inspection`."""
        return self.inspection.show_inspection(ins)

    # ================================================================== 6. the instance table (rooms/instances.py)
    def instance_index(self, pid: int | None) -> int:
        """`InstanceRoom.instance_index`."""
        return self.instances.instance_index(pid)

    def table_options(self) -> tuple[str, ...]:
        """`InstanceRoom.table_options`."""
        return self.instances.table_options()

    def choose_instance(self, pid: int | None) -> None:
        """`InstanceRoom.choose_instance`."""
        self.instances.choose_instance(pid)

    def set_instance_visible(self, pid: int | None, visible: bool) -> None:
        """`InstanceRoom.set_instance_visible`."""
        self.instances.set_instance_visible(pid, visible)

    def fly_target(self, pid: int | None) -> FlyTarget:
        """`InstanceRoom.fly_target`."""
        return self.instances.fly_target(pid)

    def next_instance(self, step: int) -> int:
        """`InstanceRoom.next_instance`."""
        return self.instances.next_instance(step)

    # ================================================================== 7. export (rooms/export.py)
    def export_results(self, out_dir: str | Path, *, root: Path | None = None) -> Path | None:
        """`ExportRoom.export_results`."""
        return self.export.export_results(out_dir, root=root)

    def static_target(self, folder: Path | None = None) -> Path | None:
        """`ExportRoom.static_target`."""
        return self.export.static_target(folder)

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None,
                      on_progress: Callable[[float | None], None] | None = None) -> Path | None:
        """`ExportRoom.export_static`."""
        return self.export.export_static(out_dir, root=root, on_progress=on_progress)

    def cancel_export(self) -> None:
        """`ExportRoom.cancel_export`."""
        self.export.cancel_export()
