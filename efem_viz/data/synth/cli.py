"""The `efem-viz generate` command (`GenerateArgs`): scenes in a row of seeds, written as PLY."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from efem_viz.data.synth.generate import generate_scene
from efem_viz.data.synth.layout import Config, Mode

logger = logging.getLogger(__name__)


@dataclass
class GenerateArgs:
    """Generate synthetic scans with per-point ground truth: procedural mugs (or kitchen objects) on a table, or
    chairs on a floor."""

    config: Config = "z"
    """Scene configuration: z (upright objects), so3 (random orientations), pile (stacked, touching), tree (hanging
    on a mug tree), box (inside an open box), shelf (on the levels of a shelf)."""
    count: int = 1
    """Number of scenes; scene i uses seed `seed + i`."""
    seed: int = 0
    """Seed of the first scene."""
    out: Path = Path("generated")
    """Output folder; files are named <prefix><config>_<seed>.ply."""
    mode: Mode = "tsdf"
    """tsdf: fused mesh (like the paper's scans); points: merged depth points, voxel-downsampled."""
    objects: int | None = None
    """Labelled objects per scene, 1..10 (default: drawn by the seed, 3..7 on the table, 2..5 chairs)."""
    distractors: bool = True
    """Add 0-2 unlabelled distractor objects (boxes, cans, bowls, bottles on the table; cabinets on the
    floor)."""
    split: Literal["train", "val", "test"] = "test"
    """Object seed split to draw from."""
    voxel: float | None = None
    """TSDF voxel / point spacing in metres (default: 0.004 for mug and kitchen targets, 0.01 for chairs)."""
    prefix: str = ""
    """Prefix of the file and scene names (e.g. "syn_" gives syn_z_0.ply)."""
    targets: Literal["mug", "kitchen", "chair"] = "mug"
    """The labelled objects: mugs; kitchen objects mixed (mugs, bowls, bottles, cans: the paper's SynKit, on
    the table, boxes are the distractors); or chairs (the paper's SynChairs: on a 6 m square floor scanned from
    about 3 m, cabinets are the distractors). kitchen and chair take --config z, so3 or pile."""

    def run(self) -> int:
        """Generate the scenes with a progress bar; returns the exit code."""
        from tqdm import tqdm

        from efem_viz.data.io import save_scene

        if self.count < 1:
            raise ValueError(f"--count must be >= 1, got {self.count}")
        self.out.mkdir(parents=True, exist_ok=True)
        bar = tqdm(range(self.seed, self.seed + self.count), desc=f"generate {self.config}", unit="scene")
        for s in bar:
            name = f"{self.prefix}{self.config}_{s}"
            scene = generate_scene(
                self.config,
                seed=s,
                n_objects=self.objects,
                mode=self.mode,
                distractors=self.distractors,
                split=self.split,
                voxel=self.voxel,
                name=name,
                targets=self.targets,
            )
            if self.prefix:
                prov = dict(scene.provenance)
                prov["command"] = f"{prov['command']} --prefix {self.prefix}"
                scene = dataclasses.replace(scene, provenance=prov)
            path = save_scene(scene, self.out / f"{name}.ply")
            bar.set_postfix(points=scene.num_points, objects=len(scene.categories))
            logger.info("wrote %s (%d points, %d %s)", path, scene.num_points, len(scene.categories),
                        "mugs" if self.targets == "mug" else "objects")
        return 0
