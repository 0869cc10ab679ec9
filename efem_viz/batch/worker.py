"""One batch worker: loads the priors once, then segments scenes one at a time and writes their outputs.

Every backend runs this same class (in the driver process, in a pool process, or in a Ray actor), which is why the
same job and seed give the same files whatever the backend. A scene that cannot be read, or whose solve raises,
becomes a failed `SceneOutcome` with a one-line error; the worker stays usable for the next scene.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.batch.job import BatchJob, SceneOutcome, SceneTask, WorkerInfo, scene_stamp
from efem_viz.terminal import one_line

if TYPE_CHECKING:
    from efem_viz.em.solver import StepInfo
    from efem_viz.prior.config import ShapePriorLike

logger = logging.getLogger(__name__)

MAX_SCENE_SPAN_M = 1000.0
"""Largest extent (m) of a scene `segment` runs: beyond it the points are not metric (a 5 km mug)."""

StepCallback = Callable[["StepInfo"], None]
"""Called after every EM step of the scene being solved (progress)."""


def peak_rss_mb() -> float:
    """This process's peak resident memory (MiB)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / (1024.0 * 1024.0) if sys.platform == "darwin" else kib / 1024.0


def current_rss_mb() -> float:
    """This process's resident memory now (MiB; the peak where /proc is not available)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / (1024.0 * 1024.0)
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()


class SceneWorker:
    """Segments scenes of one job; the priors are loaded once, when the worker is built.

    Args:
        job: the batch job.
        worker: this worker's id (for outcomes and logs).

    Raises:
        ValueError, FileNotFoundError: a prior cannot be loaded (that is a job error, not a scene failure).
    """

    def __init__(self, job: BatchJob, *, worker: str = "local") -> None:
        t0 = time.perf_counter()
        import torch

        if job.threads:  # torch intra-op threads of this worker (the job's, after the backend's defaults)
            torch.set_num_threads(int(job.threads))
        from efem_viz.prior.registry import ANALYTIC_PRIORS, PriorSet

        self.job = job
        self.worker = worker
        self.cfg = job.config()
        self.fingerprint = job.fingerprint()
        t1 = time.perf_counter()
        self.prior_set = PriorSet.from_specs(list(job.priors), device=job.device)
        """The job's priors, loaded once (`efem_viz.prior.registry.PriorSet`)."""
        self.priors: list[ShapePriorLike] = self.prior_set.solve_priors()
        """The job's priors in the job's order (what `run_em(priors=...)` takes)."""
        self.prior_load_s = time.perf_counter() - t1
        for spec, prior in zip(job.priors, self.priors):
            if prior.codebook is None and spec not in ANALYTIC_PRIORS:
                logger.warning("prior %r has no codebook: poses fall back to identity", spec)
        self.info = WorkerInfo(
            worker=worker, host=socket.gethostname(), pid=os.getpid(), threads=int(torch.get_num_threads()),
            start_s=time.perf_counter() - t0, prior_load_s=self.prior_load_s, rss_mb=current_rss_mb(),
        )
        self.scenes_done = 0

    def priors_for(self, scene: Any) -> tuple[list[ShapePriorLike], str]:
        """The priors a scene is solved with and what its line says about them: the job's priors, or, for a job
        with `scene_priors`, a generated chair or kitchen scene's own prior (`PriorSet.solve_priors`; ", chair
        prior")."""
        if not self.job.scene_priors:
            return self.priors, ""
        from efem_viz.em.config import suggested_prior
        from efem_viz.prior.config import prior_category

        category = suggested_prior(scene)
        priors = self.prior_set.solve_priors(category)
        if [id(p) for p in priors] == [id(p) for p in self.priors]:
            return self.priors, ""
        return priors, f", {prior_category(priors[0]).name} prior"

    def process(self, task: SceneTask, *, on_step: StepCallback | None = None) -> SceneOutcome:
        """Segment one scene and write its outputs (`<name>.efem.npz` last).

        A result file already at `task.result_path` is removed first: the planner only hands out scenes whose
        result is missing or stale, and a stale result must not survive next to this run's other outputs if the
        run is killed.

        Args:
            task: the scene.
            on_step: progress callback (after every EM step).

        Returns:
            The outcome ("ok" or "failed"; never raises for a scene's own problems).
        """
        from efem_viz.data.io import load_scene
        from efem_viz.data.io import atomic_write_text
        from efem_viz.data.scene import SceneError
        from efem_viz.data.scan import ScanFrame, scene_in_file_frame, scene_in_scene_frame
        from efem_viz.em.solver import EMCancelled, run_em

        t0 = time.perf_counter()
        c0 = time.process_time()
        stamp = scene_stamp(task.path)  # before reading it: a file changed during the solve is redone next time
        load_s = solve_s = 0.0
        cancel = threading.Event()
        timer: threading.Timer | None = None
        fp = self.fingerprint

        def failed(msg: str, points: int = -1) -> SceneOutcome:
            logger.warning("%s: failed: %s", task.name, msg)
            return SceneOutcome(name=task.name, path=str(task.path), status="failed", points=points,
                                seconds=time.perf_counter() - t0, error=msg, worker=self.worker, load_s=load_s,
                                solve_s=solve_s, rss_mb=peak_rss_mb(), fingerprint=fp,
                                cpu_s=time.process_time() - c0)

        points = -1
        try:
            # a recompute that fails must not leave the previous run's outputs looking current
            for stale in (task.result_path, task.ply_path, task.scannet_path, task.objects_path):
                stale.unlink(missing_ok=True)
            scene, notice = scene_in_scene_frame(load_scene(task.path))
            if notice is not None:
                logger.warning("%s", notice)
            points = scene.num_points
            span = float(np.max(scene.points.max(axis=0) - scene.points.min(axis=0)))
            if not span <= MAX_SCENE_SPAN_M:
                raise SceneError(f"the scene spans {span:.3g} m: not a scan in metres (EFEM's objects are cm-sized); "
                                 "bring it in with `efem-viz import-scan --units ...`")
            priors, prior_words = self.priors_for(scene)
            if self.job.preset == "auto":  # the scene's own preset, for the prior it is solved with
                from efem_viz.prior.config import prior_category

                cfg = self.job.config(scene, prior=prior_category(priors[0]).name)
            else:
                cfg = self.cfg
            t1 = time.perf_counter()
            load_s = t1 - t0
            if self.job.timeout_s is not None:
                timer = threading.Timer(float(self.job.timeout_s), cancel.set)
                timer.daemon = True
                timer.start()
            result = run_em(scene, cfg=cfg, priors=priors, seed=self.job.seed, device=self.job.device,
                            on_step=on_step, cancel=cancel)
            t2 = time.perf_counter()
            solve_s = t2 - t1
            out_scene, out_instances, frame_name = scene, result.instances, "scene"
            scan_frame = ScanFrame.from_provenance(scene.provenance)
            if self.job.frame == "original" and scan_frame is not None and not scan_frame.is_identity:
                out_scene, _ = scene_in_file_frame(scene)
                out_instances = result.instances.transformed(scan_frame.to_scene.inverse())
                frame_name = f"original ({scan_frame.units})"
            if self.job.ply:
                out_instances.to_colored_ply(out_scene, task.ply_path, threshold=self.job.threshold)
            about = {"scene": task.name, "scan_frame": None if scan_frame is None else scan_frame.to_provenance()}
            atomic_write_text(task.objects_path, json.dumps(
                {**about, "frame": frame_name, "instances": out_instances.to_json_objects()}, indent=1) + "\n")
            folder = task.objects_folder(self.job)
            if folder is not None:
                out_instances.export_objects(folder, fmt=self.job.objects_format, frame=frame_name, extra=about)
            if self.job.scannet:
                result.instances.to_scannet(task.scannet_path.parent, task.name, scene.num_points)
            result.save(task.result_path)  # last: the commit record of the scene
            write_s = time.perf_counter() - t2
        except EMCancelled:
            return failed(f"timed out after {self.job.timeout_s:g} s (--scene-timeout)", points)
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # a bad scene or a failing solve is this scene's failure, not the batch's
            logger.debug("%s failed", task.name, exc_info=True)
            return failed(one_line(exc), points)
        finally:
            if timer is not None:
                timer.cancel()
        self.scenes_done += 1
        return SceneOutcome(
            name=task.name, path=str(task.path), status="ok", instances=len(result.instances), points=points,
            seconds=time.perf_counter() - t0, worker=self.worker, load_s=load_s, solve_s=solve_s, write_s=write_s,
            rss_mb=peak_rss_mb(), fingerprint=fp, cpu_s=time.process_time() - c0, scene_stamp=stamp,
            preset=cfg.name + prior_words + _free_space_words(cfg, scene),
        )


def _free_space_words(cfg: Any, scene: Any) -> str:
    """What a scene's line adds to its preset about the free-space check: ", free space from 4 cameras" when the
    run checked against recorded cameras, nothing otherwise."""
    if cfg.free_space.margin is None:
        return ""
    from efem_viz.geometry.camera import Camera

    try:
        n = len(Camera.parse_all(scene.provenance)[0])
    except (TypeError, ValueError, AttributeError):
        return ""
    return f", free space from {n} camera{'s' if n != 1 else ''}" if n else ""
