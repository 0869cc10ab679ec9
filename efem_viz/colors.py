"""Per-instance colours: the one palette of efem-viz (viewer, exports and annotator).

Which id each caller colours by, so that the same instance has the same colour everywhere:

* an EFEM result's instance is coloured by its **proposal id** (`Instances.ids`, stable under any confidence
  threshold), through `result_colors`: the viewer's points, mesh, box, legend swatch and "#id" label, the
  coloured PLY (`Instances.to_colored_ply`) and the annotator's EFEM pre-labels (which are numbered k + 1 but keep
  that colour in their instance table); the viewer's EM proposals use the same key, so an accepted proposal keeps
  its colour from the timeline to the final result — unless its id's colour was too close to a neighbouring
  instance's, which `result_colors` then replaces (deterministically, over the whole result);
* an instance known only by a label id (the annotator's own instances, a labelled file without an instance
  table) is coloured by that **label id**.

The other colour maps of the apps live here too, one name per contract: `instance_colors(ids)` is the palette (a
colour per id); `instance_point_colors(base, instances, keep)` colours the points of a result's shown instances
with it; `label_colors` colours points by label ids; `gt_match_colors` with the ground-truth comparison colours
`TP_COLOR` / `FP_COLOR` / `FN_COLOR`; `heatmap` and `weights_colors` for a proposal's weights; `dim` the scan under
overlays; `hex_color` / `rgb_tuple` convert for HTML and viser.

Pure NumPy; no GUI here.
"""

from __future__ import annotations

from typing import Any, Protocol, Sequence

import numpy as np

__all__ = [
    "BACKGROUND_COLOR",
    "DEAD_COLOR",
    "FN_COLOR",
    "FP_COLOR",
    "HEAT_RGB",
    "HEAT_STOPS",
    "TP_COLOR",
    "dim",
    "gt_match_colors",
    "heatmap",
    "hex_color",
    "instance_color",
    "instance_colors",
    "instance_point_colors",
    "label_colors",
    "result_colors",
    "rgb_tuple",
    "weights_colors",
]

TP_COLOR = np.array([46, 180, 80], np.uint8)
"""Ground-truth comparison: a prediction that matched a ground-truth object (green, uint8 RGB)."""
FP_COLOR = np.array([220, 50, 47], np.uint8)
"""Ground-truth comparison: a prediction that matched none (red)."""
FN_COLOR = np.array([38, 110, 230], np.uint8)
"""Ground-truth comparison: a ground-truth object no prediction matched (blue)."""
BACKGROUND_COLOR = np.array([200, 200, 200], np.uint8)
"""Points without a value (NaN in a heat map)."""
DEAD_COLOR = np.array([230, 30, 30], np.uint8)
"""A proposal terminated at the shown step."""

_GOLDEN = 0.618033988749895
"""Hue step (1/φ): consecutive ids land far apart on the hue circle."""
_HUE0 = 0.13
"""Hue of id 0."""


def instance_colors(ids: np.ndarray | Sequence[int]) -> np.ndarray:
    """Distinct, deterministic colours per integer id (golden-ratio hue walk, vectorised).

    Hue `(0.13 + 0.618… · id) mod 1`; saturation cycles over 0.65/0.775/0.9 with `(7 · id) mod 3` and value over
    0.95/0.75 with `(5 · id) mod 2`, so ids whose hues come close differ in saturation or brightness.

    Args:
        ids: (K,) integer ids (proposal ids or label ids; any sign). Other shapes are flattened.

    Returns:
        (K, 3) uint8 RGB; the same id always gets the same colour.
    """
    ids_arr = np.asarray(ids, dtype=np.int64).reshape(-1)
    h = (ids_arr * _GOLDEN + _HUE0) % 1.0
    s = 0.65 + 0.25 * ((ids_arr * 7) % 3) / 2.0
    v = 0.95 - 0.2 * ((ids_arr * 5) % 2)
    return _hsv_to_rgb(h, s, v)


NEIGHBOUR_COLOR_DISTANCE = 100.0
"""Two neighbouring instances whose colours are closer than this (RGB, Euclidean) get different ones
(`result_colors`)."""
_SEPARATE = np.array([[230, 25, 75], [60, 180, 75], [255, 200, 25], [0, 130, 200], [245, 130, 48],
                      [145, 30, 180], [70, 240, 240], [240, 50, 230], [128, 128, 0], [0, 128, 128],
                      [170, 110, 40], [128, 0, 0], [0, 0, 128], [250, 190, 212]], np.float64)
"""Well-separated colours `result_colors` chooses from when an id's own colour is too close to a neighbour's."""


def result_colors(instances: InstancesLike) -> np.ndarray:
    """(K, 3) uint8 colour of each instance of an EFEM result: `instance_colors` of its proposal id, except where
    that is within `NEIGHBOUR_COLOR_DISTANCE` of the colour of an earlier neighbouring instance (boxes closer than
    1.5 × the sum of their half-diagonals): then the colour of `_SEPARATE` that no other instance has yet and is
    farthest from its neighbours' colours (so that a colour still names one instance).

    Computed over the whole result in its order (the instances' order is the result's), so a confidence cut
    never changes a colour: select the rows of this array for a subset.

    Args:
        instances: `efem_viz.em.Instances` (ids (K,), obb_center (K, 3), obb_half_extents (K, 3)).
    """
    ids = np.asarray(instances.ids, np.int64).reshape(-1)
    own = instance_colors(ids).astype(np.float64)
    k = len(ids)
    if k < 2:
        return own.astype(np.uint8)
    centers = np.asarray(instances.obb_center, np.float64).reshape(k, 3)
    radii = np.linalg.norm(np.asarray(instances.obb_half_extents, np.float64).reshape(k, 3), axis=1)
    near = np.linalg.norm(centers[:, None] - centers[None], axis=-1) < 1.5 * (radii[:, None] + radii[None])
    out = own.copy()
    for i in range(1, k):
        others = out[:i][near[i, :i]]
        if not len(others) or np.linalg.norm(others - out[i], axis=1).min() >= NEIGHBOUR_COLOR_DISTANCE:
            continue
        free = [c for c in _SEPARATE if not np.any(np.all(np.abs(out[:i] - c) < 0.5, axis=1))]
        cand = np.asarray(free) if free else _SEPARATE  # a colour no other instance has, while there is one
        gap = np.linalg.norm(cand[:, None] - others[None], axis=-1).min(axis=1)
        out[i] = cand[int(np.argmax(gap))]
    return np.round(out).astype(np.uint8)


def instance_color(instance_id: int) -> tuple[int, int, int]:
    """`instance_colors` of one id as an `(r, g, b)` int triple (the form viser's `color=` and the annotator's
    instance table take).

    Args:
        instance_id: integer id (a proposal id or a label id).

    Returns:
        (r, g, b), each in [0, 255].
    """
    r, g, b = (int(c) for c in instance_colors([int(instance_id)])[0])
    return r, g, b


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) float HSV in [0, 1] → (K, 3) uint8 RGB (rounded)."""
    i = np.floor(h * 6.0).astype(np.int64) % 6
    f = h * 6.0 - np.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    r = np.choose(i, [v, q, p, p, t, v])
    g = np.choose(i, [t, v, v, q, p, p])
    b = np.choose(i, [p, p, t, v, v, q])
    return np.clip(np.round(np.stack([r, g, b], axis=-1) * 255), 0, 255).astype(np.uint8).reshape(-1, 3)


class InstancesLike(Protocol):
    """What `instance_point_colors` reads of a result's instances (`efem_viz.em.Instances` is one)."""

    @property
    def ids(self) -> Any:
        """(K,) int proposal ids."""
        ...

    def select(self, keep: np.ndarray) -> InstancesLike:
        """The instances where `keep` (K,) bool is True (same type)."""
        ...

    @property
    def obb_center(self) -> Any:
        """(K, 3) box centres."""
        ...

    @property
    def obb_half_extents(self) -> Any:
        """(K, 3) box half extents."""
        ...

    def label_array(self, n_points: int) -> np.ndarray:
        """(N,) int32: k + 1 on the points of the k-th instance (overlaps: higher confidence wins), 0 elsewhere."""
        ...


# ---------------------------------------------------------------------------------------------- colour maps
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


def label_colors(base: np.ndarray, labels: np.ndarray, *,
                 ids_to_color: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """Colour points by integer labels (0 = none keeps the dimmed base colour).

    Args:
        base: (N, 3) uint8 scene colours.
        labels: (N,) int labels, 0 = unassigned.
        ids_to_color: optional fixed colour per label id (else `instance_colors` of the id).

    Returns:
        (N, 3) uint8.
    """
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != base.shape[0]:
        raise ValueError(f"labels have shape {lab.shape}, scene colours {base.shape}")
    out = dim(base)
    ids = np.unique(lab[lab > 0])
    if ids.size:
        cols = instance_colors(ids) if ids_to_color is None else np.stack([ids_to_color[int(i)] for i in ids])
        lut_idx = np.searchsorted(ids, lab)
        mask = lab > 0
        out[mask] = cols[lut_idx[mask]]
    return out


def instance_point_colors(base: np.ndarray, instances: InstancesLike, keep: np.ndarray) -> np.ndarray:
    """Colour the points of the kept instances of a result, each with its `result_colors` colour (the colour of
    its mesh, box and legend swatch, of the coloured PLY export and of the annotator's EFEM import).

    Args:
        base: (N, 3) uint8 scene colours.
        instances: `efem_viz.em.Instances` (ids (K,), masks, confidence; overlaps: higher confidence wins).
        keep: (K,) bool, the instances shown (confidence ≥ threshold).

    Returns:
        (N, 3) uint8.
    """
    keep = np.asarray(keep, bool)
    shown = instances.select(keep)
    labels = shown.label_array(base.shape[0])  # k + 1 for the k-th shown instance
    cols = result_colors(instances)[keep]
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
