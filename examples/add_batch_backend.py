"""Add a batch backend: where the scenes of `run_batch` (and `efem-viz segment`) are solved.

A backend implements the `efem_viz.batch.backends.Backend` protocol (a `name`, `describe()`,
`resolve_job(job)` and `run(job, tasks, events)`, which yields one `SceneOutcome` per task as it finishes)
and registers a factory in `efem_viz.batch.registry.BACKENDS`. Planning, resuming, `batch.json` and the report
stay in the runner, and the scenes are solved by the same `SceneWorker` on every backend, so a backend is only
about *where* they run.

This example adds "thread": N threads of the driver's own process, each with its own `SceneWorker` (torch and
NumPy release the GIL in their kernels). Worker threads never call the observer; they post messages that the
driver's loop relays, as the process pool does, because observer callbacks run in the driver's main thread.

It writes a few analytic sphere scenes (no trained weights needed), segments them with the new backend and
with the default `local` one, checks that both give the same instances, and runs the batch again to show that
it resumes (every scene skipped).

Run (a few seconds with the defaults)::

    python examples/add_batch_backend.py
    python examples/add_batch_backend.py --scenes 4 --workers 2 --out /tmp/batch
"""

from __future__ import annotations

import argparse
import dataclasses
import queue
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.batch import (
    BackendOptions,
    BatchError,
    BatchJob,
    BatchObserver,
    SceneOutcome,
    SceneTask,
    WorkerInfo,
)
from efem_viz.batch.backends import cpu_count


class ThreadBackend:
    """Scenes on `workers` threads of this process, one `SceneWorker` (priors loaded once) per thread."""

    name = "thread"

    def __init__(self, options: BackendOptions | None = None) -> None:
        self.workers = int((options.workers if options is not None else None) or 2)
        if self.workers < 1:
            raise BatchError(f"--workers must be >= 1, got {self.workers}")

    def describe(self) -> dict[str, object]:
        return {"backend": self.name, "workers": self.workers}

    def resolve_job(self, job: BatchJob) -> BatchJob:
        if job.threads is None:  # torch threads are per process: share the CPUs between the worker threads
            return dataclasses.replace(job, threads=max(1, cpu_count() // self.workers))
        return job

    def run(self, job: BatchJob, tasks: Sequence[SceneTask], events: BatchObserver) -> Iterator[SceneOutcome]:
        import torch

        from efem_viz.batch.worker import SceneWorker
        from efem_viz.terminal import one_line

        if not tasks:
            return
        if job.threads:  # torch threads are per process; each SceneWorker sets the same value again
            torch.set_num_threads(int(job.threads))
        todo: queue.SimpleQueue[SceneTask] = queue.SimpleQueue()
        for t in tasks:
            todo.put(t)
        msgs: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()

        def body(wid: str) -> None:
            try:
                worker = SceneWorker(job, worker=wid)
            except Exception as exc:  # a prior that does not load: the whole batch cannot run
                msgs.put(("error", one_line(exc)))
                return
            msgs.put(("ready", worker.info))
            try:
                while True:
                    try:
                        task = todo.get_nowait()
                    except queue.Empty:
                        return
                    msgs.put(("start", task, wid))

                    def on_step(s: Any, _task: SceneTask = task) -> None:
                        msgs.put(("step", _task, wid, s.step + 1, s.num_steps, s.status()))

                    t0 = time.perf_counter()
                    out = worker.process(task, on_step=on_step)  # never raises for a scene's own problems
                    msgs.put(("done", dataclasses.replace(out, wall_s=time.perf_counter() - t0)))
            finally:
                msgs.put(("exit", wid))

        threads = [threading.Thread(target=body, args=(f"thread-{i + 1}",), daemon=True)
                   for i in range(min(self.workers, len(tasks)))]
        for th in threads:
            th.start()
        running = len(threads)
        while running:
            try:
                msg = msgs.get(timeout=0.5)  # a timeout keeps Ctrl+C responsive
            except queue.Empty:
                continue
            kind = msg[0]
            if kind == "ready":
                events.on_worker(msg[1])
            elif kind == "error":
                raise BatchError(msg[1])
            elif kind == "start":
                events.on_start(msg[1], msg[2])
            elif kind == "step":
                events.on_step(*msg[1:])
            elif kind == "done":
                yield msg[1]
            elif kind == "exit":
                running -= 1


class PrintObserver(BatchObserver):
    """Prints the events a progress display would show (override only what you need)."""

    def on_worker(self, info: WorkerInfo) -> None:
        print(f"  worker {info.worker} ready ({info.threads} torch threads, "
              f"priors in {info.prior_load_s:.2f} s)")

    def on_done(self, outcome: SceneOutcome) -> None:
        error = f" ({outcome.error})" if outcome.error else ""
        print(f"  {outcome.name}: {outcome.status} on {outcome.worker or '-'}, {outcome.instances} "
              f"instances, {outcome.seconds:.1f} s{error}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=3, help="sphere scenes to write and segment")
    ap.add_argument("--workers", type=int, default=2, help="worker threads of the new backend")
    ap.add_argument("--proposals", type=int, default=48, help="proposals per scene")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (shared by the worker threads)")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temp dir)")
    args = ap.parse_args(argv)

    from efem_viz.batch import BACKENDS, make_backend, run_batch
    from efem_viz.data.io import save_scene
    from efem_viz.em import EMResult
    from efem_viz.prior.analytic import make_sphere_scene

    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    scenes = out / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    for i in range(args.scenes):
        save_scene(make_sphere_scene(seed=i, name=f"spheres_{i}"), scenes / f"spheres_{i}.ply")

    BACKENDS["thread"] = ThreadBackend  # register: make_backend("thread", options) now builds it
    print(f"backends: {sorted(BACKENDS)}")
    job = BatchJob.create(priors=("sphere",), preset="fast", proposals=args.proposals, seed=0,
                          threads=args.threads)
    runs = {}
    for name in ("thread", "local"):
        backend = make_backend(name, BackendOptions(workers=args.workers if name == "thread" else None))
        print(f"batch on {name!r} ({backend.describe()}):")
        report = run_batch(job, [scenes], out / name, backend=backend, observer=PrintObserver())
        recorded = (out / name / "batch.json").is_file()
        print(f"  counts {report.counts()}, passed {report.passed}, batch.json written {recorded}")
        runs[name] = report
    same = all(
        np.array_equal(EMResult.load(out / "thread" / f"spheres_{i}.efem.npz").instances.confidence,
                       EMResult.load(out / "local" / f"spheres_{i}.efem.npz").instances.confidence)
        for i in range(args.scenes))
    print(f"same instances on both backends: {same}")
    backend = make_backend("thread", BackendOptions(workers=args.workers))
    again = run_batch(job, [scenes], out / "thread", backend=backend)
    print(f"second run on 'thread' resumes: counts {again.counts()}")
    return 0 if same and all(r.passed for r in runs.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
