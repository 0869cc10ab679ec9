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
holds it while it draws. `runs.run()` and `results.load_result()` are synchronous: the app calls them from its
worker threads.
"""

from __future__ import annotations

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

__all__ = [
    "BUNDLED_SCENE_DIR", "CHECKOUT_SCENE_DIR", "DEFAULT_SCENE_DIR", "REPO_ROOT", "FlyTarget", "Inspection",
    "PointColors", "ProgressCallback", "RunSettings", "StatusListener", "StepView", "ViewerSession",
    "default_scene_dir",
]


class ViewerSession(ViewerCore):
    """The viewer without its GUI: state and every action, each in its part.

    Built like `ViewerCore` (`ViewerSession(paths, prior=..., prior_name=..., run_priors=..., out_dir=..., results=...,
    max_points=..., device=...)`; the parameters are declared and documented there only).
    """

    scenes: ScenePart
    """Opening scenes and the display choices."""
    results: ResultPart
    """The shown result: cut, mask band, ground truth, point colours."""
    runs: RunPart
    """EFEM runs (start, progress, cancel)."""
    timeline: TimelinePart
    """Stepping through the EM iterations."""
    inspection: InspectPart
    """The inspected proposal (Fig. S9 views)."""
    instances: InstancePart
    """The instance table."""
    export: ExportPart
    """Result and static-demo exports."""

    def attach_parts(self) -> None:
        self.scenes = ScenePart(self)
        self.results = ResultPart(self)
        self.runs = RunPart(self, self.results)
        self.timeline = TimelinePart(self)
        self.inspection = InspectPart(self)
        self.instances = InstancePart(self, self.results)
        self.export = ExportPart(self)
