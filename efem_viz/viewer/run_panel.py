"""The Run button's job: EFEM on the open scene in the runner thread, its progress in the panels, its result shown.

The run itself is the session's (`efem_viz.viewer.parts.runs`: one run at a time, cancel at the next step); this
module submits it to `Jobs.runner` (a run never queues loads or decodes behind it), keeps the Run/Load/Cancel
buttons and the progress bar current, and hands the finished result to the app's `set_result`. No viser import at
run time.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any, Callable

from efem_viz.em.solver import PROGRESSIVE_EVERY_S
from efem_viz.viewer import panel_views as pv
from efem_viz.viewer.parts.runs import RunSettings

if TYPE_CHECKING:
    from efem_viz.em.results import EMResult
    from efem_viz.em.solver import StepInfo
    from efem_viz.viewer.jobs import Jobs
    from efem_viz.viewer.panels import Panels
    from efem_viz.viewer.session import ViewerSession
    from efem_viz.viewer.state import ViewMode


class RunPanel:
    """Starts runs from the GUI (or from a Python caller) and shows their progress.

    Args:
        session: the viewer session (runs EFEM; its lock).
        panels: the viewer's panels (buttons, progress bar, progress line).
        jobs: the viewer's worker threads (runs go to `jobs.runner`).
        show_result: shows a run's result (`ViewerApp.set_result`) in a view mode: a running or stopped run's
            state in the step view (its proposals at the newest step), a finished run's in the result view.
        progressive_every_s: the run is shown as it goes, its proposals at the newest step and the instances
            accepted so far, at most this often (None: only the finished result).
    """

    def __init__(self, session: ViewerSession, panels: Panels, jobs: Jobs, *,
                 show_result: Callable[[EMResult, str, ViewMode], None],
                 progressive_every_s: float | None = PROGRESSIVE_EVERY_S) -> None:
        self.session = session
        self.panels = panels
        self.jobs = jobs
        self.show_result = show_result
        self.progressive_every_s = progressive_every_s

    def start_run(self, settings: RunSettings | None = None, **knobs: Any) -> Future[EMResult | None] | None:
        """Run EFEM on the open scene in the runner thread (progress bar, cancel) with `RunSettings.of(settings,
        **knobs)` (`knobs`: its fields, e.g. `preset="fast"`). Returns the job's Future (None: a run is going)."""
        settings = RunSettings.of(settings, **knobs)
        with self.session.lock:
            generation = self.session.runs.begin_run()
            if generation is None:
                return None
            pv.show_running(self.panels, True)
        return self.jobs.submit(self.jobs.runner, self._run_job, settings, generation)

    def _run_job(self, settings: RunSettings, generation: int) -> EMResult | None:
        """The run, in the runner thread: progress per step, the buttons back at the end, the result shown."""
        last_shown = [-math.inf]
        shown: list[tuple[EMResult, StepInfo]] = []  # the newest state shown while running

        def on_step(info: StepInfo) -> None:
            pv.show_run_progress(self.panels, info)
            every = self.progressive_every_s
            if every is None or info.partial is None or not self.session.runs.is_current(generation):
                return
            now = time.monotonic()
            if info.step > 0 and now - last_shown[0] < every:
                return
            last_shown[0] = now
            partial = info.partial()
            shown[:] = [(partial, info)]
            self.show_result(partial, f"running: {info.active} proposals drawn, step 1 of {info.num_steps} under way"
                             if info.step < 0 else f"running: step {info.step + 1} of {info.num_steps}, "
                                                   f"{info.active} proposals alive, {len(partial.instances)} accepted "
                                                   "so far", "step")

        try:
            from efem_viz.prior import fused

            fused.prepare(lambda notice: setattr(self.panels.gui_run_info, "content", notice))  # a first run builds
            result = self.session.runs.run(settings, show=False, on_step=on_step, generation=generation)
        finally:
            with self.session.lock:
                pv.show_running(self.panels, False)
        if result is None:
            if shown and self.session.runs.is_current(generation):  # say what the screen still shows
                partial, info = shown[0]
                self.show_result(partial, f"stopped run (not saved): as far as it went, step {info.step + 1} of "
                                          f"{info.num_steps}", "step")
            return None
        self.show_result(result, self.session.runs.last_run_source, "result")
        return result
