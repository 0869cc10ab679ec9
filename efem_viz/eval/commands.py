"""`efem-viz evaluate`: AP / AP50 / AP25 of saved predictions against labelled scenes (efem-method.md §5)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

log = logging.getLogger(__name__)


@dataclass
class EvaluateArgs:
    """Score predictions (ScanNet layout, or `<scene>.efem.npz` results) against scenes with ground-truth labels."""

    results: Annotated[Path, tyro.conf.Positional]
    """Results folder: `<scene>.txt` + masks (ScanNet layout; also looked for in `scannet/`), or `*.efem.npz`."""
    gt: list[Path] = field(default_factory=list)
    """Labelled scene files (per-vertex `instance`) and/or folders of them; names must match the results."""
    classes: tuple[str, ...] = ("mug",)
    """Evaluated classes; class id k in the predictions is classes[k-1]."""
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
        import numpy as np
        from rich.console import Console
        from rich.table import Table

        from efem_viz.data.io import find_scenes, load_scene
        from efem_viz.data.scene import SceneError
        from efem_viz.eval.ap import evaluate
        from efem_viz.eval.matching import SceneGroundTruth, ScenePrediction
        from efem_viz.eval.scannet import load_scannet_predictions

        if not self.gt:
            raise SceneError("give the labelled scenes with --gt SCENE... (files or folders)")
        if self.json_out is not None:
            from efem_viz.cli import check_output_file

            check_output_file(self.json_out, option="--json-out")
        gts = []
        gt_paths: dict[str, Path] = {}
        for p in find_scenes(self.gt):
            scene = load_scene(p)
            if scene.instance is None:
                raise SceneError(f"{p} has no ground-truth `instance` labels")
            gts.append(SceneGroundTruth.from_scene(scene))
            gt_paths[scene.name] = p
        if not self.results.is_dir():
            raise SceneError(f"{self.results}: not a folder")
        efem_files = sorted(self.results.glob("*.efem.npz"))
        preds: list[ScenePrediction]
        # ScanNet layout only where a `<scene>.txt` names a labelled scene: a README/LICENSE .txt beside the
        # .efem.npz results (as in sample_scenes/) must not switch the reader
        gt_names = {g.name for g in gts}
        txt_stems = {t.stem for t in self.results.glob("*.txt")} | {t.stem for t in self.results.glob("scannet/*.txt")}
        if efem_files and not (txt_stems & gt_names):
            from efem_viz.em.results import EMResult
            from efem_viz.eval.ap import prediction_from_instances

            preds = []
            gt_points = {g.name: g.num_points for g in gts}
            for efem_file in efem_files:
                res = EMResult.load(efem_file)
                name = efem_file.name[: -len(".efem.npz")]
                if name in gt_points and res.num_points != gt_points[name]:
                    raise SceneError(f"{efem_file} was computed on {res.num_points} points but the ground-truth "
                                     f"scene {gt_paths[name]} has {gt_points[name]}")
                preds.append(prediction_from_instances(res.instances, name=name, class_names=self.classes))
        else:
            preds = load_scannet_predictions(self.results)
        if not preds:
            raise SceneError(f"{self.results}: no predictions found (<scene>.txt or <scene>.efem.npz)")
        for pred in preds:  # a NaN would sort anywhere and silently change the AP
            conf = np.asarray(pred.confidences, np.float64)
            if not np.isfinite(conf).all():
                raise SceneError(f"{self.results}: scene {pred.name!r} has a non-finite prediction confidence")
        if self.threshold > 0:
            preds = [
                ScenePrediction(
                    name=p.name,
                    masks=[p.masks[int(i)] for i in np.flatnonzero(p.confidences >= self.threshold)],
                    confidences=p.confidences[p.confidences >= self.threshold],
                    labels=None if p.labels is None else p.labels[p.confidences >= self.threshold],
                )
                for p in preds
            ]
        result = evaluate(preds, gts, class_names=self.classes, strict=self.strict, scannet_flag=self.scannet_flag)
        console = Console()
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
        console.print(table)
        if self.json_out is not None:
            from efem_viz.data.io import atomic_write_text

            atomic_write_text(self.json_out, json.dumps(result.to_dict(), indent=1))
            console.print(f"wrote {self.json_out}")
        return 0
