"""`efem-viz segment`: run EFEM on scenes and write `<scene>.efem.npz`, the ScanNet export and a coloured PLY.

Imported lazily by the CLI dispatcher; torch is only imported inside `run`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

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
