"""The proposal inspection part: replay one proposal at one step (the paper's Fig. S9 views)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from efem_viz.colors import DEAD_COLOR, heatmap, instance_colors

if TYPE_CHECKING:
    from efem_viz.em.trace import ProposalView
    from efem_viz.prior.config import ShapePriorLike
    from efem_viz.viewer.parts.core import ViewerCore

logger = logging.getLogger(__name__)


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


class InspectPart:
    """The inspected proposal: its choice, its replayed views (cached in the core) and its weights colouring."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""

    def select_proposal(self, pid: int | None) -> bool:
        """Choose the inspected proposal (None clears). Returns whether one is to be inspected (then call
        `inspect()`); clearing leaves the weights colouring for the instance (or scene) colours."""
        with self.core.lock:
            s = self.core.state
            s.selected = None if pid is None else int(pid)
            if pid is None or s.result is None:
                if s.color_mode == "weights":
                    s.color_mode = "instances" if s.result is not None else "rgb"
                return False
            return True

    def proposal_view(self, pid: int, step: int, prior: ShapePriorLike | None) -> ProposalView:
        """The replayed view of proposal `pid` at `step` (cached; with its decoded mesh when `prior` is given)."""
        key = (int(pid), int(step))
        v = self.core.view_cache.get(key)
        if v is None or (prior is not None and getattr(v, "mesh", None) is None):
            v = self.core.state.require_result().replay.view(int(pid), int(step), prior, mesh=prior is not None)
            self.core.view_cache[key] = v
            if len(self.core.view_cache) > 256:
                self.core.view_cache.pop(next(iter(self.core.view_cache)))
        return v

    def inspect(self, pid: int, step: int | None = None) -> Inspection:
        """The Fig. S9 views of proposal `pid` at `step` (default: the current step).

        Raises:
            ValueError: the proposal cannot be replayed at that step.
        """
        s = self.core.state
        t = s.step if step is None else int(step)
        try:
            prior = self.core.priors.for_trace(s.require_result().trace, pid)
        except RuntimeError as exc:
            prior = None  # the first step of an episode still has weights (the crop); later steps need the prior
            logger.info("inspecting without a prior: %s", exc)
        view = self.proposal_view(pid, t, prior)
        scene, result = s.require_scene(), s.require_result()
        w = np.asarray(view.weights, np.float32).reshape(-1)
        r_err = float(result.trace.prop_r_err[pid])
        center = result.trace.center_at(pid, t)
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
        with self.core.lock:
            s = self.core.state
            if s.selected != ins.pid or s.step != ins.step or s.result is None:
                return False
            self.core.inspect_weights = ins.weights
            s.color_mode = "weights"
            return True
