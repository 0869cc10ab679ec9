"""The results part: load or show an EMResult, the confidence cut, the mask band, ground truth and point colours."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Hashable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from efem_viz.colors import FP_COLOR, TP_COLOR, gt_match_colors, instance_point_colors, weights_colors
from efem_viz.eval.comparison import GTMetrics, gt_metrics
from efem_viz.viewer import state as st
from efem_viz.viewer.state import DEFAULT_CONFIDENCE_CUT, MASK_BAND_RANGE

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.masks import InstanceDistances
    from efem_viz.em.results import EMResult
    from efem_viz.viewer.parts.core import ViewerCore

logger = logging.getLogger(__name__)


class PointColors(NamedTuple):
    """The scene points' colours for the current colour mode."""

    colors: np.ndarray
    """(N, 3) uint8."""
    key: Hashable
    """A cache key: equal keys mean equal colours (the nodes skip resending them)."""
    shown: str
    """The colouring in effect ("rgb", "instances", "gt_match", "weights" or "step": scene colours while one EM
    step is on screen): its key is shown under the control."""
    boxes: np.ndarray | None
    """(K, 3) uint8 box colours of the final instances (TP/FP in the ground-truth view), or None: their own."""


class ResultPart:
    """Shows one result at a time: which instances the cut keeps and draws, their masks, their colours."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""
        self._gt_cache: dict[tuple[int, float], GTMetrics] = {}
        self._mask_dist: tuple[int, InstanceDistances] | None = None
        """(generation, InstanceDistances) of the shown result: masks at any τ_out without a re-run."""

    def read_result(self, path: str | Path | None = None) -> tuple[EMResult, str] | None:
        """Read `<scene>.efem.npz` (or `path`, inside the given paths) of the open scene (no state change).
        Returns (result, source name), or None with the status saying why."""
        from efem_viz.em import EMResult

        s = self.core.state
        if s.scene is None or s.scene_name is None:
            self.core.set_status("Open a scene first.", error=True)
            return None
        p = Path(path) if path is not None else s.entry(s.scene_name).trace_path
        if not self.core.allowed(p):
            self.core.set_status(f"refusing to read {p}: outside the given paths", error=True)
            return None
        if not p.is_file():
            self.core.set_status(f"No saved trace at {p.name}; run EFEM first.", error=True)
            return None
        try:
            return EMResult.load(p), str(p.name)
        except Exception as exc:  # noqa: BLE001 - corrupt file: show, stay up
            logger.exception("loading %s failed", p)
            self.core.set_status(f"Could not load {p.name}: {exc}", error=True)
            return None

    def load_result(self, path: str | Path | None = None) -> EMResult | None:
        """Read and show the open scene's saved result (or `path`). None when it cannot (status says why)."""
        got = self.read_result(path)
        if got is None:
            return None
        try:
            self.set_result(got[0], source=got[1])
        except Exception as exc:  # noqa: BLE001 - another scene's result: show, stay up
            self.core.set_status(f"Could not load {got[1]}: {exc}", error=True)
            return None
        return got[0]

    def threshold_max(self, result: EMResult) -> float:
        """The top of the threshold slider: just above the most confident instance (it hides every instance)."""
        conf = np.asarray(result.instances.confidence, float)
        hi = float(conf.max()) if conf.size else 1.0
        return float(np.ceil(hi * 100.0 + 1e-6) / 100.0 + 0.01)

    def set_result(self, result: EMResult, *, source: str) -> None:
        """Show an EMResult: the last step, no proposal inspected, its final instances in instance colours.

        Raises:
            ValueError: the result belongs to another scene.
        """
        with self.core.lock:
            s = self.core.state
            s.playing = False
            self.core.forget_views()
            if s.scene is not None and hasattr(result, "bind"):
                result.bind(s.scene)  # raises ValueError when the result belongs to another scene
            s.result, s.result_source, s.selected = result, source, None
            s.hidden, s.table_row = set(), None  # another result: other instances
            s.step = max(int(result.trace.num_steps) - 1, 0)
            conf = np.asarray(result.instances.confidence, float)
            best = float(conf.max()) if conf.size else 0.0
            cut_note = ""
            if s.threshold_by_user and conf.size and s.threshold <= best:  # a person's cut that still shows some
                cut_note = f" Your confidence cut {s.threshold:.2f} is kept."
            else:
                if s.threshold_by_user and conf.size:
                    cut_note = (f" Your confidence cut {s.threshold:.2f} would hide every instance (best "
                                f"{best:.2f}): this result opens at {self.default_threshold(result):.2f}.")
                s.threshold, s.threshold_by_user = self.default_threshold(result), False
            s.threshold = float(np.clip(s.threshold, 0.0, self.threshold_max(result)))
            self._mask_dist = None
            s.color_mode = "instances"
        warn = "; ".join(getattr(result, "warnings", ()))  # e.g. the free-space check was off: never silently
        self.core.set_status(f"Loaded result: {source}.{cut_note}" + (f" Warning: {warn}" if warn else ""),
                             error=bool(warn))

    def set_threshold(self, threshold: float, *, by_user: bool = True) -> None:
        """Filter the final instances by confidence (a view, no re-run). `by_user=False` for the app's own
        redraws: only a person's cut is carried over to the next result (`set_result`). The cut is kept within
        the slider's range (0 to `threshold_max` of the shown result): a script's cut above the top hid the same
        instances as the top but left the field showing a value the slider could not."""
        s = self.core.state
        top = self.threshold_max(s.result) if s.result is not None else 1.0
        s.threshold = float(min(max(float(threshold), 0.0), top))
        if by_user:
            self.core.state.threshold_by_user = True

    def suggested_preset(self, scene: "Scene") -> str:
        """The Run preset that fits a scene solved with the prior its Run solves with
        (`efem_viz.em.config.suggested_preset`, `PriorSet.solve_category`: a scan opened in a viewer started with
        the chair prior runs "chairs"; a generated kitchen scene, solved with its own prior, does not)."""
        from efem_viz.em.config import suggested_preset, suggested_prior

        try:
            category: str | None = self.core.priors.solve_category(suggested_prior(scene))
        except RuntimeError:  # no prior to run with: the scene decides alone
            category = None
        return suggested_preset(scene, category)

    def default_threshold(self, result: EMResult) -> float:
        """The cut a result opens with: `DEFAULT_CONFIDENCE_CUT`, lowered to its best instance's confidence when
        that is below (a real frame whose best instance is 0.11 opened with every instance hidden) and, on a scene
        with ground truth, to the least confident instance that matches an object at IoU 0.5 (what `evaluate`
        counts as found is shown: a second correct mug at 0.0101 was hidden by a 0.05 cut)."""
        conf = np.asarray(result.instances.confidence, float)
        if not conf.size:
            return DEFAULT_CONFIDENCE_CUT
        cut = min(DEFAULT_CONFIDENCE_CUT, float(conf.max()))
        scene = self.core.state.scene
        gt = scene.instance if scene is not None and scene.has_gt else None
        if gt is not None and len(gt) == result.trace.num_points:
            from efem_viz.eval.matching import match_instances

            masks = [np.asarray(m, np.int64) for m in result.instances.masks]
            tp = match_instances(masks, gt, iou=0.5, confidences=conf).tp_pred
            if len(tp):
                cut = min(cut, float(conf[np.asarray(tp, int)].min()))
        return float(np.floor(cut * 100.0) / 100.0)

    def set_mask_band(self, tau_out: float) -> bool:
        """Re-derive the output masks at SDF band `tau_out` (clamped to `MASK_BAND_RANGE`) from the stored
        latents (no re-run). Colours, metrics and exports follow; the result's config records the band.

        Returns:
            False (status says why) when there is no result or no prior to decode with.
        """
        with self.core.lock:
            s = self.core.state
            if s.result is None or s.scene is None:
                return False
            tau = float(np.clip(tau_out, *MASK_BAND_RANGE))
            if abs(tau - s.result.config.output.out_tau) < 1e-9:
                return True
            try:
                if self._mask_dist is None or self._mask_dist[0] != self.core.generation:
                    from efem_viz.em.masks import instance_distances

                    self.core.set_status("Decoding the instances' final shapes for the mask band …")
                    self._mask_dist = (self.core.generation,
                                       instance_distances(s.result, s.scene,
                                                          self.core.priors.for_run(s.result.trace)))
                masks = self._mask_dist[1].masks(tau, s.result.config.output.gamma_out)
            except (RuntimeError, ValueError) as exc:
                self.core.set_status(f"Mask band unavailable: {exc}", error=True)
                return False
            inst = dataclasses.replace(s.result.instances, masks=masks)
            s.result = dataclasses.replace(s.result, instances=inst,
                                           config=s.result.config.replace(output={"tau_out": tau}))
            self._gt_cache.clear()
            self.core.mask_version += 1
            self.core.set_status(f"Masks re-derived at τ_out = {tau:g} from the stored latents; nothing was re-run.")
            return True

    def kept_mask(self) -> np.ndarray:
        """(K,) bool: final instances at or above the threshold (what the metrics and exports take)."""
        res = self.core.state.result
        if res is None:
            return np.zeros(0, bool)
        return res.instances.kept(self.core.state.threshold)

    def shown_mask(self) -> np.ndarray:
        """(K,) bool: final instances drawn: at or above the threshold and not hidden in the instance table."""
        res = self.core.state.result
        if res is None:
            return np.zeros(0, bool)
        return st.shown_mask(res.instances, self.core.state.threshold, self.core.state.hidden)

    def gt_metrics(self) -> GTMetrics:
        """Ground-truth metrics of the result at the current threshold (cached per threshold).

        Raises:
            RuntimeError: no scene or result; ValueError: the scene has no ground truth.
        """
        s = self.core.state
        key = (self.core.generation, round(float(s.threshold), 6))
        cached = self._gt_cache.get(key)
        if cached is None:
            cached = gt_metrics(s.require_result().instances, s.require_scene(), s.threshold)
            if len(self._gt_cache) > 64:
                self._gt_cache.clear()
            self._gt_cache[key] = cached
        return cached

    def gt_metrics_or_none(self) -> GTMetrics | None:
        """`gt_metrics()`, or None when they cannot be computed."""
        try:
            return self.gt_metrics()
        except Exception:  # noqa: BLE001 - shown in the ground-truth panel
            return None

    def point_colors(self, result_box_colors: np.ndarray | None = None) -> PointColors | None:
        """The scene points' colours for the colour mode and view (None without a scene).

        Args:
            result_box_colors: (K, 3) uint8 the final instances' own box colours (the TP/FP view recolours a copy).
        """
        s = self.core.state
        if s.scene is None:
            return None
        base = s.scene.colors
        mode = s.color_mode
        if mode in ("instances", "gt_match") and s.view_mode != "result":
            return PointColors(base, ("rgb", id(base)), "step", None)  # one EM step on screen: no final instances
        if (mode == "gt_match" and s.result is not None and s.scene.has_gt
                and self.gt_metrics_or_none() is not None):
            return self._gt_point_colors(base, result_box_colors)
        if mode in ("instances", "gt_match") and s.result is not None:
            keep = self.shown_mask()
            key = ("inst", self.core.generation, self.core.mask_version, keep.tobytes())
            return PointColors(instance_point_colors(base, s.result.instances, keep), key, "instances", None)
        if mode == "weights" and s.selected is not None and self.core.inspect_weights is not None:
            return PointColors(weights_colors(base, self.core.inspect_weights),
                               ("w", self.core.generation, s.selected, s.step), "weights", None)
        return PointColors(base, ("rgb", id(base)), "step" if s.view_mode == "step" else "rgb", None)

    def _gt_point_colors(self, base: np.ndarray, result_box_colors: np.ndarray | None) -> PointColors:
        """TP/FP/FN colours of the points and boxes (instances hidden in the table: grey)."""
        m = self.gt_metrics()
        kept = np.flatnonzero(self.kept_mask())  # the metrics index the kept instances
        drawn = self.shown_mask()
        off = {j for j, k in enumerate(kept) if not drawn[k]}
        gt_instance = self.core.state.require_scene().instance
        assert gt_instance is not None  # has_gt
        cols = gt_match_colors(base, m.masks, gt_instance, tp=[j for j in m.tp if j not in off],
                               fp=[j for j in m.fp if j not in off], fn=m.fn)
        boxes = None
        if result_box_colors is not None:
            boxes = np.array(result_box_colors, np.uint8, copy=True)
            for ks, colour in ((m.tp, TP_COLOR), (m.fp, FP_COLOR)):
                for k in ks:
                    if int(k) < kept.size and kept[int(k)] < len(boxes):
                        boxes[kept[int(k)]] = colour
        key = ("gt", self.core.generation, self.core.mask_version, drawn.tobytes())
        return PointColors(cols, key, "gt_match", boxes)
