"""Per-instance colours: the one palette of efem-viz (viewer, exports and annotator).

Which id each caller colours by, so that the same instance has the same colour everywhere:

* an EFEM result's instance is coloured by its **proposal id** (`Instances.ids`, stable under any confidence
  threshold): the viewer's points, mesh, box, legend swatch and "#id" label, the coloured PLY
  (`Instances.to_colored_ply`) and the annotator's EFEM pre-labels (which are numbered k + 1 but keep the colour
  of their proposal id in their instance table); the viewer's EM proposals use the same key, so an accepted
  proposal keeps its colour from the timeline to the final result;
* an instance known only by a label id (the annotator's own instances, a labelled file without an instance
  table) is coloured by that **label id**.

Pure NumPy; no GUI here.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["instance_color", "instance_colors"]

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
