"""The timeline part: step through the EM iterations of the shown result (live proposals, samples, shapes)."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from efem_viz.viewer.trace_queries import decode_shape, proposal_anchors, proposal_samples, top_n

if TYPE_CHECKING:
    from efem_viz.viewer.parts.core import ViewerCore


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


class TimelinePart:
    """The EM step on show, what it shows, and the step's samples and decoded shapes."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""

    def step_view(self, step: int | None = None) -> StepView | None:
        """The proposals of a step (default: the current one), clamped to the trace; None without a result."""
        s = self.core.state
        if s.result is None:
            return None
        if s.num_steps == 0:  # no step yet: a running solve's first proposals (their anchors are drawn), or
            # none at all (a run that ended before its first step: a scene of one or two points)
            ids = np.arange(s.result.trace.num_proposals, dtype=np.int64)
            return StepView(0, ids, np.zeros(len(ids), np.float32), ids)
        t = int(np.clip(s.step if step is None else step, 0, max(s.num_steps - 1, 0)))
        ids, scores = s.result.trace.alive_scores(t)
        return StepView(t, ids, scores, top_n(ids, scores, s.max_shapes))

    def set_step(self, step: int) -> StepView | None:
        """Go to EM step `step` (clamped). Returns what the step shows, or None without a result."""
        with self.core.lock:
            v = self.step_view(step)
            if v is not None:
                self.core.state.step = v.step
            return v

    def next_step(self) -> StepView | None:
        """One step on (playback); None at the end or without a result (playback then stops)."""
        with self.core.lock:
            s = self.core.state
            if s.result is None or s.step + 1 >= s.num_steps:
                s.playing = False
                return None
            return self.set_step(s.step + 1)

    def set_max_shapes(self, n: int) -> None:
        """Draw decoded shapes for at most `n` live proposals."""
        self.core.state.max_shapes = max(int(n), 0)

    def set_proposal_layers(self, *, shapes: bool | None = None, samples: bool | None = None) -> None:
        """Show or hide the step's decoded shapes and samples."""
        if shapes is not None:
            self.core.state.show_shapes = bool(shapes)
        if samples is not None:
            self.core.state.show_samples = bool(samples)

    def samples(self, drawn: np.ndarray, step: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) float32 world points and (M, 3) uint8 colours of the drawn proposals' samples at a step."""
        s = self.core.state
        trace = s.require_result().trace
        if trace.num_steps == 0:  # a running solve before its first step: where its proposals start
            return proposal_anchors(trace, drawn, s.require_scene().points)
        t = s.step if step is None else int(step)
        return proposal_samples(trace, t, drawn, s.require_scene().points)

    def decode_shape(self, pid: int, step: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(vertices, faces) of proposal `pid`'s decoded shape at `step`, from its stored latent.

        Raises:
            RuntimeError: no prior to decode with.
        """
        from efem_viz.em.replay import prior_latent

        trace = self.core.state.require_result().trace
        prior, latent = prior_latent(trace, pid, step, self.core.priors.for_run(trace))
        return decode_shape(prior, latent, resolution=trace.config.review.mesh_resolution)

    def is_dead_at(self, pid: int, step: int) -> bool:
        """Whether proposal `pid` has been eliminated by `step`."""
        return self.core.state.require_result().trace.is_dead_at(pid, step)
