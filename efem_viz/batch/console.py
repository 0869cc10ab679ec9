"""The CLI's view of a batch: one rich progress bar over the scenes (with ETA), one line per scene a local worker is
solving (its EM steps), a line per finished scene and a summary table at the end.

CLI layer only (`efem-viz segment`): library code reports through `BatchObserver` and logging, never prints.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from efem_viz.batch.events import BatchObserver
from efem_viz.batch.job import BATCH_FILE, SceneOutcome, SceneTask, WorkerInfo
from efem_viz.terminal import console as terminal_console
from efem_viz.terminal import console_text

if TYPE_CHECKING:
    from efem_viz.batch.job import BatchPlan, BatchReport

PLAIN_STEP_EVERY_S = 10.0
"""When the console is not a terminal (a log file, a pipe), a scene's EM progress is printed as a plain line at
most this often (and at its last step): rich draws no live bars there."""
TABLE_ROWS = 40
"""The summary table lists every scene up to this many; beyond, the failed ones and the totals (batch.json has all)."""


_shown = console_text  # the batch console's name for the one escaping rule (efem_viz.terminal)


class RichBatchDisplay(BatchObserver):
    """Progress and summary of a batch on a rich console. Use as a context manager around `run_batch`.

    Args:
        console: where to draw.
    """

    def __init__(self, console: Console | None = None, *, plain_every_s: float = PLAIN_STEP_EVERY_S,
                 preset: str = "") -> None:
        self.console = console or terminal_console()
        self.preset = preset
        """The job's solver preset, named in the first line ("" leaves it out)."""
        self.plain = not self.console.is_terminal
        self.plain_every_s = float(plain_every_s)
        self._last_plain: dict[str, float] = {}
        self.progress = Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
            console=self.console, transient=False,
        )
        self.overall: TaskID | None = None
        self.rows: dict[str, TaskID] = {}
        self.counts = {"ok": 0, "failed": 0}
        self.out = ""

    def __enter__(self) -> RichBatchDisplay:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.stop()

    # ------------------------------------------------------------------ events
    def on_plan(self, plan: BatchPlan) -> None:
        self.out = str(plan.out)
        skipped = f", {len(plan.skipped)} skipped (valid results there)" if plan.skipped else ""
        auto = ", preset auto (real for single-view captures, chairs for the chair prior, else synthetic)"
        preset = "" if not self.preset else auto if self.preset == "auto" else f", preset {self.preset}"
        self.console.print(f"{plan.total} scene(s) -> {_shown(plan.out)}: "
                           f"{len(plan.tasks)} to segment{skipped}{preset}",
                           soft_wrap=True)  # the folder stays one piece, to copy
        self.overall = self.progress.add_task("scenes", total=len(plan.tasks), info="")

    def on_worker(self, info: WorkerInfo) -> None:
        self.console.print(f"[dim]{_shown(info.worker)} ready on {_shown(info.host)} "
                           f"(pid {info.pid}, {info.threads} thread(s), "
                           f"priors {info.prior_load_s:.1f} s, {info.rss_mb:.0f} MiB)[/]")

    def on_start(self, task: SceneTask, worker: str) -> None:
        if self.plain:
            self.console.print(f"{_shown(task.name)}: started ({_shown(worker)})")
            self._last_plain[worker] = time.monotonic()
        row = self.rows.get(worker)
        if row is None:
            self.rows[worker] = self.progress.add_task(f"{_shown(worker)} {_shown(task.name)}", total=None,
                                                       info="loading")
        else:
            self.progress.reset(row, total=None, description=f"{_shown(worker)} {_shown(task.name)}", info="loading",
                                visible=True)

    def on_step(self, task: SceneTask, worker: str, step: int, total: int, text: str) -> None:
        if self.plain:
            now = time.monotonic()
            if step >= total or now - self._last_plain.get(worker, -float("inf")) >= self.plain_every_s:
                self._last_plain[worker] = now
                self.console.print(f"{_shown(task.name)}: step {step}/{total}  {_shown(text)} ({_shown(worker)})")
        row = self.rows.get(worker)
        if row is not None:
            self.progress.update(row, total=total, completed=step, info=text)

    def on_done(self, outcome: SceneOutcome) -> None:
        self.counts["ok" if outcome.status == "ok" else "failed"] += 1
        if self.overall is not None:
            info = f"ok {self.counts['ok']}" + (f"  [red]failed {self.counts['failed']}[/]" if self.counts["failed"]
                                                 else "")
            self.progress.update(self.overall, advance=1, info=info)
        row = self.rows.get(outcome.worker)
        if row is not None:
            self.progress.update(row, visible=False)
        if outcome.status == "ok":
            preset = f", preset {outcome.preset}" if outcome.preset else ""
            self.console.print(f"{_shown(outcome.name)}: {outcome.instances} instances in {outcome.seconds:.1f} s "
                               f"({_shown(outcome.worker)}{preset})")
        else:
            self.console.print(f"[red]{_shown(outcome.name)}: failed: {_shown(outcome.error)}[/]")

    def on_finish(self, report: BatchReport) -> None:
        self.progress.stop()
        self.console.print(summary_table(report))
        c = report.counts()
        pending = f", {c['pending']} not run" if c["pending"] else ""
        self.console.print(f"{report.plan.total} scene(s): {c['ok']} ok, {c['skipped']} skipped, {c['failed']} "
                           f"failed{pending} in {report.wall_s:.1f} s; record: {_shown(report.plan.out / BATCH_FILE)}")


def summary_table(report: BatchReport, *, max_rows: int = TABLE_ROWS) -> Table:
    """Scene, status, instances, points, seconds and error of each scene (only the failed ones for big batches)."""
    rows = report.outcomes if len(report.outcomes) <= max_rows else report.failed()
    title = "batch summary" if rows is report.outcomes else (
        f"batch summary: the {len(rows)} failed of {len(report.outcomes)} scenes (all in {BATCH_FILE})")
    table = Table(title=title, title_justify="left")
    for col in ("scene", "status", "instances", "points", "seconds", "worker", "error"):
        table.add_column(col, justify="right" if col in ("instances", "points", "seconds") else "left")
    style = {"ok": "green", "skipped": "cyan", "failed": "red"}
    for o in rows:
        table.add_row(_shown(o.name), f"[{style[o.status]}]{o.status}[/]", "" if o.instances < 0 else str(o.instances),
                      "" if o.points < 0 else f"{o.points:,}", f"{o.seconds:.1f}", _shown(o.worker),
                      _shown(o.error[:120]))
    ok = [o for o in report.outcomes if o.status == "ok"]
    if ok:
        total = sum(o.seconds for o in ok)
        table.add_row(f"{len(ok)} computed", "", str(sum(o.instances for o in ok)), "", f"{total:.1f}", "",
                      f"{total / len(ok):.1f} s per scene", style="bold")
    return table
