"""The Ray backend: one actor per worker, each holding a `SceneWorker` (priors loaded once per actor).

The only module of efem-viz that imports Ray (inside `RayBackend.run`, so importing it is free); Ray is the optional
extra `pip install 'efem-viz[ray]'`. `--ray` starts a local Ray (`ray.init(num_cpus=...)`, no dashboard) and stops it
at the end; `--ray-address ADDR` joins a running cluster and leaves it running. On a cluster the scene files and the
output folder must be on a filesystem every node sees at the same path (workers read the scenes and write the
outputs themselves), and efem-viz must be installed on every node.

Each actor reserves `threads` CPUs (its torch thread count) and one GPU with `--device cuda`. Scenes are handed to
idle actors one at a time; an actor that dies (node lost, out of memory) fails the scene it held and is replaced.
Ray reports no per-step progress, only finished scenes.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import sys
import time
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

from efem_viz.batch.backends import BackendOptions, BatchError, cpu_count
from efem_viz.batch.events import BatchObserver
from efem_viz.batch.job import BatchJob, SceneOutcome, SceneTask, WorkerInfo
from efem_viz.terminal import one_line

logger = logging.getLogger(__name__)

INSTALL_HINT = "Ray is not installed: pip install 'efem-viz[ray]'"
"""The one line `--ray` prints without Ray."""
LOCAL_OBJECT_STORE_BYTES = 256 * 1024 * 1024
"""Object store of a locally started Ray: outcomes are small records, the scenes never travel through it."""


class _RayWorker:
    """The actor body: a SceneWorker built in the actor process (wrapped by `ray.remote` at run time)."""

    def __init__(self, job: BatchJob, worker: str) -> None:
        from efem_viz.batch.worker import SceneWorker

        t0 = time.perf_counter()
        self._worker = SceneWorker(job, worker=worker)
        self._info = dataclasses.replace(self._worker.info, start_s=time.perf_counter() - t0)

    def info(self) -> WorkerInfo:
        return self._info

    def process(self, task: SceneTask) -> SceneOutcome:
        return self._worker.process(task)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise BatchError(INSTALL_HINT) from exc
    return ray


def _cause(exc: BaseException) -> str:
    """The original error of a Ray task/actor error, on one line."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        return one_line(cause)
    text = " ".join(str(exc).split())
    return text[-400:] or type(exc).__name__


RAY_CONNECT_TIMEOUT_S = 10.0
"""How long `check_ray_address` waits for a TCP answer (Ray itself retries a dead address for over 10 minutes)."""


def ray_is_initialized() -> bool:
    """Whether this process is already connected to a Ray (without importing ray when it is not imported)."""
    ray = sys.modules.get("ray")
    return bool(ray is not None and ray.is_initialized())


def check_ray_address(address: str, *, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse a `--ray-address` where nothing listens, in one line within `timeout_s` ("auto" is left to Ray).

    Raises:
        BatchError: an address that is not HOST:PORT / ray://HOST:PORT, or no TCP answer there.
    """
    if address == "auto":
        return
    hostport = address.split("://", 1)[1] if "://" in address else address
    host, sep, port_text = hostport.rpartition(":")
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not sep or not host or not 0 < port < 65536:
        raise BatchError(f"--ray-address {address!r}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise BatchError(f"--ray-address {address}: nothing answers there ({exc.strerror or exc}); is the Ray "
                         "cluster running (`ray start --head`)?") from None


class RayBackend:
    """Scenes on Ray actors (local start with `--ray`, or an existing cluster with `--ray-address`).

    Args:
        options: `workers` (actors; default: the cluster's CPUs // threads), `ray_address`, `ray_cpus` (local
            start only; default workers × threads, else this machine's CPUs).

    Raises:
        BatchError: Ray is not installed (`INSTALL_HINT`).
    """

    name = "ray"

    def __init__(self, options: BackendOptions | None = None) -> None:
        _import_ray()
        self.options = options or BackendOptions()
        if self.options.workers is not None and self.options.workers < 1:
            raise BatchError(f"--workers must be >= 1, got {self.options.workers}")
        self.actors_started = 0

    def describe(self) -> dict[str, object]:
        return {"backend": self.name, "workers": self.options.workers, "address": self.options.ray_address or "local",
                "actors_started": self.actors_started}

    def resolve_job(self, job: BatchJob) -> BatchJob:
        if job.threads is None:
            return dataclasses.replace(job, threads=1)
        return job

    def run(self, job: BatchJob, tasks: Sequence[SceneTask], events: BatchObserver) -> Iterator[SceneOutcome]:
        if not tasks:
            return
        if self.options.ray_address and not ray_is_initialized():
            check_ray_address(self.options.ray_address)
        ray = _import_ray()
        from ray.exceptions import RayActorError, RayError, RayTaskError

        threads = int(job.threads or 1)
        started_here = False
        actors: dict[str, Any] = {}
        if not ray.is_initialized():
            if self.options.ray_address:
                ray.init(address=self.options.ray_address, log_to_driver=False)
            else:
                n_cpus = self.options.ray_cpus or (self.options.workers * threads if self.options.workers
                                                   else cpu_count())
                ray.init(num_cpus=int(n_cpus), include_dashboard=False, log_to_driver=False,
                         object_store_memory=LOCAL_OBJECT_STORE_BYTES)
            started_here = True
        try:
            resources = ray.cluster_resources()
            cpus = int(resources.get("CPU", 1))
            gpus = 1 if str(job.device).startswith("cuda") else 0
            # an actor that no node can host would wait forever: refuse the job in one line instead
            if threads > cpus:
                raise BatchError(f"each Ray worker asks for {threads} CPU(s) (--threads) but the cluster has {cpus}")
            if gpus and float(resources.get("GPU", 0)) < 1:
                raise BatchError("--device cuda needs a GPU in the Ray cluster, which has none")
            n_actors = min(len(tasks), self.options.workers or max(1, cpus // threads))
            actor_cls = ray.remote(num_cpus=threads, num_gpus=gpus, max_restarts=0)(_RayWorker)
            pending: deque[SceneTask] = deque(tasks)

            def start_actor() -> str:
                wid = f"ray-{self.actors_started}"
                self.actors_started += 1
                actors[wid] = actor_cls.remote(job, wid)
                return wid

            idle: deque[str] = deque()
            info_refs: dict[Any, str] = {}
            for _ in range(n_actors):
                wid = start_actor()
                info_refs[actors[wid].info.remote()] = wid
            running: dict[Any, tuple[str, SceneTask, float]] = {}
            start_failures = 0

            def hand_out() -> None:
                while idle and pending:
                    wid = idle.popleft()
                    task = pending.popleft()
                    running[actors[wid].process.remote(task)] = (wid, task, time.perf_counter())
                    events.on_start(task, wid)

            while pending or running:
                refs = list(info_refs) + list(running)
                if not refs:  # every actor died while starting and none is left
                    wid = start_actor()
                    info_refs[actors[wid].info.remote()] = wid
                    continue
                done, _ = ray.wait(refs, num_returns=1)
                ref = done[0]
                if ref in info_refs:
                    wid = info_refs.pop(ref)
                    try:
                        info: WorkerInfo = ray.get(ref)
                    except RayTaskError as exc:  # the SceneWorker constructor raised: a job error
                        raise BatchError(_cause(exc)) from exc
                    except RayError as exc:
                        start_failures += 1
                        actors.pop(wid, None)
                        if start_failures >= 2:
                            raise BatchError(f"Ray workers die while starting: {_cause(exc)}") from exc
                        if pending:
                            nid = start_actor()
                            info_refs[actors[nid].info.remote()] = nid
                        continue
                    events.on_worker(info)
                    idle.append(wid)
                    hand_out()
                    continue
                wid, task, sent = running.pop(ref)
                try:
                    out: SceneOutcome = ray.get(ref)
                except (RayActorError, RayError) as exc:
                    logger.warning("%s died on scene %s: %s", wid, task.name, _cause(exc))
                    try:
                        ray.kill(actors.pop(wid))
                    except (RayError, KeyError, ValueError):
                        pass
                    yield SceneOutcome(name=task.name, path=str(task.path), status="failed",
                                       seconds=time.perf_counter() - sent, wall_s=time.perf_counter() - sent,
                                       error=f"Ray worker died: {_cause(exc)}", worker=wid)
                    if pending:
                        nid = start_actor()
                        info_refs[actors[nid].info.remote()] = nid
                    continue
                idle.append(wid)
                yield dataclasses.replace(out, wall_s=time.perf_counter() - sent)
                hand_out()
        finally:
            for handle in actors.values():
                try:
                    ray.kill(handle)
                except Exception:  # best effort: the actor may be gone already
                    pass
            if started_here:
                ray.shutdown()
