"""Batch segmentation of many scans: `efem-viz segment SCENES... --out DIR` runs through this package.

- `job.py`: `BatchJob` (the settings every scene shares), `SceneTask`, `SceneOutcome`, `WorkerInfo`, `BatchPlan`,
  `BatchReport`.
- `worker.py`: `SceneWorker`, the same code on every backend (priors loaded once per worker).
- `backends.py`: the `Backend` protocol, `local` and `process`; `ray_backend.py`: `ray`; `registry.py`: `BACKENDS`.
- `runner.py`: `plan_batch` (resume), `run_batch`, `batch.json`.
- `console.py`: the CLI's rich progress display and summary table (the only module here that prints).
- `commands.py`: `efem-viz segment` (`SegmentArgs`), a thin CLI over `run_batch`.

Importing the package is light (no torch, no Ray); see docs/BATCH.md.
"""

from __future__ import annotations

from efem_viz.batch.backends import Backend, BackendOptions, BatchError
from efem_viz.batch.events import BatchObserver
from efem_viz.batch.job import BatchJob, SceneOutcome, SceneTask, WorkerInfo
from efem_viz.batch.registry import BACKENDS, make_backend
from efem_viz.batch.job import BatchPlan, BatchReport
from efem_viz.batch.runner import plan_batch, run_batch

__all__ = [
    "BACKENDS",
    "Backend",
    "BackendOptions",
    "BatchError",
    "BatchJob",
    "BatchObserver",
    "BatchPlan",
    "BatchReport",
    "SceneOutcome",
    "SceneTask",
    "WorkerInfo",
    "make_backend",
    "plan_batch",
    "run_batch",
]
