"""Batch segmentation: plan (what to run, what to skip), run on a backend, record `batch.json`, report.

```python
from efem_viz.batch import BatchJob, make_backend, run_batch

job = BatchJob.create(priors=("mug",), preset="fast", seed=0)
report = run_batch(job, ["scans/"], "results/", backend=make_backend("process"))
print(report.counts(), report.passed)
```

**Resuming.** A scene is skipped when its `<scene>.efem.npz` is a complete result of *the same job*: the file passes a
cheap check (every array header agrees with its member's bytes, every key a result has is there, `kind`, schema,
scene name and seed match), the folder's `batch.json` records the scene as done with the same job fingerprint
(config, priors' content hashes, seed, PLY threshold: `BatchJob.fingerprint`), and the other outputs the job writes
exist. Anything else is recomputed (`force=True` recomputes everything). Because a worker writes the result file
last and atomically (and removes a stale one before it starts), a batch killed at any moment leaves every scene
either complete or recomputed on the next run; temporary files of interrupted writes are removed when the next run
starts. A result that has no record (made by another tool, or finished in the instant between its write and the
record's) is recomputed: conservative, at most one scene per worker after a kill.

**Order.** Scenes are handed out largest file first (`largest_first`); outcomes and `batch.json` list them in scene
order.

**Isolation.** A scene that cannot be read or whose solve fails is recorded as failed with a one-line error, and the
batch goes on. `BatchReport.passed` is True only when no scene failed.

**Concurrency.** One batch at a time per output folder: `run_batch` holds an exclusive lock on `<out>/.batch.lock`
(released by the kernel if the process dies).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import re
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from efem_viz.batch.backends import Backend, BatchError
from efem_viz.batch.events import BatchObserver
from efem_viz.batch.job import (
    BATCH_FILE,
    BATCH_SCHEMA_VERSION,
    SCANNET_DIR,
    SEG_SUFFIX,
    BatchJob,
    BatchPlan,
    BatchReport,
    SceneOutcome,
    SceneTask,
    WorkerInfo,
    scene_name_of,
    scene_stamp,
)
from efem_viz.data.files import MAX_BATCH_FILE_BYTES, NO_SCENES_GIVEN

logger = logging.getLogger(__name__)

LOCK_FILE = ".batch.lock"
"""Held (flock) by the batch writing into a folder."""
RECORD_EVERY_S = 1.0
"""`batch.json` is rewritten after a finished scene at most this often (and always at the end)."""
_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9.]+)?$")
"""Temporary files of `efem_viz.data.io.atomic_write` (`.<stem>.<random>.tmp<suffix>`) left by a killed write."""


def read_batch_records(out: str | os.PathLike[str], *, warn: bool = True) -> dict[str, SceneOutcome]:
    """The per-scene records of `<out>/batch.json` (empty when there is none or it is unreadable; invalid records
    are left out, so their scenes are recomputed). `warn=False`: no warnings (a second read of the same file)."""
    p = Path(out) / BATCH_FILE
    if not p.is_file():
        return {}
    try:
        if p.stat().st_size > MAX_BATCH_FILE_BYTES:
            raise ValueError(f"{p.stat().st_size:,} bytes, more than a batch record can need")
        data = json.loads(p.read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("kind") != "efem-batch":
            raise ValueError("not an efem-viz batch record")
        scenes = data.get("scenes", [])
        if not isinstance(scenes, list):
            raise ValueError("its 'scenes' is not a list")
    except (OSError, ValueError, TypeError, AttributeError, RecursionError) as exc:  # RecursionError: deep nesting
        if warn:
            logger.warning("%s is unreadable (%s): every existing result will be recomputed", p,
                           str(exc)[:200] or type(exc).__name__)
        return {}
    records: dict[str, SceneOutcome] = {}
    bad = 0
    for r in scenes:
        try:
            if not isinstance(r, dict):
                raise ValueError("a record is not an object")
            rec = SceneOutcome.from_dict(r)
        except ValueError as exc:  # one bad record: that scene is recomputed, the others stand
            bad += 1
            if bad == 1 and warn:
                logger.warning("%s: an invalid record (%s): its scene will be recomputed", p, str(exc)[:200])
            continue
        records[rec.name] = rec
    if bad > 1 and warn:
        logger.warning("%s: %d invalid records in all; their scenes will be recomputed", p, bad)
    return records


def check_result_file(task: SceneTask, *, seed: int) -> str | None:
    """Why `task`'s result file is not a usable result (None when it is). Reads only headers and small arrays.

    Checks: every array header of the archive agrees with the bytes of its member (`check_npz_headers`), every key
    `EMResult.save` writes is present, and `kind`, `schema_version`, `scene_name` and `seed` are the expected ones.
    """
    import numpy as np

    from efem_viz.data.npz_guard import check_npz_headers
    from efem_viz.em.results import REQUIRED_RESULT_KEYS, RESULT_SCHEMA_VERSION

    p = task.result_path
    if not p.is_file():
        return "no result"
    try:
        check_npz_headers(p, 1 << 40)
        with np.load(p, allow_pickle=False) as z:
            missing = [k for k in REQUIRED_RESULT_KEYS if k not in z.files]
            if missing:
                return f"incomplete result (missing {missing[0]})"
            if str(z["kind"]) != "efem-result" or int(z["schema_version"]) != RESULT_SCHEMA_VERSION:
                return "not a result of this version"
            if str(z["scene_name"]) != task.name:
                return f"result of another scene ({str(z['scene_name'])!r})"
            if int(z["seed"]) != int(seed):
                return f"computed with seed {int(z['seed'])}"
    except Exception as exc:  # zipfile/numpy raise many types on a damaged archive
        return f"damaged result ({type(exc).__name__})"
    return None


def plan_batch(
    job: BatchJob,
    scenes: Iterable[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    force: bool = False,
) -> BatchPlan:
    """Find the scenes and decide which to run.

    Args:
        job: the batch job.
        scenes: scene files and/or folders (`efem_viz.data.io.find_scenes`; `*.seg.ply` outputs inside `out` are
            left out).
        out: output folder.
        force: recompute every scene.

    Returns:
        The plan.

    Raises:
        SceneError: a path does not exist or is not a scene file.
        ValueError: no scenes, or two scenes with the same name (their outputs would overwrite each other).
    """
    from efem_viz.data.io import find_scenes

    out_dir = Path(out).expanduser().resolve()
    found = find_scenes(list(scenes))
    paths = [p for p in found if not (p.name.endswith(SEG_SUFFIX) and p.resolve().parent == out_dir)]
    if len(paths) < len(found):
        logger.warning("the output folder %s is among the inputs: its %d segmentation output(s) (*%s) are not "
                       "segmented again", out_dir, len(found) - len(paths), SEG_SUFFIX)
    foreign = [p for p in paths if p.name.endswith(SEG_SUFFIX)]
    if foreign:
        logger.warning("%d input(s) are segmentation outputs of another run (e.g. %s): their labels are "
                       "predictions, not ground truth", len(foreign), foreign[0])
    if not paths:
        raise ValueError(f"no scene files found in {', '.join(str(s) for s in scenes)}" if scenes else
                          NO_SCENES_GIVEN)
    by_name: dict[str, Path] = {}
    for p in paths:
        name = scene_name_of(p)
        if name in by_name:
            raise ValueError(f"two scenes are named {name!r} ({by_name[name]} and {p}); their outputs in {out_dir} "
                             "would overwrite each other: rename one or run them into different --out folders")
        by_name[name] = p
    fp = job.fingerprint()
    records = {} if force else read_batch_records(out_dir)
    tasks: list[SceneTask] = []
    skipped: list[SceneOutcome] = []
    reasons: dict[str, str] = {}
    for i, (name, p) in enumerate(by_name.items()):
        task = SceneTask(index=i, path=p.resolve(), name=name, out=out_dir)
        why = "forced" if force else _why_not_done(task, job, fp, records.get(name))
        if why is None:
            rec = records[name]
            skipped.append(SceneOutcome(name=name, path=str(task.path), status="skipped", instances=rec.instances,
                                        points=rec.points, seconds=rec.seconds, worker=rec.worker,
                                        fingerprint=fp, scene_stamp=rec.scene_stamp))
            continue
        if task.result_path.exists():
            reasons[name] = why
            logger.info("%s: recomputing (%s)", name, why)
        tasks.append(task)
    return BatchPlan(tasks=tuple(tasks), skipped=tuple(skipped), out=out_dir, fingerprint=fp, reasons=reasons,
                     order=tuple(by_name))


def largest_first(tasks: Sequence[SceneTask]) -> list[SceneTask]:
    """The order scenes are handed out: largest file first (ties in scene order), so that with several workers the
    longest scenes do not start last and leave the other workers idle at the end."""

    def size(t: SceneTask) -> int:
        try:
            return t.path.stat().st_size
        except OSError:
            return 0

    return sorted(tasks, key=lambda t: (-size(t), t.index))


def _why_not_done(task: SceneTask, job: BatchJob, fp: str, record: SceneOutcome | None) -> str | None:
    problem = check_result_file(task, seed=job.seed)
    if problem is not None:
        return problem
    if record is None or not record.passed:
        return f"no record in {BATCH_FILE}"
    if record.fingerprint != fp:
        return "made with other settings (config, priors, seed or threshold)"
    if Path(record.path) != task.path:
        return f"made from another scene file ({record.path})"
    if record.scene_stamp != scene_stamp(task.path):
        return "the scene file changed since its result was made"
    if job.ply and not task.ply_path.is_file():
        return f"{task.ply_path.name} missing"
    if job.scannet and not task.scannet_path.is_file():
        return f"{SCANNET_DIR}/{task.scannet_path.name} missing"
    folder = task.objects_folder(job)
    if folder is not None and not (folder / "objects.json").is_file():
        return f"{folder / 'objects.json'} missing"
    return None


# ---------------------------------------------------------------------------------------------- batch.json
class _BatchRecord:
    """Keeps `<out>/batch.json` current: rewritten (atomically) after finished scenes and at the end.

    Records of scenes outside this run (earlier batches into the same folder) are kept, so resuming either batch
    later still finds its records; the old record of a scene this run recomputes is dropped until its new outcome
    arrives (so the file never vouches for a result that is being replaced).
    """

    def __init__(self, plan: BatchPlan, job: BatchJob, backend: dict[str, object]) -> None:
        self.path = plan.out / BATCH_FILE
        self.plan, self.job, self.backend = plan, job, backend
        self.records = read_batch_records(plan.out, warn=False)  # the plan has warned
        for o in plan.skipped:  # a skipped scene keeps the record of the run that computed it
            self.records.setdefault(o.name, o)
        for t in plan.tasks:
            self.records.pop(t.name, None)
        self.done: dict[str, str] = {}
        self.started = _now()
        self.t0 = time.perf_counter()
        self.last_write = 0.0
        self.workers: list[WorkerInfo] = []

    def add(self, outcome: SceneOutcome) -> None:
        self.records[outcome.name] = outcome
        self.done[outcome.name] = outcome.status
        if time.perf_counter() - self.last_write >= RECORD_EVERY_S:
            self.write(finished=False)

    def write(self, *, finished: bool, report: BatchReport | None = None) -> None:
        from efem_viz.data.io import atomic_write_text

        counts = {"ok": 0, "skipped": len(self.plan.skipped), "failed": 0,
                  "pending": len(self.plan.tasks) - len(self.done)}
        for status in self.done.values():
            counts[status] += 1
        doc = {
            "kind": "efem-batch",
            "schema_version": BATCH_SCHEMA_VERSION,
            "fingerprint": self.plan.fingerprint,
            "job": self.job.to_dict(),
            "backend": self.backend,
            "started": self.started,
            "finished": _now() if finished else None,
            "interrupted": bool(report.interrupted) if report is not None else False,
            "wall_s": round(time.perf_counter() - self.t0, 3),
            "counts": counts,
            "workers": [w.to_dict() for w in self.workers],
            "scenes": [self.records[k].to_dict() for k in sorted(self.records)],
        }
        atomic_write_text(self.path, json.dumps(doc, indent=1) + "\n")
        self.last_write = time.perf_counter()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@contextmanager
def folder_lock(out: Path) -> Iterator[None]:
    """Exclusive lock on `<out>/.batch.lock` for the duration (released by the kernel if the process dies); the
    lock file is removed when the batch ends, so a finished folder holds only its results.

    A process that opened the file just before its holder removed it would lock a deleted file: after locking,
    the file at the path must still be the one locked, else the lock is taken again on the new file.

    Raises:
        BatchError: another batch holds it.
    """
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    for _ in range(100):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except ImportError:  # pragma: no cover - not POSIX: no lock, documented
            break
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise BatchError(f"another batch (pid {holder}) is writing to {out}; wait for it or use another --out"
                             ) from exc
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # locked a file its holder had just removed: lock the current one
    else:  # pragma: no cover - 100 holders finishing in a row
        raise BatchError(f"could not lock {path}: it keeps being replaced")
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                path.unlink()  # still holding the lock: nobody else can be using this file
        except OSError:
            pass
        os.close(fd)


def remove_stale_temporaries(out: Path) -> int:
    """Delete temporary files of interrupted atomic writes under the output folders; returns how many."""
    n = 0
    for d in (out, out / SCANNET_DIR, out / SCANNET_DIR / "pred_mask"):
        if not d.is_dir():
            continue
        for p in d.iterdir():
            if p.is_file() and _TEMP_NAME.match(p.name):
                p.unlink(missing_ok=True)
                n += 1
    if n:
        logger.info("removed %d temporary file(s) of an interrupted run in %s", n, out)
    return n


# ---------------------------------------------------------------------------------------------- run
def run_batch(
    job: BatchJob,
    scenes: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    backend: Backend,
    force: bool = False,
    observer: BatchObserver | None = None,
) -> BatchReport:
    """Segment every scene (skipping those with valid results of the same job) and record `batch.json`.

    Args:
        job: the batch job (`BatchJob.create`).
        scenes: scene files and/or folders.
        out: output folder (created).
        backend: where to run (`make_backend("local" | "process" | "ray", options)`).
        force: recompute scenes that have valid results.
        observer: progress events (the CLI's display); default: none.

    Returns:
        The report (also when scenes failed). On Ctrl+C the report so far is recorded, then KeyboardInterrupt
        propagates.

    Raises:
        BatchError: another batch writes to `out`, or the batch cannot run (priors do not load, workers cannot
            start, Ray missing).
        ValueError, SceneError: no scenes, duplicate scene names, a path that does not exist.
    """
    events = observer or BatchObserver()
    job = backend.resolve_job(job)
    out_dir = Path(out).expanduser().resolve()
    if not out_dir.exists():
        plan_batch(job, scenes, out_dir, force=force)  # bad scene lists fail before the output folder is made
    with folder_lock(out_dir):
        remove_stale_temporaries(out_dir)
        plan = plan_batch(job, scenes, out_dir, force=force)
        events.on_plan(plan)
        record = _BatchRecord(plan, job, backend.describe())
        report = BatchReport(outcomes=list(plan.skipped), plan=plan, backend=backend.describe(), job=job)

        class _Relay(BatchObserver):
            """Collects the workers for the record, forwards everything to the caller's observer."""

            def on_worker(self, info: WorkerInfo) -> None:
                record.workers.append(info)
                events.on_worker(info)

            def on_start(self, task: SceneTask, worker: str) -> None:
                events.on_start(task, worker)

            def on_step(self, task: SceneTask, worker: str, step: int, total: int, text: str) -> None:
                events.on_step(task, worker, step, total, text)

        t0 = time.perf_counter()
        done: dict[str, SceneOutcome] = {}
        try:
            if plan.tasks:
                record.write(finished=False)
                for outcome in backend.run(job, largest_first(plan.tasks), _Relay()):
                    done[outcome.name] = outcome
                    record.add(outcome)
                    events.on_done(outcome)
        except KeyboardInterrupt:
            report.interrupted = True
            raise
        finally:
            rank = {name: i for i, name in enumerate(plan.order)}
            report.outcomes = sorted([*plan.skipped, *done.values()], key=lambda o: rank[o.name])
            report.workers = list(record.workers)
            report.backend = backend.describe()
            report.wall_s = time.perf_counter() - t0
            if len(done) < len(plan.tasks) and not report.interrupted:
                report.interrupted = True  # an error stopped the run
            record.backend = report.backend
            record.write(finished=True, report=report)
        events.on_finish(report)
        return report


__all__ = [
    "BatchError",
    "BatchPlan",
    "BatchReport",
    "check_result_file",
    "folder_lock",
    "plan_batch",
    "read_batch_records",
    "remove_stale_temporaries",
    "run_batch",
]
