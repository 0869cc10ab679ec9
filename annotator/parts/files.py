"""The files part: export the labels (PLY, NPZ, ScanNet) and import a label file, confined to the session's folders."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from annotator.io import EXPORT_FRAMES, LABEL_WRITERS, LabelIOError, load_labels, resolve_inside
from annotator.labels import Delta, unreviewed_prelabels

if TYPE_CHECKING:
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart

log = logging.getLogger("annotator.session")


class FilePart:
    """Label files in and out: writes resolve inside the output folder, reads inside the scan's or output folder."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks) -> None:
        self.scan, self.toolbox, self.hooks = scan, toolbox, hooks

    def safe_path(self, name: str, *, what: str) -> Path:
        """A path to write: it must resolve inside the output folder chosen at start (relative = below it)."""
        p = resolve_inside(name, [self.scan.out_dir], what=what)
        if p == self.scan.scan_path:
            raise LabelIOError(f"refusing to write {what} over the source scan {p}")
        return p

    def export(self, fmt: str, *, directory: str | None = None, frame: str = "scene") -> list[Path]:
        """Write the labels in one of `annotator.io.LABEL_WRITERS` (`<out>/<stem>.labels.ply`, `.labels.npz`, or
        ScanNet's `.segs.json` + `.aggregation.json`); returns the paths.

        Args:
            fmt: a `LABEL_WRITERS` name: "ply", "npz" or "scannet".
            directory: a folder inside the output folder (relative paths are taken below it); default: the
                output folder. Anything resolving elsewhere (`..`, the scan's folder, symlinks out) is refused,
                the folder and every file written.
            frame: "scene" (the scan as it was opened) or "original": a scan brought in by `import-scan`
                (units and up axis recorded) is written back on its original file's coordinates and units, so the
                labelled PLY lines up with the user's data (`efem_viz.data.scan.scene_in_file_frame`). Labels
                always index the vertices in the file's order, so the label-only formats are the same either way.
        """
        writer = LABEL_WRITERS.get(fmt)
        if writer is None:
            raise ValueError(f"unknown export format {fmt!r}; use {', '.join(LABEL_WRITERS)}")
        if frame not in EXPORT_FRAMES:
            raise ValueError(f"unknown export frame {frame!r}; use {', '.join(EXPORT_FRAMES)}")
        d = self.safe_path(directory, what="export directory") if directory else self.scan.out_dir
        stem = self.scan.stem
        for suffix in writer.suffixes:
            self.safe_path(str(d / f"{stem}{suffix}"), what="export file")
        labels, table = self.scan.store.snapshot()
        scene, undone = self.scan.scene, None
        if frame == "original":
            from efem_viz.data.scan import scene_in_file_frame
            from efem_viz.data.scene import SceneError

            try:
                scene, undone = scene_in_file_frame(scene)
            except SceneError as exc:
                raise LabelIOError(str(exc)) from None
        out = writer.write(scene, labels, table, d, stem)
        present = set(np.flatnonzero(np.bincount(labels.clip(0)) > 0).tolist())  # O(N), not a sort of N
        pending = [k for k in unreviewed_prelabels(table) if k in present]
        warn = (f"; {len(pending)} unreviewed EFEM pre-label{'s' if len(pending) != 1 else ''} exported as "
                "objects (review or delete them first)") if pending else ""
        where = ""
        if frame == "original":
            where = (f", on the scan file's own coordinates ({undone.describe()})" if undone is not None
                     else ", in the scan's own frame (it has no other)")
        self.hooks.notify("Exported", f"{', '.join(p.name for p in out)} in {d}{where}{warn}")
        log.info("exported %s", [str(p) for p in out])
        return out

    def import_labels(self, path: str) -> Delta | None:
        """Replace all labels by a file's (undoable). Only files inside the scan/output folders are read."""
        p = resolve_inside(path, self.scan.roots, what="label file")
        data = load_labels(p, self.scan.n)
        return self.scan.store.do(lambda ls: ls.replace_all(data.labels, data.instances, label=f"import {p.name}"))
