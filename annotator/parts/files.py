"""The files part: export the labels (PLY, NPZ, ScanNet) and import a label file, confined to the session's folders."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from annotator.io import LabelIOError, load_labels, resolve_inside, save_labels_npz, save_labels_ply, save_scannet
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

    def export(self, fmt: Literal["ply", "npz", "scannet"], *, directory: str | None = None) -> list[Path]:
        """Write the labels to `<out>/<stem>.labels.ply|.labels.npz` or ScanNet JSON; returns the paths.

        Args:
            fmt: "ply", "npz" or "scannet".
            directory: a folder inside the output folder (relative paths are taken below it); default: the
                output folder. Anything resolving elsewhere (`..`, the scan's folder, symlinks out) is refused.
        """
        d = self.safe_path(directory, what="export directory") if directory else self.scan.out_dir
        labels, table = self.scan.store.snapshot()
        stem = self.scan.stem
        if fmt == "ply":
            out = [save_labels_ply(self.scan.scene, labels, table,
                                   self.safe_path(str(d / f"{stem}.labels.ply"), what="export file"))]
        elif fmt == "npz":
            out = [save_labels_npz(labels, table, self.safe_path(str(d / f"{stem}.labels.npz"), what="export file"),
                                   scan_name=stem)]
        elif fmt == "scannet":
            out = list(save_scannet(labels, table, d, self.scan.stem))
        else:
            raise ValueError(f"unknown export format {fmt!r}; use ply, npz or scannet")
        present = set(np.flatnonzero(np.bincount(labels.clip(0)) > 0).tolist())  # O(N), not a sort of N
        pending = [k for k in unreviewed_prelabels(table) if k in present]
        warn = (f"; {len(pending)} unreviewed EFEM pre-label{'s' if len(pending) != 1 else ''} exported as "
                "objects (review or delete them first)") if pending else ""
        self.hooks.notify("Exported", f"{', '.join(p.name for p in out)} in {d}{warn}")
        log.info("exported %s", [str(p) for p in out])
        return out

    def import_labels(self, path: str) -> Delta | None:
        """Replace all labels by a file's (undoable). Only files inside the scan/output folders are read."""
        p = resolve_inside(path, self.scan.roots, what="label file")
        data = load_labels(p, self.scan.n)
        return self.scan.store.do(lambda ls: ls.replace_all(data.labels, data.instances, label=f"import {p.name}"))
