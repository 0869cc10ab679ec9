"""Re-score saved EFEM runs with the explained-share decay of their confidences (`confidence.explained_decay`).

The decay changes no fit, only the confidences (`efem_viz.em.rules.explained_decay`), so runs saved by `python -m
bench.em --save-results DIR` (or `bench.real --save-results`) score exactly as if they had run with any power. A run
saved with the decay on gets its method confidences back from its instances first (`method_confidences`: the
stationary score, coverage, pose score and seen-through fraction the solver multiplied); runs with a look-alike
model and the decay on cannot be undone and are refused.

    python -m bench.explained_decay DIR... [--powers 0 1 2] [--classes mug] [--by-seed] [--out FILE.json]

Each DIR is scored as one set (every `<scene>.efem.npz` beside its `<scene>.ply`, or with solver seeds
`<scene>_s<k>.efem.npz`), or with `--by-seed` as one set per solver seed (`DIR#s<k>`; runs without a seed suffix
as `DIR#s-`), class-agnostic (every labelled object one class) unless `--classes` names the evaluated categories;
prints AP / AP50 / AP25 per power and writes them as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def load_runs(folder: Path) -> list[tuple[str, object, object]]:
    """(key, scene, result) of every saved run in a folder."""
    from efem_viz.data.io import load_scene
    from efem_viz.em.results import EMResult

    out = []
    for npz in sorted(folder.glob("*.efem.npz")):
        name = npz.name[: -len(".efem.npz")]
        ply = folder / f"{name}.ply"
        if not ply.is_file():
            ply = folder / f"{re.sub(r'_s[0-9]+$', '', name)}.ply"
        if ply.is_file():
            out.append((f"{folder.name}/{name}", load_scene(ply), EMResult.load(npz)))
    return out


def by_seed(runs: list[tuple[str, object, object]]) -> dict[str, list[tuple[str, object, object]]]:
    """`load_runs`'s runs grouped by the solver seed in their names (``<scene>_s<k>``; "-" without one), seeds in
    ascending order."""
    groups: dict[str, list[tuple[str, object, object]]] = {}
    for run in runs:
        m = re.search(r"_s([0-9]+)$", run[0])
        groups.setdefault(m.group(1) if m else "-", []).append(run)
    return dict(sorted(groups.items(), key=lambda kv: (kv[0] == "-", int(kv[0]) if kv[0] != "-" else 0)))


def method_confidences(res: object) -> np.ndarray:
    """The instances' confidences before any explained-share decay: as saved when the run had none, else rebuilt
    with `solver.confidence` from each instance's stationary score, coverage and pose score and its last review's
    seen-through fraction (equal to the saved values to 1e-7 on runs without the decay).

    Raises:
        SystemExit: the run had the decay and a look-alike model (its probabilities are not stored).
    """
    from efem_viz.em.solver import confidence

    inst, cfg = res.instances, res.config.confidence  # type: ignore[attr-defined]
    if not cfg.explained_decay:
        return np.asarray(inst.confidence, np.float64)
    if cfg.look_alike is not None:
        raise SystemExit("a run with a look-alike model and the explained-share decay cannot be re-scored")
    trace = res.trace  # type: ignore[attr-defined]
    return np.array([confidence(float(s), float(c), cap=cfg.cov_cap, pose=float(db), pose_weight=cfg.pose_weight,
                                pose_ref=cfg.pose_ref, seen_through=float(trace.reviews(int(pid))[-1].seen_through))
                     for s, c, db, pid in zip(inst.stationary, inst.coverage, inst.db_sim, inst.ids)], np.float64)


def prepared(runs: list, classes: tuple[str, ...] | None) -> list[tuple[str, object, np.ndarray, object]]:
    """Per run what every power re-scores: (key, result, method confidences, ground truth), the ground truth as
    one class "object" when `classes` is None (`bench.em.agnostic_truth`)."""
    from bench.em import agnostic_truth
    from efem_viz.eval import SceneGroundTruth

    out = []
    for key, scene, res in runs:
        gt = dataclasses.replace(SceneGroundTruth.from_scene(scene), name=key)
        out.append((key, res, method_confidences(res), agnostic_truth(gt) if classes is None else gt))
    return out


def score(runs: list, power: float, classes: tuple[str, ...] | None) -> dict[str, float]:
    """AP / AP50 / AP25 (percent) of `prepared` runs with their confidences decayed at `power`."""
    from bench.em import agnostic_prediction
    from efem_viz.em.rules import explained_decay
    from efem_viz.eval import evaluate, prediction_from_instances

    preds = []
    for key, res, conf0, _ in runs:
        inst = res.instances
        conf = explained_decay(conf0, list(inst.masks), res.num_points, power)
        res = dataclasses.replace(res, instances=dataclasses.replace(inst, confidence=conf.astype(np.float32)))
        preds.append(agnostic_prediction(res, key) if classes is None
                     else prediction_from_instances(res.instances, name=key, class_names=classes))
    e = evaluate(preds, [gt for *_, gt in runs], class_names=classes or ("object",))
    return {"ap": e.ap * 100, "ap50": e.ap50 * 100, "ap25": e.ap25 * 100}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--powers", nargs="+", type=float, default=[0.0, 1.0, 2.0])
    ap.add_argument("--classes", nargs="+", default=None, help="evaluated categories (default: class-agnostic)")
    ap.add_argument("--by-seed", action="store_true", help="score each solver seed of a folder as its own set")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    classes = tuple(args.classes) if args.classes else None
    record: dict[str, dict[str, dict[str, float]]] = {}
    for folder in args.folders:
        loaded = load_runs(folder)
        if not loaded:
            raise SystemExit(f"{folder}: no saved runs (<scene>.efem.npz beside <scene>.ply)")
        sets = {f"{folder}#s{k}": group for k, group in by_seed(loaded).items()} if args.by_seed \
            else {str(folder): loaded}
        for name, group in sets.items():
            runs = prepared(group, classes)
            record[name] = {}
            for p in args.powers:
                r = score(runs, p, classes)
                record[name][f"{p:g}"] = r
                print(f"{name} ({len(runs)} runs) power {p:g}: "
                      f"AP {r['ap']:.1f} AP50 {r['ap50']:.1f} AP25 {r['ap25']:.1f}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
