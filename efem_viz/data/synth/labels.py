"""Ground truth of a synthetic scan: each point takes the id of the nearest true surface within a tolerance."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from efem_viz.data.synth.layout import SceneObject


class PointLabels(NamedTuple):
    """The ground truth of a scan's points."""

    instance: np.ndarray
    """(N,) int32 instance id per point (mug k -> k; table, structure, distractors and unlabelled points 0)."""
    categories: dict[int, str]
    """{k: category} for the labelled objects with at least one labelled point ("mug" in mug scenes)."""
    counts: np.ndarray
    """(K + 1,) int64 labelled points per instance id (index 0: background and unlabelled)."""


def label_points(
    raycaster: Any, points: np.ndarray, *, n_fixtures: int, objects: "list[SceneObject]", tolerance: float
) -> PointLabels:
    """Label each point with the instance of the nearest true surface when closer than `tolerance`.

    Args:
        raycaster: open3d `RaycastingScene` of the true geometry: `n_fixtures` background geometries (table,
            structure pieces), then one per object in order.
        points: (N, 3) float world points of the scan.
        n_fixtures: background geometries before the objects.
        objects: the scene's objects (their `label`: mug k -> k, distractor 0).
        tolerance: largest distance (metres) to the nearest surface for a label.

    Returns:
        The instance ids, the categories present and the labelled point counts.
    """
    from efem_viz._typeshims import o3d_tensor

    q = raycaster.compute_closest_points(o3d_tensor(points.astype(np.float32)))
    gid = q["geometry_ids"].numpy().astype(np.int64)
    dist = np.linalg.norm(q["points"].numpy() - points.astype(np.float32), axis=1)
    labels_of_geom = np.array([0] * n_fixtures + [o.label for o in objects], np.int32)
    instance = np.where(dist < tolerance, labels_of_geom[gid], 0).astype(np.int32)
    present = set(np.unique(instance[instance > 0]).tolist())
    categories = {o.label: o.category for o in objects if o.label in present}
    counts = np.bincount(instance, minlength=len(objects) + 1)
    return PointLabels(instance, categories, counts)
