"""What every part of the viewer session shares: the state, its lock, the status line, the priors, the paths.

`ViewerCore` is the base of `efem_viz.viewer.session.ViewerSession`; each part (`efem_viz.viewer.parts`) gets the
session as its `ViewerCore` and reads or changes only these shared parts, so a part never needs another part's
internals.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from efem_viz.data.scene import DEFAULT_MAX_POINTS
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.prior.registry import PriorSet
from efem_viz.serve.outputs import default_output_dir
from efem_viz.viewer.scene_list import discover_scenes, is_inside, trace_path_for
from efem_viz.viewer.state import ViewerState

if TYPE_CHECKING:
    from efem_viz.em.trace import ProposalView
    from efem_viz.prior.config import ShapePriorLike

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[3]
BUNDLED_SCENE_DIR = Path(__file__).resolve().parents[2] / "sample_scenes"
"""The sample scenes an installed efem-viz carries (`efem_viz/sample_scenes/`, copied from the checkout's
`sample_scenes/` when the wheel is built: setup.py)."""
CHECKOUT_SCENE_DIR = REPO_ROOT / "sample_scenes"
"""The sample scenes of a source checkout."""


def default_scene_dir() -> Path:
    """Where `efem-viz view` without arguments finds its demo: the bundled samples of an install, else the
    checkout's `sample_scenes/` (which may be missing: the caller says so)."""
    return BUNDLED_SCENE_DIR if BUNDLED_SCENE_DIR.is_dir() else CHECKOUT_SCENE_DIR


DEFAULT_SCENE_DIR = default_scene_dir()
"""`default_scene_dir()` at import."""

StatusListener = Callable[[str, bool], None]
"""Called with (text, is_error) whenever the session's status line changes."""


class ViewerCore:
    """The shared parts of the viewer session.

    Args:
        paths: scene files and/or folders; only scene files inside them are listed and opened.
        prior: a `ShapePrior`, or None to load `prior_name` lazily when first needed (decoding, runs).
        prior_name: the prior's spec (`efem_viz.prior.registry.PriorSet`).
        run_priors: specs of more priors for runs started here (a joint solve over the prior and these).
        out_dir: the output root (exports confined to it by the app); default `view/` in the user's data folder.
        results: folders of saved results searched after each scene's own folder; with no `paths`, the scenes
            are the scene files in these folders.
        max_points: refuse scenes with more points than this.
        device: where runs started here solve ("cpu" or "cuda").
    """

    def __init__(
        self,
        paths: Sequence[str | Path] = (),
        *,
        prior: ShapePriorLike | None = None,
        prior_name: str = DEFAULT_PRIOR,
        run_priors: Sequence[str] = (),
        out_dir: str | Path | None = None,
        results: Sequence[str | Path] = (),
        max_points: int = DEFAULT_MAX_POINTS,
        device: str = "cpu",
    ) -> None:
        self.max_points = int(max_points)
        """Scenes with more points are refused."""
        self.state = ViewerState()
        scene_paths = list(paths) if paths else (list(results) if results else [DEFAULT_SCENE_DIR])
        self.state.entries = discover_scenes(scene_paths, result_dirs=list(results))
        self.roots = [Path(p).expanduser().resolve() for p in [*scene_paths, *results]]
        """The given paths: nothing outside them is read."""
        self.out_root = Path(out_dir if out_dir is not None else default_output_dir("view")).expanduser().resolve()
        """The output root (fixed at start)."""
        self.priors = PriorSet(prior_name, prior=prior, extra=run_priors, device=device)
        """This viewer's priors, each loaded once on its device (`efem_viz.prior.registry.PriorSet`); runs solve
        there too."""
        self.lock = threading.RLock()
        """Guards the state (re-entrant: the app holds it while it draws)."""
        self.cancel_event = threading.Event()
        """Set to stop a running EM at its next step."""
        self.on_status: StatusListener | None = None
        """Told every status change (the app shows it in the GUI)."""
        self.generation = 0
        """Bumped on every scene/result change so stale worker results are dropped."""
        self.scene_generation = 0
        """Bumped when another scene is opened: a run's ticket (its result is dropped when the scene changed; the
        run's own results as it goes do not change it)."""
        self.mask_version = 0
        """Bumped whenever the shown masks change within one result (colour caches key on it)."""
        self.no_shapes_generation = -1
        """The generation whose shapes could not be decoded (no prior): not retried on every step."""
        self.inspect_weights: np.ndarray | None = None
        """(N,) float32 weights of the inspected proposal (the "proposal weights" colouring)."""
        self.view_cache: dict[tuple[int, int], ProposalView] = {}
        """Replayed proposal views by (proposal id, step) of the shown result (cleared with every new one)."""
        self.attach_parts()

    def attach_parts(self) -> None:
        """Build the parts that share this core (the session's, `efem_viz.viewer.session.ViewerSession`); called
        once, at the end of `__init__`, so that the constructor's parameters are declared here only."""

    def set_status(self, text: str, *, error: bool = False) -> None:
        """Record a status line (and the error, when it is one) and tell `on_status`."""
        with self.lock:
            self.state.status = text
            self.state.error = text if error else None
        if error:
            logger.warning("%s", text)
        if self.on_status is not None:
            self.on_status(text, error)

    def prior(self) -> ShapePriorLike:
        """The shape prior (loaded on first use). Raises RuntimeError with the reason when unavailable."""
        return self.priors.primary()

    def allowed(self, path: Path) -> bool:
        """May the viewer read `path`? Inside a given folder, a given file, or the saved result of a given file."""
        if is_inside(path, self.roots):
            return True
        rp = path.resolve()
        return any(r.is_file() and rp == trace_path_for(r) for r in self.roots)

    def forget_views(self) -> None:
        """Another scene or result is shown: bump the generation, drop the replayed views and the weights."""
        self.generation += 1
        self.view_cache.clear()
        self.inspect_weights = None
