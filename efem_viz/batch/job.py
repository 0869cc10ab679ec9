"""What a batch run is made of: the job (`BatchJob`), one scene's task (`SceneTask`) and its outcome (`SceneOutcome`),
the plan (`BatchPlan`) and the report (`BatchReport`).

These are plain picklable records: the driver builds them, ships tasks to workers (in-process, a local process pool
or Ray actors) and gets outcomes back. Nothing here imports torch, so the driver of a Ray cluster stays light.

The outputs of one scene, all under the output folder and all written atomically (`efem_viz.data.io.atomic_write`):
`<scene>.seg.ply` (coloured by instance), `scannet/<scene>.txt` + `scannet/pred_mask/<scene>_<k>.txt` (ScanNet
layout), then **last** `<scene>.efem.npz` (trace + instances). The result file is the scene's commit record: it only
exists once every other output of the scene has been written.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from efem_viz.data.files import BATCH_FILE as _BATCH_FILE
from efem_viz.data.io import RESULT_SUFFIX, SEG_SUFFIX  # SEG_SUFFIX: the coloured PLY written per scene
from efem_viz.em.config import AUTO_PRESET_RULE, SCENE_PRIOR_CATEGORIES, EMConfig, SolveSettings
from efem_viz.prior.config import DEFAULT_PRIOR

BATCH_SCHEMA_VERSION = 1
"""Version of `batch.json` and of the job fingerprint (bump when either changes meaning)."""
BATCH_FILE = _BATCH_FILE
"""The batch record written beside the results."""
SCANNET_DIR = "scannet"
"""Sub-folder of the ScanNet benchmark layout."""

Status = Literal["ok", "skipped", "failed"]
"""ok: computed in this run; skipped: a valid result of the same job was already there; failed: see `error`."""


def scene_name_of(path: str | os.PathLike[str]) -> str:
    """The scene name `load_scene` gives a file (its name without the last suffix): the outputs are named by it."""
    p = Path(path)
    return p.name[: -len(p.suffix)] if p.suffix else p.name


@dataclass(frozen=True, kw_only=True)
class BatchJob(SolveSettings):
    """Everything a worker needs to segment any scene of the batch (the same for every scene): the solver knobs
    (`SolveSettings`: preset, proposals, work_voxel, tau_out, matmul_dtype) and the fields below.

    Build one with `BatchJob.create(...)` (it checks the config); `config()` gives the solver config and
    `fingerprint()` identifies the settings that change a result, so a resumed batch only skips results made
    with the same settings.
    """

    priors: tuple[str, ...] = (DEFAULT_PRIOR,)
    """Prior specs for `efem_viz.prior.registry.load_priors`: a name under efem_viz/weights/, "sphere", or a .pt path
    (made absolute, so workers started elsewhere find it)."""
    seed: int = 0
    """The seed of every scene (the same seed gives the same result on every backend)."""
    device: str = "cpu"
    """torch device of the solver."""
    threads: int | None = None
    """torch CPU threads per worker (None: torch's default)."""
    threshold: float = 0.0
    """Confidence threshold of the coloured PLY."""
    scannet: bool = True
    """Write the ScanNet layout under `<out>/scannet/`."""
    ply: bool = True
    """Write `<scene>.seg.ply`."""
    timeout_s: float | None = None
    """Give up on a scene after this many seconds of solving (it is reported failed; the batch goes on)."""
    objects_dir: str | None = None
    """Also write every instance's completed mesh and `objects.json` into `<objects_dir>/<name>/` (absolute)."""
    objects_format: str = "glb"
    """Mesh format of `objects_dir`: glb, obj or ply."""
    frame: str = "scene"
    """Frame of the coloured PLY and `<name>.objects.json`: "scene" (metres, +Z up) or "original" (an imported
    scan's own frame and units, `efem_viz.data.scan.ScanFrame`; the scene frame for scenes made in it)."""
    scene_priors: bool = False
    """A generated chair or kitchen scene (`efem_viz.em.config.suggested_prior`) is solved with that category's
    shipped prior instead of the one prior of `priors` (as the viewer's Run; `PriorSet.solve_priors`): what
    `segment` does when no --prior is given."""

    @classmethod
    def create(cls, **kwargs: object) -> BatchJob:
        """A validated job: prior paths made absolute, the solver config built once (bad values raise here).

        Raises:
            ValueError: no prior, a prior given twice, bad solver values (as `EMConfig.validate`), threads < 1,
                timeout <= 0.
        """
        job = cls(**kwargs)  # type: ignore[arg-type]
        if not job.priors:
            raise ValueError("give at least one --prior")
        specs = tuple(_absolute_spec(s) for s in job.priors)
        if len(set(specs)) != len(specs):
            raise ValueError(f"a prior is given twice: {list(job.priors)}")
        if job.threads is not None and job.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {job.threads}")
        if job.objects_format not in ("glb", "obj", "ply"):
            raise ValueError(f"--object-format must be glb, obj or ply, got {job.objects_format!r}")
        if job.objects_dir is not None:
            job = dataclasses.replace(job, objects_dir=str(Path(job.objects_dir).expanduser().resolve()))
        if job.frame not in ("scene", "original"):
            raise ValueError(f"--frame must be scene or original, got {job.frame!r}")
        if job.timeout_s is not None and not job.timeout_s > 0:
            raise ValueError(f"--scene-timeout must be > 0 seconds, got {job.timeout_s}")
        job = dataclasses.replace(job, priors=specs)
        job.config()  # validate now, before any worker starts
        return job

    def config(self, scene: object = None, device: str | None = None, prior: str | None = None) -> EMConfig:
        """`SolveSettings.config` on the job's device (a precision of "auto" resolves for it)."""
        return super().config(scene, self.device if device is None else device, prior)

    def fingerprint(self) -> str:
        """A hex digest of what decides a scene's result: the solver config, each prior's identity (the weights
        file's content hash, or the analytic prior's name), the seed and the PLY threshold. Device, threads,
        backend and timeout are left out (they do not change what is computed), but a precision of "auto" enters
        as what it resolves to on this machine and device (bf16 computes another result than float32)."""
        payload = {
            "schema": BATCH_SCHEMA_VERSION,
            "config": json.loads(self.config().to_json()),
            "priors": [prior_identity(s) for s in self.priors],
            "seed": int(self.seed),
            "threshold": float(self.threshold),
        }
        if self.frame != "scene":  # the exports' frame; left out by default so earlier batches stay valid
            payload["frame"] = self.frame
        if self.preset == "auto":  # each scene's own preset: a change of the rule re-keys the results
            payload["auto_rule"] = AUTO_PRESET_RULE
        if self.scene_priors and len(self.priors) == 1:  # the priors a scene may be solved with instead
            payload["scene_priors"] = [prior_identity(c) for c in SCENE_PRIOR_CATEGORIES]
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:20]

    def to_dict(self) -> dict[str, object]:
        """JSON-able settings (for `batch.json`)."""
        d = dataclasses.asdict(self)
        d["priors"] = list(self.priors)
        return d


def _absolute_spec(spec: str) -> str:
    """A prior spec with a file path made absolute (names such as "mug" or "sphere" stay as they are)."""
    s = str(spec)
    if s.endswith(".pt") or os.sep in s or "/" in s:
        return str(Path(s).expanduser().resolve())
    return s


def prior_identity(spec: str) -> str:
    """What identifies a prior for resuming: `"<name>"` for an analytic prior, else `"<file name>:<sha256[:16]>"`
    of its weights file.

    Raises:
        FileNotFoundError: the weights file does not exist.
    """
    from efem_viz.prior.model import resolve_prior_path
    from efem_viz.prior.registry import ANALYTIC_PRIORS, check_prior_name

    if spec in ANALYTIC_PRIORS:
        return spec
    check_prior_name(spec)
    path = resolve_prior_path(spec)
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return f"{path.name}:{h.hexdigest()[:16]}"


def scene_stamp(path: Path) -> str:
    """`<bytes>:<mtime ns>` of a scene file ("" when it cannot be read): a result is only reused for the same file."""
    try:
        st = path.stat()
    except OSError:
        return ""
    return f"{st.st_size}:{st.st_mtime_ns}"


@dataclass(frozen=True)
class SceneTask:
    """One scene to segment.

    Attributes:
        index: position in the batch (scene order).
        path: the scene file (absolute).
        name: the scene name (`scene_name_of(path)`); outputs are `<out>/<name>.*`.
        out: the output folder (absolute).
    """

    index: int
    path: Path
    name: str
    out: Path

    @property
    def result_path(self) -> Path:
        """`<out>/<name>.efem.npz`: written last, so its presence means every output of the scene is complete."""
        return self.out / f"{self.name}{RESULT_SUFFIX}"

    @property
    def ply_path(self) -> Path:
        """`<out>/<name>.seg.ply`."""
        return self.out / f"{self.name}{SEG_SUFFIX}"

    def objects_folder(self, job: BatchJob) -> Path | None:
        """`<objects_dir>/<name>/` of a job that exports objects (None otherwise)."""
        return None if job.objects_dir is None else Path(job.objects_dir) / self.name

    @property
    def objects_path(self) -> Path:
        """`<out>/<name>.objects.json`: every instance's category, confidence, pose and box."""
        return self.out / f"{self.name}.objects.json"

    @property
    def scannet_path(self) -> Path:
        """`<out>/scannet/<name>.txt`."""
        return self.out / SCANNET_DIR / f"{self.name}.txt"


@dataclass(frozen=True)
class SceneOutcome:
    """What became of one scene.

    Attributes:
        name: scene name.
        path: the scene file.
        status: "ok", "skipped" (a valid result of the same job was there) or "failed".
        instances: accepted instances (-1 when unknown: failed, or skipped without a record).
        points: scene points (-1 when unknown).
        seconds: the worker's time on the scene (load + solve + write; for a skipped scene the time it took
            when it was computed, if recorded, else 0).
        error: one line saying why it failed ("" otherwise).
        worker: which worker ran it (e.g. "local", "process-1", "ray-0@host").
        load_s: seconds reading the scene.
        solve_s: seconds in `run_em`.
        write_s: seconds writing the outputs.
        rss_mb: the worker's peak resident memory after the scene (MiB; 0 when unknown).
        fingerprint: the job fingerprint the result was computed with.
        wall_s: seconds from the driver handing the scene out to it receiving the outcome; `wall_s - seconds` is
            the backend's overhead on the scene (dispatch, transfer, queueing in the worker's pipe).
        cpu_s: CPU seconds of the worker process on the scene (all its threads; unlike `seconds`, not inflated
            when other jobs share the cores).
    """

    name: str
    path: str
    status: Status
    instances: int = -1
    points: int = -1
    seconds: float = 0.0
    error: str = ""
    worker: str = ""
    load_s: float = 0.0
    solve_s: float = 0.0
    write_s: float = 0.0
    rss_mb: float = 0.0
    fingerprint: str = ""
    preset: str = ""
    """The solver preset the scene ran with (`--preset auto` picks it per scene)."""
    wall_s: float = 0.0
    cpu_s: float = 0.0
    scene_stamp: str = ""
    """Size and modification time of the scene file the result was computed from (`scene_stamp`)."""

    @property
    def passed(self) -> bool:
        """ok or skipped (a valid result exists)."""
        return self.status != "failed"

    def to_dict(self) -> dict[str, object]:
        """JSON-able record (for `batch.json`)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> SceneOutcome:
        """Inverse of `to_dict` (unknown keys are ignored, so older records still read).

        Raises:
            ValueError: a required key is missing or has the wrong type.
        """
        known = {f.name: f for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in d.items() if k in known}
        for key in ("name", "path", "status"):
            if not isinstance(kw.get(key), str):
                raise ValueError(f"batch record without a valid {key!r}: {d!r}"[:200])
        if kw["status"] not in ("ok", "skipped", "failed"):
            raise ValueError(f"batch record with unknown status {kw['status']!r}")
        for key, f in known.items():  # every other field must have its declared type ("instances":
            if key not in kw or key in ("name", "path", "status"):  # "many" crashed every later resume)
                continue
            v = kw[key]
            want = (int,) if f.type in ("int", int) else (int, float) if f.type in ("float", float) else (str,)
            if isinstance(v, bool) or not isinstance(v, want):
                raise ValueError(f"batch record {kw['name']!r}: {key} must be {want[-1].__name__}, "
                                 f"got {type(v).__name__}"[:200])
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"batch record {kw['name']!r}: {key} is not finite")
        try:
            return cls(**kw)  # type: ignore[arg-type]
        except TypeError as exc:
            raise ValueError(f"bad batch record {d!r}"[:200]) from exc


@dataclass(frozen=True)
class WorkerInfo:
    """A started worker: where it runs and what starting it cost.

    Attributes:
        worker: its id ("local", "process-1", "ray-0").
        host: host name.
        pid: process id.
        threads: torch CPU threads.
        start_s: seconds from asking for the worker to it being ready (process start, imports, prior loading).
        prior_load_s: seconds loading the priors (once per worker).
        rss_mb: resident memory once ready (MiB).
    """

    worker: str
    host: str
    pid: int
    threads: int
    start_s: float = 0.0
    prior_load_s: float = 0.0
    rss_mb: float = 0.0
    extra: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, object]:
        """JSON-able record."""
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class BatchPlan:
    """What a batch run will do.

    Attributes:
        tasks: scenes to segment, in scene order.
        skipped: outcomes (status "skipped") of scenes whose valid results of the same job exist.
        out: the output folder (absolute).
        fingerprint: the job fingerprint.
        reasons: scene name -> why an existing result is recomputed (for scenes that had one).
        order: every scene name of the batch, in scene order.
    """

    tasks: tuple[SceneTask, ...]
    skipped: tuple[SceneOutcome, ...]
    out: Path
    fingerprint: str
    reasons: dict[str, str] = field(default_factory=dict)
    order: tuple[str, ...] = ()

    @property
    def total(self) -> int:
        """Scenes in the batch (to run + skipped)."""
        return len(self.tasks) + len(self.skipped)


# ---------------------------------------------------------------------------------------------- report
@dataclass
class BatchReport:
    """The outcome of a batch run.

    Attributes:
        outcomes: one per scene of the plan, in scene order (a scene that never ran, after an interruption, is
            missing).
        plan: the plan it ran.
        backend: `Backend.describe()`.
        job: the job (with the backend's defaults filled in).
        workers: the workers that started.
        wall_s: seconds of the whole run (planning excluded).
        interrupted: the run was stopped (Ctrl+C) before every scene finished.
    """

    outcomes: list[SceneOutcome]
    plan: BatchPlan
    backend: dict[str, object]
    job: BatchJob
    workers: list[WorkerInfo] = field(default_factory=list)
    wall_s: float = 0.0
    interrupted: bool = False

    @property
    def passed(self) -> bool:
        """Every scene of the plan has a valid result (computed now or skipped)."""
        return (not self.interrupted and len(self.outcomes) == self.plan.total
                and all(o.passed for o in self.outcomes))

    def counts(self) -> dict[str, int]:
        """Scenes per status ("ok", "skipped", "failed", "pending")."""
        c = {"ok": 0, "skipped": 0, "failed": 0}
        for o in self.outcomes:
            c[o.status] += 1
        c["pending"] = self.plan.total - len(self.outcomes)
        return c

    def failed(self) -> list[SceneOutcome]:
        """The failed scenes."""
        return [o for o in self.outcomes if o.status == "failed"]
