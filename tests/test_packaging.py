"""The built wheel, used outside the checkout (item 7): `efem-viz view` without arguments opens the
bundled sample scenes with their saved results, and the wheel leaves the training resume state out.

The wheel is built from a copy of the sources in tmp_path (the checkout gets no build/ or egg-info), offline and
without build isolation (`pip wheel --no-deps --no-build-isolation --no-index`), and used from its unpacked files
with the interpreter's own dependencies.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "LICENSE", "efem_viz", "annotator",
           "sample_scenes")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel built from a copy of the checkout's sources."""
    pytest.importorskip("setuptools")
    pytest.importorskip("wheel")
    base = tmp_path_factory.mktemp("wheel")
    src = base / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in SOURCES:
        p = REPO / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=ignore)
        else:
            shutil.copy2(p, src / name)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "--no-build-isolation",
                           "--no-index", "-q", "-w", str(base / "dist")], cwd=src, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (whl,) = (base / "dist").glob("efem_viz-*.whl")
    return whl


def test_the_wheel_carries_a_demo_but_not_the_resume_state(wheel: Path) -> None:
    """A few sample scenes with their results (not all ten), the priors and their codebooks; no `*_resume.pt`."""
    names = zipfile.ZipFile(wheel).namelist()
    weights = {n for n in names if n.startswith("efem_viz/weights/")}
    assert "efem_viz/weights/mug.pt" in weights and "efem_viz/weights/mug_codebook.npz" in weights
    assert not [n for n in weights if "resume" in n], weights
    assert "efem_viz/weights/mug_training_report.md" in weights  # the report ships, the working notes do not
    assert not [n for n in weights if "notes" in n], weights
    samples = sorted(n.removeprefix("efem_viz/sample_scenes/") for n in names
                     if n.startswith("efem_viz/sample_scenes/"))
    scenes = [n for n in samples if n.endswith(".ply")]
    assert 1 <= len(scenes) <= 3, samples
    assert all(n.removesuffix(".ply") + ".efem.npz" in samples for n in scenes), samples
    assert "LICENSE-real_tabletop.txt" in samples  # the real scene's licence travels with it
    assert wheel.stat().st_size < 20_000_000  # three priors (mug, kitchen, chair) with their codebooks and a demo


@pytest.mark.slow
def test_an_installed_viewer_opens_its_demo_outside_the_checkout(wheel: Path, tmp_path: Path) -> None:
    """From the unpacked wheel, in a folder outside the checkout, the viewer's default scenes are the bundled ones:
    it opens the first with its saved result (it failed with "no such scene file or folder:
    .../site-packages/sample_scenes")."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = (
        "import efem_viz, sys\n"
        "from pathlib import Path\n"
        "from efem_viz.viewer.app import ViewerApp, default_scene_dir\n"
        "from efem_viz.viewer.commands import check_view_inputs\n"
        f"assert Path(efem_viz.__file__).is_relative_to({str(site)!r}), efem_viz.__file__\n"
        "d = default_scene_dir()\n"
        "check_view_inputs([d], (), max_points=5_000_000)\n"
        "app = ViewerApp(port=0, out_dir='out')\n"
        "try:\n"
        "    assert app.wait_idle(300)\n"
        "    print('DIR', d)\n"
        "    print('OPEN', app.state.scene_name, app.state.result is not None, len(app.state.entries))\n"
        "finally:\n"
        "    app.stop()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = dict(line.split(" ", 1) for line in proc.stdout.splitlines() if line.startswith(("DIR ", "OPEN ")))
    assert Path(lines["DIR"]) == site / "efem_viz" / "sample_scenes"
    name, has_result, count = lines["OPEN"].split()
    assert name != "None" and has_result == "True" and int(count) >= 1, proc.stdout


TREE_LIMIT_BYTES = 48 * 2**20
"""The working tree must travel: a GPU run receives it (tracked and untracked-not-ignored files) with at most
64 MiB in all, carried data included; 40 MiB is the target, 48 MiB the line this test holds."""


def test_the_working_tree_stays_small_enough_to_travel() -> None:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            capture_output=True, check=True).stdout.split(b"\0")
    sizes = {}
    for name in filter(None, listed):
        path = REPO / os.fsdecode(name)
        if path.is_file() and not path.is_symlink():
            sizes[os.fsdecode(name)] = path.stat().st_size
    total = sum(sizes.values())
    largest = sorted(sizes.items(), key=lambda kv: -kv[1])[:5]
    assert total <= TREE_LIMIT_BYTES, (f"the working tree holds {total / 2**20:.1f} MiB (limit "
                                       f"{TREE_LIMIT_BYTES / 2**20:.0f} MiB); largest: {largest}")
