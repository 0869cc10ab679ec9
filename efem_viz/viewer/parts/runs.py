"""The runs part: run EFEM on the open scene (one run at a time, progress per step, cancel at the next step)."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from efem_viz.em.config import PresetName, SolveSettings

if TYPE_CHECKING:
    from efem_viz.em.results import EMResult
    from efem_viz.em.solver import StepInfo
    from efem_viz.viewer.parts.core import ViewerCore
    from efem_viz.viewer.parts.results import ResultPart

logger = logging.getLogger(__name__)

ProgressCallback = Callable[["StepInfo"], None]
"""Called after each EM step with the solver's step info (`step`, `num_steps`, `phase`, `active`, `elapsed_s`)."""


@dataclass(frozen=True, kw_only=True)
class RunSettings(SolveSettings):
    """What a viewer run solves with: the solver knobs of `SolveSettings` (preset, proposals, work_voxel, tau_out,
    matmul_dtype; `config()` builds the `EMConfig`) and the seed. The Run tab fills preset, proposals, seed and
    precision; a script may set every field."""

    preset: PresetName = "fast"
    """Solver configuration (`efem_viz.em.preset` name); the viewer's default is the quick one."""
    seed: int = 0
    """The run's seed."""

    @classmethod
    def of(cls, settings: RunSettings | None = None, **knobs: Any) -> RunSettings:
        """`settings` with the given fields replaced (a fresh `RunSettings` from `knobs` when None).

        Raises:
            TypeError: a knob that is not a field.
        """
        return cls(**knobs) if settings is None else dataclasses.replace(settings, **knobs)


class RunPart:
    """Starts, runs and cancels EFEM runs; a finished run is shown through the results part."""

    def __init__(self, core: ViewerCore, results: ResultPart) -> None:
        self.core = core
        """The session's shared parts."""
        self.results = results
        """Where a finished run is shown."""
        self.last_run_source = ""
        """The source line of the last finished run ("run (preset, seed, time)")."""

    def begin_run(self) -> int | None:
        """Mark a run as started (`state.running`). Returns its ticket (`core.scene_generation`), or None (status
        says why) when a run is in progress or no scene is open."""
        with self.core.lock:
            if self.core.state.running:
                self.core.set_status("A run is already in progress.", error=True)
                return None
            if self.core.state.scene is None:
                self.core.set_status("Open a scene first.", error=True)
                return None
            self.core.state.running = True
            self.core.cancel_event.clear()
            return self.core.scene_generation

    def run(self, settings: RunSettings | None = None, *, on_step: ProgressCallback | None = None, show: bool = True,
            generation: int | None = None, **knobs: Any) -> EMResult | None:
        """Run EFEM on the open scene (synchronously; `cancel_run()` from another thread stops it).

        Args:
            settings: preset, proposals, seed, precision, ... (None: `RunSettings()`, the "fast" preset).
            knobs: `RunSettings` fields replaced in `settings` (`run(preset="real", seed=3)`).
            on_step: called after each EM step with the solver's step info.
            show: show the result when done (unless the scene changed meanwhile).
            generation: the ticket of a `begin_run()` already called (None: begin here).

        Returns:
            The result, or None when cancelled, failed (status says why) or another run is in progress.
        """
        from efem_viz.em import EMCancelled

        settings = RunSettings.of(settings, **knobs)
        if generation is None:
            generation = self.begin_run()
            if generation is None:
                return None
        t0 = time.perf_counter()
        try:
            result = self._solve(settings, on_step=on_step)
        except EMCancelled:
            self.core.set_status("Run cancelled.")
            return None
        except Exception as exc:  # noqa: BLE001
            self.core.set_status(f"EFEM run failed: {exc}", error=True)
            return None
        finally:
            with self.core.lock:
                self.core.state.running = False
        if generation != self.core.scene_generation:
            logger.info("scene changed during the run; result dropped")
            return None
        self.last_run_source = f"run ({settings.preset}, seed {settings.seed}, {time.perf_counter() - t0:.1f} s)"
        if show:
            self.results.set_result(result, source=self.last_run_source)
        return result

    def _solve(self, settings: RunSettings, *, on_step: ProgressCallback | None) -> EMResult:
        """The EFEM solve of a run on the open scene (its status line says what runs); raises what `run_em` raises."""
        from efem_viz.em import run_em
        from efem_viz.em.config import suggested_prior
        from efem_viz.prior.config import prior_category

        scene = self.core.state.require_scene()
        cfg = settings.config(device=self.core.priors.device)
        priors = self.core.priors.solve_priors(suggested_prior(scene))  # a chair or kitchen scene: its own prior
        self.core.set_status(f"Running EFEM ({settings.preset}, {cfg.proposals.n_init[0]} proposals, "
                             f"seed {settings.seed}, {' + '.join(prior_category(p).name for p in priors)} prior"
                             f"{', bf16 decoder' if cfg.compute.matmul_dtype == 'bfloat16' else ''}"
                             f"{', on ' + self.core.priors.device if self.core.priors.device != 'cpu' else ''}) …")
        return run_em(scene, cfg=cfg, priors=priors, seed=int(settings.seed), on_step=on_step,
                      cancel=self.core.cancel_event, device=self.core.priors.device)

    def is_current(self, generation: int) -> bool:
        """Whether a run's ticket is still the open scene's (results of a run on another scene are dropped)."""
        return generation == self.core.scene_generation

    def cancel_run(self) -> None:
        """Ask a running EM to stop at its next step."""
        self.core.cancel_event.set()
        self.core.set_status("Cancelling …")
