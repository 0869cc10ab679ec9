"""Build hook (everything else is in pyproject.toml): an installed efem-viz carries a few of the checkout's sample
scenes with their saved EM results, so that `efem-viz view` without arguments opens a demo outside the checkout
too. They are copied from `sample_scenes/` into the package as `efem_viz/sample_scenes/` when the wheel is built
(a source checkout reads `sample_scenes/` itself; `efem_viz.viewer.app.default_scene_dir`)."""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
BUNDLED_SAMPLES: tuple[str, ...] = (
    "syn_pile_0.ply", "syn_pile_0.efem.npz",  # a synthetic pile of mugs, with ground truth
    "real_tabletop_6.ply", "real_tabletop_6.efem.npz",  # a real RGB-D frame, labelled by hand
    "LICENSE-real_tabletop.txt", "README.md",
)
"""Files of `sample_scenes/` an installed efem-viz carries (about 5 MB)."""


class BuildPyWithSamples(build_py):
    """`build_py` that also copies `BUNDLED_SAMPLES` into `<build>/efem_viz/sample_scenes/`."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):  # an editable install reads the checkout's sample_scenes/
            return
        dest = Path(self.build_lib) / "efem_viz" / "sample_scenes"
        dest.mkdir(parents=True, exist_ok=True)
        for name in BUNDLED_SAMPLES:
            src = HERE / "sample_scenes" / name
            if not src.is_file():
                raise FileNotFoundError(f"bundled sample {src} is missing (setup.py BUNDLED_SAMPLES)")
            shutil.copyfile(src, dest / name)


setup(cmdclass={"build_py": BuildPyWithSamples})
