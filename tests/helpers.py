"""Small scene builders shared by several test modules (imported as ``helpers``: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from efem_viz.data.scene import Scene


def mesh_scene(seed: int = 0, *, subdivisions: int = 2) -> Scene:
    """A 0.1 m icosphere mesh with random colours, instance labels, categories and nested provenance."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    n = len(m.vertices)
    return Scene.create(
        "ball",
        m.vertices + [0.2, -0.1, 0.3],
        normals=m.vertex_normals,
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        faces=m.faces,
        instance=rng.integers(0, 4, n),
        categories={1: "mug", 2: "bowl", 3: "mug"},
        provenance={"source": "test", "seed": seed, "nested": {"a": [1, 2]}},
    )


def ball_scan(folder: Path) -> Path:
    """Write a 642-vertex icosphere scan (radius 0.1 m) to ``folder/scans/ball.ply`` (the servers' test scan)."""
    p = folder / "scans" / "ball.ply"
    p.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(p)
    return p


def server_signals(*, sigint_ignored: bool = False) -> Callable[[], None]:
    """A `preexec_fn` for the server processes tests start: SIGINT and SIGTERM at their default disposition, so that
    the servers stop on them even when the test run itself was started in the background of a non-interactive
    shell (which starts it, and every child, with SIGINT ignored).

    Args:
        sigint_ignored: start the child with SIGINT ignored instead (what such a background start gives the
            servers; the servers must stop on SIGINT all the same).
    """

    def preexec() -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN if sigint_ignored else signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    return preexec


def expanded_prior(path: Path, config: Any, *, name: str = "hostile") -> Path:
    """Write a prior file whose every weight is a zero-stride view of one stored float.

    The file stays a few KB however large `config` makes the network: ``torch.save`` keeps only the one-element
    storage, and ``torch.load`` gives back views of the declared shapes.

    Args:
        path: The ``.pt`` file to write.
        config: A `PriorConfig`; its parameter names and shapes are those of the file's state dict.
        name: The stored prior name.
    """
    import torch

    from efem_viz.prior.model import CHECKPOINT_FORMAT, ShapePrior

    with torch.device("meta"):
        shapes = {k: tuple(v.shape) for k, v in ShapePrior(config).state_dict().items()}
    one = torch.zeros(1)
    state = {k: one.reshape(()) if not s else one.expand(*s) for k, s in shapes.items()}
    torch.save({"format": CHECKPOINT_FORMAT, "name": name, "config": config.to_dict(), "state_dict": state,
                "metadata": {}}, path)
    return path


REGENERATED_SAMPLES: dict[str, tuple[str, int, int]] = {"syn_z_0": ("z", 0, 5), "syn_so3_0": ("so3", 0, 5)}
"""Synthetic sample scenes the checkout no longer ships (the tree travels small) but tests still use: name ->
(config, seed, objects) of the `efem-viz generate` call that made them (sample_scenes/README.md)."""


def sample_scene(name: str) -> Path:
    """`sample_scenes/<name>.ply`, or for a `REGENERATED_SAMPLES` name the same scene generated once per
    process into a temporary folder (bit-identical arrays; seconds of work)."""
    import tempfile

    shipped = Path(__file__).resolve().parents[1] / "sample_scenes" / f"{name}.ply"
    if shipped.is_file() or name not in REGENERATED_SAMPLES:
        return shipped
    folder = Path(tempfile.gettempdir()) / f"efem-viz-test-samples-{os.getuid()}"
    path = folder / f"{name}.ply"
    if not path.is_file():
        from efem_viz.data.io import save_scene
        from efem_viz.data.synth.generate import generate_scene

        config, seed, objects = REGENERATED_SAMPLES[name]
        folder.mkdir(parents=True, exist_ok=True)
        scene = generate_scene(config, seed=seed, n_objects=objects, mode="tsdf", name=name)  # type: ignore[arg-type]
        save_scene(scene, path)
    return path


ROOT = Path(__file__).resolve().parents[1]
"""The checkout."""


def bench_module(name: str) -> Any:
    """``bench.<name>`` of this checkout (`bench/` is not installed), with the checkout first on `sys.path` only
    while importing."""
    import importlib
    import sys

    sys.path.insert(0, str(ROOT))
    try:
        return importlib.import_module(f"bench.{name}")
    finally:
        sys.path.remove(str(ROOT))
