"""Scene nodes of the viewer: every `draw_*` function that touches `server.scene` lives here.

Rules (VISER-NOTES.md): heavy geometry is sent once and switched by `visible`; per-step and per-threshold updates
only resend colours (uint8) or flip visibility. Node paths:

* `/scene/points`, `/scene/mesh` — the scan (points always exist: they carry every recolouring);
* `/em/samples` — sampled points of the drawn proposals at the current step, coloured by id;
* `/em/shapes/p<id>_t<step>` — decoded shapes (one mesh per proposal and step, cached and re-shown);
* `/inspect/...` — the four Fig. S9 views of the inspected proposal, laid out beside the scene;
* `/results/mesh/k<i>`, `/results/obb/k<i>`, `/results/axes/k<i>` — final instances (threshold = visibility).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from efem_viz.viewer.state import DEAD_COLOR, palette

logger = logging.getLogger(__name__)

OBB_EDGES = np.array(
    [[0, 1], [1, 3], [3, 2], [2, 0], [4, 5], [5, 7], [7, 6], [6, 4], [0, 4], [1, 5], [2, 6], [3, 7]], np.int64
)
"""Edges of a box whose corners are indexed by bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1)."""


def obb_corners(center: np.ndarray, axes: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """Corners of an oriented box.

    Args:
        center: (3,) float, world frame.
        axes: (3, 3) float, columns are the box axes in world.
        half_extents: (3,) float half sizes along those axes.

    Returns:
        (8, 3) float32 corners, indexed by bits as in `OBB_EDGES`.
    """
    signs = np.array([[(i & 1) * 2 - 1, ((i >> 1) & 1) * 2 - 1, ((i >> 2) & 1) * 2 - 1] for i in range(8)], float)
    c = np.asarray(center, float).reshape(3)
    a = np.asarray(axes, float).reshape(3, 3)
    h = np.asarray(half_extents, float).reshape(3)
    return (c[None] + (signs * h[None]) @ a.T).astype(np.float32)


def obb_segments(center: np.ndarray, axes: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """(12, 2, 3) float32 line segments of an oriented box (see `obb_corners`)."""
    corners = obb_corners(center, axes, half_extents)
    return corners[OBB_EDGES].astype(np.float32)


def rotation_to_wxyz(R: np.ndarray) -> np.ndarray:
    """(4,) float64 unit quaternion (w, x, y, z) of a rotation matrix (a reflection is flipped to proper first)."""
    from scipy.spatial.transform import Rotation

    m = np.asarray(R, np.float64).reshape(3, 3)
    if np.linalg.det(m) < 0:
        m = m.copy()
        m[:, 0] *= -1.0
    xyzw = Rotation.from_matrix(m).as_quat()
    return np.array([xyzw[3], xyzw[0], xyzw[1], xyzw[2]])


@dataclass
class SceneNodes:
    """Owns the viewer's scene handles. One instance per server (the scene is shared by all clients).

    Attributes:
        scene_api: `server.scene` (a `viser.SceneApi`).
    """

    scene_api: Any
    point_size: float = 0.004
    points: Any = None
    mesh: Any = None
    samples: Any = None
    shapes: "OrderedDict[tuple[int, int], Any]" = field(default_factory=OrderedDict)
    inspect: dict[str, Any] = field(default_factory=dict)
    result_meshes: list[Any] = field(default_factory=list)
    result_obbs: list[Any] = field(default_factory=list)
    result_axes: list[Any] = field(default_factory=list)
    max_cached_shapes: int = 256
    on_shape_click: Any = None
    """Called with the proposal id when a decoded shape is clicked in the browser (or None)."""
    _colors_key: int | None = None
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
        self.result_meshes.clear()
        self.result_obbs.clear()
        self.result_axes.clear()
        self._colors_key = None

    def draw_scene(self, scene: Any, *, display: str = "points", point_size: float | None = None) -> None:
        """Send the scan once: a point cloud (always, it carries recolouring) and the mesh when it has faces.

        Args:
            scene: `efem_viz.data.scene.Scene` (points (N,3) f32 world, colors (N,3) u8, faces (M,3) or None).
            display: "points" or "mesh" (initial visibility).
            point_size: world-space point size (default: 0.4 % of the scene diagonal).
        """
        self.clear()
        pts = np.asarray(scene.points, np.float32)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        diag = float(np.linalg.norm(hi - lo)) or 1.0
        self._extent = diag
        self.point_size = float(point_size) if point_size else max(diag * 0.004, 1e-4)
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

    def set_point_colors(self, colors: np.ndarray, *, key: Any = None) -> bool:
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
        self.samples = self.scene_api.add_point_cloud(
            "/em/samples",
            points=np.asarray(points, np.float32),
            colors=np.asarray(colors, np.uint8),
            point_size=self.point_size * 1.6,
            point_shape="circle",
            visible=visible,
        )

    def hide_samples(self) -> None:
        if self.samples is not None:
            self.samples.visible = False

    def has_shape(self, pid: int, step: int) -> bool:
        return (int(pid), int(step)) in self.shapes

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
        color = DEAD_COLOR if dead else palette([pid])[0]
        h = self.scene_api.add_mesh_simple(
            f"/em/shapes/p{int(pid)}_t{int(step)}",
            vertices=np.asarray(vertices, np.float32),
            faces=np.asarray(faces, np.int32),
            color=tuple(int(c) for c in color),
            opacity=0.85,
            visible=False,
        )
        if self.on_shape_click is not None:
            callback = self.on_shape_click

            @h.on_click
            def _(_event: Any, _pid: int = int(pid)) -> None:
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
                f"/inspect/label{k}", text=f"{label}: {title}", position=tuple(float(v) for v in pos)
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
                colors=tuple(int(v) for v in np.asarray(sample_color).reshape(3)),
                point_size=ps,
                point_shape="circle",
            )
        if mesh_vertices is not None and mesh_faces is not None and len(mesh_faces):
            self.inspect["shape"] = api.add_mesh_simple(
                "/inspect/shape",
                vertices=np.asarray(mesh_vertices, np.float32) + offs[3],
                faces=np.asarray(mesh_faces, np.int32),
                color=tuple(int(v) for v in np.asarray(sample_color).reshape(3)),
            )

    def clear_inspector(self) -> None:
        if self.inspect:
            try:
                self.scene_api.remove_by_name("/inspect")
            except Exception:  # noqa: BLE001
                pass
            self.inspect.clear()

    # ------------------------------------------------------------------ results
    def draw_results(self, instances: Any) -> None:
        """Send the final instances once: a mesh, an OBB and pose axes each (all hidden until `show_results`).

        Args:
            instances: `efem_viz.em.Instances` (ids, mesh_vertices/mesh_faces lists, R, center, scale, obb_*).
        """
        try:
            self.scene_api.remove_by_name("/results")
        except Exception:  # noqa: BLE001
            pass
        self.result_meshes.clear()
        self.result_obbs.clear()
        self.result_axes.clear()
        ids = np.asarray(instances.ids).reshape(-1)
        cols = palette(ids)
        api = self.scene_api
        for k in range(ids.shape[0]):
            col = tuple(int(c) for c in cols[k])
            verts = instances.mesh_vertices[k] if k < len(instances.mesh_vertices) else None
            faces = instances.mesh_faces[k] if k < len(instances.mesh_faces) else None
            if verts is not None and faces is not None and len(faces):
                self.result_meshes.append(
                    api.add_mesh_simple(
                        f"/results/mesh/k{k}",
                        vertices=np.asarray(verts, np.float32),
                        faces=np.asarray(faces, np.int32),
                        color=col,
                        opacity=0.8,
                        visible=False,
                    )
                )
            else:
                self.result_meshes.append(None)
            seg = obb_segments(instances.obb_center[k], instances.obb_axes[k], instances.obb_half_extents[k])
            self.result_obbs.append(
                api.add_line_segments(
                    f"/results/obb/k{k}", points=seg, colors=col, thickness=2.0, thickness_units="screen", visible=False
                )
            )
            size = float(np.max(instances.obb_half_extents[k])) * 1.2 if len(instances.obb_half_extents) else 0.05
            self.result_axes.append(
                api.add_frame(
                    f"/results/axes/k{k}",
                    wxyz=tuple(rotation_to_wxyz(instances.R[k])),
                    position=tuple(float(v) for v in np.asarray(instances.center[k]).reshape(3)),
                    axes_length=max(size, 1e-3),
                    axes_radius=max(size, 1e-3) * 0.04,
                    visible=False,
                )
            )

    def show_results(self, keep: np.ndarray, *, show_meshes: bool, show_obbs: bool, show_axes: bool) -> int:
        """Set result visibility from a (K,) bool mask (instances above the threshold) and the layer toggles.

        Returns:
            The number of visibility flags that changed (each is a tiny message).
        """
        changed = 0
        for handles, on in ((self.result_meshes, show_meshes), (self.result_obbs, show_obbs), (self.result_axes, show_axes)):
            for k, h in enumerate(handles):
                if h is None:
                    continue
                vis = bool(on and k < keep.shape[0] and keep[k])
                if h.visible != vis:
                    h.visible = vis
                    changed += 1
        return changed
