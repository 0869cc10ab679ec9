"""Synthetic scans with per-point ground truth: procedural mugs (+ distractors) on a table, or chairs on a floor.

The six configurations of the EFEM paper's synthetic mug scenes:
  * ``"z"``: mugs upright with a random yaw, placed without overlap;
  * ``"so3"``: objects dropped with a random orientation (pybullet) and resting on the table;
  * ``"pile"``: objects dropped one after the other onto the ones already lying there (pybullet), so that
    they stack, lean on and touch each other;
  * ``"tree"``: mugs threaded by their handles on the pegs of a mug tree, then settled by pybullet (they drop
    onto the pegs and hang tilted); only mugs whose handle opening clears a peg are drawn;
  * ``"box"``: objects dropped one after the other into an open box whose walls hide part of them;
  * ``"shelf"``: objects upright on the 2-3 levels of a shelf, partly hidden by the level above; the cameras
    stand in front of it.
The supporting structures (`efem_viz.data.structures`) are background (id 0), like the table.
Physics uses a convex decomposition of every object (`procedural.make_shape_with_parts`); final poses are
checked for interpenetration with signed distances on the exact meshes (dropped again when above tolerance).

The table top (0.8 x 0.8 m, top face at z = 0) is scanned by virtual depth cameras at the table corners
looking at the objects (open3d ray casting; pinhole 640 x 480, Kinect-like axial noise
sigma(z) = 1.2 mm + 1.9 mm (z - 0.4)^2 and dropout at grazing angles), then fused by a projective TSDF into
a mesh (``mode="tsdf"``) or merged and voxel-downsampled as points (``mode="points"``). Ground truth: each
output point takes the label of the nearest true surface (table, object or distractor) when closer than
`label_tolerance`; labelled object k has id k, everything else 0.

The labelled objects (``targets``) are mugs, the kitchen family (mugs, bowls, bottles and cans mixed, the
paper's SynKit) or chairs (the paper's SynChairs; configurations z, so3 and pile). Each stands on a `Stage`
(`stage.TARGET_STAGES`): mugs and kitchen objects on the table, chairs on a 6 m square floor, scanned from
about 3 m away at 1.2-1.7 m height, fused with a 1 cm voxel, with furniture-sized blocks as distractors.

World frame: metres, +Z up, the support's top (table or floor) at z = 0. Same arguments -> identical arrays.

One module per step: `stage` (the support and the scale around it), `layout` (configurations, objects,
placement without physics), `physics` (pybullet drops, `contact_report`), `render` (cameras, noisy depth
frames), `fusion` (TSDF mesh or voxel-averaged points), `labels` (ground truth from the nearest true surface),
`generate` (`generate_scene`, the steps in order) and `cli` (`GenerateArgs`, the `generate` command). This
package re-exports their public names.
"""

from __future__ import annotations

from efem_viz.data.synth.cli import GenerateArgs
from efem_viz.data.synth.generate import generate_scene
from efem_viz.data.synth.labels import PointLabels, label_points
from efem_viz.data.synth.layout import (
    CONFIGS,
    DISTRACTOR_CATEGORIES,
    STRUCTURE_CONFIGS,
    TABLE_HALF,
    TABLE_THICKNESS,
    Config,
    Mode,
)
from efem_viz.data.synth.physics import COLLISION_SHRINK, PENETRATION_TOLERANCE, contact_report
from efem_viz.data.synth.stage import FLOOR, TABLETOP, TARGET_STAGES, Stage, stage_for

__all__ = [
    "COLLISION_SHRINK",
    "CONFIGS",
    "DISTRACTOR_CATEGORIES",
    "FLOOR",
    "PENETRATION_TOLERANCE",
    "STRUCTURE_CONFIGS",
    "TABLE_HALF",
    "TABLETOP",
    "TABLE_THICKNESS",
    "TARGET_STAGES",
    "Config",
    "GenerateArgs",
    "Mode",
    "PointLabels",
    "Stage",
    "contact_report",
    "generate_scene",
    "label_points",
    "stage_for",
]
