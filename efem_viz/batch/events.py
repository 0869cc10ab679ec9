"""What a batch run reports while it runs: the `BatchObserver` protocol (the CLI's progress display is one).

Backends call `on_worker`, `on_start` and `on_step`; the runner calls `on_plan`, `on_done` and `on_finish`. Every
method has a default that does nothing, so an observer implements only what it shows. Callbacks run in the
driver's main thread (the pool backend relays its workers' progress through pipes; Ray reports no steps).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from efem_viz.batch.job import SceneOutcome, SceneTask, WorkerInfo
    from efem_viz.batch.job import BatchPlan, BatchReport


class BatchObserver:
    """Receives the events of a batch run (subclass and override what you need)."""

    def on_plan(self, plan: BatchPlan) -> None:
        """The scenes to run and those skipped (valid results present), before anything runs."""

    def on_worker(self, info: WorkerInfo) -> None:
        """A worker is ready (priors loaded)."""

    def on_start(self, task: SceneTask, worker: str) -> None:
        """A worker took a scene."""

    def on_step(self, task: SceneTask, worker: str, step: int, total: int, text: str) -> None:
        """EM progress of a scene: `step` of `total` done; `text` e.g. "phase 1  active 12"."""

    def on_done(self, outcome: SceneOutcome) -> None:
        """A scene finished (ok or failed)."""

    def on_finish(self, report: BatchReport) -> None:
        """The batch is over (also after an interruption: the report then has pending scenes)."""

