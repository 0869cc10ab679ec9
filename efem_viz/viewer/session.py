"""The viewer's headless session: every viewer action on typed data, no viser, no GUI handle.

`ViewerSession` owns the viewer's state (`ViewerState`) and does what the viewer does: open a scene of the
discovered list, load a saved result or run EFEM (progress callback, cancel), step through the EM iterations,
set the confidence threshold and the mask band, inspect a proposal, the instance table's actions, and the exports
(results, static demo; both keep their path confinement). It computes what the GUI draws (`StepView`,
`Inspection`, `PointColors`) and never draws it: `efem_viz.viewer.app.ViewerApp` is the thin viser layer on top
(builds the panels, translates GUI events into session calls, draws the session's state).

The session is its parts (`efem_viz.viewer.parts`, one job each; docs/INTERFACES.md): it is the parts' shared
core (`parts.core.ViewerCore`: state, lock, status, priors, generation) and holds one part per job, which is where
each action lives (`session.scenes`, `.results`, `.runs`, `.timeline`, `.inspection`, `.instances`, `.export`).
Neither it nor anything it imports loads viser or a drawing module (`tests/test_layering.py`).

A script or a notebook drives it directly (`examples/viewer_session.py`)::

    session = ViewerSession(["sample_scenes"])
    session.scenes.open_scene("syn_z_1")
    session.results.load_result()
    session.results.set_threshold(0.3)
    print(session.results.shown_mask())

Threading: the methods are safe to call from several threads; `lock` (re-entrant) guards the state, and the app
holds it while it draws. `runs.run()` and `results.load_result()` are synchronous: the app calls them from its worker threads.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Sequence

from efem_viz.data.scene import DEFAULT_MAX_POINTS
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.viewer.parts.core import (
    BUNDLED_SCENE_DIR,
    CHECKOUT_SCENE_DIR,
    DEFAULT_SCENE_DIR,
    REPO_ROOT,
    StatusListener,
    ViewerCore,
    default_scene_dir,
)
from efem_viz.viewer.parts.exporting import ExportPart
from efem_viz.viewer.parts.inspect import Inspection, InspectPart
from efem_viz.viewer.parts.instances import FlyTarget, InstancePart
from efem_viz.viewer.parts.results import PointColors, ResultPart
from efem_viz.viewer.parts.runs import ProgressCallback, RunPart, RunSettings
from efem_viz.viewer.parts.scenes import ScenePart
from efem_viz.viewer.parts.timeline import StepView, TimelinePart

if TYPE_CHECKING:
    from efem_viz.prior.config import ShapePriorLike

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
        self.scenes = ScenePart(self)
        """Opening scenes and the display choices."""
        self.results = ResultPart(self)
        """The shown result: cut, mask band, ground truth, point colours."""
        self.runs = RunPart(self, self.results)
        """EFEM runs (start, progress, cancel)."""
        self.timeline = TimelinePart(self)
        """Stepping through the EM iterations."""
        self.inspection = InspectPart(self)
        """The inspected proposal (Fig. S9 views)."""
        self.instances = InstancePart(self, self.results)
        """The instance table."""
        self.export = ExportPart(self)
        """Result and static-demo exports."""
