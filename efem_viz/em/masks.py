"""Output masks at another SDF threshold, re-derived from a saved run, and the per-prior calibration of τ_out.

efem-method.md §3.9.12 takes a point into an instance's output mask when |d| < τ_out (0.04 canonical units
for mugs). That value fits the authors' prior, whose decoded surfaces lie within a few millimetres of the
scan. A prior with blurrier surfaces (ours, trained on two CPU cores) leaves true object points outside
that band, so masks come out too small and AP at IoU ≥ 0.5 suffers while the objects are found. τ_out is
therefore a property of the prior: `efem-viz calibrate-masks` picks it on labelled *tuning* scenes (AP over
IoU 0.50:0.95 of the re-thresholded masks; every other output of the run is unchanged) and stores it in the
prior file's metadata, and `run_em` uses it whenever the config leaves `tau_out` unset. A prior without the
key (a converted release checkpoint) keeps the spec's 0.04.

Re-thresholding decodes each accepted instance's final latent over its E-step neighbourhood (radius
r_err around Θ_c, the points available in its episode, at full resolution), exactly as the last review did,
so the mask at the run's own τ_out is the one the run produced.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.em.config import DEFAULT_TAU_OUT, MAX_TAU_OUT, EMConfig

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult

logger = logging.getLogger(__name__)

TAU_OUT_CANDIDATES: tuple[float, ...] = (0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10, 0.12)
"""Thresholds `calibrate_tau_out` tries by default (canonical units)."""
METADATA_KEY = "tau_out"


def prior_tau_out(prior: Any) -> float:
    """The prior's calibrated τ_out (metadata "tau_out"), or the spec's 0.04 when it has none or a bad one."""
    meta = getattr(prior, "metadata", None)
    value = meta.get(METADATA_KEY) if isinstance(meta, dict) else None
    if value is None:
        return DEFAULT_TAU_OUT
    try:
        tau = float(value)
    except (TypeError, ValueError):
        tau = float("nan")
    if not 0.0 < tau <= MAX_TAU_OUT:  # also rejects NaN
        logger.warning("prior metadata %s=%r is not in (0, %s]; using %s", METADATA_KEY, value, MAX_TAU_OUT,
                       DEFAULT_TAU_OUT)
        return DEFAULT_TAU_OUT
    return tau


def resolve_config(cfg: EMConfig, prior: Any) -> EMConfig:
    """`cfg` with `tau_out` filled from the prior when it is None (validated either way)."""
    cfg.validate()
    if cfg.tau_out is not None:
        return cfg
    return cfg.replace(tau_out=prior_tau_out(prior))


@dataclass(frozen=True)
class InstanceDistances:
    """Decoded SDF of every accepted instance over its final neighbourhood.

    Attributes:
        idx: K arrays of scene-point indices (the neighbourhood of instance k).
        d: K arrays of canonical SDF values, aligned with `idx`.
        gamma: K arrays of normal angles (degrees; 180 where not computed), aligned with `idx`.
    """

    idx: list[np.ndarray]
    d: list[np.ndarray]
    gamma: list[np.ndarray]

    def masks(self, tau_out: float, gamma_out: float = 180.0) -> list[np.ndarray]:
        """Output masks (int32 scene indices) at |d| < tau_out (and γ < gamma_out when below 180°)."""
        out = []
        for idx, d, g in zip(self.idx, self.d, self.gamma, strict=True):
            keep = np.abs(d) < tau_out
            if gamma_out < 180.0:
                keep &= g < gamma_out
            out.append(idx[keep].astype(np.int32))
        return out


def instance_distances(result: "EMResult", scene: "Scene", prior: Any, *,
                       normals_within: float | None = None) -> InstanceDistances:
    """Decode the final latent of every accepted instance of `result` over its neighbourhood in `scene`.

    Args:
        result: a finished run (`run_em` or `EMResult.load`).
        scene: the scene it ran on (same number of points).
        prior: the prior it ran with.
        normals_within: compute normal angles for entries with |d| ≤ this (None: only when the run's config
            gates masks by normals, then up to the largest accepted τ_out).

    Raises:
        ValueError: the scene does not match the result.
    """
    from efem_viz.em.proposals import AvailableTree, Ragged
    from efem_viz.em.solver import decode_rows

    if scene.num_points != result.num_points:
        raise ValueError(f"result {result.scene_name!r} was computed on {result.num_points} points but scene "
                         f"{scene.name!r} has {scene.num_points}")
    inst, trace, cfg = result.instances, result.trace, result.config
    if len(inst) == 0:
        return InstanceDistances([], [], [])
    if normals_within is None:
        normals_within = MAX_TAU_OUT if cfg.gamma_out < 180.0 else -1.0
    points = np.ascontiguousarray(scene.points, np.float32)
    normals = np.ascontiguousarray(scene.normals, np.float32)
    lats = [trace.latent(int(pid), trace.last_step(int(pid))) for pid in inst.ids]
    episodes = trace.prop_episode[np.asarray(inst.ids, np.int64)]
    balls: list[np.ndarray] = [np.zeros(0, np.int64)] * len(inst)
    for ep in np.unique(episodes):  # neighbourhoods among the points available in each instance's episode
        tree = AvailableTree(points, trace.available_mask(int(ep)), crop=cfg.crop)
        ks = np.flatnonzero(episodes == ep)
        nb = tree.query(np.stack([np.asarray(lats[k]["center"], np.float64) for k in ks]), cfg.r_err)
        for j, k in enumerate(ks):
            balls[k] = nb.idx[nb.row_slice(j)]
    rag = Ragged.from_lists(balls)
    lat_all = {key: np.stack([np.asarray(x[key]) for x in lats]) for key in lats[0]}
    d, g = decode_rows(prior, lat_all, rag, points, normals, chunk=cfg.decode_chunk, normals_within=normals_within)
    split = rag.offsets[1:-1]
    return InstanceDistances(list(np.split(rag.idx, split)), list(np.split(d, split)), list(np.split(g, split)))


@dataclass(frozen=True)
class MaskCalibration:
    """AP of re-thresholded masks per candidate τ_out, and the chosen one (the smallest within `tolerance` of the best
    AP)."""

    taus: tuple[float, ...]
    ap: tuple[float, ...]
    ap50: tuple[float, ...]
    ap25: tuple[float, ...]
    best: float
    scenes: tuple[str, ...]
    tolerance: float = 0.0
    """AP (fraction) below the best that counted as a tie."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    def table(self) -> str:
        lines = ["tau_out      AP   AP50   AP25"]
        for t, a, a50, a25 in zip(self.taus, self.ap, self.ap50, self.ap25, strict=True):
            mark = "  <- chosen" if t == self.best else ""
            lines.append(f"{t:7.3f} {a * 100:6.1f} {a50 * 100:6.1f} {a25 * 100:6.1f}{mark}")
        return "\n".join(lines)


def choose_tau_out(taus: Sequence[float], ap: Sequence[float], tolerance: float = 0.005) -> float:
    """The smallest of `taus` (ascending) whose AP is within `tolerance` of the best AP.

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
    runs: Sequence[tuple["EMResult", "Scene"]],
    prior: Any,
    *,
    candidates: Sequence[float] = TAU_OUT_CANDIDATES,
    class_names: Sequence[str] = ("mug",),
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

    Raises:
        ValueError: no runs, a scene without ground truth, a mismatched pair, a bad candidate or tolerance.
    """
    from efem_viz.eval import SceneGroundTruth, evaluate, prediction_from_instances

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
            inst = dataclasses.replace(res.instances, masks=dist.masks(t, res.config.gamma_out))
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
