"""The export part: write the thresholded result (ScanNet layout, coloured PLY) and the static demo page."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from efem_viz.viewer.texts import safe_name

if TYPE_CHECKING:
    from efem_viz.viewer.parts.core import ViewerCore

logger = logging.getLogger(__name__)


class ExportPart:
    """Writes the shown result's exports (paths confined to a root when given)."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""
        self.cancel_event = threading.Event()
        """Set to stop a static-demo export at its next step (`cancel_export`)."""

    def export_results(self, out_dir: str | Path, *, root: Path | None = None) -> Path | None:
        """Write the thresholded result (ScanNet layout + coloured PLY) under `out_dir`.

        Args:
            out_dir: the export folder.
            root: when given, every folder and file written must resolve inside it (links followed), checked
                before anything is written.

        Returns:
            The folder written, or None (status says why) without a result.
        """
        from efem_viz.viewer.export import export_results

        s = self.core.state
        if s.result is None or s.scene is None:
            self.core.set_status("Nothing to export: load or run a result first.", error=True)
            return None
        out = export_results(s.result, s.scene, Path(out_dir), threshold=s.threshold, root=root)
        self.core.set_status(f"Exported results to {out}.")
        return out

    def static_target(self, folder: Path | None = None) -> Path | None:
        """The static demo's folder: `<folder or output root>/static/<scene>/` (None without a scene)."""
        scene = self.core.state.scene
        if scene is None:
            return None
        return (folder if folder is not None else self.core.out_root) / "static" / safe_name(scene.name)

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None,
                      on_progress: Callable[[float | None], None] | None = None) -> Path | None:
        """Write the static demo page `<out_dir>/index.html` (final result + playback of the steps); the status
        line says which step it records, and `cancel_export()` stops it before anything is written.

        Args:
            out_dir: the page's folder; None = `<output root>/static/<scene>/`.
            root: as in `export_results`.
            on_progress: called with the fraction done (0-1) as it records, and None when it ends.

        Returns:
            The page, or None (status says why) without a result or when cancelled.
        """
        from efem_viz.viewer.export import ExportCancelled, export_static_demo

        s = self.core.state
        if s.result is None or s.scene is None:
            self.core.set_status("Nothing to export: load or run a result first.", error=True)
            return None
        target = Path(out_dir) if out_dir is not None else self.static_target()
        assert target is not None
        try:
            prior = self.core.priors.for_run(s.result.trace)
        except RuntimeError as exc:
            prior = None
            logger.info("static demo without decoded shapes: %s", exc)
        name = s.scene.name

        def progress(what: str, fraction: float) -> None:
            self.core.set_status(f"Exporting the static demo of {name}: {what} … (Cancel export stops it)")
            if on_progress is not None:
                on_progress(fraction)

        self.cancel_event.clear()
        self.core.set_status(f"Exporting the static demo of {name} …")
        try:
            out = export_static_demo(s.scene, s.result, target, threshold=s.threshold, prior=prior, root=root,
                                     on_progress=progress, cancel=self.cancel_event)
        except ExportCancelled:
            self.core.set_status(f"Static demo export of {name} cancelled: nothing was written.")
            return None
        finally:
            if on_progress is not None:
                on_progress(None)
        self.core.set_status(f"Exported static demo to {out}.")
        return out

    def cancel_export(self) -> None:
        """Stop a static-demo export at its next step (nothing is written)."""
        self.cancel_event.set()
