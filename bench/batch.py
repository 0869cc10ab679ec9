"""Batch segmentation throughput: the same 12 scenes on the `local`, `process` and `ray` backends.

Each backend runs the real `efem-viz segment` CLI in a fresh process (`--force`, so every scene is computed) on
seeded synthetic scans (`generate_scene("z", seed=9100+k, n_objects=3, distractors=False)`, cached under
runs/bench_batch/scenes). Measured per backend:

* wall time of the whole command (imports, worker start, prior loads, scenes, shutdown), and its ratio to `local`;
* throughput-equivalent per-scene overhead: (wall x workers - sum of the workers' in-scene seconds) / scenes, i.e.
  what each scene costs beyond its own work once everything is counted (start-up, dispatch, idle tails);
* dispatch overhead per scene: driver-observed seconds minus the worker's own seconds (`wall_s - seconds`);
* worker start (process start + imports + prior load) and the prior load alone;
* memory: each worker's RSS once ready and its peak, and the peak RSS of the whole process tree (driver + workers +
  Ray's own processes), sampled every 0.2 s from /proc;
* whether every backend wrote bit-identical results (all arrays but the wall-clock ones).

`local` runs with `--threads CPUS` (torch's intra-op threads); `local_1thread` is the same with one thread, the
reference for the bit-identity check (process and Ray workers run one thread each).

Usage: `python -m bench.batch [--n-scenes 12] [--proposals 16] [--cpus 2]`. Writes bench/results/batch/latest.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, result_path, write_result  # first: the OpenMP wait policy, before torch

VOLATILE = ("timings_json", "trace/timings_json", "trace/step_elapsed")


def make_scenes(folder: Path, n: int) -> list[Path]:
    """n seeded synthetic tabletop scans (3 test-split mugs, TSDF), generated once."""
    from efem_viz.data.io import save_scene
    from efem_viz.data.synth import generate_scene

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(n):
        p = folder / f"z_{9100 + k}.ply"
        if not p.is_file():
            t0 = time.perf_counter()
            save_scene(generate_scene("z", seed=9100 + k, n_objects=3, distractors=False), p)
            print(f"generated {p.name} in {time.perf_counter() - t0:.1f} s", flush=True)
        paths.append(p)
    return paths


def _tree_rss_mb(root_pid: int) -> float:
    """Resident memory of a process and all its descendants (MiB), from /proc."""
    parent: dict[int, int] = {}
    rss: dict[int, int] = {}
    page = os.sysconf("SC_PAGE_SIZE")
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", encoding="ascii", errors="replace") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            parent[int(d)] = int(fields[1])
            rss[int(d)] = int(fields[21]) * page
        except (OSError, IndexError, ValueError):
            continue
    tree, frontier = {root_pid}, [root_pid]
    while frontier:
        p = frontier.pop()
        for c, pp in parent.items():
            if pp == p and c not in tree:
                tree.add(c)
                frontier.append(c)
    return sum(rss.get(p, 0) for p in tree) / 2**20


def run_backend(name: str, args: list[str], scenes: Path, out: Path, *, env: dict[str, str]) -> dict[str, Any]:
    """One `efem-viz segment` run; returns its measurements."""
    cmd = [sys.executable, "-m", "efem_viz.cli", "segment", str(scenes), "--out", str(out), "--force", *args]
    print(f"[{name}] {' '.join(cmd[2:])}", flush=True)
    peak = [0.0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], _tree_rss_mb(proc.pid))
            stop.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    output, _ = proc.communicate()
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    if proc.returncode != 0:
        print(output[-3000:])
        raise SystemExit(f"[{name}] exit code {proc.returncode}")
    rec = json.loads((out / "batch.json").read_text())
    scenes_rec = [s for s in rec["scenes"] if s["status"] == "ok"]
    workers = rec["workers"]
    n = len(scenes_rec)
    busy = sum(s["seconds"] for s in scenes_rec)
    n_workers = len(workers)
    per_worker_peak: dict[str, float] = {}
    for s in scenes_rec:
        per_worker_peak[s["worker"]] = max(per_worker_peak.get(s["worker"], 0.0), s["rss_mb"])
    res = {
        "backend": name,
        "command": " ".join(["efem-viz", *cmd[3:]]),
        "wall_s": wall,
        "batch_wall_s": rec["wall_s"],
        "scenes": n,
        "workers": n_workers,
        "threads_per_worker": workers[0]["threads"] if workers else None,
        "sum_scene_s": busy,
        "sum_scene_cpu_s": sum(s["cpu_s"] for s in scenes_rec),
        "median_scene_cpu_s": statistics.median(s["cpu_s"] for s in scenes_rec),
        "median_scene_s": statistics.median(s["seconds"] for s in scenes_rec),
        "median_solve_s": statistics.median(s["solve_s"] for s in scenes_rec),
        "overhead_per_scene_s": (wall * n_workers - busy) / n,
        "dispatch_per_scene_s": statistics.mean(s["wall_s"] - s["seconds"] for s in scenes_rec),
        "worker_start_s": [w["start_s"] for w in workers],
        "prior_load_s": [w["prior_load_s"] for w in workers],
        "worker_ready_rss_mb": [w["rss_mb"] for w in workers],
        "worker_peak_rss_mb": sorted(per_worker_peak.values()),
        "tree_peak_rss_mb": peak[0],
        "instances": sum(s["instances"] for s in scenes_rec),
    }
    print(f"[{name}] wall {wall:.1f} s, {n} scenes, median {res['median_scene_s']:.1f} s/scene "
          f"({res['median_scene_cpu_s']:.1f} CPU s), "
          f"overhead {res['overhead_per_scene_s']:.2f} s/scene, tree peak {peak[0]:.0f} MiB", flush=True)
    return res


def same_results(a: Path, b: Path) -> list[str]:
    """Names of scenes whose results differ between two output folders (wall-clock arrays aside)."""
    bad = []
    for fa in sorted(a.glob("[!.]*.efem.npz")):
        with np.load(fa) as za, np.load(b / fa.name) as zb:
            keys = [k for k in za.files if k not in VOLATILE]
            if sorted(keys) != sorted(k for k in zb.files if k not in VOLATILE) or any(
                    not np.array_equal(za[k], zb[k], equal_nan=za[k].dtype.kind in "fc") for k in keys):
                bad.append(fa.name)
    return bad


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-scenes", type=int, default=12)
    ap.add_argument("--proposals", type=int, default=16)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--cpus", type=int, default=2, help="CPUs for every backend (local: torch threads)")
    ap.add_argument("--backends", nargs="+", default=["local", "local_1thread", "process", "ray"],
                    choices=["local", "local_1thread", "process", "ray"])
    ap.add_argument("--root", type=Path, default=ROOT / "runs" / "bench_batch")
    ap.add_argument("--json", type=Path, default=result_path("batch"))
    a = ap.parse_args()
    scenes_dir = a.root / "scenes"
    paths = make_scenes(scenes_dir, a.n_scenes)
    for extra in sorted(scenes_dir.iterdir()):
        if extra not in paths:
            raise SystemExit(f"{scenes_dir} holds other files ({extra.name}); use an empty --root")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    common = ["--preset", a.preset, "--proposals", str(a.proposals), "--seed", "0"]
    configs = {
        "local": [*common, "--threads", str(a.cpus)],
        "local_1thread": [*common, "--threads", "1"],
        "process": [*common, "--workers", str(a.cpus), "--threads", "1"],
        "ray": [*common, "--ray", "--ray-cpus", str(a.cpus), "--workers", str(a.cpus), "--threads", "1"],
    }
    rows = []
    for name in a.backends:
        rows.append(run_backend(name, configs[name], scenes_dir, a.root / f"out_{name}", env=env))
    base = next((r for r in rows if r["backend"] == "local"), rows[0])
    # identity is checked against a run with the same torch threads per worker (1) when there is one: a different
    # thread count changes the order of float reductions, hence the last bits
    ref_name = "local_1thread" if "local_1thread" in a.backends else rows[0]["backend"]
    for r in rows:
        r["wall_ratio_vs_local"] = r["wall_s"] / base["wall_s"]
        r["speedup_vs_local"] = base["wall_s"] / r["wall_s"]
        r["identity_reference"] = ref_name
        r["results_differ"] = same_results(a.root / f"out_{ref_name}", a.root / f"out_{r['backend']}")
    print()
    hdr = ("backend", "workers x threads", "wall s", "vs local", "median scene s (CPU s)", "overhead s/scene",
           "dispatch s/scene", "worker start s", "prior load s", "worker RSS MiB (ready / peak)", "tree peak MiB",
           "same files as " + ("local_1thread" if "local_1thread" in a.backends else a.backends[0]))
    print(" | ".join(hdr))
    for r in rows:
        print(" | ".join([
            r["backend"], f"{r['workers']} x {r['threads_per_worker']}", f"{r['wall_s']:.1f}",
            f"{r['wall_ratio_vs_local']:.2f}", f"{r['median_scene_s']:.1f} ({r['median_scene_cpu_s']:.1f})",
            f"{r['overhead_per_scene_s']:.2f}",
            f"{r['dispatch_per_scene_s']:.3f}", "/".join(f"{v:.1f}" for v in r["worker_start_s"]),
            "/".join(f"{v:.2f}" for v in r["prior_load_s"]),
            f"{statistics.mean(r['worker_ready_rss_mb']):.0f} / {max(r['worker_peak_rss_mb']):.0f}",
            f"{r['tree_peak_rss_mb']:.0f}",
            "yes" if not r["results_differ"] else f"no: {len(r['results_differ'])} of {r['scenes']}",
        ]))
    doc = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "settings": {"n_scenes": a.n_scenes, "preset": a.preset, "proposals": a.proposals, "cpus": a.cpus,
                     "scenes": "generate_scene('z', seed=9100+k, n_objects=3, distractors=False)",
                     "points": _points(paths)},
        "rows": rows,
    }
    a.json.parent.mkdir(parents=True, exist_ok=True)
    write_result(a.json, doc)
    return 0


def _points(paths: list[Path]) -> dict[str, float]:
    from efem_viz.data.io import load_scene

    n = [load_scene(p).num_points for p in paths]
    return {"min": min(n), "median": float(statistics.median(n)), "max": max(n)}


if __name__ == "__main__":
    sys.exit(main())
