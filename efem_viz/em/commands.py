"""`efem-viz segment`: run EFEM on scenes and write `<scene>.efem.npz`, the ScanNet export and a coloured PLY.

Imported lazily by the CLI dispatcher; torch is only imported inside `run`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from efem_viz.em.masks import TAU_OUT_CANDIDATES

logger = logging.getLogger(__name__)


@dataclass
class SegmentArgs:
    """Segment scanned scenes with EFEM (unsupervised, shape-prior EM) and record the full trace."""

    scenes: Annotated[list[Path], tyro.conf.Positional]
    """Scene files (.ply/.obj/.off/.glb/.npz) and/or folders of them."""
    prior: str = "mug"
    """Shape prior: a name under efem_viz/weights/ or a .pt path."""
    out: Path = Path("results")
    """Output folder: <scene>.efem.npz, scannet/<scene>.txt + scannet/pred_mask/, <scene>.seg.ply."""
    preset: Literal["synthetic_mugs", "real_mugs", "fast"] = "synthetic_mugs"
    """Solver configuration (efem-method.md §3.12)."""
    proposals: int | None = None
    """Override the number of proposals (first episode)."""
    work_voxel: float | None = None
    """Run EM on a thinned working set (one point per cell of this size, m); masks stay full resolution."""
    tau_out: float | None = None
    """Output-mask SDF band (canonical units); default: the prior's calibrated value (`calibrate-masks`), else 0.04."""
    seed: int = 0
    """Random seed (anchors, samples); the same seed replays the same run."""
    device: str = "cpu"
    """cpu or cuda."""
    threshold: float = 0.0
    """Confidence threshold for the coloured PLY (the .efem.npz keeps every instance)."""
    scannet: bool = True
    """Write the ScanNet benchmark layout under <out>/scannet/."""
    ply: bool = True
    """Write <scene>.seg.ply coloured by predicted instance."""
    threads: int | None = None
    """torch CPU threads (default: torch's choice)."""

    def run(self) -> int:
        """Run every scene; returns 0 when all succeeded, 1 otherwise."""
        import torch
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TaskID,
            TextColumn,
            TimeElapsedColumn,
        )

        from efem_viz.data.io import find_scenes, load_scene
        from efem_viz.em.config import preset
        from efem_viz.em.solver import StepInfo, run_em
        from efem_viz.prior.model import load_prior

        console = Console()
        if self.threads:
            torch.set_num_threads(int(self.threads))
        paths = find_scenes(self.scenes)
        if not paths:
            raise ValueError(f"no scene files found in {[str(s) for s in self.scenes]}")
        cfg = preset(self.preset)
        if self.proposals is not None:
            cfg = cfg.with_proposals(int(self.proposals))
        if self.work_voxel is not None:
            cfg = cfg.replace(work_voxel=float(self.work_voxel) or None)
        if self.tau_out is not None:
            cfg = cfg.replace(tau_out=float(self.tau_out))
        prior = load_prior(self.prior, device=self.device)
        if prior.codebook is None:
            console.print(f"[yellow]prior {self.prior!r} has no codebook: poses fall back to identity[/]")
        self.out.mkdir(parents=True, exist_ok=True)
        failures = 0
        summary: list[tuple[str, int, int, float]] = []
        for path in paths:
            try:
                scene = load_scene(path)
            except ValueError as exc:
                console.print(f"[red]{path}: {exc}[/]")
                failures += 1
                continue
            with Progress(
                TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console, transient=False,
            ) as progress:
                total = cfg.num_episodes * cfg.steps_per_episode
                task = progress.add_task(scene.name, total=total, info="")

                def on_step(s: StepInfo, _task: TaskID = task) -> None:
                    progress.update(_task, completed=s.step + 1,
                                    info=f"phase {s.phase}  active {s.active:4d}")

                t0 = time.perf_counter()
                result = run_em(scene, prior, cfg, seed=self.seed, device=self.device, on_step=on_step)
                progress.update(task, completed=total)
            dt = time.perf_counter() - t0
            res_path = result.save(self.out / f"{scene.name}.efem.npz")
            if self.scannet:
                result.instances.to_scannet(self.out / "scannet", scene.name, scene.num_points)
            if self.ply:
                result.instances.to_colored_ply(scene, self.out / f"{scene.name}.seg.ply",
                                                threshold=self.threshold)
            n_inst = len(result.instances)
            summary.append((scene.name, scene.num_points, n_inst, dt))
            confs = ", ".join(f"{c:.2f}" for c in sorted(result.instances.confidence, reverse=True))
            console.print(f"{scene.name}: {n_inst} instances [{confs}] in {dt:.1f} s -> {res_path}")
        if len(summary) > 1:
            tot = sum(s[3] for s in summary)
            n_all = sum(s[2] for s in summary)
            console.print(f"{len(summary)} scenes, {n_all} instances, {tot:.1f} s total, "
                          f"{tot / len(summary):.1f} s per scene")
        return 1 if failures else 0


@dataclass
class CalibrateMasksArgs:
    """Choose a prior's output-mask SDF threshold τ_out on labelled tuning scenes (the smallest within --tolerance of
    the best AP of re-thresholded masks)."""

    results: Annotated[list[Path], tyro.conf.Positional]
    """`<scene>.efem.npz` results (files and/or folders), computed with --prior."""
    gt: list[Path] = field(default_factory=list)
    """Labelled tuning scenes (files and/or folders); results are paired with them by scene name."""
    prior: str = "mug"
    """The prior the results were computed with (a name under efem_viz/weights/ or a .pt path)."""
    candidates: tuple[float, ...] = TAU_OUT_CANDIDATES
    """Thresholds to try (canonical units)."""
    classes: tuple[str, ...] = ("mug",)
    """Evaluated classes (as in `efem-viz evaluate`)."""
    tolerance: float = 0.5
    """AP points below the best that still count as a tie; ties go to the smaller (tighter) threshold."""
    write: bool = False
    """Store the chosen value (and the table) in the prior file's metadata; `run_em` then uses it."""
    json_out: Path | None = None
    """Also write the calibration table as JSON here."""

    def run(self) -> int:
        """Print the AP table per threshold; with --write update the prior. Returns 0."""
        import json

        from efem_viz.data.io import find_scenes, load_scene
        from efem_viz.em.masks import METADATA_KEY, calibrate_tau_out, prior_tau_out
        from efem_viz.em.results import RESULT_SUFFIX, EMResult
        from efem_viz.prior.model import load_prior, resolve_prior_path, save_prior

        if not self.gt:
            raise ValueError("give the labelled tuning scenes with --gt SCENE... (files or folders)")
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0.0):
            raise ValueError(f"--tolerance must be a number of AP points >= 0, got {self.tolerance}")
        if self.json_out is not None:
            from efem_viz.cli import check_output_file

            check_output_file(self.json_out, option="--json-out")
        scenes = {}
        scene_paths: dict[str, Path] = {}
        for p in find_scenes(self.gt):
            scene = load_scene(p)
            scenes[scene.name] = scene
            scene_paths[scene.name] = p
        files: list[Path] = []
        for r in self.results:
            if r.is_dir():
                files += sorted(r.glob(f"*{RESULT_SUFFIX}"))
            elif r.is_file():
                files.append(r)
            else:
                raise FileNotFoundError(f"results not found: {r}")
        runs = []
        for f in files:  # every result is checked (EMResult.load validates it) before the prior is loaded
            res = EMResult.load(f)
            if res.scene_name not in scenes:
                logger.info("%s: no labelled scene named %r among --gt; skipped", f, res.scene_name)
                continue
            scene = scenes[res.scene_name]
            if scene.instance is None:
                raise ValueError(f"scene {scene.name!r} has no ground-truth `instance` labels")
            if res.num_points != scene.num_points:
                raise ValueError(f"{f} was computed on {res.num_points} points but the labelled scene "
                                 f"{scene_paths[scene.name]} has {scene.num_points}")
            res.trace.bind(scene)
            runs.append((res, scene))
        if not runs:
            raise ValueError(f"no result among {len(files)} file(s) matches a labelled scene in --gt")
        prior = load_prior(self.prior)
        cal = calibrate_tau_out(runs, prior, candidates=self.candidates, class_names=self.classes,
                                tolerance=self.tolerance / 100.0)
        before = prior_tau_out(prior)
        print(f"prior {self.prior!r}: tau_out calibrated on {len(runs)} scene(s): {', '.join(cal.scenes)}")
        print(cal.table())
        print(f"chosen tau_out {cal.best:g} (prior had {before:g})")
        if self.json_out is not None:
            from efem_viz.data.io import atomic_write_text

            atomic_write_text(self.json_out, json.dumps(cal.to_dict(), indent=2))
        if self.write:
            path = resolve_prior_path(self.prior)
            save_prior(prior, path, extra={METADATA_KEY: cal.best, f"{METADATA_KEY}_calibration": cal.to_dict()})
            print(f"wrote {METADATA_KEY}={cal.best:g} into {path}")
        return 0
