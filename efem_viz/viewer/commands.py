"""`efem-viz view`: open the viewer on scene files and folders (module top stays light: no viser/torch here)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

logger = logging.getLogger(__name__)


@dataclass
class ViewArgs:
    """Open the EFEM viewer in the browser on scenes (files or folders; default: the bundled sample_scenes/)."""

    paths: tyro.conf.Positional[tuple[Path, ...]] = field(default_factory=tuple)
    """Scene files and/or folders. Only scene files inside these paths can be opened."""
    host: str = "127.0.0.1"
    """Interface to bind. The default keeps the viewer private to this machine; use 0.0.0.0 to share it."""
    port: int = 8080
    """Port (a busy port is replaced by the next free one; the real URL is printed)."""
    prior: str = "mug"
    """Shape prior used for runs and for decoding shapes."""
    out_dir: Path = Path("efem_out")
    """Default folder for exported results."""

    def run(self) -> int:
        """Start the server, print its URL, serve until Ctrl+C."""
        from efem_viz.viewer.app import DEFAULT_SCENE_DIR, ViewerApp

        paths = list(self.paths) or [DEFAULT_SCENE_DIR]
        for p in paths:
            if not Path(p).exists():
                raise FileNotFoundError(f"no such scene file or folder: {p}")
        app = ViewerApp(paths, host=self.host, port=self.port, prior_name=self.prior, out_dir=self.out_dir)
        print(f"efem-viz viewer: {app.url}  ({len(app.state.entries)} scenes; Ctrl+C to stop)", flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
        finally:
            app.stop()
        return 0
