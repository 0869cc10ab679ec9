"""Render a grid of procedural shapes (shaded, one view each) into a PNG, to judge a family's variety at a glance.

Usage: python scripts/render_previews.py chair --count 24 --out docs/img/chair_family.png [--split val]
Uses the project's own ray caster (efem_viz.geometry.raycast): no GPU or display needed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def render(mesh: object, size: int = 160) -> np.ndarray:
    """(size, size, 3) uint8: the shape seen from the front-left, above (front toward -Y), Lambert-shaded."""
    import torch

    from efem_viz.geometry.raycast import cast_rays, pinhole_rays

    v = np.asarray(mesh.vertices, np.float64)  # type: ignore[attr-defined]
    f = np.asarray(mesh.faces, np.int64)  # type: ignore[attr-defined]
    radius = float(np.linalg.norm(v.max(0) - v.min(0))) / 2
    centre = (v.max(0) + v.min(0)) / 2
    eye = centre + radius * 2.6 * np.array([-0.55, -0.75, 0.45])
    o, d = pinhole_rays(torch.tensor(eye), center=torch.tensor(centre), fov_deg=44.0, resolution=size)
    t, n = cast_rays(torch.tensor(v), torch.tensor(f), o, d)
    light = np.array([-0.4, -0.6, 0.7])
    light /= np.linalg.norm(light)
    nn = n.numpy()
    shade = np.abs(nn @ light) * 0.75 + 0.25
    img = np.where(np.isfinite(t.numpy())[:, None], (shade[:, None] * np.array([205, 160, 110])), 255.0)
    return np.flipud(img.reshape(size, size, 3)).clip(0, 255).astype(np.uint8)  # rows from the bottom up


def main() -> int:
    from PIL import Image

    from efem_viz.data.procedural import make_shape, split_seeds

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("category")
    ap.add_argument("--count", type=int, default=24)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--split", default="val", choices=["train", "val", "test"])
    ap.add_argument("--size", type=int, default=160)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    seeds = list(split_seeds(a.category, a.split))[: a.count]
    tiles = [render(make_shape(a.category, s), a.size) for s in seeds]
    rows = -(-len(tiles) // a.cols)
    grid = np.full((rows * a.size, a.cols * a.size, 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, a.cols)
        grid[r * a.size:(r + 1) * a.size, c * a.size:(c + 1) * a.size] = tile
    a.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(grid).save(a.out, optimize=True)
    print(f"wrote {a.out}: {len(tiles)} {a.category} shapes of the {a.split} split (seeds {seeds[0]}..{seeds[-1]})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
