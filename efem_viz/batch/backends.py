"""Where the scenes of a batch run: the `Backend` protocol, the registry `BACKENDS`, and the two local backends.

- `local`: one `SceneWorker` in the driver's own process, scenes one after the other (the default; nothing extra).
- `process`: a pool of `--workers` spawned processes on this machine, each with its own `SceneWorker` (priors loaded
  once per process) and `threads` torch threads (default: the CPU count split between the workers). Each worker
  takes one scene at a time over a pipe, so a worker that dies (killed, out of memory) costs exactly its scene: that
  scene is reported failed and a fresh worker takes over. Workers die with the driver (Linux: PR_SET_PDEATHSIG;
  elsewhere a watchdog thread), so a killed batch leaves no orphans behind.
- `ray`: Ray actors, locally or on a cluster (efem_viz/batch/ray_backend.py; Ray is an optional extra).

A new backend implements `Backend` (a `name`, `describe()`, `resolve_job(job)` and `run(job, tasks, events)`, an
iterator of `SceneOutcome`s in completion order) and registers a factory in `efem_viz.batch.registry.BACKENDS`.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol, cast

from efem_viz.batch.events import BatchObserver
from efem_viz.batch.job import BatchJob, SceneOutcome, SceneTask
from efem_viz.terminal import one_line
from efem_viz.cpu import cpu_count  # re-exported: the batch backends size their pools with it

logger = logging.getLogger(__name__)

STEP_REPORT_S = 0.25
"""A pool worker relays at most one progress message per this many seconds (plus the last step)."""
MAX_START_FAILURES = 2
"""A pool worker that dies before it is ready this many times in a row stops the batch (the machine is the problem,
not a scene)."""


class BatchError(ValueError):
    """The batch as a whole cannot run (a prior that does not load, workers that cannot start, Ray missing).

    A ValueError, so the CLI reports it as one `error:` line. Scene problems never raise this: they become failed
    outcomes.
    """


class Backend(Protocol):
    """How the scenes of a batch are run."""

    name: str
    """Registry name ("local", "process", "ray")."""

    def describe(self) -> dict[str, object]:
        """Settings for `batch.json` (workers, address, ...)."""
        ...

    def resolve_job(self, job: BatchJob) -> BatchJob:
        """The job with backend-dependent defaults filled in (threads per worker)."""
        ...

    def run(self, job: BatchJob, tasks: Sequence[SceneTask], events: BatchObserver) -> Iterator[SceneOutcome]:
        """Run every task once; yield each outcome as it arrives (any order).

        Raises:
            BatchError: the batch cannot run at all (e.g. the priors do not load).
        """
        ...


@dataclass(frozen=True)
class BackendOptions:
    """What the CLI says about where to run (each backend reads what applies to it)."""

    workers: int | None = None
    """Parallel workers (process: processes; ray: actors). None: the backend's default."""
    ray_address: str | None = None
    """Ray: join this cluster ("auto", "HOST:6379", "ray://HOST:10001"); None: start Ray locally."""
    ray_cpus: int | None = None
    """Ray, local start: CPUs to give the local Ray (default: workers × threads, else the CPU count)."""


# ---------------------------------------------------------------------------------------------- local
class LocalBackend:
    """Scenes one after the other in this process (the default)."""

    name = "local"

    def __init__(self, options: BackendOptions | None = None) -> None:
        if options is not None and options.workers not in (None, 1):
            raise BatchError(f"the local backend runs one scene at a time; for --workers {options.workers} use "
                             "--backend process or --ray")

    def describe(self) -> dict[str, object]:
        return {"backend": self.name, "workers": 1}

    def resolve_job(self, job: BatchJob) -> BatchJob:
        if job.threads is None:  # the cores other work leaves free (efem_viz.cpu): no barrier waits on a busy core
            from efem_viz.cpu import free_cores

            return dataclasses.replace(job, threads=free_cores())
        return job

    def run(self, job: BatchJob, tasks: Sequence[SceneTask], events: BatchObserver) -> Iterator[SceneOutcome]:
        from efem_viz.batch.worker import SceneWorker

        if not tasks:
            return
        worker = SceneWorker(job, worker="local")
        events.on_worker(worker.info)
        for task in tasks:
            events.on_start(task, "local")

            def on_step(s: Any, _task: SceneTask = task) -> None:
                events.on_step(_task, "local", s.step + 1, s.num_steps, s.status())

            t0 = time.perf_counter()
            out = worker.process(task, on_step=on_step)
            yield dataclasses.replace(out, wall_s=time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------- process pool
def _die_with_parent(parent_pid: int) -> None:
    """Make this process end when the driver does (kill -9 included)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(1.0)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="efem-parent-watch", daemon=True).start()


def _pool_worker_main(conn: Connection, worker_id: str, job: BatchJob, parent_pid: int) -> None:
    """Body of one pool process: build a SceneWorker, then solve the tasks the driver sends until it sends None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C is the driver's to handle; it stops the workers
    _die_with_parent(parent_pid)
    if job.threads:  # before torch is imported: sizes the OpenMP pool too
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(job.threads)
    from efem_viz.batch.worker import SceneWorker

    t0 = time.perf_counter()
    try:
        worker = SceneWorker(job, worker=worker_id)
    except Exception as exc:
        conn.send(("error", one_line(exc)))
        return
    conn.send(("ready", dataclasses.replace(worker.info, start_s=time.perf_counter() - t0)))
    while True:
        try:
            task = conn.recv()
        except EOFError:
            return
        if task is None:
            return
        last = [0.0]

        def on_step(s: Any, _task: SceneTask = task) -> None:
            now = time.monotonic()
            if now - last[0] >= STEP_REPORT_S or s.step + 1 >= s.num_steps:
                last[0] = now
                conn.send(("step", _task.index, s.step + 1, s.num_steps, s.status()))

        conn.send(("done", worker.process(task, on_step=on_step)))


@dataclass
class _Slot:
    """One pool process as the driver sees it."""

    worker: str
    proc: Any  # multiprocessing.context.SpawnProcess
    conn: Connection
    spawned: float
    ready: bool = False
    task: SceneTask | None = None
    sent: float = 0.0


class ProcessBackend:
    """A pool of local worker processes (`--workers N`), each loading the priors once.

    Args:
        options: `workers` (default: the CPU count); threads per worker come from the job (default: CPUs //
            workers, at least 1).
    """

    name = "process"

    def __init__(self, options: BackendOptions | None = None) -> None:
        workers = (options.workers if options is not None else None) or cpu_count()
        if workers < 1:
            raise BatchError(f"--workers must be >= 1, got {workers}")
        self.workers = int(workers)

    def describe(self) -> dict[str, object]:
        return {"backend": self.name, "workers": self.workers, "start_method": "spawn"}

    def resolve_job(self, job: BatchJob) -> BatchJob:
        self._auto_threads = job.threads is None
        if job.threads is None:
            return dataclasses.replace(job, threads=max(1, cpu_count() // self.workers))
        return job

    def run(self, job: BatchJob, tasks: Sequence[SceneTask], events: BatchObserver) -> Iterator[SceneOutcome]:
        ctx = mp.get_context("spawn")
        if getattr(self, "_auto_threads", False) and tasks:  # the CPUs go to the processes that actually start
            job = dataclasses.replace(job, threads=max(1, cpu_count() // min(self.workers, len(tasks))))
        pending: deque[SceneTask] = deque(tasks)
        slots: list[_Slot] = []
        counter = [0]
        start_failures = 0

        def spawn() -> None:
            counter[0] += 1
            wid = f"process-{counter[0]}"
            pipe = ctx.Pipe()
            parent_end, child_end = cast(Connection, pipe[0]), cast(Connection, pipe[1])
            proc = ctx.Process(target=_pool_worker_main, args=(child_end, wid, job, os.getpid()), name=wid,
                               daemon=True)
            proc.start()
            child_end.close()
            slots.append(_Slot(worker=wid, proc=proc, conn=parent_end, spawned=time.perf_counter()))

        def hand_out(slot: _Slot) -> None:
            if slot.ready and slot.task is None and pending:
                task = pending.popleft()
                try:
                    slot.conn.send(task)
                except OSError:  # the worker died after its last message: the scene waits for another worker
                    pending.appendleft(task)
                    slot.ready = False
                    return
                slot.task, slot.sent = task, time.perf_counter()
                events.on_start(task, slot.worker)

        try:
            for _ in range(min(self.workers, len(pending))):
                spawn()
            while pending or any(s.task is not None for s in slots):
                if not slots:
                    spawn()
                wait([s.conn for s in slots] + [s.proc.sentinel for s in slots], timeout=5.0)
                for slot in list(slots):
                    closed = False
                    while True:
                        try:
                            if not slot.conn.poll():
                                break
                            msg = slot.conn.recv()
                        except (EOFError, OSError):
                            closed = True
                            break
                        kind = msg[0]
                        if kind == "ready":
                            slot.ready = True
                            start_failures = 0
                            events.on_worker(msg[1])
                        elif kind == "error":
                            raise BatchError(msg[1])
                        elif kind == "step" and slot.task is not None:
                            events.on_step(slot.task, slot.worker, msg[2], msg[3], msg[4])
                        elif kind == "done":
                            slot.task = None
                            out: SceneOutcome = msg[1]
                            yield dataclasses.replace(out, wall_s=time.perf_counter() - slot.sent)
                        hand_out(slot)
                    if closed or not slot.proc.is_alive():
                        slot.proc.join(timeout=5.0)
                        slots.remove(slot)
                        code = slot.proc.exitcode
                        how = (f"signal {signal.Signals(-code).name}" if code is not None and code < 0
                               else f"exit code {code}")
                        if slot.task is not None:
                            logger.warning("%s died (%s) on scene %s", slot.worker, how, slot.task.name)
                            yield SceneOutcome(
                                name=slot.task.name, path=str(slot.task.path), status="failed",
                                seconds=time.perf_counter() - slot.sent, wall_s=time.perf_counter() - slot.sent,
                                error=f"worker process died ({how}; killed, or out of memory?)",
                                worker=slot.worker, fingerprint="",
                            )
                        elif not slot.ready:
                            start_failures += 1
                            if start_failures >= MAX_START_FAILURES:
                                raise BatchError(f"worker processes die while starting ({how}); "
                                                 "try --backend local to see the error")
                        if pending and len(slots) < self.workers:
                            spawn()
            for slot in slots:
                try:
                    slot.conn.send(None)
                except (OSError, BrokenPipeError):
                    pass
            for slot in slots:
                slot.proc.join(timeout=10.0)
        finally:
            for slot in slots:
                if slot.proc.is_alive():
                    slot.proc.kill()
                    slot.proc.join(timeout=5.0)
                slot.conn.close()
