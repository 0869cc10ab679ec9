"""A learned confidence against look-alikes, screened on saved runs without a re-run.

Every accepted fit of the saved runs (`bench/ranking.py`'s `fits_of`) becomes a feature vector of its review
features (stationary score, coverage, pose score, size, up angle, seen-through fraction, mask size); the label is
"matches a mug at IoU >= 0.5". A logistic regression (numpy, L2, standardised features) is fitted on the **tune**
frames only and scores the **judge** frames; the candidates are compared on the judge frames' pooled AP50 and on how
many judge scenes rank a mug first, with the same scorer as `bench/ranking.py` (`score_rule`).

Candidates (all fitted on tune frames only, never on a judge frame):
* `p(mug)`: the classifier's probability alone;
* `confidence x p(mug)`: the solver's confidence times it;
* the same with fewer features (which features carry the separation);
* leave-one-frame-out over the tune frames gives the held-out AP50 inside the tune set (model choice without
  touching the judge frames).

A single-episode run's instances do not depend on the confidence, so a re-scored ranking is exact end to end.

Usage: python -m bench.learned_confidence DIR/seed0 DIR/seed1 ... [--tune 0 1 6] [--judge 2 3 4 5 7 8]
       [--json bench/results/learned_confidence/learned_confidence_<tag>.json]
       python -m bench.learned_confidence TUNE_DIR ... --judge-folders JUDGE_DIR ...   (generated scenes: every
       scene of the positional folders is a tune scene, every scene of --judge-folders a judge scene; the held-out
       score inside the tune set leaves one scene out at a time)
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import bench.common  # noqa: F401 - first: the OpenMP wait policy, before torch
import bench.ranking
from bench.ranking import Fit, fits_of, run_key, score_rule
from efem_viz.em.look_alike import FEATURES, LookAlikeModel, fit_logistic, load_model, review_features
from efem_viz.em.solver import confidence

def features_of(f: Fit) -> dict[str, float]:
    """A fit's review features as the shipped model sees them (`efem_viz.em.look_alike.review_features`)."""
    return review_features(stationary=f.stationary, coverage=f.coverage, pose=f.db_sim, radius=f.radius,
                           half_height=f.half_height, up_angle=f.up_angle, seen_through=f.seen_through,
                           mask_size=f.mask_size)


def frame_of(name: str) -> int:
    tail = name.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else -1


def matrix(fits: Sequence[Fit], names: Sequence[str]) -> np.ndarray:
    rows = [features_of(f) for f in fits]
    return np.array([[r[n] for n in names] for r in rows], np.float64).reshape(len(fits), len(names))


def is_mug(f: Fit) -> bool:
    return f.category == "mug" and f.iou >= 0.5


def load_fits(folders: Sequence[Path], cache: Path | None) -> tuple[list[Fit], dict[tuple[str, str], Any]]:
    from efem_viz.data.io import load_scene

    if cache is not None and cache.is_file():
        sys.modules.setdefault("ranking", bench.ranking)  # caches pickled when the benches ran as scripts
        fits, keys = pickle.loads(cache.read_bytes())
    else:
        fits = [f for folder in folders for f in fits_of(folder)]
        keys = sorted({(run_key(folder), f.scene, str(folder)) for folder in folders for f in fits
                       if f.run == run_key(folder)})
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            cache.write_bytes(pickle.dumps((fits, keys)))
    scenes = {(run, name): load_scene(Path(folder) / f"{name}.ply") for run, name, folder in keys}
    return fits, scenes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--tune", type=int, nargs="+", default=[0, 1, 6])
    ap.add_argument("--judge", type=int, nargs="+", default=[2, 3, 4, 5, 7, 8])
    ap.add_argument("--judge-folders", type=Path, nargs="+", default=None,
                    help="split by folder instead of by frame: the positional folders are the tune scenes (e.g. "
                         "`python -m bench.em --seed0 9000 --save-results`), these the judge scenes (the fixed set)")
    ap.add_argument("--model", nargs="*", default=["mug_uois_tune"],
                    help="shipped models (efem_viz/em/models/NAME.json) to score as they are")
    ap.add_argument("--l2", type=float, nargs="+", default=[0.3, 1.0, 3.0, 10.0])
    ap.add_argument("--revive", type=float, nargs="+", default=[0.0, 1.0],
                    help="free-space kill limits to screen: 0 = as run, L = fits killed at a seen-through fraction "
                         "<= L come back (1: every one)")
    ap.add_argument("--spare", type=float, nargs="*", default=[],
                    help="also score: the free-space kill spares fits whose p(mug) (the chosen model) is >= each")
    ap.add_argument("--cache", type=Path, default=None, help="pickle of the fits (read if present, else written)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--write", type=Path, default=None, metavar="MODEL.json",
                    help="save the candidate with the best leave-one-frame-out tune AP50 as a model")
    ap.add_argument("--write-revive", type=float, default=0.0,
                    help="--write chooses among the candidates of this kill limit (0: the solver's kills as run, "
                         "which keeps a re-score exact end to end)")
    a = ap.parse_args()
    fits, scenes = load_fits([*a.folders, *(a.judge_folders or [])], a.cache)
    acc = [f for f in fits if f.accepted]
    group_of: Callable[[str], Any]
    if a.judge_folders:  # generated scenes: the split is by folder, the held-out groups are scenes
        tune_runs = {run_key(p) for p in a.folders}
        tune_names = {name for run, name in scenes if run in tune_runs}
        judge_names = {name for run, name in scenes if run not in tune_runs}
        if tune_names & judge_names:
            raise SystemExit(f"scenes in both the tune and the judge folders: {sorted(tune_names & judge_names)[:5]}")
        tune, judge = tune_names, judge_names
        group_of, split = (lambda name: name), "folders"
    else:
        tune, judge = set(a.tune), set(a.judge)
        group_of, split = frame_of, "frames"
    tr = [f for f in acc if group_of(f.scene) in tune]
    print(f"{len(acc)} accepted fits in {len(scenes)} scene runs; tune {split} ({len(tune)}): {len(tr)} fits, "
          f"{sum(map(is_mug, tr))} mugs; judge {split} ({len(judge)}): "
          f"{sum(group_of(f.scene) in judge for f in acc)} fits, "
          f"{sum(is_mug(f) for f in acc if group_of(f.scene) in judge)} mugs")

    def in_frames(frames: set[Any]) -> Callable[[str], bool]:
        return lambda name: group_of(name) in frames

    def kept(limit: float) -> Callable[[Fit], bool]:
        """The fits a run keeps when the free-space check kills only above `limit` (0: as run)."""
        return lambda f: f.accepted or (limit > 0 and f.killed_by == "seen-through" and f.seen_through <= limit)

    def table_row(label: str, rule: Callable[[Fit], float], revive: float = 0.0) -> dict[str, Any]:
        r = {"tune": score_rule(fits, scenes, rule, kept(revive), only=in_frames(tune)),
             "judge": score_rule(fits, scenes, rule, kept(revive), only=in_frames(judge))}
        print(f"| {label} | {r['tune']['ap50']:.1f} | {r['judge']['ap50']:.1f} | {r['judge']['ap']:.1f} | "
              f"{r['judge']['top_is_mug']} of {r['judge']['scenes_with_mug']} | {r['judge']['mugs_found']} of "
              f"{r['judge']['mugs']} |")
        return r

    def lofo(names: Sequence[str], l2: float, use_conf: bool, revive: float = 0.0) -> float:
        """AP50 over the tune frames (scenes), each scored by a model fitted on the other tune frames (scenes)."""
        models = {}
        pool = [f for f in tr_all if kept(revive)(f)]
        for k in tune:
            rest = [f for f in pool if group_of(f.scene) != k]
            y = np.array([is_mug(f) for f in rest], np.float64)
            models[k] = fit_logistic(matrix(rest, names), y, names, l2=l2) if 0 < y.sum() < len(y) else None

        def rule(f: Fit) -> float:
            m = models.get(group_of(f.scene))
            p = float(m.probs(matrix([f], names))[0]) if m is not None else 0.5
            return p * (conf(f) if use_conf else 1.0)

        return score_rule(fits, scenes, rule, kept(revive), only=in_frames(tune))["ap50"]

    out: dict[str, Any] = {}
    models: dict[str, LookAlikeModel] = {}
    tr_all = [f for f in fits if group_of(f.scene) in tune]

    def conf(f: Fit) -> float:
        """The paper's confidence with the free-space factor (`solver.confidence`, the presets' coverage cap 0.4),
        recomputed from the review features for every fit, revived ones included: runs saved with a `mug_model`
        store confidences that already hold that model's factor."""
        return confidence(f.stationary, f.coverage, cap=0.4, seen_through=f.seen_through)

    def _candidate(revive: float, sname: str, names: list[str], use_conf: bool) -> None:
        best = max(a.l2, key=lambda l2: lofo(names, l2, use_conf, revive))
        inner = lofo(names, best, use_conf, revive)
        pool = [f for f in tr_all if kept(revive)(f)]
        y = np.array([is_mug(f) for f in pool], np.float64)
        model = fit_logistic(matrix(pool, names), y, names, l2=best, trained_on=(
            f"bench/learned_confidence.py: accepted"
            f"{f' and free-space-killed (<= {revive:g})' if revive else ''} fits of "
            f"{split} {sorted(tune) if split == 'frames' else ', '.join(map(str, a.folders))} in "
            f"{len(a.folders)} saved runs, L2 {best:g}"), times_confidence=use_conf)

        def rule(f: Fit) -> float:
            return float(model.probs(matrix([f], names))[0]) * (conf(f) if use_conf else 1.0)

        label = (f"{f'revived <= {revive:g}: ' if revive else ''}{'confidence x ' if use_conf else ''}"
                 f"p(mug | {sname}), L2 {best:g} (LOFO tune AP50 {inner:.1f})")
        r = table_row(label, rule, revive)
        r["revive_limit"] = revive
        r["weights"] = dict(zip(["bias", *names], (model.bias, *model.weights)))
        r["l2"], r["lofo_tune_ap50"] = best, inner
        out[label] = r
        models[label] = model

    print("\n| candidate (fitted on tune frames) | AP50 tune | AP50 judge | AP judge | judge: top is a mug "
          "| judge: mugs found |\n|---|---:|---:|---:|---:|---:|")
    pose = lambda f: min(1.0, max(f.db_sim, 0.0) / 0.6) ** 2 if math.isfinite(f.db_sim) else 1.0  # noqa: E731
    out["solver (as run)"] = table_row("solver (as run)", lambda f: f.confidence)
    out["x min(1, pose/0.6)^2 (pose factor)"] = table_row("x min(1, pose/0.6)² (the earlier `real` preset)",
                                                         lambda f: conf(f) * pose(f))
    for name in a.model:
        shipped = load_model(name)
        out[f"shipped {name}"] = table_row(
            f"shipped model `{name}`", lambda f, m=shipped: m.confidence(conf(f), features_of(f)))
    all_names = list(FEATURES)
    subsets = {"all features": all_names,
               "no seen-through": [n for n in all_names if n != "seen-through"],
               "pose, size, up": ["pose score", "radius (cm)", "half height (cm)", "cos up angle"],
               "stationary, coverage, pose": ["log stationary", "log coverage", "pose score"],
               "no mask size": [n for n in all_names if n != "log mask size"],
               "no mask size, no seen-through": [n for n in all_names if n not in ("log mask size", "seen-through")]}
    for limit in a.revive:
        if limit > 0:
            out[f"revived <= {limit:g}, demoted"] = table_row(
                f"fits killed by the free-space check revived up to {limit:g}, confidence x (1 - fraction)",
                conf, revive=limit)
    for revive in a.revive:
        for sname, names in subsets.items():
            for use_conf in (False, True):
                _candidate(revive, sname, names, use_conf)
    if a.spare:  # the free-space kill spares the fits the chosen (un-revived) model finds mug-like
        label = max((k for k in models if out[k]["revive_limit"] == 0.0), key=lambda k: out[k]["lofo_tune_ap50"])
        model = models[label]

        def mug_score(f: Fit) -> float:
            p = float(model.probs(matrix([f], model.names))[0])
            return p * conf(f) if model.times_confidence else p

        for tau in a.spare:
            def spared(f: Fit, tau: float = tau) -> bool:
                return f.accepted or (f.killed_by == "seen-through" and mug_score(f) >= tau)

            r = {"tune": score_rule(fits, scenes, mug_score, spared, only=in_frames(tune)),
                 "judge": score_rule(fits, scenes, mug_score, spared, only=in_frames(judge))}
            lab = f"kill spares p(mug) >= {tau:g} ({label.split(',')[0]})"
            print(f"| {lab} | {r['tune']['ap50']:.1f} | {r['judge']['ap50']:.1f} | {r['judge']['ap']:.1f} | "
                  f"{r['judge']['top_is_mug']} of {r['judge']['scenes_with_mug']} | {r['judge']['mugs_found']} of "
                  f"{r['judge']['mugs']} |")
            n_spared = sum(1 for f in fits if not f.accepted and spared(f))
            r["spared_fits"] = n_spared
            out[lab] = r
    if a.write is not None:  # the candidate with the best held-out tune AP50 (never chosen on the judge frames)
        label = max((k for k in models if out[k]["revive_limit"] == a.write_revive),
                    key=lambda k: out[k]["lofo_tune_ap50"])
        models[label].save(a.write)
        print(f"wrote {a.write}: {label}")
    if a.json is not None:
        from efem_viz.data.io import atomic_write_text

        atomic_write_text(a.json, json.dumps({"folders": [str(p) for p in a.folders], "tune": sorted(map(str, tune)),
                                              "judge": sorted(map(str, judge)), "candidates": out},
                                             indent=1, default=float))
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
