"""The viewer's state (no viser here): everything the viewer shows, as plain typed values.

`ViewerSession` (`viewer/session.py`, headless) owns a `ViewerState` and changes it through its actions; the GUI
callbacks in `app.py` call those actions (heavy ones in worker threads) and draw the state. The pure functions the
callbacks use live in their own modules: colours in `efem_viz.colors`, the ground-truth comparison in
`efem_viz.eval.comparison`, scene discovery in `viewer/scene_list.py`, trace queries and the timeline in
`viewer/trace_queries.py`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from efem_viz.viewer.scene_list import SceneEntry

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult, Instances

ColorMode = Literal["rgb", "instances", "gt_match", "weights", "proposals"]
DisplayMode = Literal["points", "mesh"]
ViewMode = Literal["step", "result"]
"""What the 3-D view shows of a result: one EM step (its decoded shapes and samples) or the final instances."""

DEFAULT_CONFIDENCE_CUT = 0.05
"""The confidence threshold a viewer starts with: instances below it are hidden (on real scans EM keeps many
near-zero-confidence instances that cover the view and say nothing). The Results tab says how many it hides; the
slider at 0 shows them all."""

NO_PROPOSAL: str = "(none)"
"""The Inspect dropdown's "no proposal" option."""
MASK_BAND_RANGE = (0.01, 0.2)
"""Range of the mask-band slider (τ_out, canonical units)."""
VIEW_MODES = {
    "Result (final instances)": "result",
    "EM step (that step only)": "step",
}
"""Options of the Show dropdown → `ViewerState.view_mode`."""
COLOR_MODES = {
    "scene colours": "rgb",
    "instances": "instances",
    "TP / FP / FN": "gt_match",
    "proposal weights": "weights",
}
"""Options of the Colour dropdown → `ViewerState.color_mode`."""


def shown_mask(instances: Instances, threshold: float,
               hidden: set[int] | frozenset[int] = frozenset()) -> np.ndarray:
    """(K,) bool: the final instances drawn: kept by the confidence threshold (`Instances.kept`, the one
    thresholding rule) and not hidden by hand.

    Args:
        instances: `efem_viz.em.Instances`.
        threshold: the confidence threshold.
        hidden: proposal ids hidden by hand.
    """
    keep = instances.kept(float(threshold))
    if hidden:
        keep &= ~np.isin(np.asarray(instances.ids).reshape(-1), np.fromiter(hidden, np.int64))
    return keep


@dataclass
class ViewerState:
    """Everything the viewer shows, as plain values (GUI handles are read into this, never the reverse).

    One state per server: every connected browser sees the same scene, step, threshold and selection (shared
    GUI), so a demo audience and the presenter stay in sync.
    """

    entries: list[SceneEntry] = field(default_factory=list)
    """Scenes the browser lists (only inside the given paths)."""
    scene_name: str | None = None
    """Name of the open scene (an `entries` name)."""
    scene: Scene | None = None
    """The open scene, or None."""
    result: EMResult | None = None
    """The `EMResult` of the open scene (loaded or computed), or None."""
    result_source: str = ""
    """Where `result` came from: a file path, or 'run (seed=..)'."""
    step: int = 0
    """Current EM step on the timeline (0 .. num_steps-1)."""
    view_mode: ViewMode = "result"
    """"step": only step `step` (decoded shapes, samples; points in scene colours unless a proposal's weights);
    "result": only the final instances (meshes, boxes, labels, instance or TP/FP/FN colours). Moving the
    timeline shows a step; the threshold, the result layers and the instance colours show the result."""
    playing: bool = False
    speed: float = 2.0
    """Playback speed in steps per second."""
    selected: int | None = None
    """Inspected proposal id, or None."""
    max_shapes: int = 8
    """Draw decoded shapes for at most this many live proposals (top by stationary score)."""
    show_shapes: bool = True
    show_samples: bool = True
    threshold: float = DEFAULT_CONFIDENCE_CUT
    """Confidence threshold on the final instances (a view, not a re-run)."""
    threshold_by_user: bool = False
    """Whether a person set `threshold` (kept for the next result only if it still shows an instance there)."""
    proposals_by_user: bool = False
    """Whether a person edited the Run tab's Proposals field (until then it shows the chosen preset's number)."""
    hidden: set[int] = field(default_factory=set)
    """Proposal ids of final instances hidden by hand (the instance table's *Visible* box): a view, like the
    threshold; the metrics and exports follow the threshold only."""
    table_row: int | None = None
    """Proposal id of the instance chosen in the instance table (None: none yet)."""
    display: DisplayMode = "points"
    color_mode: ColorMode = "rgb"
    point_size: float = 0.004
    show_meshes: bool = True
    show_obbs: bool = True
    show_axes: bool = False
    running: bool = False
    """EM is running in the worker."""
    progress: float = 0.0
    """0-100."""
    status: str = ""
    """Last status / error line shown in the GUI."""
    error: str | None = None
    """Last error (scene failed to load, run failed...)."""

    @property
    def num_steps(self) -> int:
        """Number of EM steps in the current trace (0 without a result)."""
        if self.result is None:
            return 0
        return int(self.result.trace.num_steps)

    def require_scene(self) -> Scene:
        """The open scene. Raises RuntimeError when none is open."""
        if self.scene is None:
            raise RuntimeError("no scene is open")
        return self.scene

    def require_result(self) -> EMResult:
        """The shown result. Raises RuntimeError when there is none."""
        if self.result is None:
            raise RuntimeError("no result is loaded")
        return self.result

    def entry(self, name: str) -> SceneEntry:
        """The entry of a scene name; KeyError with the known names otherwise."""
        for e in self.entries:
            if e.name == name:
                return e
        raise KeyError(f"unknown scene {name!r}; known: {[e.name for e in self.entries]}")
