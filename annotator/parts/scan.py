"""The scan part: open the scan and its label store (journal, checkpoint, recovery), and warm up its geometry.

The scan is read once and never written; the label store lives in `<out>/<stem>.annotate/` (`LabelStore`). The
ray-casting structures are built in a background thread (`start_warm_up`) so that the first click is fast; closing
stops it (`stop_warm_up`).
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Callable

from annotator import selection as sel
from annotator.io import MAX_SCAN_POINTS, LabelData, LabelIOError, load_labels, load_scan
from annotator.journal import remove_stale_temp_files, scan_fingerprint
from annotator.store import LabelStore
from annotator.labels import InstanceInfo
from efem_viz.colors import instance_color

log = logging.getLogger("annotator.session")


class ScanPart:
    """One scan, its geometry and its label store.

    Args:
        scan_path: the scan (PLY/OBJ/OFF/GLB/NPZ scene, or an RGB-D frame .npz). Never written.
        labels_path: labels to start a *new* session from (ignored with a warning when the output directory
            already holds a journal for this scan: the session resumes instead).
        out_dir: where the journal, checkpoint and exports go (default: the current working directory).
        max_points: refuse scans with more vertices.
        autosave_delay: seconds between an edit and the checkpoint rewrite.
        accept_scan_mismatch: resume a journal written for other geometry with the same vertex count.
        on_stage: called with what the opening does next (a big scan takes seconds: the CLI prints it).

    Raises:
        LabelIOError: the scan or labels cannot be read; JournalError: the journal belongs to another scan.
    """

    def __init__(self, scan_path: str | Path, *, labels_path: str | Path | None = None,
                 out_dir: str | Path | None = None, max_points: int = MAX_SCAN_POINTS, autosave_delay: float = 0.5,
                 accept_scan_mismatch: bool = False, on_stage: Callable[[str], None] | None = None) -> None:
        stage = on_stage or (lambda _what: None)
        self.scan_path = Path(scan_path).resolve()
        """The scan (never written)."""
        stage("reading the scan")
        self.scene = load_scan(self.scan_path, max_points=max_points)
        """The scan as a `Scene`."""
        self.n = self.scene.num_points
        """Its vertex count."""
        self.out_dir = writable_dir(out_dir)
        """The output folder (every write resolves inside it)."""
        self.stem = self.scan_path.stem
        self.roots = [self.scan_path.parent, self.out_dir]
        """The folders files are read from (the scan's and the output folder)."""
        self.work_dir = self.out_dir / f"{self.stem}.annotate"
        """The journal's and checkpoint's folder."""
        stage("opening the journal")
        self.store = self._open_store(labels_path, autosave_delay=autosave_delay,
                                      accept_scan_mismatch=accept_scan_mismatch)
        """The label store (journal first, autosaved checkpoint)."""
        # We hold the scan's journal lock now: temp files of an interrupted write of ours are stale.
        for folder in {self.out_dir, self.work_dir}:
            remove_stale_temp_files(folder, self.stem)
        if self.scene.normals_pending:
            stage(f"estimating normals of {self.n:,} points")
        self.geom = sel.ScanGeometry(self.scene.points, self.scene.normals, faces=self.scene.faces)
        """The scan's selection geometry (kd-tree, ray caster, adjacency)."""
        self._warmup_cancel = threading.Event()
        self._warmup: threading.Thread | None = None

    def _initial_labels(self, labels_path: str | Path | None) -> LabelData | None:
        """The labels a new session starts from: the given file's, else the scan's own ground truth, else none."""
        if labels_path is not None:
            return load_labels(labels_path, self.n)
        if self.scene.instance is None or not self.scene.has_gt:
            return None
        cats = dict(self.scene.categories)
        return LabelData(
            self.scene.instance.copy(),
            [
                InstanceInfo(int(i), f"{cats.get(int(i), 'object')} {int(i)}", category=cats.get(int(i), "object"),
                             color=instance_color(int(i)))
                for i in self.scene.instance_ids()
            ],
        )

    def _open_store(self, labels_path: str | Path | None, *, autosave_delay: float,
                    accept_scan_mismatch: bool) -> LabelStore:
        initial = self._initial_labels(labels_path)
        journal_path = self.work_dir / f"{self.stem}.journal"
        if labels_path is not None and journal_path.exists():
            log.warning(
                "%s already has a journal: resuming it and ignoring --labels %s (use Import in the GUI to load "
                "them as an undoable edit)", self.work_dir, labels_path,
            )
        return LabelStore(
            self.n,
            journal_path=journal_path,
            label_path=self.work_dir / f"{self.stem}.labels.npz",
            scan_id={
                "name": self.scan_path.name,
                "num_vertices": self.n,
                "content_hash": scan_fingerprint(self.scene.points, self.scene.faces),
            },
            initial_labels=None if initial is None else initial.labels,
            initial_instances=None if initial is None else initial.instances,
            autosave_delay=autosave_delay,
            accept_scan_mismatch=accept_scan_mismatch,
        )

    def start_warm_up(self, on_stage: Callable[[str, int, int], None] | None = None) -> None:
        """Build the selection structures (ray caster, ...) in a daemon thread, so the first click is fast;
        `on_stage(name, done, total)` hears each structure start and ("", total, total) at the end
        (`ScanGeometry.warm_up`)."""
        self._warmup = threading.Thread(target=self.geom.warm_up, args=(self._warmup_cancel, on_stage),
                                        name="annotator-warmup", daemon=True)
        self._warmup.start()

    def stop_warm_up(self) -> None:
        """Stop the warm-up before its next structure (it used to be waited for, up to 60 s on big
        scans). Only an open3d ray-casting scene under construction is waited for (exiting under it makes open3d
        report leaks and exit with status 1); the daemon thread's scipy work is simply abandoned."""
        self._warmup_cancel.set()
        if self._warmup is not None:
            self._warmup.join(timeout=60 if self.geom.building_raycaster.is_set() else 0.5)

    def close(self) -> None:
        """Flush the checkpoint and release the journal (idempotent)."""
        self.store.close()


def writable_dir(out_dir: str | Path | None) -> Path:
    """The output folder, created when missing.

    Raises:
        LabelIOError: it is a file, cannot be created, or is read-only.
    """
    out = Path(out_dir).resolve() if out_dir is not None else Path.cwd().resolve()
    if out.exists() and not out.is_dir():
        raise LabelIOError(f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabelIOError(f"cannot create the output folder {out} ({exc}); choose one with --out") from exc
    # Mode bits too: a read-only data folder (r-x) is still writable for root, and must not be written.
    if not os.access(out, os.W_OK) or not (out.stat().st_mode & 0o222):
        raise LabelIOError(f"the output folder {out} is read-only; choose another with --out")
    return out
