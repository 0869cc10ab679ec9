"""The stage of a synthetic scan: the support the objects stand on and the scale of everything around it.

A `Stage` gathers the numbers that depend on how big the labelled objects are: the support (a table top for mugs
and kitchen objects, a room floor for chairs), the object count drawn by the seed, the distractor categories, the
scatter square, the crop box margins, the camera ring and the default voxel. Layout, physics, rendering and
generation read them from the stage chosen by the scene's targets (`stage_for`), so one scene is one scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Stage:
    """A support at z = 0 with the scale of its scene (metres)."""

    name: str
    """"tabletop" or "floor"."""
    support: str
    """What the support is ("table", "floor"); its key in a scene's provenance."""
    half_size: float
    """Half side of the square support; its top face is at z = 0."""
    thickness: float
    """Thickness of the support's slab (below z = 0)."""
    color: tuple[float, float, float]
    """RGB albedo of the support, 0..255."""
    voxel: float
    """Default TSDF voxel / point spacing."""
    label_tolerance: float
    """Default largest distance from a point to the true surface that labels it."""
    object_count: tuple[int, int]
    """Smallest and largest labelled object count drawn by the seed when none is given."""
    distractors: tuple[str, ...]
    """Categories of the unlabelled distractors (`procedural.CATEGORIES`)."""
    scatter_start: tuple[float, float]
    """Half side of the first square the objects are scattered in: base + per object times the object count."""
    scatter_inset: tuple[float, float]
    """How far inside the support's edge the first scatter square, and the grown one, must stay."""
    pile_spread: float
    """Standard deviation of a piled object's drop spot about the centre of the pile so far."""
    crop_margin: float
    """The scan keeps this much around the objects' bounding box horizontally (inside the support)."""
    crop_below: float
    """The scan keeps this much below the support's top."""
    crop_above: float
    """The scan keeps this much above the highest object."""
    camera_ring: float
    """Horizontal distance of the corner cameras from the ring's centre (times 0.9-1.05)."""
    camera_standoff: float | None
    """None: the ring is fixed about the support's centre (the cameras stand at the table's corners). Else it is
    centred on the objects and widens, when they spread far, to at least this much beyond their farthest
    horizontal reach from that centre."""
    camera_heights: tuple[float, float]
    """Range of the cameras' eye heights."""
    aim_height: float
    """Height of the point the cameras look at (above the objects' horizontal centre)."""
    aim_jitter: float
    """Each camera's aim point moves horizontally by up to this much."""
    max_range: float
    """Depth cameras measure nothing farther than this."""
    contact_rays: int
    """Rays per probe of the interpenetration check of dropped poses (`physics.contact_report`)."""
    n_cameras: int
    """Default number of depth cameras around the objects."""
    noise: bool
    """Default depth model: noisy Kinect-like depth (True) or ideal depth (False)."""


TABLETOP = Stage(
    name="tabletop",
    support="table",
    half_size=0.4,
    thickness=0.04,
    color=(190.0, 155.0, 115.0),
    voxel=0.004,
    label_tolerance=0.01,
    object_count=(3, 7),
    distractors=("box", "can", "bowl", "bottle"),
    scatter_start=(0.04, 0.02),
    scatter_inset=(0.12, 0.05),
    pile_spread=0.015,
    crop_margin=0.04,
    crop_below=0.02,
    crop_above=0.03,
    camera_ring=0.4 * math.sqrt(2),
    camera_standoff=None,
    camera_heights=(0.45, 0.6),
    aim_height=0.04,
    aim_jitter=0.02,
    max_range=3.0,
    contact_rays=1,
    n_cameras=4,
    noise=True,
)
"""A 0.8 m square table: mugs and kitchen objects, 4 mm voxel, 4 noisy Kinect-like cameras at its corners
0.45-0.6 m high."""

FLOOR = Stage(
    name="floor",
    support="floor",
    half_size=3.0,
    thickness=0.1,
    color=(165.0, 160.0, 150.0),
    voxel=0.01,
    label_tolerance=0.025,
    object_count=(2, 5),
    distractors=("cabinet",),
    scatter_start=(0.25, 0.15),
    scatter_inset=(1.5, 0.7),
    pile_spread=0.1,
    crop_margin=0.25,
    crop_below=0.05,
    crop_above=0.1,
    camera_ring=2.7,
    camera_standoff=1.0,
    camera_heights=(1.2, 1.7),
    aim_height=0.4,
    aim_jitter=0.1,
    max_range=4.0,
    contact_rays=3,
    n_cameras=8,
    noise=False,
)
"""A 6 m square room floor: chairs, 1 cm voxel, 8 cameras with ideal depth (as the paper's SynChairs scans)
2.4-2.8 m horizontally from the objects' centre (farther when many objects spread wide) at 1.2-1.7 m height,
2.6-3.1 m from the point they look at, 4 m range (with `noise=True`: Kinect v1 axial noise `render._depth_sigma`,
1.4 cm at 3 m)."""

TARGET_STAGES: dict[str, Stage] = {"mug": TABLETOP, "kitchen": TABLETOP, "chair": FLOOR}
"""The labelled objects a scene can have (`generate_scene(targets=...)`) and the stage each stands on: mugs, the
kitchen family (`procedural.FAMILIES`) and chairs."""


def stage_for(targets: str) -> Stage:
    """The stage of a scene whose labelled objects are `targets`.

    Raises:
        ValueError: `targets` is not a key of `TARGET_STAGES`.
    """
    if targets not in TARGET_STAGES:
        raise ValueError(f"unknown targets {targets!r}; expected one of {sorted(TARGET_STAGES)}")
    return TARGET_STAGES[targets]
