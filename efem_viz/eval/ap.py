"""Instance AP as in EFEM's `standalone_eval_v2` (docs/design/efem-method.md §5): AP (0.50:0.95), AP50, AP25, PR curves.

`average_precision` is the central-difference integration of §5.4, replicated exactly (including the tie handling
and the final (recall 0, precision 1) point); `evaluate` runs the filtering and matching of §5.1–5.3 per class and
IoU threshold and averages as in §5.5.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from efem_viz.em.results import confidence_mask
from efem_viz.eval.matching import (
    DEFAULT_CLASS_NAMES,
    MIN_REGION_SIZE,
    ClassMatches,
    SceneGroundTruth,
    SceneOverlaps,
    ScenePrediction,
    match_scene_class,
    scene_overlaps,
)

log = logging.getLogger(__name__)

IOU_THRESHOLDS: np.ndarray = np.append(np.arange(0.5, 0.95, 0.05), 0.25)
"""The ten IoU thresholds, exactly as the reference script builds them: 0.50, 0.55, …, 0.90, then 0.25."""
CONFIDENCE_DECIMALS = 4
"""The ScanNet export rounds confidences to 4 decimals; `evaluate` does the same by default for parity."""


def average_precision(
    y_true: Sequence[bool] | np.ndarray,
    y_score: Sequence[float] | np.ndarray,
    hard_fn: int,
) -> tuple[float, np.ndarray, np.ndarray]:
    """AP from `(is_true, score)` entries and the number of hard false negatives (§5.4).

    Args:
        y_true: (E,) bool, whether each entry is a true positive.
        y_score: (E,) float confidences.
        hard_fn: ground-truth instances matched by no prediction.

    Returns:
        `(ap, precision (U+1,), recall (U+1,))` with U distinct scores, ordered by ascending score threshold and
        ending with the point (recall 0, precision 1). `recall[0]` is the recall with all predictions.

    Raises:
        ValueError: lengths differ, or there are neither trues nor hard false negatives (no ground truth).
    """
    yt = np.asarray(y_true, dtype=bool).reshape(-1)
    ys = np.asarray(y_score, dtype=np.float64).reshape(-1)
    if yt.shape != ys.shape:
        raise ValueError(f"y_true {yt.shape} and y_score {ys.shape} differ in length")
    order = np.argsort(ys, kind="stable")
    ys, yt = ys[order], yt[order]
    cum = np.cumsum(yt.astype(np.int64))
    n = len(ys)
    total_true = int(cum[-1]) if n else 0
    if total_true + hard_fn == 0 and n:
        raise ValueError("average_precision needs at least one ground-truth instance (true entry or hard FN)")
    _, first = np.unique(ys, return_index=True)
    cum_prev = np.append(cum, 0)  # cum_prev[k - 1] with k = 0 reads the appended 0
    prec = np.zeros(len(first) + 1)
    rec = np.zeros(len(first) + 1)
    for i, k in enumerate(first):
        c = int(cum_prev[k - 1])
        tp = total_true - c
        fp = (n - k) - tp
        fn = c + hard_fn
        prec[i] = tp / (tp + fp)
        rec[i] = tp / (tp + fn)
    prec[-1] = 1.0
    rec[-1] = 0.0
    padded = np.concatenate([[rec[0]], rec, [0.0]])
    widths = 0.5 * (padded[:-2] - padded[2:])  # Δ_i = (r_{i-1} − r_{i+1}) / 2 with r_{-1} = r_0, r_{U+1} = 0
    return float(np.dot(prec, widths)), prec, rec


@dataclass
class EvalResult:
    """Instance-segmentation scores (docs/design/efem-method.md §5).

    Attributes:
        class_names: evaluated classes; class id k+1 is `class_names[k]`.
        thresholds: (T,) IoU thresholds (`IOU_THRESHOLDS`: 0.50 … 0.90, 0.25).
        ap_table: (C, T) AP per class and threshold (NaN: no ground truth of that class).
        recall_table: (C, T) recall with all predictions (`r_0`; NaN without ground truth or predictions).
        ap: NaN-mean of `ap_table` over classes and the nine thresholds 0.50–0.90.
        ap50: NaN-mean over classes at 0.50.
        ap25: NaN-mean over classes at 0.25.
        n_gt: (C,) evaluated GT instances per class.
        n_pred: (C,) kept predictions per class.
        pr: `(class name, τ rounded to 2 decimals) -> (precision, recall)` arrays of §5.4, every class/threshold
            with ground truth and predictions.
        scenes: names of the evaluated scenes.
    """

    class_names: tuple[str, ...]
    thresholds: np.ndarray
    ap_table: np.ndarray
    recall_table: np.ndarray
    ap: float
    ap50: float
    ap25: float
    n_gt: np.ndarray
    n_pred: np.ndarray
    pr: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    scenes: list[str] = field(default_factory=list)

    def _col(self, tau: float) -> int:
        return int(np.flatnonzero(np.isclose(self.thresholds, tau))[0])

    @property
    def pr_curves(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """PR curves for plotting at IoU 0.25, 0.50 and 0.75: `"<class> @ IoU 0.50" -> (recall, precision)`."""
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for tau in (0.25, 0.5, 0.75):
            for name in self.class_names:
                key = (name, round(tau, 2))
                if key in self.pr:
                    prec, rec = self.pr[key]
                    out[f"{name} @ IoU {tau:.2f}"] = (rec, prec)
        return out

    def per_class(self) -> dict[str, dict[str, float]]:
        """`class -> {ap, ap50, ap25, rc50, rc25, n_gt, n_pred}`."""
        main = ~np.isclose(self.thresholds, 0.25)
        i50, i25 = self._col(0.5), self._col(0.25)
        out = {}
        for c, name in enumerate(self.class_names):
            out[name] = {
                "ap": _nanmean(self.ap_table[c, main]),
                "ap50": float(self.ap_table[c, i50]),
                "ap25": float(self.ap_table[c, i25]),
                "rc50": float(self.recall_table[c, i50]),
                "rc25": float(self.recall_table[c, i25]),
                "n_gt": int(self.n_gt[c]),
                "n_pred": int(self.n_pred[c]),
            }
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (NaN written as None)."""

        def clean(v: Any) -> Any:
            if isinstance(v, float):
                return None if not np.isfinite(v) else v
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, list):
                return [clean(x) for x in v]
            return v

        return clean(
            {
                "ap": float(self.ap),
                "ap50": float(self.ap50),
                "ap25": float(self.ap25),
                "classes": list(self.class_names),
                "thresholds": [round(float(t), 2) for t in self.thresholds],
                "ap_table": [[float(x) for x in row] for row in self.ap_table],
                "recall_table": [[float(x) for x in row] for row in self.recall_table],
                "per_class": self.per_class(),
                "scenes": list(self.scenes),
                "pr": {
                    f"{name}@{tau:.2f}": {"precision": [float(x) for x in p], "recall": [float(x) for x in r]}
                    for (name, tau), (p, r) in self.pr.items()
                },
            }
        )


def _nanmean(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0 or np.isnan(a).all():
        return float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmean(a))


def evaluate(
    preds: Sequence[ScenePrediction],
    gts: Sequence[SceneGroundTruth],
    *,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    min_region_size: int = MIN_REGION_SIZE,
    scannet_flag: bool = False,
    strict: bool = True,
    decimals: int | None = CONFIDENCE_DECIMALS,
) -> EvalResult:
    """Instance AP over scenes, as in `standalone_eval_v2` (docs/design/efem-method.md §5).

    Args:
        preds: predictions per scene.
        gts: ground truth per scene (scenes are evaluated in name order).
        class_names: the evaluated classes (class id k+1 = `class_names[k]`).
        min_region_size: minimum points of an evaluated GT instance and of a kept prediction (100).
        scannet_flag: ignore unmatched predictions whose void + small-GT fraction exceeds τ (ScanNet only).
        strict: require predictions for exactly the GT scenes; otherwise a GT scene without predictions counts as
            having none and predictions for unknown scenes are ignored (with a warning).
        decimals: round confidences to this many decimals first (the ScanNet export does; None = keep).

    Returns:
        EvalResult.

    Raises:
        ValueError: duplicate scene names, scene lists differ (strict), mask lengths differ from the GT.
    """
    names = tuple(str(c) for c in class_names)
    if not names:
        raise ValueError("class_names is empty")
    gt_by = {g.name: g for g in gts}
    pred_by = {p.name: p for p in preds}
    if len(gt_by) != len(gts) or len(pred_by) != len(preds):
        raise ValueError("scene names must be unique in both the predictions and the ground truth")
    if strict and sorted(gt_by) != sorted(pred_by):
        missing = sorted(set(gt_by) - set(pred_by))
        extra = sorted(set(pred_by) - set(gt_by))
        raise ValueError(
            f"predicted scenes differ from the ground-truth scenes (missing predictions: {missing[:10]}, "
            f"predictions without ground truth: {extra[:10]}); pass strict=False to evaluate the overlap"
        )
    extra = sorted(set(pred_by) - set(gt_by))
    if extra:
        log.warning("ignoring predictions for %d scenes without ground truth: %s", len(extra), extra[:10])
    overlaps = {
        name: overlaps_of(pred_by.get(name), gt_by[name], class_names=names, min_region_size=min_region_size,
                          decimals=decimals)
        for name in sorted(gt_by)
    }
    return evaluate_overlaps(overlaps, class_names=names, min_region_size=min_region_size,
                             scannet_flag=scannet_flag)


def overlaps_of(
    pred: ScenePrediction | None,
    gt: SceneGroundTruth,
    *,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    min_region_size: int = MIN_REGION_SIZE,
    decimals: int | None = CONFIDENCE_DECIMALS,
) -> SceneOverlaps:
    """The overlaps of one scene's predictions (None = it has none) with its ground truth: everything AP needs of
    the scene, a few numbers per instance pair, so large datasets are scored one scene at a time
    (`evaluate_overlaps`).

    Raises:
        ValueError: mask lengths differ from the GT.
    """
    p = pred or ScenePrediction(name=gt.name, masks=[], confidences=np.zeros(0))
    if decimals is not None:
        p = ScenePrediction(name=p.name, masks=p.masks, confidences=np.round(p.confidences, decimals), labels=p.labels)
    return scene_overlaps(p, gt, class_names=tuple(str(c) for c in class_names), min_region_size=min_region_size)


def evaluate_overlaps(
    overlaps: Mapping[str, SceneOverlaps],
    *,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    min_region_size: int = MIN_REGION_SIZE,
    scannet_flag: bool = False,
) -> EvalResult:
    """Instance AP from per-scene overlaps (`overlaps_of`), scenes taken in name order: `evaluate` without the
    masks, so that a folder of any size is scored in the memory of one scene.

    Args:
        overlaps: scene name → its overlaps, computed with the same `class_names` and `min_region_size`.
        class_names: the evaluated classes.
        min_region_size: as in `evaluate`.
        scannet_flag: as in `evaluate`.
    """
    names = tuple(str(c) for c in class_names)
    if not names:
        raise ValueError("class_names is empty")
    ordered = [overlaps[k] for k in sorted(overlaps)]
    C, T = len(names), len(IOU_THRESHOLDS)
    ap_table = np.full((C, T), np.nan)
    rc_table = np.full((C, T), np.nan)
    n_gt = np.zeros(C, np.int64)
    n_pred = np.zeros(C, np.int64)
    pr: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}
    for t, tau in enumerate(IOU_THRESHOLDS):
        for c in range(C):
            acc = ClassMatches()
            for ov in ordered:
                match_scene_class(
                    ov, c + 1, float(tau), acc, min_region_size=min_region_size, scannet_flag=scannet_flag
                )
            n_gt[c], n_pred[c] = acc.n_gt, acc.n_pred
            if acc.n_gt == 0:
                continue  # AP = NaN
            if acc.n_pred == 0:
                ap_table[c, t] = 0.0
                continue
            ap, prec, rec = average_precision(acc.y_true, acc.y_score, acc.hard_fn)
            ap_table[c, t] = ap
            rc_table[c, t] = rec[0]
            pr[(names[c], round(float(tau), 2))] = (prec, rec)
    main = ~np.isclose(IOU_THRESHOLDS, 0.25)
    return EvalResult(
        class_names=names,
        thresholds=IOU_THRESHOLDS.copy(),
        ap_table=ap_table,
        recall_table=rc_table,
        ap=_nanmean(ap_table[:, main]),
        ap50=_nanmean(ap_table[:, np.isclose(IOU_THRESHOLDS, 0.5)]),
        ap25=_nanmean(ap_table[:, np.isclose(IOU_THRESHOLDS, 0.25)]),
        n_gt=n_gt,
        n_pred=n_pred,
        pr=pr,
        scenes=sorted(overlaps),
    )


def evaluate_scene(
    pred_masks: Sequence[np.ndarray],
    confidences: np.ndarray | Sequence[float],
    gt_instance: np.ndarray,
    *,
    threshold: float = 0.0,
    labels: np.ndarray | None = None,
    gt_categories: dict[int, str] | None = None,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    name: str = "scene",
    min_region_size: int = MIN_REGION_SIZE,
    decimals: int | None = CONFIDENCE_DECIMALS,
) -> EvalResult:
    """AP of one scene's predictions (for the viewer); predictions with confidence below `threshold` are dropped.

    Args:
        pred_masks: K masks, (N,) bool or int index arrays.
        confidences: (K,) scores.
        gt_instance: (N,) int GT instance ids (0 = none).
        threshold: drop predictions with confidence < threshold.
        labels: (K,) class ids (default: all 1).
        gt_categories: GT instance id -> category name (default: every instance is class 1).
        class_names: evaluated classes.
        name: scene name (for messages).
        min_region_size: as in `evaluate`.
        decimals: as in `evaluate`.
    """
    conf = np.asarray(confidences, dtype=np.float64).reshape(-1)
    if len(conf) != len(pred_masks):
        raise ValueError(f"{len(pred_masks)} masks but {len(conf)} confidences")
    keep = np.flatnonzero(confidence_mask(conf, threshold))
    lab = None if labels is None else np.asarray(labels).reshape(-1)[keep]
    pred = ScenePrediction(name=name, masks=[pred_masks[int(i)] for i in keep], confidences=conf[keep],
                           labels=lab)
    gt = SceneGroundTruth(name=name, instance=np.asarray(gt_instance), categories=dict(gt_categories or {}))
    return evaluate([pred], [gt], class_names=class_names, min_region_size=min_region_size, decimals=decimals)


def prediction_from_instances(
    instances: Any,
    *,
    name: str,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    threshold: float = 0.0,
) -> ScenePrediction:
    """A ScenePrediction from an `efem_viz.em.Instances` (index masks, `confidence`, `category` names).

    Categories not in `class_names` get class 0 and are not evaluated; with one class every instance is class 1.
    """
    conf = np.asarray(instances.confidence, dtype=np.float64).reshape(-1)
    keep = np.flatnonzero(confidence_mask(conf, threshold))
    cats = np.asarray(getattr(instances, "category", np.array([], dtype=str)))
    lookup = {n: k + 1 for k, n in enumerate(class_names)}
    if len(class_names) == 1:
        labels = np.ones(len(keep), np.int64)
    else:
        labels = np.array([lookup.get(str(cats[i]), 0) for i in keep], np.int64)
    return ScenePrediction(
        name=name, masks=[np.asarray(instances.masks[i]) for i in keep], confidences=conf[keep], labels=labels
    )


def evaluate_instances(
    instances: Any,
    scene: Any,
    threshold: float = 0.0,
    *,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
) -> EvalResult:
    """AP of an EFEM result's `Instances` against a `Scene`'s ground truth (viewer), above a confidence threshold.

    Raises:
        ValueError: the scene has no ground-truth labels.
    """
    pred = prediction_from_instances(instances, name=scene.name, class_names=class_names, threshold=threshold)
    gt = SceneGroundTruth.from_scene(scene)
    return evaluate([pred], [gt], class_names=class_names)
