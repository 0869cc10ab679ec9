"""`efem-viz segment`: run EFEM on scenes and write `<scene>.efem.npz`, the ScanNet export and a coloured PLY.

A thin CLI over the batch runner (`efem_viz.batch.run_batch`): one scene or hundreds, in this process, a local
process pool or on Ray, resumable. Imported lazily by the CLI dispatcher; torch is only imported by the workers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from efem_viz.data.files import NO_SCENES_GIVEN
from efem_viz.em.config import SolveSettings
from efem_viz.prior.config import DEFAULT_PRIOR


@dataclass(frozen=True, kw_only=True)
class SegmentArgs(SolveSettings):
    """Segment scanned scenes with EFEM (unsupervised, shape-prior EM) and record the full trace: one scene or a batch
    of hundreds, in this process (default), a local process pool (--workers N) or on Ray (--ray, --ray-address).
    Resumable: scenes whose valid results of the same settings are in --out are skipped (see docs/BATCH.md).
    The solver knobs (--preset, --proposals, --work-voxel, --tau-out, --matmul-dtype) are `SolveSettings`."""

    scenes: Annotated[list[Path], tyro.conf.Positional]
    """Scene files (.ply/.pcd/.las/.laz/.obj/.off/.glb/.npz) and/or folders of them."""
    prior: tyro.conf.UseAppendAction[list[str]] = field(default_factory=list)
    """Shape prior (repeat for several categories in one solve): a name under efem_viz/weights/, "sphere" (the
    analytic sphere) or a .pt path. Default: mug, and a generated chair or kitchen scene with its own prior."""
    out: Path | None = None
    """Output folder: <scene>.efem.npz, scannet/<scene>.txt + scannet/pred_mask/, <scene>.seg.ply,
    <scene>.objects.json, batch.json.
    Default: the efem-viz data folder, `~/.local/share/efem-viz/segment` (`$XDG_DATA_HOME`), never the current
    folder; the first line printed names it."""
    seed: int = 0
    """Random seed (anchors, samples); the same seed replays the same run, on every backend."""
    device: str = "cpu"
    """cpu or cuda."""
    threshold: float = 0.0
    """Confidence threshold for the coloured PLY (the .efem.npz keeps every instance)."""
    export_objects: Path | None = None
    """Also write each scene's completed objects into EXPORT_OBJECTS/<scene>/: one mesh per instance and
    objects.json (category, confidence, pose, scale, oriented box, mesh file), in the --frame."""
    object_format: str = "glb"
    """Mesh format of --export-objects: glb, obj or ply."""
    frame: str = "scene"
    """Frame of <scene>.seg.ply and <scene>.objects.json: scene (metres, +Z up) or original (the scan file's own
    frame and units, for scans brought in by `efem-viz import-scan` or opened directly; docs/OWN_DATA.md)."""
    scannet: bool = True
    """Write the ScanNet benchmark layout under <out>/scannet/."""
    ply: bool = True
    """Write <scene>.seg.ply coloured by predicted instance."""
    threads: int | None = None
    """torch CPU threads per worker (default: local, the cores not busy with other work, `efem_viz.cpu.free_cores`;
    process, the CPUs split between the workers; ray, 1 per actor)."""
    backend: str = "auto"
    """Where scenes run: a name registered in efem_viz.batch.registry.BACKENDS (local, process, ray, ...) or auto
    = ray with --ray/--ray-address, process with --workers > 1, else local."""
    workers: int | None = None
    """Parallel workers (process: processes, default the CPU count; ray: actors, default cluster CPUs // threads)."""
    ray: bool = False
    """Run on Ray, started locally for this batch (pip install 'efem-viz[ray]')."""
    ray_address: str | None = None
    """Run on an existing Ray cluster at this address ("auto", HOST:6379 or ray://HOST:10001)."""
    ray_cpus: int | None = None
    """CPUs of the Ray started by --ray (default: workers × threads, else this machine's CPUs)."""
    force: bool = False
    """Recompute scenes that already have valid results in --out."""
    scene_timeout: float | None = None
    """Give up on a scene after this many seconds of solving (reported failed; the batch goes on)."""

    def backend_name(self) -> str:
        """The backend `--backend auto` resolves to."""
        if self.backend != "auto":
            return self.backend
        if self.ray or self.ray_address:
            return "ray"
        return "process" if (self.workers or 1) > 1 else "local"

    def run(self) -> int:
        """Segment every scene; returns 0 when every scene has a valid result, 1 otherwise."""
        from efem_viz.terminal import console

        from efem_viz.batch import BackendOptions, BatchJob, make_backend, run_batch
        from efem_viz.batch.console import RichBatchDisplay

        job = BatchJob.create(
            priors=tuple(self.prior or [DEFAULT_PRIOR]), scene_priors=not self.prior, seed=self.seed,
            device=self.device,
            threads=self.threads, threshold=self.threshold, frame=self.frame,
            objects_dir=None if self.export_objects is None else str(self.export_objects),
            objects_format=self.object_format, scannet=self.scannet, ply=self.ply,
            timeout_s=self.scene_timeout, **self.settings(),
        )
        name = self.backend_name()
        if name != "ray" and (self.ray or self.ray_address or self.ray_cpus):
            raise ValueError(f"--ray/--ray-address/--ray-cpus need the ray backend, not --backend {name}")
        backend = make_backend(name, BackendOptions(workers=self.workers, ray_address=self.ray_address,
                                                    ray_cpus=self.ray_cpus))
        if self.out is not None:
            out = self.out
        else:
            from efem_viz.serve.outputs import default_output_dir

            out = default_output_dir("segment")
        from efem_viz.batch.job import prior_identity
        from efem_viz.serve.lifecycle import stop_signals

        if not self.scenes:
            raise ValueError(NO_SCENES_GIVEN)
        for spec in job.priors:  # a typo in a prior name is one line at once, before any display or scene work
            prior_identity(spec)

        # its own SIGINT/SIGTERM handlers: a segment started in the background by a script inherits SIGINT as
        # ignored and would run on after Ctrl+C / `kill -INT`; the batch records what finished and stops
        with stop_signals("efem-viz segment"), RichBatchDisplay(console(), preset=self.preset) as display:
            report = run_batch(job, self.scenes, out, backend=backend, force=self.force, observer=display)
        return 0 if report.passed else 1
