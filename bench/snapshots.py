"""Choose among a training run's snapshots by solving scenes, not by single-view validation.

`train-prior --snapshot-every N` saves the weights every N iterations (``<run>/snap_<N>.pt``) next to the run's
report, whose validation curve holds the iso offset each validation calibrated. For every chosen snapshot this
bench folds that offset in (as the run's own export would), builds the snapshot's pose codebook, solves the
tuning scenes of the prior's targets with `bench.em` (scene seeds from ``--seed0``: not the fixed test set) and
prints, per snapshot, its single-view validation IoU beside the scenes' AP / AP50; ``--baseline`` adds a shipped
prior solved the same way. Where validation and scenes disagree (a chair validation rising while the piles fall),
the scenes are what a user sees.

    python -m bench.snapshots RUN_DIR [--category chair] [--iterations 2000 4000] [--baseline efem_viz/weights/chair.pt]
        [--configs pile] [--seed0 9100] [--n-scenes 10] [--em-seeds 0] [--threads 1] [--tag T]

Writes ``bench/results/snapshots/latest.json`` (or ``snapshots_<tag>.json``); the calibrated snapshots, their
codebooks and the solves go to ``<RUN_DIR>/snapshot_scenes/`` (``--keep-runs``: the solved scenes too, to open in
the viewer). Solves run at one thread each, in turn; at 10 chair piles a snapshot takes about 3-4 minutes of one
core.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

from bench.common import ROOT, machine, result_path, write_result

SNAPSHOT = re.compile(r"^snap_([0-9]+)\.pt$")
FIXED_SEEDS = (7000, 7010)
"""Scene seeds of the fixed test sets (`bench.em`'s default): never used to choose."""


def snapshots(run_dir: Path) -> dict[int, Path]:
    """The run's snapshots by iteration."""
    out = {int(m.group(1)): p for p in run_dir.glob("snap_*.pt") if (m := SNAPSHOT.match(p.name))}
    return dict(sorted(out.items()))


def run_args(run_dir: Path) -> dict[str, Any]:
    """The run's training arguments (``config.json``)."""
    cfg = run_dir / "config.json"
    if not cfg.is_file():
        raise SystemExit(f"{run_dir}: no config.json (not a train-prior run folder)")
    return dict(json.loads(cfg.read_text()).get("args") or {})


def val_curve(run_dir: Path) -> dict[int, dict[str, Any]]:
    """The run's validations by iteration, from its training report (next to its export)."""
    a = run_args(run_dir)
    export = Path(a["export"]) if a.get("export") else run_dir / f"{a.get('category', 'mug')}.pt"
    candidates = [export, ROOT / export] if not export.is_absolute() else [export]
    reports = [c.with_name(f"{c.stem}_training_report.json") for c in candidates]
    report = next((r for r in reports if r.is_file()), None)
    if report is None:
        raise SystemExit(f"{run_dir}: no training report at {reports[0]} (the run's, with the calibrated offsets)")
    curve = json.loads(report.read_text()).get("val_curve") or []
    return {int(v["iteration"]): v for v in curve if "iteration" in v}


def calibrated(v: dict[str, Any]) -> tuple[float, float]:
    """(iso offset, calibrated IoU) a validation chose: on sensor inputs when the run validated on them, as the
    run's export does."""
    prefix = "sensor_" if "sensor_iso_offset" in v else ""
    return float(v.get(prefix + "iso_offset", 0.0)), float(v.get(prefix + "iou_cal", float("nan")))


def prepare(snap: Path, offset: float, category: str, out: Path, *, count: int, n_store: int) -> Path:
    """The snapshot with its offset folded in, saved in half precision with its own codebook."""
    from efem_viz.prior.commands import BuildCodebookArgs
    from efem_viz.prior.model import load_prior, save_prior
    from efem_viz.prior.train import with_iso_offset

    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{category}.pt"
    prior = load_prior(snap, load_codebook=False)
    save_prior(with_iso_offset(prior, offset), path, extra={"iso_offset": offset}, storage="float16")
    if BuildCodebookArgs(prior=str(path), category=category, count=count, n_store=n_store, seed=0).run() != 0:
        raise SystemExit(f"{path}: the codebook could not be built")
    return path


def solve(prior: Path, args: argparse.Namespace, out: Path) -> dict[str, dict[str, float]]:
    """AP / AP50 / AP25 per configuration of the tuning scenes (`bench.em`, one thread)."""
    record = out / "em.json"
    cmd = [sys.executable, "-m", "bench.em", "--prior", str(prior), "--targets", args.category, "--mode", "tsdf",
           "--configs", *args.configs, "--seed0", str(args.seed0), "--n-scenes", str(args.n_scenes),
           "--em-seeds", *map(str, args.em_seeds), "--skip-speed", "--threads", str(args.threads),
           "--out", str(record)]
    if args.keep_runs:
        cmd += ["--save-results", str(out / "runs")]
    subprocess.run(cmd, cwd=ROOT, check=True)
    acc = json.loads(record.read_text())["accuracy"]
    return {c: {k: float(acc[c][k]) for k in ("ap", "ap50", "ap25")} for c in args.configs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--category", default=None, help="the targets and codebook category (default: the run's)")
    ap.add_argument("--iterations", nargs="+", type=int, default=None, help="snapshots to judge (default: all)")
    ap.add_argument("--baseline", type=Path, default=None, help="a saved prior (with its codebook) solved alike")
    ap.add_argument("--configs", nargs="+", default=["pile"])
    ap.add_argument("--seed0", type=int, default=9100, help="first tuning scene seed (the fixed set is 7000+)")
    ap.add_argument("--n-scenes", type=int, default=10)
    ap.add_argument("--em-seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--codebook-count", type=int, default=100)
    ap.add_argument("--codebook-store", type=int, default=1000)
    ap.add_argument("--keep-runs", action="store_true")
    ap.add_argument("--tag", default=None)
    args = ap.parse_args()
    if args.seed0 < FIXED_SEEDS[1] and args.seed0 + args.n_scenes > FIXED_SEEDS[0]:
        raise SystemExit(f"--seed0 {args.seed0} with --n-scenes {args.n_scenes} takes scenes of the fixed test set "
                         f"(seeds {FIXED_SEEDS[0]}-{FIXED_SEEDS[1] - 1}): choose snapshots on tuning scenes")
    snaps = snapshots(args.run_dir)
    if not snaps:
        raise SystemExit(f"{args.run_dir}: no snap_<iteration>.pt (train with --snapshot-every N)")
    chosen = args.iterations or list(snaps)
    missing = [i for i in chosen if i not in snaps]
    if missing:
        raise SystemExit(f"{args.run_dir}: no snapshot at iteration {missing}; it has {list(snaps)}")
    args.category = args.category or run_args(args.run_dir).get("category", "mug")
    curve = val_curve(args.run_dir)
    work = args.run_dir / "snapshot_scenes"
    rows: list[dict[str, Any]] = []
    if args.baseline is not None:
        rows.append({"name": str(args.baseline), "scenes": solve(args.baseline, args, work / "baseline")})
    for it in chosen:
        if it not in curve:
            raise SystemExit(f"{args.run_dir}: snapshot {it} has no validation in the report (snapshot at "
                             f"multiples of --val-every)")
        offset, iou = calibrated(curve[it])
        prior = prepare(snaps[it], offset, args.category, work / f"snap_{it}", count=args.codebook_count,
                        n_store=args.codebook_store)
        rows.append({"name": f"snap_{it}", "iteration": it, "val_iou_cal": iou, "iso_offset": offset,
                     "scenes": solve(prior, args, work / f"snap_{it}")})
    head = " | ".join(f"{c} AP / AP50" for c in args.configs)
    print(f"\n| snapshot | single-view validation IoU | {head} |")
    print("|---|---|" + "---|" * len(args.configs))
    for r in rows:
        val = f"{r['val_iou_cal']:.3f}" if "val_iou_cal" in r else "-"
        cells = " | ".join(f"{r['scenes'][c]['ap']:.1f} / {r['scenes'][c]['ap50']:.1f}" for c in args.configs)
        print(f"| {r['name']} | {val} | {cells} |")
    out = {"machine": machine(args.threads), "run_dir": str(args.run_dir), "category": args.category,
           "configs": args.configs, "seed0": args.seed0, "n_scenes": args.n_scenes, "em_seeds": args.em_seeds,
           "rows": rows}
    write_result(result_path("snapshots", args.tag), out)
    print(f"wrote {result_path('snapshots', args.tag)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
