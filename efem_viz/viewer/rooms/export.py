"""The export room: write the thresholded result (ScanNet layout, coloured PLY) and the static demo page."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from efem_viz.viewer.texts import safe_name

if TYPE_CHECKING:
    from efem_viz.viewer.rooms.core import ViewerCore

logger = logging.getLogger(__name__)


class ExportRoom:
    """Writes the shown result's exports (paths confined to a root when given)."""

    def __init__(self, core: ViewerCore) -> None:
        self.core = core
        """The session's shared parts."""

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

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None) -> Path | None:
        """Write the static demo page `<out_dir>/index.html` (final result + playback of the steps).

        Args:
            out_dir: the page's folder; None = `<output root>/static/<scene>/`.
            root: as in `export_results`.
        """
        from efem_viz.viewer.export import export_static_demo

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
        self.core.set_status(f"Exporting the static demo of {s.scene.name} …")
        out = export_static_demo(s.scene, s.result, target, threshold=s.threshold, prior=prior, root=root)
        self.core.set_status(f"Exported static demo to {out}.")
        return out
