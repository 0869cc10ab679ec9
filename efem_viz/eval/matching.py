"""Ground truth and predictions for instance evaluation, their overlaps, and the ScanNet matching of §5.1–5.3.

Conventions (docs/design/efem-method.md §5): class ids are 1-based indices into `class_names` (a single mug prior gives
class 1); a ground-truth instance is evaluated only if it has a valid class and at least `min_region_size` points;
predictions with fewer points are dropped; all IoU comparisons are strict (`IoU > τ`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from efem_viz.prior.config import DEFAULT_PRIOR

MIN_REGION_SIZE = 100
"""Ground-truth instances and predictions with fewer points are not evaluated (§5.1, §5.2)."""
DEFAULT_CLASS_NAMES: tuple[str, ...] = (DEFAULT_PRIOR,)
"""Default evaluated classes: the shipped prior's category (id 1)."""


@dataclass(frozen=True)
class ScenePrediction:
    """Predicted instances of one scene.

    Attributes:
        name: scene name (matches `SceneGroundTruth.name`).
        masks: K masks over the scene's N points: (N,) bool arrays, or int index arrays into the points.
        confidences: (K,) float scores.
        labels: (K,) int class ids (1-based into the class names) or None (all class 1).
    """

    name: str
    masks: Sequence[np.ndarray]
    confidences: np.ndarray
    labels: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.masks)
        conf = np.asarray(self.confidences, dtype=np.float64).reshape(-1)
        if conf.shape[0] != k:
            raise ValueError(f"prediction {self.name!r}: {k} masks but {conf.shape[0]} confidences")
        if not np.isfinite(conf).all():
            raise ValueError(f"prediction {self.name!r}: confidences contain NaN or Inf")
        object.__setattr__(self, "confidences", conf)
        if self.labels is None:
            labels = np.ones(k, np.int64)
        else:
            labels = np.asarray(self.labels).reshape(-1)
            if labels.shape[0] != k:
                raise ValueError(f"prediction {self.name!r}: {k} masks but {labels.shape[0]} labels")
            if k and not np.issubdtype(labels.dtype, np.integer):
                raise ValueError(f"prediction {self.name!r}: labels must be integer class ids, got {labels.dtype}")
            labels = labels.astype(np.int64)
        object.__setattr__(self, "labels", labels)


@dataclass(frozen=True)
class SceneGroundTruth:
    """Ground truth of one scene.

    Attributes:
        name: scene name.
        instance: (N,) int instance id per point; 0 or negative = no instance.
        semantic: (N,) int class id per point (1-based into the class names, 0 = none) or None, in which case each
            instance's class comes from `categories` (instance id -> category name, looked up in the class names;
            an id without a category gets the first class; a category not in the class names is not evaluated).
        categories: instance id -> category name (used when `semantic` is None).
    """

    name: str
    instance: np.ndarray
    semantic: np.ndarray | None = None
    categories: Mapping[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        inst = np.asarray(self.instance)
        if inst.ndim != 1:
            raise ValueError(f"ground truth {self.name!r}: instance must be (N,), got {inst.shape}")
        if not np.issubdtype(inst.dtype, np.integer):
            raise ValueError(f"ground truth {self.name!r}: instance ids must be integers, got {inst.dtype}")
        object.__setattr__(self, "instance", inst.astype(np.int64))
        if self.semantic is not None:
            sem = np.asarray(self.semantic)
            if sem.shape != inst.shape:
                raise ValueError(f"ground truth {self.name!r}: semantic {sem.shape} vs instance {inst.shape}")
            object.__setattr__(self, "semantic", sem.astype(np.int64))

    @property
    def num_points(self) -> int:
        return int(self.instance.shape[0])

    @classmethod
    def from_scene(cls, scene: Any) -> "SceneGroundTruth":
        """From a `Scene` with `instance` labels (raises ValueError without them)."""
        if scene.instance is None:
            raise ValueError(f"scene {scene.name!r} has no ground-truth instance labels")
        return cls(name=scene.name, instance=scene.instance, categories=dict(scene.categories))


@dataclass(frozen=True)
class GTInstance:
    """One ground-truth instance of a scene."""

    id: int
    cls: int
    size: int
    evaluated: bool
    """True when its class is valid and size >= the minimum region size."""


@dataclass
class SceneOverlaps:
    """Sizes and intersections of one scene's predictions and GT instances (class-consistent pairs only).

    Attributes:
        gts: GT instances with a valid class, in ascending id order (the code order of §5.1 within a class).
        pred_index: indices (into the scene's prediction list) of the kept predictions, in prediction order.
        pred_cls, pred_size, pred_conf, pred_void: per kept prediction.
        inter: (P, G) int intersections (0 where the classes differ).
    """

    gts: list[GTInstance]
    pred_index: np.ndarray
    pred_cls: np.ndarray
    pred_size: np.ndarray
    pred_conf: np.ndarray
    pred_void: np.ndarray
    inter: np.ndarray

    def iou(self) -> np.ndarray:
        """(P, G) float IoU = |P∩G| / (|G| + |P| − |P∩G|)."""
        gsize = np.array([g.size for g in self.gts], dtype=np.float64)
        inter = self.inter.astype(np.float64)
        union = gsize[None, :] + self.pred_size[:, None].astype(np.float64) - inter
        return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def gt_classes(gt: SceneGroundTruth, class_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Instance ids (> 0) of a scene and their class ids (0 = not an evaluated class).

    Returns:
        `(ids (G,) int64 ascending, cls (G,) int64)`.
    """
    ids = np.unique(gt.instance)
    ids = ids[ids > 0]
    n_cls = len(class_names)
    if gt.semantic is not None:
        cls = np.zeros(len(ids), np.int64)
        for j, i in enumerate(ids):
            vals, counts = np.unique(gt.semantic[gt.instance == i], return_counts=True)
            cls[j] = vals[np.argmax(counts)]  # the instance's (majority) semantic class
    else:
        lookup = {name: k + 1 for k, name in enumerate(class_names)}
        cls = np.array(
            [lookup.get(gt.categories[int(i)], 0) if int(i) in gt.categories else 1 for i in ids], dtype=np.int64
        )
    cls[(cls < 1) | (cls > n_cls)] = 0
    return ids.astype(np.int64), cls


def bool_mask(m: np.ndarray, n: int, where: str) -> np.ndarray:
    a = np.asarray(m)
    if a.dtype == bool:
        if a.shape != (n,):
            raise ValueError(f"{where}: mask has shape {a.shape}, but the scene has {n} points")
        return a
    if a.ndim == 1 and (np.issubdtype(a.dtype, np.integer) or a.size == 0):
        if a.size and (a.min() < 0 or a.max() >= n):
            raise ValueError(f"{where}: mask indices out of range [0, {n}): [{a.min()}, {a.max()}]")
        b = np.zeros(n, bool)
        b[a.astype(np.int64)] = True
        return b
    raise ValueError(f"{where}: a mask must be an (N,) bool array or an int index array, got {a.dtype} {a.shape}")


def scene_overlaps(
    pred: ScenePrediction,
    gt: SceneGroundTruth,
    *,
    class_names: Sequence[str] = DEFAULT_CLASS_NAMES,
    min_region_size: int = MIN_REGION_SIZE,
) -> SceneOverlaps:
    """Filter one scene's GT and predictions (§5.1, §5.2) and intersect them.

    Raises:
        ValueError: a mask's length differs from the GT point count.
    """
    n = gt.num_points
    ids, cls = gt_classes(gt, class_names)
    valid = cls > 0
    gts = []
    sizes = np.bincount(np.searchsorted(ids, gt.instance[gt.instance > 0]), minlength=len(ids)) if len(ids) else []
    for i, c, s, v in zip(ids, cls, sizes, valid):
        if v:
            gts.append(GTInstance(id=int(i), cls=int(c), size=int(s), evaluated=bool(s >= min_region_size)))
    # per-point GT column (index into gts) or -1; and whether the point is void (no valid-class GT instance)
    point_col = np.full(n, -1, np.int64)
    if gts:
        lut_ids = np.array([g.id for g in gts])
        pos = np.searchsorted(lut_ids, gt.instance)
        pos_c = np.clip(pos, 0, len(lut_ids) - 1)
        hit = lut_ids[pos_c] == gt.instance
        point_col[hit] = pos_c[hit]
    if gt.semantic is not None:
        void_point = (gt.semantic < 1) | (gt.semantic > len(class_names))
    else:
        void_point = point_col < 0
    gcls = np.array([g.cls for g in gts], np.int64)
    keep_idx, p_cls, p_size, p_conf, p_void, rows = [], [], [], [], [], []
    for k, (m, c, conf) in enumerate(zip(pred.masks, pred.labels, pred.confidences)):  # type: ignore[arg-type]
        if c < 1 or c > len(class_names):
            continue
        b = bool_mask(m, n, f"prediction {k} of scene {pred.name!r}")
        size = int(b.sum())
        if size < min_region_size:
            continue
        cols = point_col[b]
        inter = np.bincount(cols[cols >= 0], minlength=len(gts)).astype(np.int64)
        inter[gcls != c] = 0
        keep_idx.append(k)
        p_cls.append(int(c))
        p_size.append(size)
        p_conf.append(float(conf))
        p_void.append(int(void_point[b].sum()))
        rows.append(inter)
    inter_mat = np.stack(rows) if rows else np.zeros((0, len(gts)), np.int64)
    return SceneOverlaps(
        gts=gts,
        pred_index=np.asarray(keep_idx, np.int64),
        pred_cls=np.asarray(p_cls, np.int64),
        pred_size=np.asarray(p_size, np.int64),
        pred_conf=np.asarray(p_conf, np.float64),
        pred_void=np.asarray(p_void, np.int64),
        inter=inter_mat.reshape(len(keep_idx), len(gts)),
    )


@dataclass
class ClassMatches:
    """The `(is_true, score)` entries and hard false negatives of one class at one IoU threshold (§5.3)."""

    y_true: list[bool] = field(default_factory=list)
    y_score: list[float] = field(default_factory=list)
    hard_fn: int = 0
    n_gt: int = 0
    n_pred: int = 0


def match_scene_class(
    ov: SceneOverlaps,
    cls: int,
    tau: float,
    acc: ClassMatches,
    *,
    min_region_size: int = MIN_REGION_SIZE,
    scannet_flag: bool = False,
) -> None:
    """Add one scene's entries for class `cls` at threshold `tau` to `acc` (§5.3, steps 1–2)."""
    iou = ov.iou()
    preds = np.flatnonzero(ov.pred_cls == cls)
    used = np.zeros(len(ov.pred_cls), bool)
    acc.n_pred += len(preds)
    for j, g in enumerate(ov.gts):
        if g.cls != cls or not g.evaluated:
            continue
        acc.n_gt += 1
        matched = False
        score = 0.0
        for p in preds:  # overlapping predictions, in prediction order
            if ov.inter[p, j] == 0 or used[p]:
                continue
            if iou[p, j] > tau:
                conf = float(ov.pred_conf[p])
                if matched:  # a duplicate: the lower of the two scores becomes a false positive
                    acc.y_true.append(False)
                    acc.y_score.append(min(score, conf))
                    score = max(score, conf)
                else:
                    matched = True
                    score = conf
                    used[p] = True
        if matched:
            acc.y_true.append(True)
            acc.y_score.append(score)
        else:
            acc.hard_fn += 1
    small = np.array([not g.evaluated for g in ov.gts], bool)
    for p in preds:
        overl = ov.inter[p] > 0
        if (iou[p][overl] > tau).any():
            continue  # handled in the GT loop (or overlaps only a small, unevaluated GT)
        if scannet_flag:
            ignore = ov.pred_void[p] + ov.inter[p][overl & small].sum()
            if ignore / ov.pred_size[p] > tau:
                continue
        acc.y_true.append(False)
        acc.y_score.append(float(ov.pred_conf[p]))


# ---------------------------------------------------------------------------------------------- viewer matching
@dataclass(frozen=True)
class MatchResult:
    """TP/FP/FN of one scene for colouring. Unpacks as `tp_pred, fp_pred, fn_gt = result`.

    Attributes:
        tp_pred: indices (into the given masks) of predictions matched to a GT instance.
        fp_pred: indices of predictions matched to none (including duplicates of a matched GT).
        fn_gt: GT instance ids without a matching prediction.
        pairs: `(pred index, gt id, IoU)` for each match.
    """

    tp_pred: list[int]
    fp_pred: list[int]
    fn_gt: list[int]
    pairs: list[tuple[int, int, float]]

    def __iter__(self) -> Iterator[list[int]]:
        return iter((self.tp_pred, self.fp_pred, self.fn_gt))


def match_instances(
    pred_masks: Sequence[np.ndarray],
    gt_instance: np.ndarray,
    *,
    iou: float = 0.5,
    confidences: np.ndarray | None = None,
    min_gt_size: int = 0,
) -> MatchResult:
    """Greedy one-to-one matching of predictions to GT instances at `IoU > iou` (class-agnostic), for colouring.

    Predictions are visited by descending confidence (in the given order without `confidences`); each takes the
    unmatched GT instance with which it has the largest IoU above the threshold.

    Args:
        pred_masks: K masks, (N,) bool arrays or int index arrays.
        gt_instance: (N,) int GT instance ids (0 / negative = none).
        iou: strict IoU threshold.
        confidences: (K,) scores or None.
        min_gt_size: GT instances with fewer points are neither matched nor counted as FN.

    Returns:
        MatchResult (iterates as `(tp_pred, fp_pred, fn_gt)`).
    """
    if gt_instance is None:
        raise ValueError("match_instances needs ground-truth instance labels (got None)")
    gt = np.asarray(gt_instance).astype(np.int64).reshape(-1)
    n = gt.shape[0]
    ids, counts = np.unique(gt[gt > 0], return_counts=True)
    keep = counts >= min_gt_size
    ids, counts = ids[keep], counts[keep]
    col = np.full(n, -1, np.int64)
    if len(ids):
        pos = np.clip(np.searchsorted(ids, gt), 0, len(ids) - 1)
        hit = ids[pos] == gt
        col[hit] = pos[hit]
    k = len(pred_masks)
    order = np.arange(k) if confidences is None else np.argsort(-np.asarray(confidences, float), kind="stable")
    taken = np.zeros(len(ids), bool)
    tp: list[int] = []
    fp: list[int] = []
    pairs: list[tuple[int, int, float]] = []
    for p in order:
        b = bool_mask(pred_masks[int(p)], n, f"prediction {p}")
        size = int(b.sum())
        c = col[b]
        inter = np.bincount(c[c >= 0], minlength=len(ids)).astype(np.float64)
        union = counts + size - inter
        ious = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
        ious[taken] = -1.0
        j = int(np.argmax(ious)) if len(ids) else -1
        if j >= 0 and ious[j] > iou:
            taken[j] = True
            tp.append(int(p))
            pairs.append((int(p), int(ids[j]), float(ious[j])))
        else:
            fp.append(int(p))
    return MatchResult(
        tp_pred=sorted(tp), fp_pred=sorted(fp), fn_gt=[int(i) for i in ids[~taken]], pairs=sorted(pairs)
    )
