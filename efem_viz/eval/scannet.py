"""The ScanNet benchmark prediction layout (docs/design/efem-method.md §4.2), read and written.

`<dir>/<scene>.txt` holds one line per predicted instance, `<mask path> <class id> <confidence>`, the mask path
relative to `<dir>`. A mask is a `.npy` of N 0/1 values (EFEM appends `.npy` to the listed name:
`pred_mask/<scene>_000.txt` is stored as `pred_mask/<scene>_000.txt.npy`) or a text file with one 0/1 per line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from efem_viz.eval.matching import ScenePrediction


def _scannet_dir(path: Path) -> Path:
    """The folder that holds the `<scene>.txt` files: `path` itself, `path/scannet` (what `efem-viz segment`
    writes) or `path/scannet_format` (the EFEM release)."""
    if any(path.glob("*.txt")):
        return path
    for name in ("scannet", "scannet_format"):
        sub = path / name
        if sub.is_dir() and any(sub.glob("*.txt")):
            return sub
    return path


def _read_mask(base: Path, rel: str, where: str) -> np.ndarray:
    cands = [base / rel, base / (rel + ".npy")]
    for c in cands:
        if c.is_file():
            try:
                if c.suffix == ".npy":
                    m = np.load(c, allow_pickle=False)
                else:
                    m = np.loadtxt(c, dtype=np.int64, ndmin=1)
            except Exception as exc:
                raise ValueError(f"{where}: could not read mask {c} ({type(exc).__name__}: {exc})") from exc
            return np.asarray(m).reshape(-1) != 0  # nonzero means "in the mask" (§5.2)
    raise ValueError(f"{where}: mask file {cands[0]} (or {cands[1].name}) not found")


def load_scannet_predictions(path: str | os.PathLike[str]) -> list[ScenePrediction]:
    """Read every `<scene>.txt` of a ScanNet-format prediction folder (or its `scannet/` or `scannet_format/`
    subfolder).

    Args:
        path: the folder.

    Returns:
        One ScenePrediction per txt file, sorted by scene name; masks are (N,) bool.

    Raises:
        ValueError: missing folder or mask, malformed line.
    """
    return [load_scannet_prediction(txt) for txt in scannet_prediction_files(path).values()]


def scannet_prediction_files(path: str | os.PathLike[str]) -> dict[str, Path]:
    """Scene name → `<scene>.txt` of a ScanNet-format prediction folder (or its `scannet/` or `scannet_format/`
    subfolder), sorted by name; nothing is read.

    Raises:
        ValueError: not a folder.
    """
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder of ScanNet-format predictions")
    base = _scannet_dir(root)
    # hidden files are temporaries of interrupted writes, never predictions
    return {txt.stem: txt for txt in sorted(base.glob("*.txt")) if not txt.name.startswith(".")}


def load_scannet_prediction(txt: Path) -> ScenePrediction:
    """Read one `<scene>.txt` of the ScanNet layout and its masks (paths relative to its folder).

    Raises:
        ValueError: missing mask, malformed line.
    """
    base = txt.parent
    masks, labels, confs = [], [], []
    for ln_no, line in enumerate(txt.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        parts = line.rsplit(maxsplit=2)  # a scene name (in the mask path) may hold spaces
        where = f"{txt}:{ln_no}"
        if len(parts) != 3:
            raise ValueError(f"{where}: expected '<mask path> <class id> <confidence>', got {line!r}")
        try:
            label, conf = int(parts[1]), float(parts[2])
        except ValueError as exc:
            raise ValueError(f"{where}: bad class id or confidence in {line!r}") from exc
        masks.append(_read_mask(base, parts[0], where))
        labels.append(label)
        confs.append(conf)
    return ScenePrediction(
        name=txt.stem, masks=masks, confidences=np.asarray(confs, np.float64), labels=np.asarray(labels, np.int64)
    )


def write_scannet_predictions(
    path: str | os.PathLike[str],
    pred: ScenePrediction,
    *,
    num_points: int,
    mask_dir: str = "pred_mask",
    npy: bool = True,
) -> Path:
    """Write one scene's predictions in the ScanNet layout (confidences with 4 decimals). Atomic per file.

    Args:
        path: the output folder.
        pred: the predictions (bool or index masks).
        num_points: N, the scene's point count.
        mask_dir: subfolder for the masks.
        npy: write masks as `<name>.txt.npy` uint8 (EFEM) instead of text.

    Returns:
        The written `<scene>.txt`.
    """
    from efem_viz.data.io import atomic_write, atomic_write_text
    from efem_viz.eval.matching import bool_mask

    root = Path(path)
    (root / mask_dir).mkdir(parents=True, exist_ok=True)
    lines = []
    labels: Sequence[int] | np.ndarray = (
        pred.labels if pred.labels is not None else np.ones(len(pred.masks), np.int64)
    )
    for k, (m, lab, conf) in enumerate(zip(pred.masks, labels, pred.confidences)):
        rel = f"{mask_dir}/{pred.name}_{k:03d}.txt"
        b = bool_mask(m, num_points, f"prediction {k}").astype(np.uint8)
        if npy:
            atomic_write(root / (rel + ".npy"), lambda t, b=b: np.save(t, b))
        else:
            atomic_write_text(root / rel, "\n".join(str(int(v)) for v in b) + "\n")
        lines.append(f"{rel} {int(lab)} {conf:.4f}")
    return atomic_write_text(root / f"{pred.name}.txt", "\n".join(lines) + ("\n" if lines else ""))
