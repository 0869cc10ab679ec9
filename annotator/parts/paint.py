"""The paint part: paint and erase (dabs, strokes), region grow, fill, pick, and the active tool at a point."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator

import numpy as np

from annotator import selection as sel
from annotator.labels import Delta
from annotator.tools import Hit

if TYPE_CHECKING:
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart
    from annotator.parts.cursor import CursorPart
    from annotator.parts.instances import InstancePart
    from annotator.tools import ToolHost


@dataclass
class Stroke:
    """A drag stroke in progress (one undo group)."""

    group: str
    last: np.ndarray
    """(3,) float32, the last brush position, world frame."""
    normal: np.ndarray
    erase: bool
    source: str = ""
    """Label of the tool that paints the stroke (history)."""


class PaintPart:
    """Every edit that paints vertices with the active instance (or erases them); one journalled edit each."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks, brush: CursorPart,
                 instances: InstancePart, host: ToolHost) -> None:
        self.scan, self.toolbox, self.hooks = scan, toolbox, hooks
        self.brush, self.instances = brush, instances
        self.host = host
        """What the tools' functions get (the session)."""
        self.strokes: dict[int, Stroke] = {}
        """Drag strokes in progress, by client id."""
        self._tls = threading.local()

    def paint(self, idx: np.ndarray, *, erase: bool = False, group: str = "", client: str = "") -> Delta | None:
        """Paint vertices `idx` with the active instance (or erase them); one journalled edit.

        Inside a gesture the edit's label names the tool ("paint 1,234 → mug 1 (Region grow)"), as the history
        panel and the journal show it; a paint that relabels vertices of other instances says how many ("paint
        1,234 → mug 1, 56 taken from other instances (Brush)": *Only unlabelled vertices* keeps them).
        """
        source = getattr(self._tls, "source", "")

        def tagged(d: Delta) -> Delta:
            label = d.label
            taken = 0 if erase else int(np.count_nonzero(d.before > 0))
            if taken:
                label += f", {taken:,} taken from other instances"
            if source:
                label += f" ({source})"
            return d if label == d.label else dataclasses.replace(d, label=label)

        if erase:
            return self.scan.store.do(lambda ls: tagged(ls.erase(idx)), client=client, group=group)
        iid = self.instances.require_active()
        return self.scan.store.do(
            lambda ls: tagged(ls.paint(idx, iid, overwrite=not self.toolbox.settings.only_unlabelled)), client=client,
            group=group,
        )

    @contextlib.contextmanager
    def edit_source(self, source: str) -> Iterator[None]:
        """Edits made in this thread inside the block are labelled with `source` (a tool or gesture name)."""
        prev = getattr(self._tls, "source", "")
        self._tls.source = source
        try:
            yield
        finally:
            self._tls.source = prev

    def _brush_normal(self, vertex: int) -> tuple[np.ndarray | None, float | None]:
        lim = self.toolbox.settings.brush_max_angle_deg
        if lim >= 180:
            return None, None
        return self.scan.geom.normals[vertex], lim

    def _brush_at(self, position: np.ndarray, vertex: int, start: np.ndarray | None = None) -> np.ndarray:
        """Vertices under a dab at `position` (or along the segment from `start`), with the normal limit."""
        nrm, lim = self._brush_normal(vertex)
        radius = self.toolbox.settings.radius
        if start is None:
            return sel.brush(self.scan.geom, position, radius, normal=nrm, max_normal_angle_deg=lim)
        return sel.brush_segment(self.scan.geom, start, position, radius, normal=nrm, max_normal_angle_deg=lim)

    def paint_stroke(self, points: np.ndarray, *, erase: bool = False, client: str = "") -> int:
        """Paint a whole stroke through surface points (what a drag does): returns vertices changed.

        Args:
            points: (S, 3) brush positions on the surface, world frame.
            erase: erase instead of painting the active instance.
        """
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        group = uuid.uuid4().hex[:12]
        changed = 0
        prev = None
        for p in pts:
            v = int(self.scan.geom.tree.query(p)[1])
            self.brush.move_cursor(p, v)
            d = self.paint(self._brush_at(p, v, prev), erase=erase, group=group, client=client)
            changed += 0 if d is None else d.num_vertices
            prev = p
        return changed

    def dab(self, vertex: int, position: np.ndarray, *, erase: bool, client: str = "") -> Delta | None:
        """One brush (or erase) dab of the current radius at a surface point.

        Args:
            vertex: the scan vertex at the point (its normal limits the brush when a normal limit is set).
            position: (3,) float, the point on the surface, world frame.
            erase: erase instead of painting the active instance.
        """
        self.brush.move_cursor(position, int(vertex))
        return self.paint(self._brush_at(position, int(vertex)), erase=erase, client=client)

    def grow(self, seed: int, *, client: str = "") -> Delta | None:
        """Region grow from a vertex with the current settings and paint the result."""
        ls = self.scan.store.labelset
        allowed = ~np.isin(ls.labels, ls.protected_ids())
        if self.toolbox.settings.only_unlabelled:
            allowed &= ls.labels == 0
        if self.toolbox.settings.grow_min_height > 0:
            allowed &= self.scan.scene.points[:, 2] >= self.toolbox.settings.grow_min_height
        idx = sel.region_grow(self.scan.geom, seed, max_angle_deg=self.toolbox.settings.grow_angle_deg,
                              max_distance=self.toolbox.settings.grow_distance, allowed=allowed)
        return self.paint(idx, client=client)

    def fill(self, seed: int, *, client: str = "") -> Delta | None:
        """Bucket fill: the connected region sharing the seed's label becomes the active instance."""
        idx = sel.fill_same_label(self.scan.geom, seed, self.scan.store.labels)
        if self.toolbox.settings.grow_min_height > 0:
            idx = idx[self.scan.scene.points[idx, 2] >= self.toolbox.settings.grow_min_height]
        return self.paint(idx, client=client)

    def pick_instance(self, vertex: int) -> int:
        """Make the instance under a vertex active; returns its id (0 = unlabelled, nothing changes)."""
        iid = int(self.scan.store.labels[vertex])
        if iid > 0:
            self.instances.set_active(iid)
        return iid

    def apply_tool(self, hit: Hit) -> None:
        """The active tool at a surface point (`Tool.apply_at`; nothing for a tool without one)."""
        tool = self.toolbox.tool
        if tool.apply_at is not None:
            with self.edit_source(tool.label):
                tool.apply_at(self.host, hit)

    def click(self, origin: np.ndarray, direction: np.ndarray, *, client: str = "") -> int | None:
        """Apply the active tool at the surface point hit by a ray; returns the hit vertex (None = miss)."""
        hit = sel.pick(self.scan.geom, origin, direction)
        if hit is None:
            return None
        v, pos = hit
        self.apply_tool(Hit(int(v), np.asarray(pos), client))
        return v

    def stroke_start(self, key: int, position: np.ndarray, *, client: str = "") -> None:
        """A Ctrl/Cmd+drag starts at a surface point: a stroke tool paints its first dab, other tools act once.

        Args:
            key: the dragging client's id (strokes of several clients may run at once).
            position: (3,) float, the grabbed surface point, world frame.
        """
        tool = self.toolbox.tool
        start = np.asarray(position, np.float32)
        v = int(self.scan.geom.tree.query(start)[1])
        if not tool.stroke:
            self.apply_tool(Hit(v, start, client))
            return
        p = self.scan.scene.points[v] if self.scan.geom.is_mesh is False else start
        stroke = Stroke(group=uuid.uuid4().hex[:12], last=np.asarray(p, np.float32), normal=self.scan.geom.normals[v],
                        erase=tool.erase, source=tool.label)
        self.brush.move_cursor(stroke.last, v)
        self.strokes[key] = stroke
        with self.edit_source(stroke.source):
            self.paint(self._brush_at(stroke.last, v), erase=stroke.erase, group=stroke.group, client=client)

    def stroke_to(self, key: int, camera_position: np.ndarray, target: np.ndarray, *, end: bool = False,
                  client: str = "") -> None:
        """Continue a client's stroke to the surface point seen from the camera through `target` (world).

        Args:
            key: the dragging client's id.
            camera_position: (3,) float, the camera, world frame.
            target: (3,) float, a point on the ray (viser's drag `end_position`), world frame.
            end: the drag ends here.
        """
        stroke = self.strokes.get(key)
        if stroke is None:
            return
        if end:
            self.strokes.pop(key, None)
        cam = np.asarray(camera_position, np.float64)
        hit = sel.pick(self.scan.geom, cam, np.asarray(target, np.float64) - cam)
        if hit is None:
            return
        v, pos = hit
        self.brush.move_cursor(pos, v)
        idx = self._brush_at(pos, v, stroke.last)
        stroke.last = np.asarray(pos, np.float32)
        with self.edit_source(stroke.source):
            self.paint(idx, erase=stroke.erase, group=stroke.group, client=client)
