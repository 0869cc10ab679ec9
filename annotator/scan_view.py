"""The scan as the browser sees it: coloured point chunks, the surface that catches gestures, the brush cursor, the
lasso outline and the camera; a level of detail for scans larger than the display budget.

viser cannot update part of an array, so the drawn points are split into spatial chunks (`annotator.render`); an
edit resends the colours of the chunks it touched only. A scan with more vertices than `display_points` is drawn
from a fixed, evenly spread subset of them (points only: no full-resolution mesh is sent), so a 5M-vertex scan
reaches the browser as about 15 MB instead of several hundred. Every tool still selects and labels the full
vertex set on the server: the subset only decides what is drawn.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from annotator.labels import Delta
from annotator.render import Chunks, build_chunks, color_lut, compose_colors, ring_segments, splat_proxy
from efem_viz.serve.camera import PANEL_PX, CameraGuard, fitted_view, fly_to_view, framing

if TYPE_CHECKING:
    import viser
    from viser import ClientHandle

    from annotator.session import AnnotatorSession

log = logging.getLogger(__name__)

DISPLAY_POINTS = 1_000_000
"""Default display budget: scans with more vertices are drawn from a subset of this many."""
MAX_SPLATS = 150_000
"""Triangles of the invisible proxy surface that catches drags on scans drawn as points."""
CURSOR_COLOR = (255, 150, 0)
"""Colour of the brush cursor's ring."""
CURSOR_THICKNESS_PX = 2.5
"""Line width of the brush cursor's ring, screen pixels."""
LASSO_COLOR = (255, 200, 0)
"""Colour of the lasso outline."""


@dataclass
class Stats:
    """Counters for the benchmark and the status line."""

    bytes_sent: int = 0
    """Colour payload bytes sent to clients since start (3 bytes per drawn point of each redrawn chunk)."""
    chunks_sent: int = 0
    last_edit_bytes: int = 0
    last_edit_ms: float = 0.0
    edits: int = 0


def display_subset(n: int, budget: int, *, seed: int = 0) -> np.ndarray:
    """The vertices drawn for a scan of `n` vertices: all of them, or a fixed random subset of `budget`.

    A uniform subset of a scan's vertices keeps their spatial density (dense parts stay dense), so the drawn cloud
    looks like the scan; it is the same on every open (fixed seed), so the view does not change between sessions.

    Returns:
        (D,) int32 sorted vertex ids, D = min(n, budget).

    Raises:
        ValueError: a budget below 1.
    """
    if budget < 1:
        raise ValueError(f"the display budget must be at least 1 point, got {budget}")
    if n <= budget:
        return np.arange(n, dtype=np.int32)
    return np.sort(np.random.default_rng(seed).choice(n, size=budget, replace=False)).astype(np.int32)


HOME_DIRECTION = (0.0, -1.0, 0.8)
"""From the scan's centre toward the camera of the fitted view: from the front (-Y), looking down at about 40°."""


class ScanView:
    """Draws a session's scan and keeps it up to date (every client sees the same scene).

    Args:
        server: the viser server.
        session: the headless session whose scan, labels and settings are drawn.
        chunk_size: points per drawn chunk.
        display_points: display budget (`DISPLAY_POINTS`); larger scans are drawn from `display_subset`.
        max_splats: triangles of the invisible drag surface of a scan drawn as points (None: `MAX_SPLATS`).
    """

    def __init__(self, server: viser.ViserServer, session: AnnotatorSession, *, chunk_size: int = 16384,
                 display_points: int = DISPLAY_POINTS, max_splats: int | None = None) -> None:
        self.server, self.session = server, session
        scene = session.scan.scene
        self.display = display_subset(scene.num_points, display_points)
        """(D,) int32 vertex ids drawn."""
        self.reduced = len(self.display) < scene.num_points
        """True when the scan is drawn from a subset (level of detail)."""
        self.chunks: Chunks = (build_chunks(scene.points[self.display], max_chunk=chunk_size).lifted(
            self.display, scene.num_points) if self.reduced else build_chunks(scene.points, max_chunk=chunk_size))
        self.stats = Stats()
        self.cursor_handle: viser.LineSegmentsHandle | None = None
        self.lasso_handle: viser.LineSegmentsHandle | None = None
        self._draw_lock = threading.Lock()
        self._cursor_lock = threading.Lock()
        self._lasso_lock = threading.Lock()
        pts = scene.points
        self.extent = float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0
        # Points drawn from a subset of D of the n vertices are sqrt(n / D) times further apart on a surface.
        n = scene.num_points
        spacing = session.scan.geom.spacing * float(np.sqrt(n / max(len(self.display), 1)))
        self.point_size = float(max(spacing * 1.6, self.extent * 5e-4))
        # The proxy's k splats (at most `max_splats`) must cover the surface at their own spacing: 2.5 spacings
        # when every vertex has one (as always), 1.6 of the wider spacing of a subset (fewer overlapping
        # transparent triangles keep software-rendered pages fast).
        max_splats = MAX_SPLATS if max_splats is None else int(max_splats)
        k = min(len(self.display), max_splats)
        splat_spacing = session.scan.geom.spacing * float(np.sqrt(n / max(k, 1)))
        self.surface = self._add_surface((2.5 if k == n else 1.6) * splat_spacing, max_splats)
        """The mesh that receives drag gestures (the scan's own when it is drawn in full, else an invisible proxy)."""
        self.chunk_handles = self._add_chunks()
        flo, fhi, sample = framing(pts)
        self.home_view = fitted_view(flo, fhi, direction=HOME_DIRECTION, points=sample)
        """The fitted view (the scan's central 99 % filling the view, as the viewer frames its scenes) for the planned
        canvas: where a new page starts; each browser is then moved to it fitted to its own canvas, clear of the
        control panel (`camera_guard.view_for`), where R (reset view) also puts it."""
        self.camera_guard = CameraGuard(
            server, self.home_view, pts.min(axis=0), pts.max(axis=0), hint="R (reset view) brings it back any time.",
            panel_px=PANEL_PX,
            fit=lambda aspect: fitted_view(flo, fhi, direction=HOME_DIRECTION, points=sample, aspect=aspect))
        """Puts a camera that left the scan back on its home view, fitted to the part of each browser's canvas the
        control panel leaves free (`CameraGuard.view_for`; see `efem_viz.serve.camera`)."""

    def _add_surface(self, splat_size: float, max_splats: int) -> viser.MeshHandle:
        scene = self.session.scan.scene
        if scene.is_mesh and not self.reduced:
            assert scene.faces is not None
            return self.server.scene.add_mesh_simple("/scan/surface", scene.points, scene.faces,
                                                     color=(205, 205, 205), side="double")
        # An invisible proxy surface: it receives the drag gestures that point clouds do not.
        shown = self.display
        verts, faces = splat_proxy(scene.points[shown], self.session.scan.geom.normals[shown], size=splat_size,
                                   max_splats=max_splats)
        return self.server.scene.add_mesh_simple("/scan/surface", verts, faces, color=(200, 200, 200), opacity=0.0,
                                                 side="double")

    def _add_chunks(self) -> list[viser.PointCloudHandle]:
        lut_show = self._lut()  # one colour table for every chunk
        handles = []
        for c in range(self.chunks.count):
            m = self.chunks.members(c)
            handles.append(self.server.scene.add_point_cloud(
                f"/scan/labels/chunk_{c:04d}", points=self.session.scan.scene.points[m],
                colors=self._colors(m, lut_show), point_size=self.point_size, point_shape="circle"))
        return handles

    def _lut(self) -> tuple[np.ndarray, np.ndarray]:
        """The label colour table (`color_lut`) of the labels now."""
        store = self.session.scan.store
        return color_lut(store.labelset.instances, int(store.labels.max(initial=0)))

    def _colors(self, m: np.ndarray, lut_show: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        ses = self.session
        lut, show = lut_show
        hl = None if ses.assist.preview is None else ses.assist.preview[m]
        run = ses.assist.run_overlay
        return compose_colors(ses.scan.scene.colors[m], ses.scan.store.labels[m], lut, show, highlight=hl,
                              dim_unlabelled=ses.toolbox.settings.labels_only,
                              overlay=None if run is None else (run.codes[m], run.colors))

    def draw_chunks(self, chunk_ids: np.ndarray) -> int:
        """Recompute and send the colours of some chunks; returns the payload bytes sent."""
        with self._draw_lock:
            lut_show = self._lut()
            sent = 0
            for c in np.asarray(chunk_ids, np.int64):
                cols = self._colors(self.chunks.members(int(c)), lut_show)
                self.chunk_handles[int(c)].colors = cols
                sent += cols.nbytes
            self.stats.bytes_sent += sent
            self.stats.chunks_sent += len(chunk_ids)
            return sent

    def redraw(self) -> int:
        """Recompute and send every chunk's colours (a view setting changed)."""
        return self.draw_chunks(np.arange(self.chunks.count))

    def draw_preview(self, idx: np.ndarray) -> int:
        """Redraw the chunks holding some vertices (a segment preview or a running EFEM's overlay changed)."""
        return self.draw_chunks(self.chunks.touched(idx))

    def draw_delta(self, d: Delta) -> int:
        """Redraw what a label change altered: the chunks of its vertices, and those of every instance whose colour
        or visibility it changed; returns the bytes sent."""
        touched = self.chunks.touched(d.idx)
        visual = [k for k, after in d.table_after.items() if _looks_different(d.table_before.get(k), after)]
        if visual:
            mask = np.isin(self.session.scan.store.labels, np.array(visual, np.int32))
            touched = np.union1d(touched, self.chunks.touched(np.flatnonzero(mask)))
        return self.draw_chunks(touched)

    # ---- overlays
    def draw_cursor(self) -> None:
        """Draw the brush cursor where the session has it (hidden for tools without a brush radius)."""
        with self._cursor_lock:
            cur = self.session.brush.cursor
            if cur is None:
                return
            try:
                self.cursor_handle = self.server.scene.add_line_segments(
                    "/annotator/brush_cursor", ring_segments(cur.position, cur.normal, cur.radius),
                    colors=CURSOR_COLOR, thickness=CURSOR_THICKNESS_PX, thickness_units="screen",
                    visible=cur.visible)
            except ValueError:  # a degenerate radius: keep the last ring
                log.debug("brush cursor not drawn", exc_info=True)

    def draw_lasso(self) -> None:
        """Draw the lasso outline (removed when it has fewer than two points)."""
        with self._lasso_lock:
            seg = self.session.box_lasso.lasso_outline.segments()
            if seg is not None:
                self.lasso_handle = self.server.scene.add_line_segments(
                    "/annotator/lasso", seg, colors=LASSO_COLOR, thickness=2.0, thickness_units="screen")
            elif self.lasso_handle is not None:
                with contextlib.suppress(Exception):
                    self.lasso_handle.remove()
                self.lasso_handle = None

    # ---- camera
    def fly_to(self, idx: np.ndarray, client: ClientHandle | None = None) -> None:
        """Point a client's camera (every client's when None) at some vertices: their box, seen from the fitted
        view's direction, filling about half the view."""
        idx = np.asarray(idx, np.int64)
        if idx.size == 0:
            return
        pts = self.session.scan.scene.points[idx]
        self.camera_guard.place(fly_to_view(pts.min(axis=0), pts.max(axis=0), home=self.home_view,
                                            scene_diagonal=self.extent), client)


def _looks_different(before: object, after: object) -> bool:
    """Whether an instance-table change alters how its vertices are drawn (added, removed, colour, visibility or
    review state)."""
    if (before is None) != (after is None):
        return True
    if before is None or after is None:
        return False
    return any(getattr(before, a) != getattr(after, a) for a in ("color", "visible", "unreviewed"))
