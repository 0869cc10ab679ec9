"""Add a scene file format: one reader, one writer and one row of `efem_viz.data.formats.FORMATS`.

Every way into efem-viz — `load_scene` / `save_scene`, `find_scenes` (the folder walk of `view`, `segment` and
`efem-annotate`), the viewer and annotator sessions — picks a format by the file's suffix from that one table, so a
row added at run time is a format all of them know in that process from then on. A row is a `SceneFormat(load, save,
keeps_labels, keeps_faces)`:

* ``load(path, max_points) -> dict``: the keyword arguments of `Scene.create` (points, and optionally normals,
  colors, faces, instance, categories, provenance). Check sizes before reading (a reader must refuse a file with
  more points than ``max_points`` in bounded memory) and raise `SceneError` with the reason; `load_scene` names
  the file in the message.
* ``save(scene, tmp_path, *, ascii)``: write the whole file to ``tmp_path``; `save_scene` renames it into place
  (atomic: a crash never leaves half a file).

This example adds ".xyz": the plain text most scanners and CloudCompare export, one point per line as
``x y z [nx ny nz [instance]]``. It writes an analytic sphere scene as .xyz, lists the folder with `find_scenes`,
reads the file back (same points, normals and labels), refuses a damaged file and one that is too big in one line
each, and runs EFEM with the analytic sphere prior on the scene read from the new format.

Run (a few seconds)::

    python examples/add_scene_format.py
    python examples/add_scene_format.py --out /tmp/xyz
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.formats import FORMATS, SceneFormat
from efem_viz.data.scene import Scene, SceneError

MAX_LINE_BYTES = 256
"""Longest line a point may take: with ``max_points`` it bounds the file size a reader accepts before parsing."""


def load_xyz(path: Path, max_points: int) -> dict[str, Any]:
    """The `Scene.create` arguments of an .xyz file: 3 columns (points), 6 (and normals) or 7 (and labels)."""
    size = path.stat().st_size
    if size > max_points * MAX_LINE_BYTES:  # refused before anything is parsed
        raise SceneError(f"{size:,} bytes is more than {max_points:,} points (max_points) of at most "
                         f"{MAX_LINE_BYTES} bytes each")
    lines = 0
    with open(path, "rb") as fh:  # counted in blocks: memory stays bounded whatever the file holds
        while block := fh.read(1 << 20):
            if b"\x00" in block:
                raise SceneError("binary data in an .xyz file (expected text lines `x y z [nx ny nz [instance]]`)")
            lines += block.count(b"\n")
    if lines > max_points:
        raise SceneError(f"{lines:,} points is more than the limit of {max_points:,} (max_points)")
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise SceneError(f"not numeric columns: {exc}") from exc
    if table.shape[1] not in (3, 6, 7):
        raise SceneError(f"{table.shape[1]} columns; expected 3 (x y z), 6 (+ normals) or 7 (+ instance)")
    out: dict[str, Any] = {"points": table[:, :3]}
    if table.shape[1] >= 6:
        out["normals"] = table[:, 3:6]
    if table.shape[1] == 7:
        out["instance"] = table[:, 6].astype(np.int64)
    return out


def save_xyz(scene: Scene, tmp_path: Path, *, ascii: bool = True) -> None:
    """Write ``x y z nx ny nz [instance]`` lines (the format is text only, so ``ascii`` changes nothing)."""
    cols = [np.asarray(scene.points, np.float64), np.asarray(scene.normals, np.float64)]
    fmt = ["%.6f"] * 6
    if scene.has_gt:
        cols.append(np.asarray(scene.instance, np.float64)[:, None])
        fmt.append("%d")
    np.savetxt(tmp_path, np.concatenate(cols, axis=1), fmt=fmt)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--proposals", type=int, default=16, help="proposals of the EFEM run on the scene")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temp dir)")
    args = ap.parse_args(argv)

    import torch

    from efem_viz.data.io import find_scenes, load_scene, save_scene
    from efem_viz.em import preset, run_em
    from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

    torch.set_num_threads(1)
    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)

    # ---- 1. the row: from here on every reader and writer of efem-viz knows ".xyz"
    FORMATS[".xyz"] = SceneFormat(load_xyz, save_xyz, keeps_faces=False)
    print(f"formats: {', '.join(FORMATS)}")

    # ---- 2. write a scene in the new format, find it in its folder, read it back
    scene = make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    path = save_scene(scene, out / "spheres.xyz")
    print(f"wrote {path.name}: {scene.num_points:,} points, {len(scene.instance_ids())} labelled spheres")
    print(f"find_scenes lists: {[p.name for p in find_scenes(out)]}")
    back = load_scene(path)
    same = (np.allclose(back.points, scene.points, atol=1e-6) and np.allclose(back.normals, scene.normals, atol=1e-6)
            and np.array_equal(back.instance, scene.instance))
    print(f"read back {back.name}: {back.num_points:,} points, same points, normals and labels: {same}")

    # ---- 3. bad files: one line each, nothing half-read
    bad = out / "damaged.xyz"
    bad.write_text("0.1 0.2 0.3\n0.4 zero 0.6\n")
    big = out / "big.xyz"
    big.write_text("0 0 0\n" * 20)  # 120 bytes: within 10 points' bytes, but 20 lines
    for p, limit in ((bad, 1000), (big, 10)):
        try:
            load_scene(p, max_points=limit)
        except SceneError as exc:
            print(f"refused: {exc}")
        p.unlink()

    # ---- 4. EFEM on the scene read from the new format
    cfg = preset("fast").with_proposals(args.proposals).replace(elimination={"min_size": 30})
    result = run_em(back, make_sphere_prior(), cfg, seed=0)
    print(f"EFEM on {back.name}.xyz: {len(result.instances)} instances of {len(scene.instance_ids())} spheres")
    result.save(out / "spheres.efem.npz")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
