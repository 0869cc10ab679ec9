"""`efem-viz view`: open the viewer on scene files and folders (module top stays light: no viser/torch here)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import tyro

from efem_viz.data.scene import DEFAULT_MAX_POINTS, SceneError
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.terminal import count

logger = logging.getLogger(__name__)


@dataclass
class ViewArgs:
    """Open the EFEM viewer in the browser on scenes (files or folders; default: the sample scenes)."""

    paths: tyro.conf.Positional[tuple[Path, ...]] = field(default_factory=tuple)
    """Scene files and/or folders. Only scene files inside these paths can be opened."""
    host: str = "127.0.0.1"
    """Interface to bind. The default keeps the viewer private to this machine; 0.0.0.0 shares it with anyone on
    the network who has the printed URL (it carries the access token)."""
    port: int = 8080
    """Port (a busy port is replaced by the next free one; the real URL is printed)."""
    prior: tyro.conf.UseAppendAction[list[str]] = field(default_factory=list)
    """Shape prior used for runs and for decoding shapes (default mug); repeat it for runs over several categories
    (`--prior mug --prior sphere`: a joint solve, the first prior is the viewer's)."""
    out_dir: Path | None = None
    """Output root: exports from the GUI (results, static demo) go into this folder or below it, nowhere else
    (default: `view/` in the user's data folder, e.g. ~/.local/share/efem-viz/view; printed at start)."""
    token: str | None = None
    """Access token to require (default: a fresh random one, printed in the URL). At least 16 characters."""
    results: tuple[Path, ...] = ()
    """Folders of saved results (`efem-viz segment --out DIR`): each scene's `<scene>.efem.npz` is looked for there
    first, then next to the scene. Without scene paths, the scenes are those the folders' `batch.json` names
    (a line lists the results whose scene file is gone)."""
    max_points: int = DEFAULT_MAX_POINTS
    """Refuse scenes with more points than this."""
    device: str = "auto"
    """Where runs and shape decoding run: auto (CUDA when this machine has it, else the CPU), cpu or cuda."""

    def run(self) -> int:
        """Start the server, print its URL, serve until Ctrl+C / SIGTERM (`efem_viz.serve.lifecycle`)."""
        from efem_viz.cli import check_device, check_port
        from efem_viz.serve.lifecycle import announce, stop_signals, wait_for_stop
        from efem_viz.serve.outputs import default_output_dir
        from efem_viz.viewer.app import ViewerApp, default_scene_dir

        check_port(self.port)  # before anything starts (a bad port used to hang in viser's server thread)
        device = check_device(self.device)  # CUDA asked for without CUDA: one line, before anything starts

        if self.paths:
            paths = list(self.paths)
        elif self.results:
            paths = scenes_of_results(self.results)
        else:
            samples = default_scene_dir()
            if not samples.is_dir():
                raise FileNotFoundError(
                    f"no sample scenes in this install (looked in {samples}): give scene files or folders "
                    "(efem-viz view SCENE.ply ...; efem-viz generate makes some), or run it from a checkout of "
                    "the project, whose sample_scenes/ it opens")
            paths = [samples]
        with stop_signals("efem-viz view"):  # before loading: Ctrl+C stops a long load too
            check_view_inputs(paths, self.results, max_points=self.max_points)
            priors = list(self.prior) or [DEFAULT_PRIOR]
            out_dir = self.out_dir if self.out_dir is not None else default_output_dir("view")
            app = ViewerApp(paths, host=self.host, port=self.port, prior_name=priors[0], run_priors=priors[1:],
                            out_dir=out_dir, token=self.token, results=self.results, max_points=self.max_points,
                            device=device)
            try:
                announce("efem-viz viewer", f"{app.url}  ({count(len(app.state.entries), 'scene')}; Ctrl+C to stop)",
                         url=app.url, local_url=app.local_url, exposure_warning=app.access.exposure_warning,
                         details=(f"exports go to: {app.out_root}", f"EFEM runs on: {device}"))
                wait_for_stop()
            finally:
                app.stop()
        return 0


def scenes_of_results(results: Sequence[Path]) -> list[Path]:
    """The scene files that results folders (`efem-viz segment --out DIR`) name in their `batch.json`, for
    `view --results DIR` without scene paths; one warning line lists the results whose scene is not there.

    Raises:
        FileNotFoundError: a results folder does not exist.
        SceneError: none of the named scenes exists (the line says how to give them).
    """
    from efem_viz.data.files import RESULT_SUFFIX, recorded_scene_paths
    from efem_viz.data.formats import FORMATS

    found: list[Path] = []
    missing: list[str] = []
    for d in results:
        folder = Path(d).expanduser()
        if not folder.is_dir():
            raise FileNotFoundError(f"no such results folder: {d}")
        recorded = recorded_scene_paths(folder)
        for result in sorted(folder.glob(f"*{RESULT_SUFFIX}")):
            name = result.name[: -len(RESULT_SUFFIX)]
            scene = recorded.get(name)
            if scene is not None and scene.suffix.lower() in FORMATS and scene.is_file():
                if scene not in found:
                    found.append(scene)
            else:
                missing.append(name if scene is None else f"{name} ({scene})")
    if missing:
        logger.warning("%s: scene file not found for %d result(s): %s%s (give the scenes: efem-viz view SCENES "
                       "--results DIR)", ", ".join(str(d) for d in results), len(missing), ", ".join(missing[:8]),
                       " ..." if len(missing) > 8 else "")
    if not found:
        raise SceneError(f"no scene to show: {', '.join(str(d) for d in results)} holds no result whose scene file "
                         "is still where its batch.json says; give the scene files or folders too "
                         "(efem-viz view SCENES --results DIR)")
    return found


def check_view_inputs(paths: list[Path], results: tuple[Path, ...], *, max_points: int) -> None:
    """Refuse what the viewer could not show, before a server starts (one line, like every other command): a
    missing path or results folder, a scene file named on the command line that does not load, or paths holding
    no scene file at all. (A bad file found in a folder is shown in the viewer instead.)

    Raises:
        FileNotFoundError: a path or results folder does not exist.
        SceneError: a named file is not a readable scene (the loader's message names the file and the reason), or
            no scene file was found.
    """
    from efem_viz.data.io import load_scene
    from efem_viz.viewer.scene_list import discover_scenes

    for p in paths:
        if not Path(p).exists():
            raise FileNotFoundError(f"no such scene file or folder: {p}")
    for d in results:
        if not Path(d).is_dir():
            raise FileNotFoundError(f"no such results folder: {d}")
    entries = discover_scenes(paths, result_dirs=list(results))
    if not entries:
        raise SceneError(f"no scene files in {', '.join(str(p) for p in [*paths, *results])}")
    for p in paths:
        if Path(p).is_file():
            load_scene(Path(p), max_points=max_points)
