"""Instance-segmentation evaluation as in EFEM's `standalone_eval_v2` (docs/design/efem-method.md §5): AP, AP50, AP25,
PR curves.

Public API: `evaluate(preds, gts) -> EvalResult`, `evaluate_scene(...)` and `evaluate_instances(...)` for one scene
(viewer), `match_instances(...)` for TP/FP/FN colouring, `average_precision` (§5.4), and the ScanNet prediction
layout (`load_scannet_predictions`, `write_scannet_predictions`). NumPy only: cheap to import.
"""

from __future__ import annotations

from efem_viz.eval.ap import (
    IOU_THRESHOLDS,
    EvalResult,
    average_precision,
    evaluate,
    evaluate_instances,
    evaluate_scene,
    prediction_from_instances,
)
from efem_viz.eval.matching import (
    DEFAULT_CLASS_NAMES,
    MIN_REGION_SIZE,
    MatchResult,
    SceneGroundTruth,
    ScenePrediction,
    match_instances,
)
from efem_viz.eval.scannet import load_scannet_predictions, write_scannet_predictions

__all__ = [
    "DEFAULT_CLASS_NAMES",
    "IOU_THRESHOLDS",
    "MIN_REGION_SIZE",
    "EvalResult",
    "MatchResult",
    "SceneGroundTruth",
    "ScenePrediction",
    "average_precision",
    "evaluate",
    "evaluate_instances",
    "evaluate_scene",
    "load_scannet_predictions",
    "match_instances",
    "prediction_from_instances",
    "write_scannet_predictions",
]
