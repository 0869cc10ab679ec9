"""Per-prior calibration of the output-mask threshold τ_out on labelled tuning scenes.

docs/design/efem-method.md §3.9.12 takes a point into an instance's output mask when |d| < τ_out (0.04 canonical units
for mugs). A prior with blurrier surfaces than the authors' leaves true object points outside that band, so τ_out is a
property of the prior: `calibrate_tau_out` re-thresholds the masks of saved runs (`efem_viz.em.masks`, every other
output of the run unchanged), scores each candidate by AP over IoU 0.50:0.95 against the ground truth and picks
the smallest within a tolerance of the best. `efem-viz calibrate-masks` (`efem_viz.eval.commands`) stores the
choice in the prior file's metadata, where `run_em` finds it.

This is an evaluation concern (it needs ground truth and AP), so it lives here, above the solver; the pure
re-thresholding stays in `efem_viz.em.masks`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.em.masks import instance_distances
from efem_viz.eval.ap import evaluate, prediction_from_instances
from efem_viz.eval.matching import SceneGroundTruth
from efem_viz.prior.config import MAX_TAU_OUT
from efem_viz.prior.config import DEFAULT_PRIOR

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult

TAU_OUT_CANDIDATES: tuple[float, ...] = (0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10, 0.12)
"""Thresholds `calibrate_tau_out` tries by default (canonical units)."""


@dataclass(frozen=True)
class MaskCalibration:
    """AP of re-thresholded masks per candidate τ_out, and the chosen one (the smallest within `tolerance` of the best
    AP)."""

    taus: tuple[float, ...]
    """Candidate thresholds, ascending (canonical units)."""
    ap: tuple[float, ...]
    """AP over IoU 0.50:0.95 per candidate."""
    ap50: tuple[float, ...]
    """AP at IoU 0.5 per candidate."""
    ap25: tuple[float, ...]
    """AP at IoU 0.25 per candidate."""
    best: float
    """The chosen threshold."""
    scenes: tuple[str, ...]
    """Names of the tuning scenes."""
    tolerance: float = 0.0
    """AP (fraction) below the best that counted as a tie."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    def table(self) -> str:
        """The AP table, one row per candidate, the chosen one marked."""
        lines = ["tau_out      AP   AP50   AP25"]
        for t, a, a50, a25 in zip(self.taus, self.ap, self.ap50, self.ap25, strict=True):
            mark = "  <- chosen" if t == self.best else ""
            lines.append(f"{t:7.3f} {a * 100:6.1f} {a50 * 100:6.1f} {a25 * 100:6.1f}{mark}")
        return "\n".join(lines)


def choose_tau_out(taus: Sequence[float], ap: Sequence[float], tolerance: float = 0.005) -> float:
    """The smallest of `taus` (ascending) whose AP is within `tolerance` of the best AP.

    Args:
        taus: candidate thresholds, ascending.
        ap: their APs (fractions), aligned with `taus`.
        tolerance: AP (fraction) below the best that still counts as a tie.

    Returns:
        The chosen threshold.

    Raises:
        ValueError: empty or mismatched inputs, or a negative or non-finite tolerance.
    """
    if not len(taus) or len(taus) != len(ap):
        raise ValueError(f"need one AP per candidate, got {len(taus)} candidates and {len(ap)} APs")
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance}")
    a = np.round(np.asarray(ap, np.float64), 9)
    return float(taus[int(np.flatnonzero(a >= a.max() - tolerance)[0])])


def calibrate_tau_out(
    runs: Sequence[tuple[EMResult, Scene]],
    prior: Any,
    *,
    candidates: Sequence[float] = TAU_OUT_CANDIDATES,
    class_names: Sequence[str] = (DEFAULT_PRIOR,),
    tolerance: float = 0.005,
) -> MaskCalibration:
    """Choose τ_out for `prior` on labelled tuning scenes: the smallest candidate whose AP (IoU 0.50:0.95) is within
    `tolerance` of the best.

    A few tuning scenes cannot tell AP differences of a few tenths of a point apart, and a wider band only adds
    risk (masks spreading into touching objects), so near-ties go to the tighter band, the one closer to the
    method's own value.

    Args:
        runs: (result, labelled scene) pairs, every result computed with `prior`.
        prior: the shape prior.
        candidates: thresholds to try (canonical units, each in (0, 0.5]).
        class_names: evaluated classes (instances take class 1 with one class).
        tolerance: AP (as a fraction, 0.005 = half a point) below the best that still counts as a tie.

    Returns:
        The AP table and the chosen threshold.

    Raises:
        ValueError: no runs, a scene without ground truth, a mismatched pair, a bad candidate or tolerance.
    """
    if not (np.isfinite(tolerance) and tolerance >= 0.0):  # checked before the decoding, not after it
        raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance}")
    if not runs:
        raise ValueError("calibrate_tau_out needs at least one (result, labelled scene) pair")
    taus = tuple(sorted({float(t) for t in candidates}))
    if not taus or not all(0.0 < t <= MAX_TAU_OUT for t in taus):
        raise ValueError(f"candidate thresholds must be in (0, {MAX_TAU_OUT}], got {list(candidates)}")
    gts = [SceneGroundTruth.from_scene(scene) for _, scene in runs]
    dists = [instance_distances(res, scene, prior) for res, scene in runs]
    ap, ap50, ap25 = [], [], []
    for t in taus:
        preds = []
        for (res, scene), dist in zip(runs, dists, strict=True):
            inst = dataclasses.replace(res.instances, masks=dist.masks(t, res.config.output.gamma_out))
            preds.append(prediction_from_instances(inst, name=scene.name, class_names=tuple(class_names)))
        ev = evaluate(preds, gts, class_names=tuple(class_names))
        if not np.isfinite(ev.ap):
            raise ValueError(f"no ground-truth instance of the classes {list(class_names)} in the tuning scenes "
                             f"{[scene.name for _, scene in runs]}")
        ap.append(float(ev.ap))
        ap50.append(float(ev.ap50))
        ap25.append(float(ev.ap25))
    best = choose_tau_out(taus, ap, tolerance)
    return MaskCalibration(taus=taus, ap=tuple(ap), ap50=tuple(ap50), ap25=tuple(ap25), best=best,
                           scenes=tuple(scene.name for _, scene in runs), tolerance=float(tolerance))
