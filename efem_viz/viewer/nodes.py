"""Scene nodes of the viewer: every `draw_*` function that touches `server.scene` lives here.

Rules (docs/design/VISER-NOTES.md): heavy geometry is sent once and switched by `visible`; per-step and
per-threshold updates only resend colours (uint8) or flip visibility. Node paths:

* `/scene/points`, `/scene/mesh` — the scan (points always exist: they carry every recolouring);
* `/em/samples` — sampled points of the drawn proposals at the current step, coloured by id;
* `/em/shapes/p<id>_t<step>` — decoded shapes (one mesh per proposal and step, cached and re-shown);
* `/inspect/...` — the four Fig. S9 views of the inspected proposal, laid out beside the scene;
* `/results/mesh/k<i>`, `/results/obb/k<i>`, `/results/axes/k<i>`, `/results/label/k<i>` — final instances
  (threshold = visibility; the label names the category). Labels sit above their boxes and are lifted apart so
  that the shown ones do not overlap (`efem_viz.viewer.label_layout`); `/results/leaders` links a lifted label
  to its box.

The `add_*` functions draw on any `SceneApi` with the constants below; the live viewer (`SceneNodes`) and the
static demo (`efem_viz.viewer.export`) both draw through them, so the two look the same.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from efem_viz.colors import DEAD_COLOR, instance_colors, result_colors, rgb_tuple
from efem_viz.geometry.transforms import rotation_to_quat_wxyz, xyz_tuple
from efem_viz.serve.camera import View, fitted_view
from efem_viz.viewer.label_layout import leader_segments, place_labels
from efem_viz.viewer.legend import instance_label

if TYPE_CHECKING:
    from viser import (
        FrameHandle,
        GlbHandle,
        LabelHandle,
        LineSegmentsHandle,
        MeshHandle,
        PointCloudHandle,
        SceneApi,
        SceneNodeHandle,
        SceneNodePointerEvent,
    )

    from efem_viz.data.scene import Scene
    from efem_viz.em.results import Instances

logger = logging.getLogger(__name__)

POINT_SIZE_OF_DIAGONAL = 0.004
"""Default scan point size, as a fraction of the scene's bounding-box diagonal."""
SAMPLE_SIZE = 1.6
"""Sampled points are drawn this many times the scan's point size."""
SHAPE_OPACITY = 0.85
"""Opacity of the decoded per-step shapes."""
RESULT_MESH_OPACITY = 0.8
"""Opacity of the final instances' meshes."""
OBB_THICKNESS_PX = 2.0
"""Line width of the boxes, screen pixels."""
AXES_LENGTH_OF_EXTENT = 1.2
"""Pose axes are this many times the box's largest half extent long."""
AXES_RADIUS_OF_LENGTH = 0.04
"""Pose axes radius, as a fraction of their length."""
VIEW_DIRECTION = np.array([0.5, -0.95, 0.85])
"""Initial camera offset from the scene centre, in scene diagonals (looking down at the table from the front)."""
LEADER_COLOR = (90, 90, 90)
"""Colour of the leader lines from lifted labels down to their boxes."""
LEADER_THICKNESS_PX = 1.0
"""Line width of the leader lines, screen pixels."""


def scene_diagonal(lo: np.ndarray, hi: np.ndarray) -> float:
    """Length of the bounding-box diagonal from corner `lo` to `hi` ((3,) world); 1 for an empty box."""
    return float(np.linalg.norm(np.asarray(hi) - np.asarray(lo))) or 1.0


def default_point_size(diagonal: float) -> float:
    """Scan point size (world units) for a scene of this bounding-box diagonal (`POINT_SIZE_OF_DIAGONAL` of it)."""
    return max(float(diagonal) * POINT_SIZE_OF_DIAGONAL, 1e-4)


def add_sample_cloud(
    api: SceneApi, points: np.ndarray, colors: np.ndarray, *, point_size: float, visible: bool = True
) -> PointCloudHandle:
    """`/em/samples`: the sampled points of the drawn proposals ((S, 3) float32 world, (S, 3) uint8)."""
    return api.add_point_cloud(
        "/em/samples",
        points=np.asarray(points, np.float32),
        colors=np.asarray(colors, np.uint8),
        point_size=point_size * SAMPLE_SIZE,
        point_shape="circle",
        visible=visible,
    )


def add_shape_mesh(
    api: SceneApi, name: str, vertices: np.ndarray, faces: np.ndarray, *, pid: int, dead: bool, visible: bool = True
) -> MeshHandle:
    """A decoded proposal shape: coloured by proposal id, red (`DEAD_COLOR`) once terminated.

    Args:
        api: `server.scene`.
        name: node path.
        vertices: (V, 3) float32 world.
        faces: (F, 3) int32.
        pid: proposal id (its colour).
        dead: the proposal is terminated at the shown step.
        visible: initial visibility.
    """
    color = DEAD_COLOR if dead else instance_colors([pid])[0]
    return api.add_mesh_simple(
        name,
        vertices=np.asarray(vertices, np.float32),
        faces=np.asarray(faces, np.int32),
        color=rgb_tuple(color),
        opacity=SHAPE_OPACITY,
        visible=visible,
    )


def instance_label_position(instances: Instances, k: int) -> tuple[float, float, float]:
    """Just above the top of instance k's box (world frame)."""
    c = np.asarray(instances.obb_center[k], np.float64).reshape(3)
    axes = np.asarray(instances.obb_axes[k], np.float64).reshape(3, 3)
    h = np.asarray(instances.obb_half_extents[k], np.float64).reshape(3)
    top = float(np.abs(axes[2]) @ h)  # the box's half height along world z
    return xyz_tuple(c + np.array([0.0, 0.0, top * 1.15]))


@dataclass
class ResultNodes:
    """Scene handles of the final instances, one entry per instance (in the order of the `Instances`)."""

    meshes: list[MeshHandle | None] = field(default_factory=list)
    """`/results/mesh/k<i>` (None: the instance has no mesh)."""
    obbs: list[LineSegmentsHandle] = field(default_factory=list)
    """`/results/obb/k<i>`."""
    axes: list[FrameHandle] = field(default_factory=list)
    """`/results/axes/k<i>`: the pose."""
    labels: list[LabelHandle] = field(default_factory=list)
    """`/results/label/k<i>`: category, id and confidence (`instance_label`)."""
    label_anchors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(K, 3) where each label wants to be: just above its box (`instance_label_position`), world frame."""
    label_texts: list[str] = field(default_factory=list)
    """The K label texts."""
    label_priority: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(K,) the confidences: the more confident label keeps its spot when two would overlap."""
    label_view: View | None = None
    """The view the labels are laid out for (`efem_viz.viewer.label_layout.place_labels`)."""
    label_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(K, 3) where each label is now, world frame."""
    laid_out_for: bytes | None = None
    """The (K,) bool mask of shown labels the current positions were laid out for."""
    leaders: LineSegmentsHandle | None = None
    """`/results/leaders`: a line from each lifted, shown label down to its anchor (None: no label is lifted)."""
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    """(K, 3) uint8: each instance's own colour (`result_colors`)."""
    box_colors: list[tuple[int, int, int]] = field(default_factory=list)
    """The colour each box is drawn in now (its own, or green / red in the TP/FP/FN mode)."""


def label_view(instances: Instances, view: View | None = None) -> View:
    """The view the instance labels are laid out for: `view` (the viewer's fitted view of the scene), or without
    one the fitted view of the instances' boxes from twice `VIEW_DIRECTION`'s distance (the scene holds the
    boxes and is seen from farther away; laying out for a farther camera only spaces the labels more)."""
    if view is not None:
        return view
    k = len(np.asarray(instances.ids).reshape(-1))
    if k == 0:
        return fitted_view(np.full(3, -0.5), np.full(3, 0.5), direction=VIEW_DIRECTION)
    corners = np.concatenate([np.asarray(instances.obb(i).corners, np.float64).reshape(-1, 3) for i in range(k)])
    return fitted_view(corners.min(axis=0), corners.max(axis=0), direction=2.0 * VIEW_DIRECTION)


def add_leaders(api: SceneApi, anchors: np.ndarray, positions: np.ndarray, *, visible: bool = True
                ) -> LineSegmentsHandle | None:
    """`/results/leaders`: one thin line from each lifted label down to its anchor (None, and the node removed,
    when no label is lifted).

    Args:
        api: `server.scene`.
        anchors: (K, 3) float wanted label positions, world frame.
        positions: (K, 3) float placed label positions, world frame.
        visible: initial visibility.
    """
    seg = leader_segments(anchors, positions)
    if seg.shape[0] == 0:
        try:
            api.remove_by_name("/results/leaders")
        except Exception:  # noqa: BLE001 - none drawn
            pass
        return None
    return api.add_line_segments("/results/leaders", points=seg, colors=LEADER_COLOR,
                                 thickness=LEADER_THICKNESS_PX, thickness_units="screen", visible=visible)


def add_result_nodes(api: SceneApi, instances: Instances, *, visible: bool,
                     view: View | None = None) -> ResultNodes:
    """Draw every final instance: its mesh, box, pose axes and label, in its palette colour.

    The live viewer draws them hidden and switches visibility with the threshold; the static demo draws the
    instances above its threshold visible. Both go through here, so they look the same. The labels are laid out
    over all the given instances so that none overlaps another (`efem_viz.viewer.label_layout`); the live viewer
    lays them out again over the shown ones (`SceneNodes.show_results`).

    Args:
        api: `server.scene`.
        instances: `efem_viz.em.Instances` (ids, category, confidence, mesh_vertices/mesh_faces lists, R,
            center, obb_half_extents and `obb(k)`).
        visible: initial visibility of every node.
        view: the camera the labels must not overlap in (the fitted view of the scene); default `label_view`.
    """
    ids = np.asarray(instances.ids).reshape(-1)
    cols = result_colors(instances)
    out = ResultNodes(colors=cols, box_colors=[rgb_tuple(c) for c in cols])
    out.label_anchors = np.array([instance_label_position(instances, k) for k in range(ids.shape[0])],
                                 np.float64).reshape(-1, 3)
    out.label_texts = [instance_label(instances, k) for k in range(ids.shape[0])]
    out.label_priority = np.asarray(instances.confidence, np.float64).reshape(-1)
    out.label_view = label_view(instances, view)
    if visible:
        out.label_positions = place_labels(out.label_anchors, out.label_texts, view=out.label_view,
                                           priority=out.label_priority)
    else:  # laid out over the shown ones when they are shown (`SceneNodes.lay_out_labels`)
        out.label_positions = out.label_anchors.copy()
    out.laid_out_for = np.full(ids.shape[0], bool(visible)).tobytes()
    for k in range(ids.shape[0]):
        col = rgb_tuple(cols[k])
        verts = instances.mesh_vertices[k] if k < len(instances.mesh_vertices) else None
        faces = instances.mesh_faces[k] if k < len(instances.mesh_faces) else None
        if verts is not None and faces is not None and len(faces):
            out.meshes.append(api.add_mesh_simple(
                f"/results/mesh/k{k}", vertices=np.asarray(verts, np.float32), faces=np.asarray(faces, np.int32),
                color=col, opacity=RESULT_MESH_OPACITY, visible=visible,
            ))
        else:
            out.meshes.append(None)
        half = np.asarray(instances.obb_half_extents[k], np.float64).reshape(3)
        seg = instances.obb(k).line_segments().astype(np.float32)  # (12, 2, 3) world
        out.obbs.append(api.add_line_segments(
            f"/results/obb/k{k}", points=seg, colors=col, thickness=OBB_THICKNESS_PX, thickness_units="screen",
            visible=visible,
        ))
        length = max(float(np.max(half)) * AXES_LENGTH_OF_EXTENT, 1e-3)
        w, x, y, z = (float(v) for v in rotation_to_quat_wxyz(np.asarray(instances.R[k], np.float64)))
        out.axes.append(api.add_frame(
            f"/results/axes/k{k}", wxyz=(w, x, y, z), position=xyz_tuple(np.asarray(instances.center[k]).reshape(3)),
            axes_length=length, axes_radius=length * AXES_RADIUS_OF_LENGTH, visible=visible,
        ))
        out.labels.append(api.add_label(
            f"/results/label/k{k}", text=out.label_texts[k], position=xyz_tuple(out.label_positions[k]),
            visible=visible, anchor="bottom-center",
        ))
    out.leaders = add_leaders(api, out.label_anchors, out.label_positions, visible=visible)
    return out


@dataclass
class SceneNodes:
    """Owns the viewer's scene handles. One instance per server (the scene is shared by all clients).

    Attributes:
        scene_api: `server.scene` (a `viser.SceneApi`).
    """

    scene_api: SceneApi
    point_size: float = POINT_SIZE_OF_DIAGONAL
    points: PointCloudHandle | None = None
    """`/scene/points`: the scan (carries every recolouring)."""
    mesh: GlbHandle | None = None
    """`/scene/mesh`: the scan's mesh (mesh scenes only)."""
    samples: PointCloudHandle | None = None
    shapes: OrderedDict[tuple[int, int], MeshHandle] = field(default_factory=OrderedDict)
    """Decoded shapes by (proposal id, step), least recently shown first."""
    inspect: dict[str, SceneNodeHandle] = field(default_factory=dict)
    results: ResultNodes = field(default_factory=ResultNodes)
    """The final instances (see `add_result_nodes`)."""
    max_cached_shapes: int = 256
    on_shape_click: Callable[[int], None] | None = None
    """Called with the proposal id when a decoded shape is clicked in the browser (or None)."""
    _colors_key: Hashable | None = None
    _extent: float = 1.0
    _bounds: np.ndarray = field(default_factory=lambda: np.array([[-0.5, -0.5, 0.0], [0.5, 0.5, 0.5]]))

    # ------------------------------------------------------------------ scene
    def clear(self) -> None:
        """Remove every node this viewer created (scene change)."""
        for name in ("/scene", "/em", "/inspect", "/results"):
            try:
                self.scene_api.remove_by_name(name)
            except Exception:  # noqa: BLE001 - removing a missing node is fine
                pass
        self.points = self.mesh = self.samples = None
        self.shapes.clear()
        self.inspect.clear()
        self.results = ResultNodes()
        self._colors_key = None

    def draw_scene(self, scene: Scene, *, display: str = "points", point_size: float | None = None) -> None:
        """Send the scan once: a point cloud (always, it carries recolouring) and the mesh when it has faces.

        Args:
            scene: `efem_viz.data.scene.Scene` (points (N,3) f32 world, colors (N,3) u8, faces (M,3) or None).
            display: "points" or "mesh" (initial visibility).
            point_size: world-space point size (default: 0.4 % of the scene diagonal).
        """
        self.clear()
        pts = np.asarray(scene.points, np.float32)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        diag = scene_diagonal(lo, hi)
        self._extent = diag
        self.point_size = float(point_size) if point_size else default_point_size(diag)
        self._bounds = np.stack([lo, hi]).astype(np.float64)
        self.points = self.scene_api.add_point_cloud(
            "/scene/points",
            points=pts,
            colors=np.asarray(scene.colors, np.uint8),
            point_size=self.point_size,
            point_shape="rounded",
            precision="float32",
        )
        if scene.is_mesh:
            import trimesh

            tm = trimesh.Trimesh(
                vertices=pts, faces=np.asarray(scene.faces), vertex_colors=np.asarray(scene.colors), process=False
            )
            self.mesh = self.scene_api.add_mesh_trimesh("/scene/mesh", tm)
        self._colors_key = id(scene.colors)
        self.set_display(display, recolored=False)

    def set_display(self, display: str, *, recolored: bool) -> None:
        """Points or mesh. With a mesh and a recolouring active, the points stay visible over the mesh."""
        if self.points is None:
            return
        if self.mesh is None:
            self.points.visible = True
            return
        self.mesh.visible = display == "mesh"
        self.points.visible = display == "points" or recolored

    def set_point_colors(self, colors: np.ndarray, *, key: Hashable | None = None) -> bool:
        """Recolour the scene points (sends only the (N,3) uint8 colour array).

        Args:
            colors: (N, 3) uint8.
            key: a hashable identity of the colouring; when equal to the last one nothing is sent.

        Returns:
            True when colours were sent.
        """
        if self.points is None:
            return False
        k = key if key is not None else None
        if k is not None and k == self._colors_key:
            return False
        self.points.colors = np.ascontiguousarray(colors, dtype=np.uint8)
        self._colors_key = k
        return True

    # ------------------------------------------------------------------ EM step
    def draw_samples(self, points: np.ndarray, colors: np.ndarray, *, visible: bool = True) -> None:
        """Sampled points of the drawn proposals at the current step, coloured by proposal id.

        Args:
            points: (S, 3) float32 world.
            colors: (S, 3) uint8.
        """
        if points.shape[0] == 0:
            if self.samples is not None:
                self.samples.visible = False
            return
        self.samples = add_sample_cloud(self.scene_api, points, colors, point_size=self.point_size, visible=visible)

    def hide_samples(self) -> None:
        if self.samples is not None:
            self.samples.visible = False

    def has_shape(self, pid: int, step: int) -> bool:
        return (int(pid), int(step)) in self.shapes

    def remove_shapes(self) -> None:
        """Remove every decoded shape (another result: other proposals)."""
        for key in list(self.shapes):
            h = self.shapes.pop(key)
            try:
                h.remove()
            except Exception:  # noqa: BLE001 - already gone
                pass

    def add_shape(self, pid: int, step: int, vertices: np.ndarray, faces: np.ndarray, *, dead: bool = False) -> None:
        """Send one decoded shape (once per proposal and step; later steps switch it by visibility).

        Args:
            pid: proposal id (its colour).
            step: EM step the shape was decoded at.
            vertices: (V, 3) float32 world.
            faces: (F, 3) int32.
            dead: draw it red (the proposal is terminated at this step).
        """
        key = (int(pid), int(step))
        if key in self.shapes:
            return
        h = add_shape_mesh(self.scene_api, f"/em/shapes/p{int(pid)}_t{int(step)}", vertices, faces, pid=int(pid),
                           dead=dead, visible=False)
        if self.on_shape_click is not None:
            callback = self.on_shape_click

            @h.on_click
            def _(_event: SceneNodePointerEvent[MeshHandle], _pid: int = int(pid)) -> None:
                callback(_pid)

        self.shapes[key] = h
        while len(self.shapes) > self.max_cached_shapes:
            old_key, old = self.shapes.popitem(last=False)
            try:
                old.remove()
            except Exception:  # noqa: BLE001
                logger.debug("shape %s already removed", old_key)

    def show_shapes(self, keys: Sequence[tuple[int, int]]) -> int:
        """Make exactly the given (pid, step) shapes visible; returns how many visibility flags changed."""
        want = {(int(p), int(s)) for p, s in keys}
        changed = 0
        for key, h in list(self.shapes.items()):
            vis = key in want
            if h.visible != vis:
                h.visible = vis
                changed += 1
            if vis:
                self.shapes.move_to_end(key)  # most recently shown = last evicted
        return changed

    # ------------------------------------------------------------------ inspector (paper Fig. S9)
    def panel_offset(self, k: int, *, center: np.ndarray, radius: float) -> np.ndarray:
        """World translation that moves content around `center` into inspector panel k (1, 2, 3).

        The panels float in a row above the scene (camera looks down on the table, so they appear above it on
        screen), spaced by 2.6 × `radius` (r_err) and centred on the scene's x.
        """
        lo, hi = self._bounds
        spacing = 2.6 * radius
        target = np.array([(lo[0] + hi[0]) / 2 + (k - 2) * spacing, (lo[1] + hi[1]) / 2, hi[2] + 1.8 * radius])
        return (target - np.asarray(center, float).reshape(3)).astype(np.float32)

    def draw_inspector(
        self,
        *,
        crop_points: np.ndarray,
        crop_colors: np.ndarray,
        sampled_points: np.ndarray,
        sample_color: np.ndarray,
        mesh_vertices: np.ndarray | None,
        mesh_faces: np.ndarray | None,
        center: np.ndarray,
        radius: float,
        label: str,
    ) -> None:
        """Draw the crop, the sampled points and the decoded shape in three panels above the scene (Fig. S9).

        Panel 0 is the scene itself, recoloured by the weights (done through `set_point_colors`).

        Args:
            crop_points: (C, 3) float32 world, points within r_err of the proposal centre.
            crop_colors: (C, 3) uint8 heat-map colours of their weights.
            sampled_points: (M, 3) float32 world.
            sample_color: (3,) uint8 (red once the proposal is terminated).
            mesh_vertices: (V, 3) float32 world or None (not decoded).
            mesh_faces: (F, 3) int32 or None.
            center: (3,) proposal centre Θ_c, world.
            radius: r_err of the proposal (panel size).
            label: text shown above the panels.
        """
        self.clear_inspector()
        c = np.asarray(center, np.float32).reshape(3)
        api = self.scene_api
        ps = self.point_size * 1.3
        offs = {k: self.panel_offset(k, center=c, radius=radius) for k in (1, 2, 3)}
        for k, title in ((1, "weights (crop)"), (2, "sampled points"), (3, "decoded shape")):
            pos = c + offs[k] + np.array([0.0, 0.0, 1.15 * radius], np.float32)
            self.inspect[f"label{k}"] = api.add_label(
                f"/inspect/label{k}", text=f"{label}: {title}", position=xyz_tuple(pos)
            )
        if crop_points.shape[0]:
            self.inspect["crop"] = api.add_point_cloud(
                "/inspect/crop",
                points=np.asarray(crop_points, np.float32) + offs[1],
                colors=np.asarray(crop_colors, np.uint8),
                point_size=ps,
                point_shape="rounded",
            )
        if sampled_points.shape[0]:
            self.inspect["samples"] = api.add_point_cloud(
                "/inspect/samples",
                points=np.asarray(sampled_points, np.float32) + offs[2],
                colors=rgb_tuple(np.asarray(sample_color).reshape(3)),
                point_size=ps,
                point_shape="circle",
            )
        if mesh_vertices is not None and mesh_faces is not None and len(mesh_faces):
            self.inspect["shape"] = api.add_mesh_simple(
                "/inspect/shape",
                vertices=np.asarray(mesh_vertices, np.float32) + offs[3],
                faces=np.asarray(mesh_faces, np.int32),
                color=rgb_tuple(np.asarray(sample_color).reshape(3)),
            )

    def clear_inspector(self) -> None:
        if self.inspect:
            try:
                self.scene_api.remove_by_name("/inspect")
            except Exception:  # noqa: BLE001
                pass
            self.inspect.clear()

    # ------------------------------------------------------------------ results
    def draw_results(self, instances: Instances) -> None:
        """Send the final instances once: mesh, box, pose axes and label each (all hidden until `show_results`).

        Args:
            instances: `efem_viz.em.Instances` (see `add_result_nodes`).
        """
        try:
            self.scene_api.remove_by_name("/results")
        except Exception:  # noqa: BLE001
            pass
        lo, hi = self._bounds
        self.results = add_result_nodes(self.scene_api, instances, visible=False,
                                        view=fitted_view(lo, hi, direction=VIEW_DIRECTION))

    def set_box_colors(self, colors: np.ndarray | None) -> int:
        """Colour the boxes: (K, 3) uint8 one colour per instance (the TP/FP/FN mode), or None for each
        instance's own colour. Only boxes whose colour changes are resent; returns how many."""
        r = self.results
        want = r.colors if colors is None else np.asarray(colors, np.uint8).reshape(-1, 3)
        changed = 0
        for k, h in enumerate(r.obbs):
            col = rgb_tuple(want[k])
            if k < len(r.box_colors) and r.box_colors[k] == col:
                continue
            h.colors = np.array(col, np.uint8)  # one colour, as the box was made: viser's client draws a
            r.box_colors[k] = col  # per-vertex (12, 2, 3) update of a one-colour line set in white
            changed += 1
        return changed

    def show_results(self, keep: np.ndarray, *, show_meshes: bool, show_obbs: bool, show_axes: bool) -> int:
        """Set result visibility from a (K,) bool mask (instances above the threshold) and the layer toggles.

        The labels go with the boxes: both mark where the instances are, and neither hides the points.

        Returns:
            The number of visibility flags that changed (each is a tiny message).
        """
        r = self.results
        layers: tuple[tuple[Sequence[SceneNodeHandle | None], bool], ...] = (
            (r.meshes, show_meshes), (r.obbs, show_obbs), (r.labels, show_obbs), (r.axes, show_axes)
        )
        changed = 0
        for handles, on in layers:
            for k, h in enumerate(handles):
                if h is None:
                    continue
                vis = bool(on and k < keep.shape[0] and keep[k])
                if h.visible != vis:
                    h.visible = vis
                    changed += 1
        return changed + self.lay_out_labels(np.array([h.visible for h in r.labels], bool))

    def lay_out_labels(self, shown: np.ndarray) -> int:
        """Lay the shown labels out so that none overlaps another (hidden ones take no room), move the labels
        whose place changed and redraw the leader lines. Nothing is sent when the shown set is unchanged.

        Args:
            shown: (K,) bool, the labels shown.

        Returns:
            The number of labels moved.
        """
        r = self.results
        shown = np.asarray(shown, bool).reshape(-1)
        if r.label_view is None or shown.shape[0] != len(r.labels) or shown.tobytes() == r.laid_out_for:
            return 0
        idx = np.flatnonzero(shown)
        pos = r.label_positions.copy()
        pos[idx] = place_labels(r.label_anchors[idx], [r.label_texts[i] for i in idx], view=r.label_view,
                                priority=r.label_priority[idx])
        moved = 0
        for k in idx:
            if not np.allclose(pos[k], r.label_positions[k], rtol=0.0, atol=1e-9):
                r.labels[k].position = xyz_tuple(pos[k])
                moved += 1
        r.label_positions = pos
        r.laid_out_for = shown.tobytes()
        r.leaders = add_leaders(self.scene_api, r.label_anchors[idx], pos[idx])
        return moved
