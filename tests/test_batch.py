"""Batch segmentation (efem_viz/batch): the three backends give the same files, resume after kill -9, isolated failures,
one-line job errors, and `evaluate` / `view` on a 200-scene batch folder.

The runner's own tests use the analytic sphere prior (fast); the backend comparison and the kill test use the shipped
mug prior on three small single-mug scans. Ray is a test dependency (`bash scripts/setup.sh --test` installs it): the
Ray test fails, never skips, without it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from efem_viz.batch import BackendOptions, BatchError, BatchJob, BatchObserver, BatchReport, make_backend, run_batch
from efem_viz.batch.job import BATCH_FILE, SceneOutcome, SceneTask, WorkerInfo
from efem_viz.batch.runner import folder_lock, plan_batch
from efem_viz.data.io import save_scene
from efem_viz.em.results import EMResult

REPO = Path(__file__).resolve().parents[1]
MUG_JOB: dict[str, Any] = {"priors": ("mug",), "preset": "fast", "proposals": 4, "seed": 1, "threads": 1}
"""The mug runs: fast preset, 4 proposals, seed 1, one torch thread per worker."""
MUG_ARGS = ["--prior", "mug", "--preset", "fast", "--proposals", "4", "--seed", "1", "--threads", "1"]
"""The same job on the command line."""
SPHERE_ARGS = ["--prior", "sphere", "--preset", "fast", "--proposals", "48", "--threads", "1"]
VOLATILE = ("timings_json", "trace/timings_json", "trace/step_elapsed")
"""Result arrays that hold wall-clock times (everything else must be identical for the same seed)."""


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


def result_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of a saved result except the wall-clock ones."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files if k not in VOLATILE}


def assert_same_results(a: Path, b: Path, names: list[str]) -> None:
    """The result files of `names` in folders `a` and `b` hold the same arrays, bit for bit (NaN == NaN)."""
    for name in names:
        ra, rb = result_arrays(a / f"{name}.efem.npz"), result_arrays(b / f"{name}.efem.npz")
        assert sorted(ra) == sorted(rb), name
        diff = [k for k in ra if not np.array_equal(ra[k], rb[k], equal_nan=ra[k].dtype.kind in "fc")]
        assert not diff, f"{name}: {diff} differ between {a} and {b}"


def sphere_folder(folder: Path, n: int = 3) -> list[str]:
    """`n` seeded sphere tabletops s0.. as .npz files in `folder`."""
    from efem_viz.prior.analytic import make_sphere_scene

    folder.mkdir(parents=True, exist_ok=True)
    names = [f"s{k}" for k in range(n)]
    for k, name in enumerate(names):
        save_scene(make_sphere_scene(seed=k, spacing=0.005, name=name), folder / f"{name}.npz")
    return names


def batch_json(out: Path) -> dict[str, Any]:
    return json.loads((out / BATCH_FILE).read_text())


@pytest.fixture(scope="module")
def mug_scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three single-mug scans (procedural test mugs, 2,000 surface points each, ground truth = the mug)."""
    from efem_viz.data.procedural import make_mug
    from efem_viz.data.scene import Scene
    from efem_viz.geometry.sampling import sample_surface

    folder = tmp_path_factory.mktemp("mug_scenes")
    for seed in (3, 5, 8):
        s = sample_surface(make_mug(seed), 2000, seed=seed)
        scene = Scene.create(f"mug_{seed}", s.points.astype(np.float32), normals=s.normals.astype(np.float32),
                             instance=np.ones(2000, np.int32), categories={1: "mug"})
        save_scene(scene, folder / f"mug_{seed}.ply")
    return folder


@pytest.fixture(scope="module")
def local_run(mug_scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, BatchReport]:
    out = tmp_path_factory.mktemp("local_out")
    report = run_batch(BatchJob.create(**MUG_JOB), [mug_scenes], out, backend=make_backend("local"))
    return out, report


MUG_NAMES = ["mug_3", "mug_5", "mug_8"]


# ---------------------------------------------------------------------------------------------- backends
def test_local_batch_segments_every_scene_and_records_it(local_run: tuple[Path, BatchReport]) -> None:
    out, report = local_run
    assert report.passed and [o.name for o in report.outcomes] == MUG_NAMES
    for o in report.outcomes:
        assert o.status == "ok" and o.instances >= 1 and o.points == 2000 and o.worker == "local"
        res = EMResult.load(out / f"{o.name}.efem.npz")
        assert res.seed == 1 and res.trace.num_proposals == 4 and len(res.instances) == o.instances
        assert (out / f"{o.name}.seg.ply").is_file() and (out / "scannet" / f"{o.name}.txt").is_file()
    rec = batch_json(out)
    assert rec["kind"] == "efem-batch" and rec["counts"] == {"ok": 3, "skipped": 0, "failed": 0, "pending": 0}
    assert rec["finished"] and rec["fingerprint"] == BatchJob.create(**MUG_JOB).fingerprint()
    assert [w["worker"] for w in rec["workers"]] == ["local"]  # the prior was loaded once for three scenes
    assert {s["name"]: s["status"] for s in rec["scenes"]} == dict.fromkeys(MUG_NAMES, "ok")


def test_process_pool_writes_the_same_files(local_run: tuple[Path, BatchReport], mug_scenes: Path,
                                            tmp_path: Path) -> None:
    out = tmp_path / "out"
    report = run_batch(BatchJob.create(**MUG_JOB), [mug_scenes], out,
                       backend=make_backend("process", BackendOptions(workers=2)))
    assert report.passed and report.job.threads == 1
    assert sorted(w.worker for w in report.workers) == ["process-1", "process-2"]  # one prior load per worker
    assert {o.worker for o in report.outcomes} <= {"process-1", "process-2"}
    assert len({w.pid for w in report.workers} | {os.getpid()}) == 3  # separate processes
    assert_same_results(local_run[0], out, MUG_NAMES)


@pytest.mark.slow  # starting Ray takes ~10 s on two cores
def test_ray_started_locally_writes_the_same_files(local_run: tuple[Path, BatchReport], mug_scenes: Path,
                                                   tmp_path: Path) -> None:
    try:
        import ray
    except ImportError:
        pytest.fail("Ray is not installed in the test environment: run `bash scripts/setup.sh --test` "
                    "(it installs efem-viz[test,ray])")
    out = tmp_path / "out"
    report = run_batch(BatchJob.create(**MUG_JOB), [mug_scenes], out,
                       backend=make_backend("ray", BackendOptions(workers=2, ray_cpus=2)))
    assert report.passed, [o.error for o in report.failed()]
    assert report.backend["backend"] == "ray" and len(report.workers) == 2
    assert len({w.pid for w in report.workers} | {os.getpid()}) == 3
    assert not ray.is_initialized()  # the Ray it started is shut down again
    assert_same_results(local_run[0], out, MUG_NAMES)


# ---------------------------------------------------------------------------------------------- resume
def _efem_cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "efem_viz.cli", "segment", *args]


@pytest.mark.slow  # two CLI processes on the mug prior, ~15 s
def test_kill_9_mid_batch_then_resume(local_run: tuple[Path, BatchReport], mug_scenes: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = _efem_cli(str(mug_scenes), "--out", str(out), *MUG_ARGS)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    done_before: list[str] = []
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / BATCH_FILE).is_file():
                done_before = [s["name"] for s in batch_json(out)["scenes"] if s["status"] == "ok"]
                if done_before:
                    break
            time.sleep(0.02)
        assert proc.poll() is None, "the batch finished before it could be killed"
        assert done_before, "no scene finished in time"
        os.kill(proc.pid, signal.SIGKILL)  # mid-batch: the next scene is being solved
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=30)
    # what the kill left: every result there is complete and right; the scene in flight has none
    results = sorted(p.name[: -len(".efem.npz")] for p in out.glob("[!.]*.efem.npz"))
    assert set(done_before) <= set(results) and len(results) < len(MUG_NAMES)
    for name in results:
        EMResult.load(out / f"{name}.efem.npz")
    assert_same_results(local_run[0], out, results)
    mtimes = {n: (out / f"{n}.efem.npz").stat().st_mtime_ns for n in done_before}
    fd, stale = tempfile.mkstemp(prefix=".mug_8.", suffix=".tmp.efem.npz", dir=out)  # as a killed atomic write
    os.close(fd)

    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    rec = batch_json(out)
    assert rec["counts"] == {"ok": 3 - len(done_before), "skipped": len(done_before), "failed": 0, "pending": 0}
    assert {n: (out / f"{n}.efem.npz").stat().st_mtime_ns for n in done_before} == mtimes  # not recomputed
    assert not Path(stale).exists()
    assert_same_results(local_run[0], out, MUG_NAMES)


def test_resume_skips_only_complete_results_of_the_same_job(local_run: tuple[Path, BatchReport], mug_scenes: Path,
                                                            tmp_path: Path) -> None:
    out = tmp_path / "out"
    shutil.copytree(local_run[0], out)
    job = BatchJob.create(**MUG_JOB)
    plan = plan_batch(job, [mug_scenes], out)
    assert not plan.tasks and [o.name for o in plan.skipped] == MUG_NAMES
    assert all(o.status == "skipped" and o.instances >= 1 for o in plan.skipped)
    assert [t.name for t in plan_batch(job, [mug_scenes], out, force=True).tasks] == MUG_NAMES

    data = (out / "mug_3.efem.npz").read_bytes()
    (out / "mug_3.efem.npz").write_bytes(data[: len(data) // 2])  # damaged (as a disk error would leave it)
    (out / "mug_5.seg.ply").unlink()  # an output of the job missing
    plan = plan_batch(job, [mug_scenes], out)
    assert [t.name for t in plan.tasks] == ["mug_3", "mug_5"] and [o.name for o in plan.skipped] == ["mug_8"]
    assert "damaged" in plan.reasons["mug_3"] and "mug_5.seg.ply missing" in plan.reasons["mug_5"]
    assert plan_batch(dataclasses.replace(job, ply=False), [mug_scenes], out).skipped  # no PLY wanted: mug_5 ok

    other = BatchJob.create(**{**MUG_JOB, "proposals": 5})
    assert [t.name for t in plan_batch(other, [mug_scenes], out).tasks] == MUG_NAMES
    assert "other settings" in plan_batch(other, [mug_scenes], out).reasons["mug_8"]
    reseeded = BatchJob.create(**{**MUG_JOB, "seed": 2})
    assert "seed 1" in plan_batch(reseeded, [mug_scenes], out).reasons["mug_8"]

    elsewhere = tmp_path / "elsewhere"  # another scene file with the same name is not the scene of the result
    elsewhere.mkdir()
    shutil.copy(mug_scenes / "mug_8.ply", elsewhere / "mug_8.ply")
    assert "another scene file" in plan_batch(job, [elsewhere], out).reasons["mug_8"]
    scene8 = mug_scenes / "mug_8.ply"
    st8 = scene8.stat()
    try:  # the same file, edited since its result was made
        os.utime(scene8, ns=(st8.st_atime_ns, st8.st_mtime_ns + 10**9))
        assert "changed" in plan_batch(job, [mug_scenes], out).reasons["mug_8"]
    finally:
        os.utime(scene8, ns=(st8.st_atime_ns, st8.st_mtime_ns))

    twin = tmp_path / "twin"
    twin.mkdir()
    shutil.copy(mug_scenes / "mug_3.ply", twin / "mug_3.ply")
    with pytest.raises(ValueError, match="two scenes are named 'mug_3'"):
        plan_batch(job, [mug_scenes, twin], out)


def test_one_batch_per_output_folder(tmp_path: Path) -> None:
    scenes = tmp_path / "scenes"
    sphere_folder(scenes, 1)
    out = tmp_path / "out"
    job = BatchJob.create(priors=("sphere",), preset="fast", proposals=48)
    with folder_lock(out):
        assert (out / ".batch.lock").is_file()
        with pytest.raises(BatchError, match="another batch .* is writing to"):
            run_batch(job, [scenes], out, backend=make_backend("local"))
        assert (out / ".batch.lock").is_file()  # the refused batch left the holder's lock alone
    assert not (out / ".batch.lock").exists()
    assert run_batch(job, [scenes], out, backend=make_backend("local")).passed
    assert not (out / ".batch.lock").exists()  # a finished batch leaves only its results
    # a lock file left by a killed holder (the kernel released its lock) is taken over, then removed
    (out / ".batch.lock").write_text("12345")
    with folder_lock(out):
        assert (out / ".batch.lock").read_text() == str(os.getpid())
    assert not (out / ".batch.lock").exists()


def test_the_output_folder_among_the_inputs_is_said(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """`segment out/ --out out/`: the folder's own segmentation outputs are left out with a warning; another run's
    outputs given as inputs are segmented, with a warning that their labels are predictions."""
    import logging
    import shutil

    from efem_viz.data.scene import Scene

    names = sphere_folder(tmp_path / "out", 2)
    save_scene(Scene.create("s0", np.random.default_rng(0).normal(size=(50, 3))), tmp_path / "out" / "s0.seg.ply")
    (tmp_path / "other").mkdir()
    shutil.copy(tmp_path / "out" / "s0.seg.ply", tmp_path / "other" / "x.seg.ply")
    job = BatchJob.create(priors=("sphere",), preset="fast")
    with caplog.at_level(logging.WARNING, logger="efem_viz.batch.runner"):
        plan = plan_batch(job, [tmp_path / "out", tmp_path / "other"], tmp_path / "out")
    assert {t.name for t in plan.tasks} == {*names, "x.seg"}
    assert "its 1 segmentation output(s) (*.seg.ply) are not segmented again" in caplog.text
    assert "1 input(s) are segmentation outputs of another run" in caplog.text


# ---------------------------------------------------------------------------------------------- failures
def test_bad_scenes_are_reported_and_the_batch_goes_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli

    scenes = tmp_path / "scenes"
    names = sphere_folder(scenes, 3)
    (scenes / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    (scenes / "empty.npz").write_bytes(b"")
    out = tmp_path / "out"
    args = ["segment", str(scenes), "--out", str(out), *SPHERE_ARGS]
    assert cli.main(args) == 1  # some scenes failed
    text = capsys.readouterr().out
    assert "batch summary" in text and "failed" in text and "3 ok, 0 skipped, 2 failed" in text
    rec = {s["name"]: s for s in batch_json(out)["scenes"]}
    assert {n: rec[n]["status"] for n in names} == dict.fromkeys(names, "ok")
    for bad, where in (("broken", "broken.ply"), ("empty", "empty.npz")):
        assert rec[bad]["status"] == "failed" and where in rec[bad]["error"] and "\n" not in rec[bad]["error"]
        assert not (out / f"{bad}.efem.npz").exists()
    for n in names:
        EMResult.load(out / f"{n}.efem.npz")

    assert cli.main(args) == 1  # resumed: the good ones are skipped, the bad ones are tried (and fail) again
    assert batch_json(out)["counts"] == {"ok": 0, "skipped": 3, "failed": 2, "pending": 0}
    (scenes / "broken.ply").unlink()
    (scenes / "empty.npz").unlink()
    assert cli.main(args) == 0


def test_a_worker_that_dies_fails_only_its_scene(tmp_path: Path) -> None:
    scenes = tmp_path / "scenes"
    names = sphere_folder(scenes, 4)
    out = tmp_path / "out"

    class KillOnFirstStep(BatchObserver):
        """SIGKILLs the worker solving s1 at its first progress report (so it dies mid-scene)."""

        def __init__(self) -> None:
            self.pids: dict[str, int] = {}
            self.killed = False

        def on_worker(self, info: WorkerInfo) -> None:
            self.pids[info.worker] = info.pid

        def on_step(self, task: SceneTask, worker: str, step: int, total: int, text: str) -> None:
            if task.name == "s1" and not self.killed:
                self.killed = True
                os.kill(self.pids[worker], signal.SIGKILL)

    job = BatchJob.create(priors=("sphere",), preset="fast", proposals=48, threads=1)
    watcher = KillOnFirstStep()
    report = run_batch(job, [scenes], out, backend=make_backend("process", BackendOptions(workers=2)),
                       observer=watcher)
    assert watcher.killed and not report.passed
    status = {o.name: o for o in report.outcomes}
    assert status["s1"].status == "failed" and "worker process died (signal SIGKILL" in status["s1"].error
    assert all(status[n].status == "ok" for n in names if n != "s1")
    assert {o.worker for o in report.outcomes} <= {w.worker for w in report.workers}  # (a replacement if needed)
    assert not (out / "s1.efem.npz").exists()
    again = run_batch(job, [scenes], out, backend=make_backend("local"))
    assert again.passed and [o.name for o in again.outcomes if o.status == "ok"] == ["s1"]


def test_job_errors_are_one_line_on_every_backend(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from efem_viz import cli

    scenes = tmp_path / "scenes"
    sphere_folder(scenes, 1)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 64)
    for backend in (["--backend", "local"], ["--workers", "2"]):
        assert cli.main(["segment", str(scenes), "--out", str(tmp_path / "o"), "--prior", str(bad), *backend]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a readable torch checkpoint" in err[0], err
    monkeypatch.setitem(sys.modules, "ray", None)  # as without the extra
    assert cli.main(["segment", str(scenes), "--out", str(tmp_path / "o"), *SPHERE_ARGS, "--ray"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["efem-viz segment: error: Ray is not installed: pip install 'efem-viz[ray]'"]
    assert cli.main(["segment", str(scenes), "--out", str(tmp_path / "o"), *SPHERE_ARGS, "--tau-out", "0.9"]) == 1
    assert "tau_out" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- big folders
def test_evaluate_and_view_a_200_scene_batch_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A batch folder of 200 scenes: `evaluate` scores it, the viewer lists it and opens one scene only.

    One real batch run on a sphere tabletop; the folder is then filled with 200 copies of that scene under their own
    names, each with its result (the same arrays with the scene name changed, written uncompressed to keep the test
    fast) and its coloured PLY.
    """
    from efem_viz import cli
    from efem_viz.data import io as data_io
    from efem_viz.data.io import load_scene
    from efem_viz.prior.analytic import make_sphere_prior

    scenes = tmp_path / "one"
    sphere_folder(scenes, 1)
    first = tmp_path / "first"
    run_batch(BatchJob.create(priors=("sphere",), preset="fast", proposals=48), [scenes], first,
              backend=make_backend("local"))
    scene, arrays = load_scene(scenes / "s0.npz"), result_arrays(first / "s0.efem.npz")
    with np.load(first / "s0.efem.npz") as z:
        arrays |= {k: z[k] for k in VOLATILE}
    gt, out = tmp_path / "gt", tmp_path / "out"
    gt.mkdir()
    out.mkdir()
    names = [f"scan_{k:03d}" for k in range(200)]
    for name in names:
        save_scene(scene.replace(name=name), gt / f"{name}.ply")
        np.savez(out / f"{name}.efem.npz", **{**arrays, "scene_name": np.array(name)})
        shutil.copy(first / "s0.seg.ply", out / f"{name}.seg.ply")
    EMResult.load(out / "scan_199.efem.npz")
    shutil.copytree(first / "scannet", out / "scannet")  # a ScanNet export beside them does not take over
    (out / ".scan_000.a1b2c3d4.tmp.efem.npz").write_bytes(b"half a file")  # an interrupted write is ignored

    js = tmp_path / "ev.json"
    t0 = time.perf_counter()
    assert cli.main(["evaluate", str(out), "--gt", str(gt), "--classes", "sphere", "--json-out", str(js)]) == 0
    t_eval = time.perf_counter() - t0
    ev = json.loads(js.read_text())
    single = tmp_path / "ev1.json"
    assert cli.main(["evaluate", str(first), "--gt", str(scenes), "--classes", "sphere", "--json-out",
                     str(single)]) == 0
    assert len(ev["scenes"]) == 200 and ev["ap50"] == json.loads(single.read_text())["ap50"] > 0.5
    assert t_eval < 90, f"evaluate of 200 small scenes took {t_eval:.1f} s"

    from efem_viz.viewer.app import ViewerApp

    loads: list[Path] = []
    real_load = data_io.load_scene
    monkeypatch.setattr(data_io, "load_scene", lambda p, **kw: (loads.append(Path(p)), real_load(p, **kw))[1])
    t0 = time.perf_counter()
    app = ViewerApp([], port=0, prior=make_sphere_prior(), results=[out])
    try:
        t_view = time.perf_counter() - t0
        assert len(app.state.entries) == 200 and len(loads) == 1  # listed, one scene opened
        assert all(e.trace_path == (out / f"{e.name[:-len('.seg')]}.efem.npz").resolve() for e in app.state.entries)
    finally:
        app.stop()
    assert t_view < 30, f"the viewer took {t_view:.1f} s to list 200 scenes"
    capsys.readouterr()


def test_several_priors_are_loaded_once_and_solved_together(tmp_path: Path) -> None:
    from efem_viz.batch.worker import SceneWorker
    from efem_viz.prior.analytic import make_sphere_scene

    both = BatchJob.create(priors=("sphere", "mug"), preset="fast", proposals=8)
    assert both.fingerprint() != BatchJob.create(priors=("sphere",), preset="fast", proposals=8).fingerprint()
    worker = SceneWorker(both)
    assert [p.name for p in worker.priors] == ["sphere", "mug"]
    save_scene(make_sphere_scene(seed=0, spacing=0.008, radii=(0.05,), name="one"), tmp_path / "one.npz")
    task = SceneTask(index=0, path=tmp_path / "one.npz", name="one", out=tmp_path / "out")
    out = worker.process(task)
    assert out.status == "ok", out.error
    res = EMResult.load(task.result_path)
    assert set(np.asarray(res.instances.category).tolist()) <= {"sphere", "mug"}
    with pytest.raises(ValueError, match="given twice"):
        BatchJob.create(priors=("mug", "mug"))


def test_segment_solves_a_generated_chair_scene_with_the_chair_prior(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """`segment` without --prior solves a scene generated for chairs with the chair prior (as the viewer's Run),
    says so in the scene's line, and keeps the mug prior for every other scene; an explicit --prior is kept."""
    from efem_viz.batch import worker as worker_mod
    from efem_viz.batch.commands import SegmentArgs
    from efem_viz.data.scene import Scene
    from efem_viz.em import solver
    from efem_viz.prior.analytic import make_sphere_scene

    base = make_sphere_scene(seed=0, spacing=0.01, radii=(0.05,), name="chairs")
    for name, targets in (("chairs", "chair"), ("mugs", "mug")):
        save_scene(Scene.create(name, base.points, provenance={"source": "synthetic", "targets": targets}),
                   tmp_path / f"{name}.npz")
    used: dict[str, list[str]] = {}
    real_run_em = solver.run_em

    def spy(scene: Any, **kw: Any) -> Any:
        used[scene.name] = [p.name for p in kw["priors"]]
        return real_run_em(scene, **kw)

    monkeypatch.setattr(solver, "run_em", spy)
    args = SegmentArgs(scenes=[tmp_path], proposals=4)
    default = BatchJob.create(**args.settings(), priors=("mug",), scene_priors=True)
    explicit = BatchJob.create(**args.settings(), priors=("mug",))
    assert default.fingerprint() != explicit.fingerprint()
    lines = {}
    for job in (default, explicit):
        worker = worker_mod.SceneWorker(job)
        for name in ("chairs", "mugs"):
            out = worker.process(SceneTask(index=0, path=tmp_path / f"{name}.npz", name=name,
                                           out=tmp_path / f"out{int(job.scene_priors)}"))
            assert out.status == "ok", out.error
            lines[(job.scene_priors, name)] = (used[name], out.preset)
    assert lines[(True, "chairs")] == (["chair"], "chairs, chair prior")
    assert lines[(True, "mugs")][0] == ["mug"] and "prior" not in lines[(True, "mugs")][1]
    assert lines[(False, "chairs")][0] == ["mug"] and "prior" not in lines[(False, "chairs")][1]
    # a scan of no chair scene solved with the chair prior (a room scan): `chairs`, whose floor joins no chair
    chair_job = BatchJob.create(**args.settings(), priors=("chair",))
    out = worker_mod.SceneWorker(chair_job).process(SceneTask(index=0, path=tmp_path / "mugs.npz", name="mugs",
                                                              out=tmp_path / "out_chair"))
    assert out.status == "ok", out.error
    assert used["mugs"] == ["chair"] and out.preset == "chairs"
    # results of "auto" are keyed by its rule, apart from the preset it names without a scene
    synthetic = BatchJob.create(**{**args.settings(), "preset": "synthetic"}, priors=("mug",))
    assert explicit.fingerprint() != synthetic.fingerprint()


def test_outcome_records_round_trip() -> None:
    o = SceneOutcome(name="a", path="/x/a.ply", status="failed", error="SceneError: bad", seconds=1.5)
    assert SceneOutcome.from_dict({**o.to_dict(), "future_key": 1}) == o
    with pytest.raises(ValueError, match="status"):
        SceneOutcome.from_dict({**o.to_dict(), "status": "maybe"})


def test_console_shows_scene_names_and_errors_verbatim() -> None:
    """Rich markup in a scene name or an error (`[b]`, `[/data/x]`) is shown as text and never stops the batch."""
    import io

    from rich.console import Console

    from efem_viz.batch.console import RichBatchDisplay
    from efem_viz.batch.job import SceneOutcome

    buf = io.StringIO()
    display = RichBatchDisplay(Console(file=buf, width=200))
    display.on_done(SceneOutcome(name="room[b]x", path="/s/room[b]x.ply", status="failed",
                                 error="cannot read [/data/x]"))
    text = buf.getvalue()
    assert "room[b]x" in text and "[/data/x]" in text


@pytest.mark.slow
def test_ray_job_that_no_node_can_host_fails_in_one_line(tmp_path: Path) -> None:
    """Actors asking for more CPUs than the cluster has would wait forever: the CLI says so and exits 1."""
    from efem_viz.prior.analytic import make_sphere_scene

    scene = tmp_path / "s.ply"
    save_scene(make_sphere_scene(seed=0, spacing=0.012, radii=(0.05,)), scene)
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(scene), "--out", str(tmp_path / "o"),
                           "--prior", "sphere", "--ray", "--ray-cpus", "1", "--threads", "2"],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "asks for 2 CPU(s)" in proc.stderr and "cluster has 1" in proc.stderr, proc.stderr


def test_a_ray_address_where_nothing_listens_is_one_line_at_once(tmp_path: Path) -> None:
    """Ray retries a dead --ray-address for over 10 minutes: the CLI checks it first (a hang guard of 10x the
    connect timeout), and a malformed address is refused without a connection."""
    import socket

    from efem_viz.batch.ray_backend import RAY_CONNECT_TIMEOUT_S, check_ray_address
    from efem_viz.prior.analytic import make_sphere_scene

    with socket.socket() as sock:  # a port that was free a moment ago: nothing listens there
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    scene = tmp_path / "s.ply"
    save_scene(make_sphere_scene(seed=0, spacing=0.012, radii=(0.05,)), scene)
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(scene), "--out", str(tmp_path / "o"),
                           "--prior", "sphere", "--ray-address", f"ray://127.0.0.1:{port}"],
                          capture_output=True, text=True, timeout=10 * RAY_CONNECT_TIMEOUT_S + 60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"--ray-address ray://127.0.0.1:{port}: nothing answers there" in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    for bad in ("127.0.0.1", "host:port", "ray://:6379", "127.0.0.1:70000"):
        with pytest.raises(BatchError, match="expected auto, HOST:PORT"):
            check_ray_address(bad)


def test_control_characters_in_scene_names_reach_the_console_escaped(tmp_path: Path) -> None:
    """on the real CLI: an ESC sequence and a newline in scene file names (one scene that
    segments, one that fails) are printed as visible escapes, in the console lines, the summary table and the log."""
    from efem_viz.prior.analytic import make_sphere_scene

    src = tmp_path / "in"
    src.mkdir()
    good = "ok\x1b[2J\nFAKE LINE A"
    save_scene(make_sphere_scene(seed=0, spacing=0.012, radii=(0.05,)), src / f"{good}.ply")
    (src / "bad\x1b]0;title\x07\rFAKE LINE B.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 9\n"
                                                                 b"property float x\nend_header\n1\n")
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="400")
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(src), "--out", str(tmp_path / "o"),
                           "--prior", "sphere"], capture_output=True, text=True, timeout=600, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out  # one scene failed
    assert not any(c in out for c in "\x1b\x07\r"), "no raw ESC, BEL or CR"
    assert not any(line.lstrip("│ ").startswith("FAKE") for line in out.splitlines()), "no line starts in a name"
    assert re.search(r"^ok\\x1b\[2J\\nFAKE LINE A: \d+ instances in ", proc.stdout, re.M), proc.stdout
    assert re.search(r"^│ ok\\x1b\[2J\\nFAKE LINE A +│ ok ", proc.stdout, re.M), "the summary table"
    assert "bad\\x1b]0;title\\x07\\rFAKE LINE B: failed" in proc.stdout
    assert "bad\\x1b]0;title\\x07\\rFAKE LINE B: failed" in proc.stderr  # the worker's log line


def test_terminal_text_escapes_controls_only() -> None:
    from efem_viz.terminal import terminal_text

    assert terminal_text("mug_01 café 杯 [b]") == "mug_01 café 杯 [b]"
    assert terminal_text("a\x1b[2Jb\nc\rd\te\x7f\x9b\u202ef") == "a\\x1b[2Jb\\nc\\rd\\te\\x7f\\x9b\\u202ef"


def test_solve_knobs_are_declared_once_and_reach_the_job(tmp_path: Path) -> None:
    """`SolveSettings` holds the solver knobs; `efem-viz segment` and `BatchJob` inherit them, so
    a new knob (matmul_dtype) reaches the solver config and the resume fingerprint with no copy."""
    from efem_viz.batch.commands import SegmentArgs
    from efem_viz.em.config import SolveSettings

    knobs = {f.name for f in dataclasses.fields(SolveSettings)}
    assert {"preset", "proposals", "work_voxel", "tau_out", "matmul_dtype"} <= knobs
    for cls in (SegmentArgs, BatchJob):
        assert issubclass(cls, SolveSettings)
        assert not knobs & set(cls.__dict__.get("__annotations__", {})), f"{cls.__name__} redeclares a knob"
    args = SegmentArgs(scenes=[tmp_path], matmul_dtype="bfloat16", proposals=12, work_voxel=0.006)
    job = BatchJob.create(priors=("sphere",), **args.settings())
    cfg = job.config()
    assert (cfg.compute.matmul_dtype, cfg.proposals.n_init[0], cfg.compute.work_voxel) == ("bfloat16", 12, 0.006)
    assert job.fingerprint() != BatchJob.create(priors=("sphere",), proposals=12, work_voxel=0.006,
                                                matmul_dtype="float32").fingerprint()
    with pytest.raises(ValueError, match="matmul_dtype"):
        BatchJob.create(priors=("sphere",), matmul_dtype="float16")  # type: ignore[arg-type]


def test_solve_precision_resolves_for_the_machine_and_the_device(monkeypatch: pytest.MonkeyPatch) -> None:
    """bfloat16 runs the decoder's products in bf16 and keeps the encoder float32; auto is that on a CPU with
    native bf16 and float32 on one without it and on a GPU; a job resolves it for its own device."""
    from efem_viz.em.config import SolveSettings, precision_compute
    from efem_viz.prior import config as prior_config

    assert precision_compute("float32") == {"matmul_dtype": "float32", "encoder_dtype": None}
    assert precision_compute("bfloat16") == {"matmul_dtype": "bfloat16", "encoder_dtype": "float32"}
    assert precision_compute("bfloat16", "cuda") == {"matmul_dtype": "bfloat16", "encoder_dtype": None}
    for native, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(prior_config, "fast_cpu_bf16", lambda native=native: native)
        assert precision_compute("auto")["matmul_dtype"] == want
        assert SolveSettings(matmul_dtype="auto").config().compute.matmul_dtype == want
        assert precision_compute("auto", "cuda:0")["matmul_dtype"] == "float32"
        job = BatchJob.create(priors=("sphere",), matmul_dtype="auto", device="cuda")
        assert job.config().compute.matmul_dtype == "float32"
    with pytest.raises(ValueError, match="matmul_dtype must be one of"):
        precision_compute("float16")


def test_segment_without_scenes_creates_nothing(tmp_path: Path) -> None:
    out = tmp_path / "never"
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(tmp_path / "missing.ply"),
                           "--out", str(out), "--prior", "sphere"], capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and "missing.ply" in proc.stderr
    assert not out.exists(), "a failed segment left an output folder behind"


def test_free_cores_and_the_wait_policy(monkeypatch: pytest.MonkeyPatch) -> None:
    """efem_viz.cpu: the thread count leaves the cores other work holds, and the OpenMP wait policy is set only
    before torch is imported and only when the user has not chosen one."""
    import torch  # noqa: F401 - the "too late" case below needs it imported

    from efem_viz import cpu

    assert cpu.free_cores(load=0.0, cpus=2) == 2
    assert cpu.free_cores(load=0.9, cpus=2) == 1  # one busy core (a training run, a test suite)
    assert cpu.free_cores(load=5.0, cpus=2) == 1  # never below one
    assert cpu.free_cores(load=float("nan"), cpus=4) == 4
    assert cpu.free_cores(load=1.4, cpus=16) == 15
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert not cpu.configure_openmp()  # torch is imported in this process: too late, and it says so
    monkeypatch.delitem(sys.modules, "torch")
    assert cpu.configure_openmp() and cpu.os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert not cpu.configure_openmp() and cpu.os.environ["OMP_WAIT_POLICY"] == "ACTIVE"


def test_segment_without_out_writes_to_the_data_folder_and_says_where(tmp_path: Path) -> None:
    """without --out, `segment` wrote ./results/ silently (into the checkout when run from it).
    Now the results go to the efem-viz data folder and the first line names it; nothing lands in the cwd."""
    scenes = tmp_path / "scenes"
    names = sphere_folder(scenes, 1)
    work = tmp_path / "cwd"
    work.mkdir()
    env = {**os.environ, "XDG_DATA_HOME": str(tmp_path / "data"), "PYTHONPATH": str(Path(__file__).parents[1])}
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(scenes), *SPHERE_ARGS],
                          capture_output=True, text=True, timeout=600, cwd=work, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = tmp_path / "data" / "efem-viz" / "segment"
    assert (out / f"{names[0]}.efem.npz").is_file() and not any(work.iterdir())
    first = [ln for ln in proc.stdout.splitlines() if ln.strip()][0]
    assert str(out) in first.replace("\n", ""), proc.stdout[:500]


def test_a_damaged_batch_json_means_recompute_not_a_crash(tmp_path: Path) -> None:
    """a wrongly typed record ("instances": "many") crashed every resume with "internal
    error: TypeError", and a deeply nested batch.json with RecursionError. On the full CLI: one warning, the
    affected scenes recomputed, the others skipped, exit 0."""
    scenes = tmp_path / "scenes"
    names = sphere_folder(scenes, 2)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    cmd = [sys.executable, "-m", "efem_viz.cli", "segment", str(scenes), "--out", str(out), *SPHERE_ARGS]
    assert subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env).returncode == 0
    good = batch_json(out)
    bad = json.loads(json.dumps(good))
    first = next(s for s in bad["scenes"] if s["name"] == names[0])
    first["instances"] = "many"
    (out / "batch.json").write_text(json.dumps(bad))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0 and "internal error" not in proc.stderr, proc.stderr[-2000:]
    text = proc.stdout + proc.stderr
    assert text.count("invalid record") == 1  # one warning line
    assert f"{names[0]}: recomputing" in text and f"{names[1]}: recomputing" not in text  # the others stand
    assert "1 ok, 1 skipped" in text.replace("\n", " ")
    (out / "batch.json").write_text("[" * 100_000 + "]" * 100_000)
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0 and "internal error" not in proc.stderr, proc.stderr[-2000:]
    assert (proc.stdout + proc.stderr).count("unreadable") == 1
    assert {s["name"]: s["status"] for s in batch_json(out)["scenes"]} == {n: "ok" for n in names}


def test_segment_started_with_sigint_ignored_stops_on_sigint_and_leaves_nothing_half_written(tmp_path: Path) -> None:
    """A `segment` a script started in the background inherits SIGINT as ignored; it used to run on for minutes
    after `kill -INT` and write its results. Full CLI: it stops after the scene in progress, records the batch as
    interrupted, and leaves no temporary file, no lock and no result of a scene it did not finish."""
    from efem_viz.prior import analytic
    from helpers import server_signals

    scans = tmp_path / "scans"
    scans.mkdir()
    for k in range(6):
        save_scene(analytic.make_sphere_scene(seed=k, spacing=0.01, name=f"balls_{k}"), scans / f"balls_{k}.ply")
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "efem_viz.cli", "segment", str(scans), "--prior", "sphere",
                             "--preset", "fast", "--proposals", "60", "--out", str(out), "--no-scannet",
                             "--no-ply"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            preexec_fn=server_signals(sigint_ignored=True))
    assert proc.stdout is not None
    seen = []
    for line in proc.stdout:  # the first scene has started: interrupt
        seen.append(line)
        if ": started (" in line:
            break
    proc.send_signal(signal.SIGINT)
    try:
        rest, _ = proc.communicate(timeout=600)  # a hang guard: it stops after the scene in progress
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("segment ran on after SIGINT:\n" + "".join(seen)) from None
    log = "".join(seen) + rest
    assert proc.returncode != 0, log
    assert (out / BATCH_FILE).is_file(), log
    record = json.loads((out / BATCH_FILE).read_text())
    assert record["interrupted"] is True
    done = {p.name for p in out.glob("*.efem.npz")}
    assert len(done) < 6 and done == {f"{r['name']}.efem.npz" for r in record["scenes"] if r["status"] == "ok"}
    assert not [p for p in out.rglob("*") if p.name.startswith(".") or p.suffix == ".tmp"], list(out.rglob("*"))
