"""`efem-viz evaluate`: AP / AP50 / AP25 of saved predictions against labelled scenes (docs/design/efem-method.md §5);
`efem-viz calibrate-masks`: a prior's output-mask threshold τ_out chosen on labelled tuning scenes
(`efem_viz.eval.calibrate`)."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import tyro

from efem_viz.eval.calibrate import TAU_OUT_CANDIDATES
from efem_viz.prior.config import DEFAULT_PRIOR

if TYPE_CHECKING:
    from rich.table import Table

    from efem_viz.eval.ap import EvalResult
    from efem_viz.eval.matching import SceneGroundTruth, ScenePrediction

log = logging.getLogger(__name__)


@dataclass
class EvaluateArgs:
    """Score predictions (ScanNet layout, or `<scene>.efem.npz` results) against scenes with ground-truth labels."""

    results: Annotated[Path, tyro.conf.Positional]
    """Results folder: `*.efem.npz` (e.g. a `segment --out` folder of any size), else `<scene>.txt` + masks (ScanNet
    layout; also looked for in `scannet/`; give `OUT/scannet` to score a batch's ScanNet export instead)."""
    gt: list[Path] = field(default_factory=list)
    """Labelled scene files (per-vertex `instance`) and/or folders of them; names must match the results."""
    classes: tuple[str, ...] | None = None
    """Evaluated classes, e.g. --classes mug sphere; `.efem.npz` instances are matched by their category name (with
    one class, every instance counts as it), class id k of ScanNet-layout predictions is classes[k-1]. Default: the
    categories of the labelled objects in --gt, in the order met (mug when they name none); ScanNet-layout
    predictions: mug."""
    threshold: float = 0.0
    """Drop predictions with a lower confidence."""
    strict: bool = True
    """Require predictions for exactly the ground-truth scenes."""
    scannet_flag: bool = False
    """ScanNet mode: ignore unmatched predictions mostly on void or small objects (§5.3)."""
    json_out: Path | None = None
    """Also write the full result (tables, per class, PR curves) as JSON here."""

    def run(self) -> int:
        """Evaluate and print the table; returns 0."""
        from efem_viz.terminal import console

        from efem_viz.data.io import find_scenes, load_scene
        from efem_viz.data.scene import SceneError
        from efem_viz.eval.ap import evaluate_overlaps, overlaps_of
        from efem_viz.eval.matching import SceneGroundTruth, SceneOverlaps

        if not self.gt:
            raise SceneError("give the labelled scenes with --gt SCENE... (files or folders)")
        if self.json_out is not None:
            from efem_viz.cli import check_output_file

            check_output_file(self.json_out, option="--json-out")
        gt_files = find_scenes(self.gt)  # missing paths are reported first, before anything is read
        sources, from_efem = self._prediction_sources()
        classes = tuple(self.classes) if self.classes else (
            labelled_categories(gt_files) if from_efem else (DEFAULT_PRIOR,))
        # one scene at a time: its labels and predictions are dropped once its overlaps (a few numbers per
        # instance pair) are computed, so a folder of any size is scored in the memory of its largest scene
        overlaps: dict[str, SceneOverlaps] = {}
        gt_paths: dict[str, Path] = {}
        for p in gt_files:
            scene = load_scene(p)
            if scene.instance is None:
                raise SceneError(f"{p} has no ground-truth `instance` labels")
            if scene.name in gt_paths:
                raise SceneError(f"two labelled scenes are named {scene.name!r}: {gt_paths[scene.name]} and {p}")
            gt_paths[scene.name] = p
            gt = SceneGroundTruth.from_scene(scene)
            del scene
            src = sources.get(gt.name)
            pred = None
            if src is not None:
                pred = self._prediction(src, gt, from_efem=from_efem, classes=classes)
            elif self.strict:
                raise SceneError(f"no prediction for the labelled scene {gt.name!r} ({p}) in {self.results}; "
                                 "pass --no-strict to count it as having none")
            overlaps[gt.name] = overlaps_of(pred, gt, class_names=classes)
        extra = sorted(set(sources) - set(gt_paths))
        if extra and self.strict:
            raise SceneError(f"predictions without a labelled scene in --gt: {extra[:10]}; pass --no-strict to ignore "
                             "them")
        if extra:
            log.warning("ignoring predictions for %d scenes without ground truth: %s", len(extra), extra[:10])
        if not overlaps:
            raise SceneError(f"no labelled scenes found in {[str(g) for g in self.gt]}")
        result = evaluate_overlaps(overlaps, class_names=classes, scannet_flag=self.scannet_flag)
        console = console()
        console.print(_ap_table(result))
        if self.json_out is not None:
            from efem_viz.data.io import atomic_write_text

            atomic_write_text(self.json_out, json.dumps(result.to_dict(), indent=1))
            console.print(f"wrote {self.json_out}")
        return 0


    def _prediction_sources(self) -> tuple[dict[str, Path], bool]:
        """The prediction file of each scene in `--results`, by scene name, and whether they are `.efem.npz` results
        (else ScanNet `<scene>.txt` files).

        Raises:
            SceneError: `--results` is not a folder or holds no predictions.
        """
        from efem_viz.data.io import RESULT_SUFFIX
        from efem_viz.data.scene import SceneError
        from efem_viz.eval.scannet import scannet_prediction_files

        if not self.results.is_dir():
            raise SceneError(f"{self.results}: not a folder")
        # hidden files are temporaries of interrupted writes (a killed batch), never results. `.efem.npz` results
        # win over a ScanNet export beside them (a `segment --out` folder has both): they keep exact confidences
        # and each instance's category; the ScanNet layout is read when there are none
        sources: dict[str, Path] = {
            f.name[: -len(RESULT_SUFFIX)]: f for f in sorted(self.results.glob(f"*{RESULT_SUFFIX}"))
            if not f.name.startswith(".")
        }
        from_efem = bool(sources)
        if not from_efem:
            sources = scannet_prediction_files(self.results)
        if not sources:
            raise SceneError(f"{self.results}: no predictions found (<scene>.txt or <scene>.efem.npz)")
        return sources, from_efem

    def _prediction(self, src: Path, gt: "SceneGroundTruth", *, from_efem: bool,
                    classes: tuple[str, ...]) -> "ScenePrediction":
        """One scene's predictions from its `.efem.npz` or ScanNet `<scene>.txt`, checked and thresholded."""
        import numpy as np

        from efem_viz.data.scene import SceneError
        from efem_viz.eval.matching import ScenePrediction

        if from_efem:
            from efem_viz.em.results import EMResult
            from efem_viz.eval.ap import prediction_from_instances

            res = EMResult.load(src)
            if res.num_points != gt.num_points:
                raise SceneError(f"{src} was computed on {res.num_points} points but the ground-truth scene "
                                 f"{gt.name!r} has {gt.num_points}")
            pred = prediction_from_instances(res.instances, name=gt.name, class_names=classes)
        else:
            from efem_viz.eval.scannet import load_scannet_prediction

            pred = load_scannet_prediction(src)
        conf = np.asarray(pred.confidences, np.float64)
        if not np.isfinite(conf).all():  # a NaN would sort anywhere and silently change the AP
            raise SceneError(f"{self.results}: scene {pred.name!r} has a non-finite prediction confidence")
        if self.threshold > 0:
            from efem_viz.em.results import confidence_mask

            keep = confidence_mask(conf, self.threshold)
            pred = ScenePrediction(name=pred.name, masks=[pred.masks[int(i)] for i in np.flatnonzero(keep)],
                                   confidences=conf[keep], labels=None if pred.labels is None else pred.labels[keep])
        return pred


def labelled_categories(gt_files: list[Path]) -> tuple[str, ...]:
    """The categories of the labelled objects (instance > 0) in these scenes, in the order met (files in order,
    objects by id); mug when they name none. Reads one scene at a time, so `evaluate` without --classes reads each
    labelled scene twice (no scene format has a header-only reader; the classes must be known before the first
    scene's overlaps are computed, and keeping every scene would cost a folder's memory)."""
    import numpy as np

    from efem_viz.data.io import load_scene

    names: list[str] = []
    for p in gt_files:
        scene = load_scene(p)
        if scene.instance is None:
            continue
        for i in np.unique(scene.instance):
            c = scene.categories.get(int(i)) if i > 0 else None
            if c is not None and c not in names:
                names.append(str(c))
    return tuple(names) or (DEFAULT_PRIOR,)


def _ap_table(result: EvalResult) -> Table:
    """The AP table of an evaluation: per class AP, AP50, AP25, recalls, counts, then the mean (in %)."""
    import numpy as np
    from rich.table import Table

    table = Table(title=f"instance AP over {len(result.scenes)} scenes", title_justify="left")
    for col in ("class", "AP", "AP50", "AP25", "RC50", "RC25", "GT", "pred"):
        table.add_column(col, justify="right" if col != "class" else "left")

    def f(v: float) -> str:
        return "nan" if not np.isfinite(v) else f"{100 * v:.1f}"

    for name, row in result.per_class().items():
        table.add_row(
            name, f(row["ap"]), f(row["ap50"]), f(row["ap25"]), f(row["rc50"]), f(row["rc25"]),
            str(row["n_gt"]), str(row["n_pred"]),
        )
    table.add_row("mean", f(result.ap), f(result.ap50), f(result.ap25), "", "", "", "", style="bold")
    return table


@dataclass
class CalibrateMasksArgs:
    """Choose a prior's output-mask SDF threshold τ_out on labelled tuning scenes (the smallest within --tolerance of
    the best AP of re-thresholded masks)."""

    results: Annotated[list[Path], tyro.conf.Positional]
    """`<scene>.efem.npz` results (files and/or folders), computed with --prior."""
    gt: list[Path] = field(default_factory=list)
    """Labelled tuning scenes (files and/or folders); results are paired with them by scene name."""
    prior: str = DEFAULT_PRIOR
    """The prior the results were computed with (a name under efem_viz/weights/ or a .pt path)."""
    candidates: tuple[float, ...] = TAU_OUT_CANDIDATES
    """Thresholds to try (canonical units)."""
    classes: tuple[str, ...] = (DEFAULT_PRIOR,)
    """Evaluated classes (as in `efem-viz evaluate`)."""
    tolerance: float = 0.5
    """AP points below the best that still count as a tie; ties go to the smaller (tighter) threshold."""
    write: bool = False
    """Store the chosen value (and the table) in the prior file's metadata; `run_em` then uses it."""
    json_out: Path | None = None
    """Also write the calibration table as JSON here."""

    def run(self) -> int:
        """Print the AP table per threshold; with --write update the prior. Returns 0."""
        from efem_viz.data.io import find_scenes, load_scene
        from efem_viz.em.results import RESULT_SUFFIX, EMResult
        from efem_viz.eval.calibrate import calibrate_tau_out
        from efem_viz.prior.config import TAU_OUT_KEY as METADATA_KEY, prior_category
        from efem_viz.prior.model import load_prior, resolve_prior_path, save_prior

        if not self.gt:
            raise ValueError("give the labelled tuning scenes with --gt SCENE... (files or folders)")
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0.0):
            raise ValueError(f"--tolerance must be a number of AP points >= 0, got {self.tolerance}")
        if self.json_out is not None:
            from efem_viz.cli import check_output_file

            check_output_file(self.json_out, option="--json-out")
        scenes = {}
        scene_paths: dict[str, Path] = {}
        for p in find_scenes(self.gt):
            scene = load_scene(p)
            scenes[scene.name] = scene
            scene_paths[scene.name] = p
        files: list[Path] = []
        for r in self.results:
            if r.is_dir():
                files += sorted(r.glob(f"*{RESULT_SUFFIX}"))
            elif r.is_file():
                files.append(r)
            else:
                raise FileNotFoundError(f"results not found: {r}")
        runs = []
        for f in files:  # every result is checked (EMResult.load validates it) before the prior is loaded
            res = EMResult.load(f)
            if res.scene_name not in scenes:
                log.info("%s: no labelled scene named %r among --gt; skipped", f, res.scene_name)
                continue
            scene = scenes[res.scene_name]
            if scene.instance is None:
                raise ValueError(f"scene {scene.name!r} has no ground-truth `instance` labels")
            if res.num_points != scene.num_points:
                raise ValueError(f"{f} was computed on {res.num_points} points but the labelled scene "
                                 f"{scene_paths[scene.name]} has {scene.num_points}")
            res.bind(scene)
            runs.append((res, scene))
        if not runs:
            raise ValueError(f"no result among {len(files)} file(s) matches a labelled scene in --gt")
        prior = load_prior(self.prior)
        cal = calibrate_tau_out(runs, prior, candidates=self.candidates, class_names=self.classes,
                                tolerance=self.tolerance / 100.0)
        before = prior_category(prior).out_tau
        print(f"prior {self.prior!r}: tau_out calibrated on {len(runs)} scene(s): {', '.join(cal.scenes)}")
        print(cal.table())
        print(f"chosen tau_out {cal.best:g} (prior had {before:g})")
        if self.json_out is not None:
            from efem_viz.data.io import atomic_write_text

            atomic_write_text(self.json_out, json.dumps(cal.to_dict(), indent=2))
        if self.write:
            path = resolve_prior_path(self.prior)
            save_prior(prior, path, extra={METADATA_KEY: cal.best, f"{METADATA_KEY}_calibration": cal.to_dict()})
            print(f"wrote {METADATA_KEY}={cal.best:g} into {path}")
        return 0
