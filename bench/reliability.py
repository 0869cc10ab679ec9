"""Reliability of the full `efem-annotate` CLI, measured (issue 13): edits acknowledged vs recovered.

Every number comes from the real CLI process driven by the scripted WebSocket client in tests/viser_client.py
(an edit is *acknowledged* when the server has sent the instance table that shows it):

* kill: a seeded script of painting, undo, redo, EFEM pre-label import and PLY export on a bundled scene is run
  once uninterrupted (the reference tables), then N times with a kill -9 at a random moment; the restarted CLI
  must show the last acknowledged table or the next one (the edit in flight). Also counts stale temp files left.
* damage: a finished session's journal damaged in the middle (with and without a checkpoint), at the end
  (truncated), or its checkpoint damaged; the restarted CLI's table against the last one shown.
* faults: ENOSPC injected on journal writes for a while (a sitecustomize wrapping os.write); refused edits must
  change nothing, later edits must survive a clean stop and restart.
* load: K clients x M brush clicks at once on a 1M-vertex scan: every edit journalled, each client's edits in
  its sending order, and the latency from send to the first table update after the edit was journalled.
* fuzz: the loader fuzzer of tests/test_fuzz_loaders.py (inputs per loader, errors by kind, worst time and
  peak memory).

Writes bench/results/reliability.json. Usage: `python bench/reliability.py [--kills 20] [--clients 4] [--edits 50]`
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
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
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
    from annotator.journal import LabelStore

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
    for case in ("middle", "middle-no-checkpoint", "end", "checkpoint"):
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
        else:
            ckpt.write_bytes(b"PK\x03\x04 not a zip any more")
        again = AnnotateProcess(scan, d)
        seen = again.table()
        status = next((m for m in again.client.markdowns() if "Recovered" in m), "")
        out[case] = {
            "recovered_equals_last_shown": seen == final,
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
    """bench/annotator.py's height-field tabletop (n_side^2 vertices) as a PLY."""
    import importlib.util

    from efem_viz.data.io import save_scene

    spec = importlib.util.spec_from_file_location("bench_annotator", ROOT / "bench" / "annotator.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "surface.ply"
    save_scene(mod.make_surface(n_side), path)
    return path


def bench_load(tmp: Path, clients: int, edits: int, n_side: int) -> dict[str, Any]:
    from annotator.journal import LabelStore

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


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--edits", type=int, default=50)
    ap.add_argument("--n-side", type=int, default=1000, help="load test scan: n_side^2 vertices")
    ap.add_argument("--fuzz-seconds", type=float, default=60.0)
    ap.add_argument("--only", nargs="*", default=["kill", "damage", "faults", "load", "fuzz"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "reliability.json")
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
    a.out.parent.mkdir(parents=True, exist_ok=True)
    from efem_viz.data.io import atomic_write_text

    atomic_write_text(a.out, json.dumps(result, indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
