"""Reliability of the full `efem-annotate` CLI, measured: edits acknowledged vs recovered.

Every number comes from the real CLI process driven by the scripted WebSocket client in tests/viser_client.py
(an edit is *acknowledged* when the server has sent the instance table that shows it):

* kill: a seeded script of painting, undo, redo, EFEM pre-label import and PLY export on a bundled scene is run
  once uninterrupted (the reference tables), then N times with a kill -9 at a random moment; the restarted CLI
  must show the last acknowledged table or the next one (the edit in flight). Also counts stale temp files left.
* damage: a finished session's journal damaged in the middle (with and without a checkpoint), at the end
  (truncated), or its checkpoint damaged, or its edit records cut to half their bytes with the checkpoint deleted; the
  restarted CLI's table against the last one shown, and what its GUI says.
* faults: ENOSPC injected on journal writes for a while (a sitecustomize wrapping os.write); refused edits must
  change nothing, later edits must survive a clean stop and restart.
* load: K clients x M brush clicks at once on a 1M-vertex scan: every edit journalled, each client's edits in
  its sending order, and the latency from send to the first table update after the edit was journalled.
* fuzz: the loader fuzzer of tests/test_fuzz_loaders.py (inputs per loader, errors by kind, worst time and
  peak memory).
* hostile-prior: `efem-viz segment --prior` on a few-KB prior file declaring a huge decoder as
  zero-stride views (20,000 and 200,000 wide), and on one with plausible sizes but view weights: exit status,
  error lines, seconds and peak memory of the CLI process.
* links: the real `efem-viz view` CLI and a scripted client pressing *Export results* into folders of
  the output root where a link leads out (a `pred_mask` folder link, a file link, a folder link inside the root
  whose `pred_mask` leads out): refused or not, and files written outside and inside.

Writes bench/results/reliability/latest.json (sections not run keep their previous results). Usage:
`python -m bench.reliability [--kills 20] [--clients 4] [--edits 50] [--only hostile-prior links]`
(1 torch/OMP thread per process).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import re
import shutil
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch
sys.path.insert(0, str(ROOT / "tests"))

from viser_client import JOURNAL_FAULTS_SITECUSTOMIZE, AnnotateProcess, ViserClient  # noqa: E402

SCENE = "syn_z_0"


def _scene_copy(tmp: Path) -> Path:
    d = tmp / "scans"
    d.mkdir(parents=True, exist_ok=True)
    for suffix in (".ply", ".efem.npz"):
        shutil.copy(ROOT / "sample_scenes" / f"{SCENE}{suffix}", d / f"{SCENE}{suffix}")
    return d / f"{SCENE}.ply"


def _rays(scan: Path, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n rays straight down onto well-separated unlabelled, upward-facing vertices (the table), from 0.3 m up."""
    from efem_viz.data.io import load_scene

    sc = load_scene(scan)
    free = np.ones(sc.num_points, bool) if sc.instance is None else sc.instance == 0
    lo, hi = np.percentile(sc.points[:, :2], [10, 90], axis=0)
    inner = np.all((sc.points[:, :2] > lo) & (sc.points[:, :2] < hi), axis=1)
    cand = np.flatnonzero(free & inner & (sc.normals[:, 2] > 0.9))
    rng = np.random.default_rng(seed)
    chosen = [int(rng.choice(cand))]
    d = np.linalg.norm(sc.points[cand] - sc.points[chosen[0]], axis=1)
    for _ in range(n - 1):
        k = int(cand[int(np.argmax(d))])
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(sc.points[cand] - sc.points[k], axis=1))
    down = np.array([0.0, 0.0, -1.0])
    return [(sc.points[i] - 0.3 * down, down) for i in chosen]


def _script(scan: Path, n: int, seed: int) -> list[tuple]:
    rng = random.Random(seed)
    rays = _rays(scan, n, seed)
    steps: list[tuple] = [("new",)]
    for k in range(n):
        steps.append(("paint", rays[k][0], rays[k][1]))
        r = rng.random()
        if r < 0.15:
            steps.append(("undo",))
        elif r < 0.22:
            steps += [("undo",), ("redo",)]
        elif r < 0.27:
            steps.append(("click", "Export PLY"))
        if k == n // 2:
            steps.append(("press", "Import EFEM pre-labels"))
    return steps


def _counts(table: str) -> dict[int, int]:
    """Instance id -> vertex count of a shown instance table (rows with vertices only; the active marker, names and
    the row order are GUI state, not labels)."""
    out = {}
    for m in re.finditer(r"^\| (\d+)[^|]*\|[^|]*\|[^|]*\| ([\d,]+) \|", table, re.M):
        c = int(m.group(2).replace(",", ""))
        if c:
            out[int(m.group(1))] = c
    return out


def _journal_without_last_records(out: Path, tmp: Path, n: int, drop: int = 1) -> dict[int, int]:
    """Counts of the state the journal holds without its last `drop` records (checkpoint ignored)."""
    from annotator.store import LabelStore

    journal = next(out.glob("*.annotate/*.journal"))
    scratch = tmp / "scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    data = journal.read_bytes()
    (scratch / "j.journal").write_bytes(data[: _offsets(journal)[-drop]])
    s = LabelStore(n, journal_path=scratch / "j.journal", label_path=scratch / "j.labels.npz")
    counts = {k: v for k, v in s.labelset.counts().items() if k > 0 and v}
    s.close()
    return counts


def bench_kill(tmp: Path, kills: int, seed: int) -> dict[str, Any]:
    """Kill -9 while a scripted session runs; the restarted CLI must show every acknowledged edit."""
    scan = _scene_copy(tmp)
    from efem_viz.data.io import load_scene

    n = load_scene(scan).num_points
    ref = AnnotateProcess(scan, tmp / "ref")
    steps = []
    for s in _script(scan, 24, seed):  # the reference run keeps the steps that do something (no no-op clicks)
        try:
            ref.edit(s, timeout=5)
            steps.append(s)
        except TimeoutError:
            continue
    ref.stop()
    rng = np.random.default_rng(seed)
    rows = []
    for trial in range(kills):
        out = tmp / f"kill{trial}"
        cli = AnnotateProcess(scan, out)
        stop_after = int(rng.integers(2, len(steps) - 1))
        shown = cli.table()
        for s in steps[:stop_after]:
            try:
                shown = cli.edit(s, timeout=5)
            except TimeoutError:  # a click that changed nothing in this run: not an edit
                pass
        acked = _counts(shown)
        cli.edit(steps[stop_after], expect_change=False)
        time.sleep(float(rng.uniform(0.0, 0.08)))
        cli.kill()
        stale_before = len([p for p in out.rglob(".*") if ".tmp" in p.name])
        again = AnnotateProcess(scan, out)
        seen = _counts(again.table())
        # recovered == the last table the client saw, or that table plus the journal's last few records (the edit
        # in flight, or edits whose table the client had not received yet when its wait ran out)
        ahead = next((k for k in range(1, 6) if _journal_without_last_records(out, tmp, n, k) == acked), None)
        if seen == acked:
            state = "acked"
        elif ahead is not None:
            state = "acked+in-flight" if ahead == 1 else f"acked+{ahead} newer"
        else:
            state = "LOST"
            print(f"--- last acked: {acked}\n--- recovered: {seen}", flush=True)
        stale_after = len([p for p in out.rglob(".*") if ".tmp" in p.name])
        during = steps[stop_after][0] if steps[stop_after][0] not in ("click", "press") else steps[stop_after][1]
        rows.append({"trial": trial, "killed_during": during, "acked_steps": stop_after, "recovered": state,
                     "restart_s": round(again.t_url, 2), "stale_tmp_before": stale_before,
                     "stale_tmp_after": stale_after})
        again.stop()
        print(f"kill {trial}: during {during!r}, {stop_after:2d} steps acked -> {state}, "
              f"restart {again.t_url:.1f} s, stale temp files {stale_before} -> {stale_after}", flush=True)
    return {
        "trials": rows,
        "all_acknowledged_recovered": all(r["recovered"] != "LOST" for r in rows),
        "median_restart_s": statistics.median(r["restart_s"] for r in rows) if rows else None,
    }


def _offsets(path: Path) -> list[int]:
    return [m.start() for m in re.finditer(b"EFJ1", path.read_bytes())]


def bench_damage(tmp: Path, seed: int) -> dict[str, Any]:
    scan = _scene_copy(tmp)
    rays = _rays(scan, 12, seed + 1)
    out: dict[str, Any] = {}
    for case in ("middle", "middle-no-checkpoint", "end", "checkpoint", "half-no-checkpoint"):
        d = tmp / f"damage-{case}"
        cli = AnnotateProcess(scan, d)
        cli.edit(("new",))
        for o, r in rays:
            cli.edit(("paint", o, r))
        final = cli.table()
        cli.stop()
        journal = next(d.glob("*.annotate/*.journal"))
        ckpt = next(d.glob("*.annotate/*.labels.npz"))
        offs = _offsets(journal)
        data = bytearray(journal.read_bytes())
        if case.startswith("middle"):
            data[offs[len(offs) // 2] + 40] ^= 0xFF
            journal.write_bytes(bytes(data))
            if case == "middle-no-checkpoint":
                ckpt.unlink()
        elif case == "end":
            journal.write_bytes(bytes(data[: offs[len(offs) - 3]]))
        elif case == "half-no-checkpoint":  # edit records cut to half, inside a record; checkpoint deleted
            half = offs[1] + (len(data) - offs[1]) // 2
            half += 7 if half in offs else 0
            journal.write_bytes(bytes(data[:half]))
            ckpt.unlink()
        else:
            ckpt.write_bytes(b"PK\x03\x04 not a zip any more")
        again = AnnotateProcess(scan, d)
        seen = again.table()
        status = next((m for m in again.client.markdowns() if "Recovered" in m), "")
        out[case] = {
            "recovered_equals_last_shown": seen == final,
            "vertices_shown_before": sum(_counts(final).values()),
            "vertices_recovered": sum(_counts(seen).values()),
            "gui_report": status.replace("  \n", " | ")[:400],
            "restart_s": round(again.t_url, 2),
        }
        again.stop()
        print(f"damage {case:>22}: recovered == last shown: {seen == final}; GUI: {out[case]['gui_report'][:120]}",
              flush=True)
    return out


def bench_faults(tmp: Path, seed: int) -> dict[str, Any]:
    scan = _scene_copy(tmp)
    site = tmp / "site"
    site.mkdir(parents=True, exist_ok=True)
    (site / "sitecustomize.py").write_text(JOURNAL_FAULTS_SITECUSTOMIZE)
    flag = tmp / "disk-full"
    rays = _rays(scan, 30, seed + 2)
    d = tmp / "faults"
    cli = AnnotateProcess(scan, d, {"PYTHONPATH_FIRST": str(site), "EFEM_TEST_FAULT_FILE": str(flag)})
    cli.edit(("new",))
    acked = refused_ok = refused = 0
    for k, (o, r) in enumerate(rays):
        full = 10 <= k < 20
        if full and not flag.exists():
            flag.write_text("full")
        if not full and flag.exists():
            flag.unlink()
        before = cli.table()
        n = len(cli.client.notifications)
        if full:
            cli.edit(("paint", o, r), expect_change=False)
            cli.must(lambda n=n: len(cli.client.notifications) > n)
            time.sleep(0.1)
            refused += 1
            refused_ok += cli.table() == before
        else:
            cli.edit(("paint", o, r))
            acked += 1
    final = cli.table()
    cli.stop()
    again = AnnotateProcess(scan, d)
    ok = again.table() == final
    again.stop()
    print(f"faults: {acked} acked edits, {refused} refused (unchanged table: {refused_ok}); after restart "
          f"every acked edit is there: {ok}", flush=True)
    return {"acked": acked, "refused": refused, "refused_left_no_trace": refused_ok, "all_acked_recovered": ok}


def _surface_file(folder: Path, n_side: int) -> Path:
    """bench/annotator_scale.py's height-field tabletop (n_side^2 vertices) as a PLY."""
    from bench.annotator_scale import make_surface
    from efem_viz.data.io import save_scene

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "surface.ply"
    save_scene(make_surface(n_side), path)
    return path


def bench_load(tmp: Path, clients: int, edits: int, n_side: int) -> dict[str, Any]:
    from annotator.store import LabelStore

    scan = _surface_file(tmp / "load", n_side)
    d = tmp / "load-out"
    proc = AnnotateProcess(scan, d, args=("--max-points", str(n_side * n_side + 1)), timeout=600)
    proc.client.set_value("Brush radius (cm)", 0.5)
    proc.edit(("new",))
    proc.client.close()
    rng = np.random.default_rng(0)
    cs = [ViserClient(proc.url) for _ in range(clients)]
    sends: list[list[float]] = [[] for _ in cs]
    updates: list[list[float]] = [[] for _ in cs]

    def watch(k: int) -> None:
        c = cs[k]
        last = ""
        while not stop.is_set():
            t = next((m for m in c.markdowns() if "vertices labelled" in m), "")
            if t != last:
                updates[k].append(time.time())
                last = t
            time.sleep(0.002)

    targets = [rng.uniform(-0.55, 0.55, size=(edits, 2)) for _ in cs]

    def drive(k: int) -> None:
        c = cs[k]
        for x, y in targets[k]:
            sends[k].append(time.time())
            c.scene_click((float(x), float(y), 1.0), (0.0, 0.0, -1.0))
            time.sleep(0.05)

    stop = threading.Event()
    watchers = [threading.Thread(target=watch, args=(k,), daemon=True) for k in range(clients)]
    drivers = [threading.Thread(target=drive, args=(k,)) for k in range(clients)]
    t0 = time.monotonic()
    for t in watchers + drivers:
        t.start()
    for t in drivers:
        t.join()
    time.sleep(3.0)
    stop.set()
    wall = time.monotonic() - t0
    for c in cs:
        c.close()
    proc.stop()
    # Journal: each client's edits in its order (the server records the client id and the append time).
    n = n_side * n_side
    store = LabelStore(n, journal_path=next(d.glob("*.annotate/*.journal")),
                       label_path=next(d.glob("*.annotate/*.labels.npz")))
    dos = [r for r in store.journal.records if r.kind == "do" and r.header.get("label", "").startswith(("brush",
                                                                                                          "paint"))]
    store.close()
    from efem_viz.data.io import load_scene

    pts = load_scene(scan).points
    by_client: dict[str, list[float]] = {}
    where: dict[str, list[np.ndarray]] = {}
    for r in dos:
        key = str(r.header.get("client", ""))
        by_client.setdefault(key, []).append(float(r.header["time"]))
        where.setdefault(key, []).append(pts[r.arrays["idx"], :2].mean(axis=0))
    lat = []
    journalled = sorted(by_client.values(), key=lambda v: v[0])
    # Each server-side client's edits must be one scripted client's clicks, in its sending order: the painted
    # vertices' centre lies under the i-th click (within 2 cm; overlapping clicks that changed nothing are skipped).
    ordered = True
    for key, cents in where.items():
        best = min(range(len(cs)), key=lambda k: float(np.linalg.norm(targets[k][0] - cents[0])))
        i = 0
        for c in cents:
            while i < edits and np.linalg.norm(targets[best][i] - c) > 0.02:
                i += 1
            if i == edits:
                ordered = False
                break
            i += 1
    # latency: per client k, its i-th send -> the first table update it received after the i-th journal record
    # of that client (records map to sends in order; no-op clicks on already painted spots are not journalled)
    starts = sorted((s[0], k) for k, s in enumerate(sends))
    for (_, k), times in zip(starts, journalled):
        for i, tj in enumerate(times):
            if i >= len(sends[k]):
                break
            nxt = next((u for u in updates[k] if u >= tj), None)
            if nxt is not None:
                lat.append(1000 * (nxt - sends[k][i]))
    res = {
        "vertices": n, "clients": clients, "edits_per_client": edits, "sent": clients * edits,
        "journalled": len(dos), "per_client_order_kept": ordered, "wall_s": round(wall, 1),
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 1) if lat else None,
        "latency_ms_p95": round(float(np.percentile(lat, 95)), 1) if lat else None,
    }
    print(f"load: {res}", flush=True)
    return res


def bench_fuzz(seconds: float) -> dict[str, Any]:
    try:
        from test_fuzz_loaders import run_fuzz
    except ImportError as exc:
        return {"skipped": str(exc)}
    res = run_fuzz(budget_s=seconds, seed=0)
    print(f"fuzz: {json.dumps(res)[:600]}", flush=True)
    return res


_HOSTILE_PRIOR_RUN = """
import json, resource, sys, time
sys.argv = ["efem-viz"] + json.loads(sys.argv[1])
import torch  # imported before the clock starts: the time is the refusal's, not Python's start-up
import efem_viz.batch.commands, efem_viz.prior.model
from efem_viz import cli
t = time.perf_counter()
rc = cli.main(sys.argv[1:])
print(json.dumps({"rc": rc, "seconds": time.perf_counter() - t,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}), file=sys.__stdout__)
"""


def bench_hostile_prior(tmp: Path) -> dict[str, Any]:
    """`segment --prior` on hostile prior files: one error line, seconds (from the command's start, after the
    imports) and peak memory of the CLI process."""
    import dataclasses
    import subprocess

    from helpers import expanded_prior

    from efem_viz.data.io import save_scene
    from efem_viz.prior.analytic import make_sphere_scene
    from efem_viz.prior.config import PriorConfig

    tmp.mkdir(parents=True, exist_ok=True)
    scene = save_scene(make_sphere_scene(seed=1, radii=(0.05,)), tmp / "one.npz")
    tiny = PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16, center_hidden=8,
                       n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=1)
    cases = {"decoder 20,000 wide": dataclasses.replace(PriorConfig(), decoder_hidden=20_000),
             "decoder 200,000 wide": dataclasses.replace(PriorConfig(), decoder_hidden=200_000),
             "plausible sizes, view weights": tiny}
    out: dict[str, Any] = {}
    for name, cfg in cases.items():
        path = expanded_prior(tmp / f"{len(out)}.pt", cfg)
        args = ["segment", str(scene), "--prior", str(path), "--out", str(tmp / f"out{len(out)}")]
        r = subprocess.run([sys.executable, "-c", _HOSTILE_PRIOR_RUN, json.dumps(args)], capture_output=True,
                           text=True, timeout=600, cwd=ROOT)
        stats = json.loads(r.stdout.strip().splitlines()[-1])
        errors = [ln for ln in r.stderr.splitlines() if ln.strip()]
        out[name] = {"file_bytes": path.stat().st_size, "exit": stats["rc"], "error_lines": len(errors),
                     "message": errors[-1][:300] if errors else "", "seconds": round(stats["seconds"], 3),
                     "peak_rss_mb": round(stats["peak_rss_mb"])}
        print(f"hostile prior, {name}: {out[name]}", flush=True)
    return out


def bench_links(tmp: Path) -> dict[str, Any]:
    """*Export results* on the real viewer CLI into folders where a link below the typed folder leads out."""
    import subprocess

    from efem_viz import em
    from efem_viz.data.io import save_scene
    from efem_viz.prior import analytic

    scenes = tmp / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    scene = analytic.make_sphere_scene(seed=0, spacing=0.012, name="spheres")
    save_scene(scene, scenes / "spheres.ply")
    cfg = em.preset("fast").with_proposals(8).replace(elimination={"min_size": 30})
    em.run_em(scene, analytic.make_sphere_prior(), cfg, seed=0).save(scenes / "spheres.efem.npz")
    root, outside = tmp / "root", tmp / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("keep\n")
    (root / "trap").mkdir(parents=True)
    os.symlink(outside, root / "trap" / "pred_mask")
    (root / "trap2" / "pred_mask").mkdir(parents=True)
    os.symlink(outside / "victim.txt", root / "trap2" / "spheres.txt")
    os.symlink(root / "trap", root / "trap3")
    cases = {"pred_mask is a folder link out": "trap", "<scene>.txt is a file link out": "trap2",
             "folder link inside the root, pred_mask leads out": "trap3", "plain folder (control)": "plain"}
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "efem_viz.cli", "view", str(scenes / "spheres.ply"), "--port", "0",
                             "--out-dir", str(root)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env, cwd=ROOT)
    assert proc.stdout is not None
    lines: list[str] = []
    url = ""
    while not url:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError("efem-viz view exited:\n" + "".join(lines))
        lines.append(line)
        m = re.search(r"viewer: (http://\S+)", line)
        url = m.group(1) if m else ""
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()  # type: ignore[arg-type]
    client = ViserClient(url)
    out: dict[str, Any] = {}
    try:
        for name, folder in cases.items():
            n = len(client.notification_texts())
            before_in = {p for p in root.rglob("*")}
            client.set_value("Output folder", folder)
            client.click("Export results")
            if folder == "plain":
                client.wait_for(lambda: (root / "plain" / "spheres_instances.ply").is_file(), 60)
            else:
                client.wait_for(lambda n=n: any("refusing" in t for t in client.notification_texts()[n:]), 60)
            time.sleep(0.5)
            notes = client.notification_texts()[n:]
            out[name] = {
                "refused": any("refusing" in t for t in notes),
                "files_written_outside": len(list(outside.iterdir())) - 1,
                "files_written_inside": len({p for p in root.rglob("*")} - before_in),
                "notice": next((t for t in notes if "refusing" in t), "")[:300],
            }
            print(f"links, {name}: {out[name]}", flush=True)
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        proc.wait(60)
    out["server_log_tracebacks"] = "".join(lines).count("Traceback")
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--edits", type=int, default=50)
    ap.add_argument("--n-side", type=int, default=1000, help="load test scan: n_side^2 vertices")
    ap.add_argument("--fuzz-seconds", type=float, default=60.0)
    ap.add_argument("--only", nargs="*",
                    default=["kill", "damage", "faults", "load", "fuzz", "hostile-prior", "links"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=result_path("reliability"))
    a = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    result: dict[str, Any] = {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "threads": 1}
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        if "kill" in a.only:
            result["kill"] = bench_kill(tmp / "k", a.kills, a.seed)
        if "damage" in a.only:
            result["damage"] = bench_damage(tmp / "d", a.seed)
        if "faults" in a.only:
            result["faults"] = bench_faults(tmp / "f", a.seed)
        if "load" in a.only:
            result["load"] = bench_load(tmp / "l", a.clients, a.edits, a.n_side)
        if "fuzz" in a.only:
            result["fuzz"] = bench_fuzz(a.fuzz_seconds)
        if "hostile-prior" in a.only:
            result["hostile_prior"] = bench_hostile_prior(tmp / "p")
        if "links" in a.only:
            result["links"] = bench_links(tmp / "x")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if a.out.is_file():  # sections not run this time keep their previous results
        result = {**json.loads(a.out.read_text()), **result}
    write_result(a.out, result, archive=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
