"""Comparing one scene's predicted instances with its ground truth at a confidence threshold, for display: the
TP / FP / FN split (IoU 0.5), AP / AP50 / AP25, the PR curves and each shown prediction's IoU (`gt_metrics`; the
viewer's colours, panel and instance table read it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from efem_viz.eval.ap import evaluate_instances
from efem_viz.eval.matching import DEFAULT_CLASS_NAMES, match_instances

@dataclass(frozen=True)
class GTMetrics:
    """Ground-truth comparison of the instances at a threshold (for colours and the panel)."""

    masks: list[np.ndarray]
    """Index arrays of the shown predictions."""
    tp: list[int]
    fp: list[int]
    fn: list[int]
    ap: float
    ap50: float
    ap25: float
    curves: list[tuple[str, np.ndarray, np.ndarray]]
    point: tuple[float, float] | None
    """(recall, precision) at IoU 0.5 of the shown predictions."""
    ious: tuple[float, ...] = ()
    """Per shown prediction (as `masks`): IoU with its matched ground-truth object for a TP, the best IoU with
    any ground-truth object for an FP (0 when it touches none)."""
    per_class: tuple[tuple[str, float, int], ...] = ()
    """(class, AP50, ground-truth objects) of each class of a scene with several (a family prior's scene: the
    instance's named member must match the object's category); empty for one class."""


def best_ious(pred_masks: Sequence[np.ndarray], gt_instance: np.ndarray) -> np.ndarray:
    """(K,) float64: each prediction's largest IoU with any ground-truth object (0 when it touches none).

    Args:
        pred_masks: K index arrays of scene points.
        gt_instance: (N,) int ground-truth instance ids (0 / negative = background).
    """
    gt = np.asarray(gt_instance).astype(np.int64).reshape(-1)
    ids, counts = np.unique(gt[gt > 0], return_counts=True)
    out = np.zeros(len(pred_masks))
    if not len(ids):
        return out
    col = np.searchsorted(ids, gt)
    col[gt <= 0] = -1
    for k, m in enumerate(pred_masks):
        m = np.unique(np.asarray(m, np.int64))
        c = col[m]
        inter = np.bincount(c[c >= 0], minlength=len(ids)).astype(np.float64)
        out[k] = float(np.max(inter / (counts + m.size - inter)))
    return out


def gt_metrics(instances: Any, scene: Any, threshold: float) -> GTMetrics:
    """Match the instances above `threshold` to the scene's ground truth at IoU 0.5 and compute AP/AP50/AP25.

    Evaluated classes are the scene's ground-truth category names (one class: every prediction counts as it).
    """
    shown = instances.above(float(threshold))
    masks = [np.asarray(m, np.int64) for m in shown.masks]
    matched = match_instances(masks, scene.instance, iou=0.5, confidences=np.asarray(shown.confidence))
    tp, fp, fn = matched
    cats = sorted({str(v) for v in dict(scene.categories).values()})
    class_names = tuple(cats) if cats else DEFAULT_CLASS_NAMES
    res = evaluate_instances(instances, scene, threshold=float(threshold), class_names=class_names)
    n_gt = len(scene.instance_ids())
    point = (len(tp) / max(n_gt, 1), len(tp) / len(masks)) if masks else None
    ious = best_ious(masks, scene.instance)
    for k, _gt_id, iou in getattr(matched, "pairs", ()):
        ious[int(k)] = float(iou)  # a TP: the IoU of its match
    return GTMetrics(
        masks=masks,
        tp=[int(i) for i in tp],
        fp=[int(i) for i in fp],
        fn=[int(i) for i in fn],
        ap=float(res.ap),
        ap50=float(res.ap50),
        ap25=float(res.ap25),
        curves=_pr_curves(res),
        point=point,
        ious=tuple(float(v) for v in ious),
        per_class=tuple((name, float(v["ap50"]), int(v["n_gt"])) for name, v in res.per_class().items())
        if len(class_names) > 1 else (),
    )


def _pr_curves(res: Any) -> list[tuple[str, np.ndarray, np.ndarray]]:
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    curves = getattr(res, "pr_curves", None) or {}
    for key, curve in dict(curves).items():
        rec, prec = curve
        out.append((str(key), np.asarray(rec, float), np.asarray(prec, float)))
    return out
