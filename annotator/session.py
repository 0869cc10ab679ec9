"""The annotator's headless session: every labelling action on typed data, no viser, no GUI handle.

`AnnotatorSession` opens one scan and its label store (`annotator.store.LabelStore`: journal first, autosaved
checkpoint, recovery) and does what the annotator does: paint and erase (dabs, strokes), region grow, fill, box
and lasso select, instances (new, update, delete, merge, pick, cycle), undo/redo, import, export, EFEM pre-labels
and their review, and click-to-segment with the shape prior (preview, accept, discard). It is the tools' host
(`annotator.tools.ToolHost`): a tool's functions get the session. `annotator.app.AnnotatorApp` is the thin viser
layer on top: it builds the GUI, translates events into session calls and draws what the session reports through
its hooks (`on_change`, `on_cursor`, `on_lasso`, `on_preview`, `on_segment`, `on_efem`, `notify`).

The session is its parts (`annotator.parts`, one job each; docs/INTERFACES.md), and each action lives in the part
that does it: `toolbox` (the tool table and the settings the tools read), `scan` (the scan, its geometry and label
store, the warm-up), `instances` (the active tool, the instance table, undo/redo), `painting`, `brush` (the brush
cursor), `box_lasso`, `files` and `assist` (EFEM pre-labels, click-to-segment and its thread). The session itself
holds the hooks (`parts.context.SessionHooks`) the parts call, and is the tools' host (`annotator.tools.ToolHost`).

A script or a notebook drives it directly::

    session = AnnotatorSession("sample_scenes/syn_z_1.ply", out_dir="labels")
    session.instances.new_instance(category="mug")
    session.painting.grow(seed=123)
    session.files.export("ply")
    session.close()

Threading: edits go through the store's lock; the click-to-segment run has its own thread (or the caller's with
`wait=True`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

from annotator.io import MAX_SCAN_POINTS
from annotator.parts.assist import AssistPart
from annotator.parts.box_lasso import BoxLassoPart
from annotator.parts.context import SessionHooks, Toolbox
from annotator.parts.cursor import BrushCursor, CursorPart
from annotator.parts.files import FilePart
from annotator.parts.instances import InstancePart
from annotator.parts.paint import PaintPart, Stroke
from annotator.parts.scan import ScanPart
from annotator.tools import DEFAULT_TOOLS, Tool, all_controls, check_tools, scaled_to_scan

if TYPE_CHECKING:
    pass

__all__ = ["AnnotatorSession", "BrushCursor", "Stroke"]


TABLE_CLEARANCE_MIN = 0.005
"""Least height above the table (m) that region grow and fill keep to on an imported tabletop scan."""


def table_clearance(provenance: Mapping[str, Any] | None) -> float:
    """The default *Grow: min height* of a scan (m): on a tabletop imported from an RGB-D frame (`import-rgbd`: the
    table at z = 0) 2.5x the table fit's RMS residual, at least `TABLE_CLEARANCE_MIN`, to 1 mm (a grow from a mug
    then stops at the table instead of flooding it); 0 (off) for any other scan.

    Args:
        provenance: the scene's provenance (`Scene.provenance`).
    """
    prov = dict(provenance or {})
    if prov.get("source") != "rgbd":
        return 0.0
    try:
        rms = float(prov.get("plane_residual_rms_m", 0.0))
    except (TypeError, ValueError):
        rms = 0.0
    rms = rms if np.isfinite(rms) and 0.0 <= rms < 0.05 else 0.0
    return round(max(TABLE_CLEARANCE_MIN, 2.5 * rms), 3)


class AnnotatorSession(SessionHooks):
    """One scan, its label store and every annotator action.

    Args:
        scan_path: the scan (PLY/OBJ/OFF/GLB/NPZ scene, or an RGB-D frame .npz). Never written.
        labels_path: labels to start a *new* session from (ignored with a warning when the output directory
            already holds a journal for this scan: the session resumes instead).
        out_dir: where the journal, checkpoint and exports go (default: the current working directory). The
            journal and checkpoint live in `<out>/<stem>.annotate/`; read-only folders are refused.
        max_points: refuse scans with more vertices.
        autosave_delay: seconds between an edit and the checkpoint rewrite (the journal is always immediate).
        accept_scan_mismatch: resume a journal written for other geometry with the same vertex count.
        tools: the tool table (`annotator.tools.Tool` entries; default `DEFAULT_TOOLS`). The first is active.
        on_stage: called with what the opening does next (`ScanPart`).

    Raises:
        LabelIOError: the scan or labels cannot be read; JournalError: the journal belongs to another scan.
    """

    def __init__(
        self,
        scan_path: str | Path,
        *,
        labels_path: str | Path | None = None,
        out_dir: str | Path | None = None,
        max_points: int = MAX_SCAN_POINTS,
        autosave_delay: float = 0.5,
        accept_scan_mismatch: bool = False,
        tools: Sequence[Tool] = DEFAULT_TOOLS,
        on_stage: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__()
        self.toolbox = Toolbox(tools)
        """The tool table and the settings the tools read."""
        self.scan = ScanPart(scan_path, labels_path=labels_path, out_dir=out_dir, max_points=max_points,
                             autosave_delay=autosave_delay, accept_scan_mismatch=accept_scan_mismatch,
                             on_stage=on_stage)
        """The scan, its geometry and its label store."""
        diagonal = float(np.linalg.norm(np.ptp(self.scan.scene.points, axis=0)))
        self.toolbox.tools = scaled_to_scan(self.toolbox.tools, diagonal)  # sliders as long as the scan needs
        self.toolbox.tool_of = check_tools(self.toolbox.tools)
        settings = self.toolbox.settings
        radius = next(c for c in all_controls(self.toolbox.tools) if c.setting == "radius")
        settings.radius = float(np.clip(0.02 * diagonal, max(0.005, radius.min / radius.scale),
                                        radius.max / radius.scale))
        settings.grow_min_height = table_clearance(self.scan.scene.provenance)
        ls = self.scan.store.labelset
        if ls.instances:
            settings.active_id = max(ls.instances)
            settings.category = ls.instances[settings.active_id].category or "object"
        self.brush = CursorPart(self.scan, self.toolbox, self)
        """The brush cursor."""
        self.instances = InstancePart(self.scan, self.toolbox, self, self.brush)
        """The active tool and the instance table."""
        self.painting = PaintPart(self.scan, self.toolbox, self, self.brush, self.instances, self)
        """Painting, erasing, region grow, fill, the active tool at a point."""
        self.box_lasso = BoxLassoPart(self.scan, self.toolbox, self, self.painting)
        """Box and lasso selection."""
        self.files = FilePart(self.scan, self.toolbox, self)
        """Label export and import."""
        self.assist = AssistPart(self.scan, self.toolbox, self, self.instances, self.painting)
        """EFEM assistance: pre-labels and their review, click-to-segment."""

    def close(self) -> None:
        """Commit what was typed, flush the checkpoint and release the journal (idempotent)."""
        try:
            self.instances.flush_typing()
        finally:
            self.scan.close()
