"""The runs room: run EFEM on the open scene (one run at a time, progress per step, cancel at the next step)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from efem_viz.em.results import EMResult
    from efem_viz.em.solver import StepInfo
    from efem_viz.viewer.rooms.core import ViewerCore
    from efem_viz.viewer.rooms.results import ResultRoom

logger = logging.getLogger(__name__)

ProgressCallback = Callable[["StepInfo"], None]
"""Called after each EM step with the solver's step info (`step`, `num_steps`, `phase`, `active`, `elapsed_s`)."""


class RunRoom:
    """Starts, runs and cancels EFEM runs; a finished run is shown through the results room."""

    def __init__(self, core: ViewerCore, results: ResultRoom) -> None:
        self.core = core
        """The session's shared parts."""
        self.results = results
        """Where a finished run is shown."""
        self.last_run_source = ""
        """The source line of the last finished run ("run (preset, seed, time)")."""

    def begin_run(self) -> int | None:
        """Mark a run as started (`state.running`). Returns its ticket (the scene generation), or None (status
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
            return self.core.generation

    def run(self, *, preset: str = "fast", proposals: int | None = None, seed: int = 0,
            on_step: ProgressCallback | None = None, show: bool = True,
            generation: int | None = None, matmul_dtype: str = "float32") -> EMResult | None:
        """Run EFEM on the open scene (synchronously; `cancel_run()` from another thread stops it).

        Args:
            preset: an `efem_viz.em.preset` name.
            proposals: the initial proposal count (None: the preset's).
            seed: the run's seed.
            matmul_dtype: `EMConfig.matmul_dtype` ("float32" or "bfloat16").
            on_step: called after each EM step with the solver's step info.
            show: show the result when done (unless the scene changed meanwhile).
            generation: the ticket of a `begin_run()` already called (None: begin here).

        Returns:
            The result, or None when cancelled, failed (status says why) or another run is in progress.
        """
        from efem_viz.em import EMCancelled

        if generation is None:
            generation = self.begin_run()
            if generation is None:
                return None
        t0 = time.perf_counter()
        try:
            result = self._solve(preset, proposals=proposals, seed=seed, on_step=on_step, matmul_dtype=matmul_dtype)
        except EMCancelled:
            self.core.set_status("Run cancelled.")
            return None
        except Exception as exc:  # noqa: BLE001
            self.core.set_status(f"EFEM run failed: {exc}", error=True)
            return None
        finally:
            with self.core.lock:
                self.core.state.running = False
        if generation != self.core.generation:
            logger.info("scene changed during the run; result dropped")
            return None
        self.last_run_source = f"run ({preset}, seed {seed}, {time.perf_counter() - t0:.1f} s)"
        if show:
            self.results.set_result(result, source=self.last_run_source)
        return result

    def _solve(self, preset: str, *, proposals: int | None, seed: int, on_step: ProgressCallback | None,
               matmul_dtype: str) -> EMResult:
        """The EFEM solve of a run on the open scene (its status line says what runs); raises what `run_em` raises."""
        from efem_viz.em import preset as make_preset, run_em

        scene = self.core.state.require_scene()
        cfg = make_preset(preset)
        if proposals is not None:
            cfg = cfg.with_proposals(int(proposals))
        cfg = cfg.replace(matmul_dtype=matmul_dtype)
        self.core.set_status(f"Running EFEM ({preset}, {cfg.n_init[0]} proposals, seed {seed}"
                             f"{', bf16' if matmul_dtype == 'bfloat16' else ''}) …")
        prior = self.core.prior()
        priors = self.core.priors.run_priors()
        if priors is None:
            return run_em(scene, prior, cfg, seed=int(seed), on_step=on_step, cancel=self.core.cancel_event)
        return run_em(scene, cfg=cfg, priors=priors, seed=int(seed), on_step=on_step, cancel=self.core.cancel_event)

    def cancel_run(self) -> None:
        """Ask a running EM to stop at its next step."""
        self.core.cancel_event.set()
        self.core.set_status("Cancelling …")
