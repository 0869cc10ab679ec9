"""Viewer state and the pure functions the viewer's callbacks use (no viser here).

The GUI callbacks in `app.py` read handle values into a `ViewerState`, submit heavy work to a worker thread and
redraw through the `draw_*` functions of `nodes.py`. Everything in this module is plain NumPy so that it can be
tested without a server: scene discovery (restricted to the given paths), colour maps, the timeline marks and the
top-N choice of proposals to draw.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from efem_viz import colors
from efem_viz.data.io import RESULT_SUFFIX, find_scenes

logger = logging.getLogger(__name__)

LABELS_INFIX = ".labels"
"""`<scene>.labels.ply` is an annotated copy of `<scene>.ply` (annotator output) and may share its result."""
SEG_INFIX = ".seg"
"""`<scene>.seg.ply` is `efem-viz segment`'s coloured copy of `<scene>` and shares its result."""

ColorMode = Literal["rgb", "instances", "gt_match", "weights", "proposals"]
DisplayMode = Literal["points", "mesh"]
ViewMode = Literal["step", "result"]
"""What the 3-D view shows of a result: one EM step (its decoded shapes and samples) or the final instances."""

# Colours for the ground-truth comparison (uint8 RGB).
TP_COLOR = np.array([46, 180, 80], np.uint8)
FP_COLOR = np.array([220, 50, 47], np.uint8)
FN_COLOR = np.array([38, 110, 230], np.uint8)
BACKGROUND_COLOR = np.array([200, 200, 200], np.uint8)
DEAD_COLOR = np.array([230, 30, 30], np.uint8)

DEFAULT_CONFIDENCE_CUT = 0.05
"""The confidence threshold a viewer starts with: instances below it are hidden (on real scans EM keeps many
near-zero-confidence instances that cover the view and say nothing). The Results tab says how many it hides; the
slider at 0 shows them all."""


# ---------------------------------------------------------------------------------------------- scene discovery
@dataclass(frozen=True)
class SceneEntry:
    """One scene file the browser may open.

    Attributes:
        name: unique display name (file stem, with the parent folder added when stems collide).
        path: resolved absolute path, guaranteed to lie inside one of the roots given to `discover_scenes`.
        root: the resolved root (file or folder) it was found under.
    """

    name: str
    path: Path
    root: Path
    result_dirs: tuple[Path, ...] = ()
    """Folders of saved results (`efem-viz view --results DIR`, e.g. a `segment --out` folder) searched after the
    scene's own folder."""

    @property
    def trace_path(self) -> Path:
        """The saved result to open with this scene, looked up when asked (a result written meanwhile is found):
        `<scene>.efem.npz` next to it, then in each results folder; for an annotated copy `<base>.labels.ply` or a
        `segment` output `<base>.seg.ply`, the result of `<base>` (same points). When none exists, the path next
        to the scene (where a run would be saved)."""
        stem = self.path.name[: -len(self.path.suffix)] if self.path.suffix else self.path.name
        stems = [stem] + [stem[: -len(infix)] for infix in (LABELS_INFIX, SEG_INFIX) if stem.endswith(infix)]
        folders = [self.path.parent, *self.result_dirs]
        for base in stems:
            for d in folders:
                cand = d / (base + RESULT_SUFFIX)
                if cand.is_file():
                    return cand
        return trace_path_for(self.path)


def trace_path_for(scene_path: Path) -> Path:
    """Path of the saved EM result of a scene: `<dir>/<stem>.efem.npz`.

    Args:
        scene_path: a scene file such as `sample_scenes/mugs_01.ply`.
    """
    name = scene_path.name
    if name.endswith(RESULT_SUFFIX):
        return scene_path
    return scene_path.with_name(scene_path.stem + RESULT_SUFFIX)


def is_inside(path: Path, roots: Sequence[Path]) -> bool:
    """True when `path` (resolved, symlinks followed) is one of `roots` or lies below a root folder."""
    try:
        rp = path.resolve(strict=False)
    except OSError:
        return False
    for r in roots:
        if rp == r or (r.is_dir() and rp.is_relative_to(r)):
            return True
    return False


def discover_scenes(
    paths: Sequence[str | os.PathLike[str]],
    *,
    recursive: bool = False,
    result_dirs: Sequence[str | os.PathLike[str]] = (),
) -> list[SceneEntry]:
    """List the scene files given directly or found inside the given folders.

    The folders are walked by `efem_viz.data.io.find_scenes` (the CLI's walk: same files, same errors). Only
    files inside the given paths are returned (symlinks are resolved and anything that points outside is
    dropped), so the viewer never opens a file the user did not hand it.

    Args:
        paths: scene files and/or folders.
        recursive: also search sub-folders of the given folders (default: only the folder itself).
        result_dirs: folders of saved results to look in for each scene's `<scene>.efem.npz`.

    Returns:
        Entries sorted by name, with unique names.

    Raises:
        FileNotFoundError: a results folder or a given path does not exist (for a scene path the
            `efem_viz.data.io.ScenePathNotFoundError`, also a `SceneError`).
        SceneError: a file given explicitly is not a scene file (an EFEM result, an unknown suffix).
    """
    rdirs: list[Path] = []
    for d in result_dirs:
        dd = Path(d).expanduser()
        if not dd.is_dir():
            raise FileNotFoundError(f"results folder does not exist: {dd}")
        rdirs.append(dd.resolve())
    given = [Path(p).expanduser() for p in paths]
    roots = [g.resolve() for g in given]
    found: list[tuple[Path, Path]] = []
    seen: set[Path] = set()
    for g, root in zip(given, roots):
        for c in find_scenes(g, recursive=recursive):
            rc = c.resolve()
            if rc in seen or not is_inside(rc, roots):
                continue
            seen.add(rc)
            found.append((rc, root))
    stems: dict[str, int] = {}
    for rc, _ in found:
        stems[rc.stem] = stems.get(rc.stem, 0) + 1
    entries: list[SceneEntry] = []
    used: set[str] = set()
    for rc, root in found:
        name = rc.stem if stems[rc.stem] == 1 else f"{rc.parent.name}/{rc.stem}"
        base, k = name, 2
        while name in used:
            name = f"{base} ({k})"
            k += 1
        used.add(name)
        entries.append(SceneEntry(name=name, path=rc, root=root, result_dirs=tuple(rdirs)))
    entries.sort(key=lambda e: e.name)
    return entries


# ---------------------------------------------------------------------------------------------- colours
HEAT_STOPS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
"""Positions of the `heatmap` ramp's colours (`HEAT_RGB`) in [0, 1]."""
HEAT_RGB = np.array(
    [[48, 18, 59], [40, 130, 240], [60, 220, 120], [250, 185, 40], [180, 20, 20]], dtype=np.float64
)  # turbo-like: dark blue -> blue -> green -> orange -> red


def heatmap(values: np.ndarray, *, vmin: float = 0.0, vmax: float | None = None) -> np.ndarray:
    """Map scalars to a perceptual blue-to-red colour ramp.

    Args:
        values: (N,) float; NaN maps to the background grey.
        vmin: value mapped to the cold end.
        vmax: value mapped to the hot end (default: max of finite values, at least vmin + 1e-12).

    Returns:
        (N, 3) uint8 RGB.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    finite = np.isfinite(v)
    hi = float(v[finite].max()) if vmax is None and finite.any() else (vmax if vmax is not None else 1.0)
    hi = max(hi, vmin + 1e-12)
    x = np.clip((np.where(finite, v, vmin) - vmin) / (hi - vmin), 0.0, 1.0)
    out = np.stack([np.interp(x, HEAT_STOPS, HEAT_RGB[:, c]) for c in range(3)], axis=1)
    out = np.round(out).astype(np.uint8)
    out[~finite] = BACKGROUND_COLOR
    return out


def weights_colors(base: np.ndarray, weights: np.ndarray, *, floor: float = 1e-3) -> np.ndarray:
    """Colour a scene by a proposal's weights: heat map where weight > floor, dimmed scene colours elsewhere.

    Args:
        base: (N, 3) uint8 scene colours.
        weights: (N,) float weights in [0, 1] over the scene (0 outside the proposal's neighbourhood).
        floor: weights at or below this show the dimmed base colour.

    Returns:
        (N, 3) uint8.
    """
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape[0] != base.shape[0]:
        raise ValueError(f"weights have shape {w.shape}, scene colours {base.shape}")
    out = dim(base)
    hot = np.isfinite(w) & (w > floor)
    if hot.any():
        out[hot] = heatmap(w[hot], vmin=0.0, vmax=max(1.0, float(w[hot].max())) if w[hot].max() > 1 else 1.0)
    return out


def dim(base: np.ndarray, *, amount: float = 0.55) -> np.ndarray:
    """(N, 3) uint8 grey shades of the scene colours (their luminance, blended toward light grey), so that
    overlays stand out and no scan colour can read as a prediction's colour; the shading of the scan stays."""
    b = np.asarray(base).astype(np.float32).reshape(-1, 3)
    lum = b @ np.array([0.299, 0.587, 0.114], np.float32)
    grey = np.round(lum * (1 - amount) + 215.0 * amount).astype(np.uint8)
    return np.repeat(grey[:, None], 3, axis=1)


def label_colors(base: np.ndarray, labels: np.ndarray, *, ids_to_color: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """Colour points by integer labels (0 = none keeps the dimmed base colour).

    Args:
        base: (N, 3) uint8 scene colours.
        labels: (N,) int labels, 0 = unassigned.
        ids_to_color: optional fixed colour per label id (else `efem_viz.colors.instance_colors` of the id).

    Returns:
        (N, 3) uint8.
    """
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != base.shape[0]:
        raise ValueError(f"labels have shape {lab.shape}, scene colours {base.shape}")
    out = dim(base)
    ids = np.unique(lab[lab > 0])
    if ids.size:
        cols = colors.instance_colors(ids) if ids_to_color is None else np.stack([ids_to_color[int(i)] for i in ids])
        lut_idx = np.searchsorted(ids, lab)
        mask = lab > 0
        out[mask] = cols[lut_idx[mask]]
    return out


def instance_colors(base: np.ndarray, instances: Any, keep: np.ndarray) -> np.ndarray:
    """Colour the points of the kept instances, each with `efem_viz.colors.instance_colors` of its proposal id
    (the colour of its mesh, box and legend swatch, of the coloured PLY export and of the annotator's EFEM import).

    Args:
        base: (N, 3) uint8 scene colours.
        instances: `efem_viz.em.Instances` (ids (K,), masks, confidence; overlaps: higher confidence wins).
        keep: (K,) bool, the instances shown (confidence ≥ threshold).

    Returns:
        (N, 3) uint8.
    """
    shown = instances.select(np.asarray(keep, bool))
    labels = shown.label_array(base.shape[0])  # k + 1 for the k-th shown instance
    cols = colors.instance_colors(np.asarray(shown.ids))
    return label_colors(base, labels, ids_to_color={k + 1: cols[k] for k in range(len(cols))})


def gt_match_colors(
    base: np.ndarray,
    pred_masks: Sequence[np.ndarray],
    gt_instance: np.ndarray,
    *,
    tp: Sequence[int],
    fp: Sequence[int],
    fn: Sequence[int],
) -> np.ndarray:
    """TP / FP / FN colouring: FN ground-truth objects blue, FP predictions red, TP predictions green.

    Args:
        base: (N, 3) uint8 scene colours.
        pred_masks: K index arrays (or (N,) bool masks) of the shown predictions.
        gt_instance: (N,) int ground-truth instance ids (0 = background).
        tp: indices into `pred_masks` that matched a ground-truth object.
        fp: indices into `pred_masks` that matched none.
        fn: ground-truth instance ids that no prediction matched.

    Returns:
        (N, 3) uint8.
    """
    out = dim(base)
    gt = np.asarray(gt_instance).reshape(-1)
    for g in fn:
        out[gt == int(g)] = FN_COLOR
    for k in fp:
        out[np.asarray(pred_masks[int(k)])] = FP_COLOR
    for k in tp:
        out[np.asarray(pred_masks[int(k)])] = TP_COLOR
    return out


def hex_color(rgb: np.ndarray | Sequence[int]) -> str:
    """'#rrggbb' for a uint8 RGB triple."""
    r, g, b = (int(c) for c in np.asarray(rgb).reshape(3))
    return f"#{r:02x}{g:02x}{b:02x}"


def rgb_tuple(rgb: np.ndarray | Sequence[int]) -> tuple[int, int, int]:
    """A uint8 RGB colour as the int triple viser's `color` arguments take."""
    r, g, b = (int(c) for c in rgb)
    return r, g, b


# ---------------------------------------------------------------------------------------------- timeline
@dataclass(frozen=True)
class PhaseMark:
    """A labelled step on the timeline (phase start or end-of-phase review)."""

    step: int
    label: str


def phase_marks(phase: np.ndarray) -> list[PhaseMark]:
    """Timeline marks from the per-step phase array.

    Args:
        phase: (T,) int phase (1 or 2, possibly with episodes repeating the pattern) of each EM step.

    Returns:
        A mark at step 0 ("P1"), at each phase change ("P<phase>") and a review mark ("R") at the last step of
        every phase run (the review runs after that step).
    """
    ph = np.asarray(phase).reshape(-1)
    marks: list[PhaseMark] = []
    if ph.size == 0:
        return marks
    marks.append(PhaseMark(0, f"P{int(ph[0])}"))
    for t in range(1, ph.size):
        if ph[t] != ph[t - 1]:
            marks.append(PhaseMark(t - 1, "R"))
            marks.append(PhaseMark(t, f"P{int(ph[t])}"))
    marks.append(PhaseMark(int(ph.size - 1), "R"))
    # Merge marks that fall on the same step: "R|P2".
    merged: dict[int, str] = {}
    for m in marks:
        merged[m.step] = f"{merged[m.step]}|{m.label}" if m.step in merged else m.label
    return [PhaseMark(s, lab) for s, lab in sorted(merged.items())]


def top_n(ids: np.ndarray, scores: np.ndarray, n: int) -> np.ndarray:
    """The `n` ids with the highest scores (ties broken by id), in descending score order.

    Args:
        ids: (K,) int proposal ids.
        scores: (K,) float scores (NaN counts as lowest).
        n: how many to keep (<= 0 keeps none).
    """
    ids_arr = np.asarray(ids).reshape(-1)
    sc = np.asarray(scores, dtype=np.float64).reshape(-1)
    if ids_arr.shape != sc.shape:
        raise ValueError(f"ids {ids_arr.shape} and scores {sc.shape} differ in shape")
    if n <= 0 or ids_arr.size == 0:
        return ids_arr[:0]
    sc = np.where(np.isfinite(sc), sc, -np.inf)
    order = np.lexsort((ids_arr, -sc))
    return ids_arr[order[:n]]


# ---------------------------------------------------------------------------------------------- the state
@dataclass
class ViewerState:
    """Everything the viewer shows, as plain values (GUI handles are read into this, never the reverse).

    One state per server: every connected browser sees the same scene, step, threshold and selection (shared
    GUI), so a demo audience and the presenter stay in sync.
    """

    entries: list[SceneEntry] = field(default_factory=list)
    """Scenes the browser lists (only inside the given paths)."""
    scene_name: str | None = None
    """Name of the open scene (an `entries` name)."""
    scene: Any = None
    """The open `efem_viz.data.scene.Scene`, or None."""
    result: Any = None
    """The `EMResult` of the open scene (loaded or computed), or None."""
    result_source: str = ""
    """Where `result` came from: a file path, or 'run (seed=..)'."""
    step: int = 0
    """Current EM step on the timeline (0 .. num_steps-1)."""
    view_mode: ViewMode = "result"
    """"step": only step `step` (decoded shapes, samples; points in scene colours unless a proposal's weights);
    "result": only the final instances (meshes, boxes, labels, instance or TP/FP/FN colours). Moving the
    timeline shows a step; the threshold, the result layers and the instance colours show the result."""
    playing: bool = False
    speed: float = 2.0
    """Playback speed in steps per second."""
    selected: int | None = None
    """Inspected proposal id, or None."""
    max_shapes: int = 8
    """Draw decoded shapes for at most this many live proposals (top by stationary score)."""
    show_shapes: bool = True
    show_samples: bool = True
    threshold: float = DEFAULT_CONFIDENCE_CUT
    """Confidence threshold on the final instances (a view, not a re-run)."""
    hidden: set[int] = field(default_factory=set)
    """Proposal ids of final instances hidden by hand (the instance table's *Visible* box): a view, like the
    threshold; the metrics and exports follow the threshold only."""
    table_row: int | None = None
    """Proposal id of the instance chosen in the instance table (None: none yet)."""
    display: DisplayMode = "points"
    color_mode: ColorMode = "rgb"
    point_size: float = 0.004
    show_meshes: bool = True
    show_obbs: bool = True
    show_axes: bool = False
    running: bool = False
    """EM is running in the worker."""
    progress: float = 0.0
    """0-100."""
    status: str = ""
    """Last status / error line shown in the GUI."""
    error: str | None = None
    """Last error (scene failed to load, run failed...)."""

    @property
    def num_steps(self) -> int:
        """Number of EM steps in the current trace (0 without a result)."""
        if self.result is None:
            return 0
        return int(self.result.trace.num_steps)

    def entry(self, name: str) -> SceneEntry:
        """The entry of a scene name; KeyError with the known names otherwise."""
        for e in self.entries:
            if e.name == name:
                return e
        raise KeyError(f"unknown scene {name!r}; known: {[e.name for e in self.entries]}")


# ---------------------------------------------------------------------------------------------- trace access
@dataclass(frozen=True)
class Death:
    """A terminated proposal: id, step, reason ("proposal too small", "duplicated or included", ...), partner."""

    pid: int
    step: int
    reason: str
    partner: int | None = None
    ratio: float | None = None


def alive_table(trace: Any, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Proposals taking part in a step (live at its start) and their stationary scores.

    Args:
        trace: an `efem_viz.em.EMTrace`.
        step: global EM step.

    Returns:
        ((K,) int64 ids, (K,) float64 stationary scores).
    """
    rows = trace.rows(int(step))
    ids = np.asarray(trace.row_id[rows], dtype=np.int64)
    scores = np.asarray(trace.row_stationary[rows], dtype=np.float64)
    return ids, scores


def sample_indices(trace: Any, pid: int, step: int) -> np.ndarray | None:
    """(M,) int64 scene-point indices sampled by proposal `pid` at `step` (None when it did not take part)."""
    r = trace.row_of(int(pid), int(step))
    return None if r is None else np.asarray(trace.row_samples[r], dtype=np.int64).reshape(-1)


def deaths(trace: Any) -> list[Death]:
    """Every terminated proposal with its step and reason (accepted survivors excluded), in order of death."""
    out: list[Death] = []
    for ev in trace.events():
        reason = str(ev.reason)
        if reason == "survive":
            continue
        partner, ratio = int(ev.partner), float(ev.ratio)
        out.append(
            Death(
                pid=int(ev.proposal_id),
                step=int(ev.step),
                reason=reason,
                partner=None if partner < 0 else partner,
                ratio=None if not np.isfinite(ratio) else ratio,
            )
        )
    return out


def is_dead_at(trace: Any, pid: int, step: int) -> bool:
    """True when the proposal was terminated (not accepted) at or before `step`."""
    d = trace.death(int(pid))
    return d is not None and d[1] != "survive" and int(d[0]) <= int(step)


def proposal_center(trace: Any, pid: int, step: int) -> np.ndarray:
    """(3,) float32 world centre Θ_c of a proposal at a step (its last recorded step if it died before)."""
    s = min(int(step), int(trace.last_step(int(pid))))
    r = trace.row_of(int(pid), s)
    if r is None:
        raise ValueError(f"proposal {pid} has no record at step {s}")
    return np.asarray(trace.row_center[r], np.float32).reshape(3)


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


def shown_mask(instances: Any, threshold: float, hidden: set[int] | frozenset[int] = frozenset()) -> np.ndarray:
    """(K,) bool: the final instances drawn: kept by the confidence threshold (`Instances.kept`, the one
    thresholding rule) and not hidden by hand.

    Args:
        instances: `efem_viz.em.Instances`.
        threshold: the confidence threshold.
        hidden: proposal ids hidden by hand.
    """
    keep = instances.kept(float(threshold))
    if hidden:
        keep &= ~np.isin(np.asarray(instances.ids).reshape(-1), np.fromiter(hidden, np.int64))
    return keep


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
    from efem_viz.eval import DEFAULT_CLASS_NAMES, evaluate_instances, match_instances

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
    )


def _pr_curves(res: Any) -> list[tuple[str, np.ndarray, np.ndarray]]:
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    curves = getattr(res, "pr_curves", None) or {}
    for key, curve in dict(curves).items():
        rec, prec = curve
        out.append((str(key), np.asarray(rec, float), np.asarray(prec, float)))
    return out
