"""OBJ and OFF scenes (text formats without a place for per-vertex integer labels: ground truth is dropped on save,
with a warning, and never present on load; use PLY or NPZ for labelled scenes).

OBJ is read through trimesh after bounds checks (vertex count, element indices); OFF/COFF/NOFF/CNOFF is read here.
OBJ keeps colours as `v x y z r g b`; OFF writes CNOFF (normals and colours).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.formats.common import from_trimesh, triangulate
from efem_viz.data.scene import LIMIT_FLAG_HINT, MAX_FACES_PER_POINT, TOO_MANY_POINTS_HINT, Scene, SceneError

def _obj_vertex_count(p: Path, chunk: int = 4 << 20) -> int:
    """Number of `v` lines of an OBJ file, counted in chunks (C speed, one chunk of memory)."""
    n = 0
    prev = b"\n"  # the last two bytes of the previous chunk: a 3-byte match may straddle the boundary
    with open(p, "rb") as fh:
        while block := fh.read(chunk):
            data = prev[-2:] + block
            n += data.count(b"\nv ") + data.count(b"\nv\t") + data.count(b"\rv ") + data.count(b"\rv\t")
            prev = data
    return n


_OBJ_ELEMENT_LINES = re.compile(rb"(?m)^[ \t]*[flp][ \t][^\r\n]*")
_DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"000000000")


def _check_obj_indices(p: Path, chunk: int = 4 << 20) -> None:
    """Refuse an OBJ whose `f`/`l`/`p` lines hold an index with more digits than its number of lines (trimesh
    allocates arrays as long as the largest index: one `f 1 2 1000000000000` line cost 7 TiB); what passes is
    below 10x the line count. C-speed regexes (about 0.2 s for 30 MB), one chunk of memory.

    Raises:
        SceneError: the first such index, with the file's line count.
    """
    n_lines = 1
    with open(p, "rb") as fh:
        while block := fh.read(chunk):
            n_lines += block.count(b"\n") + block.count(b"\r")
    too_long = b"0" * (len(str(n_lines)) + 1)  # more digits than the line count (digits read as 0 below)
    carry = b""
    with open(p, "rb") as fh:
        while True:
            block = fh.read(chunk)
            data = carry + block
            cut = max(data.rfind(b"\n"), data.rfind(b"\r")) if block else len(data) - 1
            data, carry = data[: cut + 1], data[cut + 1 :]
            elements = b"\n".join(_OBJ_ELEMENT_LINES.findall(data))
            at = elements.translate(_DIGITS_AS_ZERO).find(too_long)
            if at >= 0:
                start = elements.rfind(b"\n", 0, at) + 1
                line = elements[start : elements.find(b"\n", at) % (len(elements) + 1)]
                index = re.match(rb"\d+", elements[at:])
                raise SceneError(
                    f"{p}: OBJ element line {line[:60].decode('ascii', 'replace')!r} refers to vertex "
                    f"{int(index.group()) if index else 0:,}, but the file has only {n_lines:,} lines (corrupt file)"
                )
            if not block:
                return


def load_obj(p: Path, max_points: int) -> dict[str, Any]:
    import trimesh

    n_v = _obj_vertex_count(p)
    if n_v > max_points:
        raise SceneError(
            f"{p} has {n_v:,} vertices ('v' lines), more than the limit of {max_points:,}; {TOO_MANY_POINTS_HINT}"
        )
    _check_obj_indices(p)
    geom = trimesh.load(str(p), file_type="obj", process=False, maintain_order=True)
    if isinstance(geom, trimesh.Scene):
        if not geom.geometry:
            raise SceneError(f"{p}: OBJ file has no geometry")
        geom = geom.to_geometry()
    out = from_trimesh(geom, p)
    if isinstance(geom, trimesh.PointCloud):
        # trimesh drops `vn` lines of a point-cloud OBJ; read them back when there is one per vertex.
        vn = _obj_vn(p)
        if vn is not None and len(vn) == len(out["points"]):
            out["normals"] = vn
    return out


def _obj_vn(p: Path) -> np.ndarray | None:
    rows = []
    with open(p, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("vn "):
                rows.append(line.split()[1:4])
    return np.asarray(rows, dtype=np.float64) if rows else None


def load_off(p: Path, max_points: int) -> dict[str, Any]:
    """Read OFF/COFF/NOFF/CNOFF (ASCII): vertices `x y z [nx ny nz] [r g b [a]]`, faces `n i0 .. i(n-1) [...]`."""
    text = p.read_text(encoding="utf-8", errors="strict")
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise SceneError(f"{p}: OFF file has no content")
    first = lines[0].split()
    key = first[0].upper()
    if key not in ("OFF", "COFF", "NOFF", "CNOFF", "NCOFF"):
        raise SceneError(f"{p}: not an OFF file (first keyword {first[0]!r}; expected OFF, COFF, NOFF or CNOFF)")
    has_normals = "N" in key[:-3]
    has_colors = "C" in key[:-3]
    rest = first[1:]
    idx = 1
    if not rest:
        rest = lines[1].split()
        idx = 2
    if len(rest) < 2:
        raise SceneError(f"{p}: OFF count line must hold 'n_vertices n_faces [n_edges]', got {rest}")
    nv, nf = int(rest[0]), int(rest[1])
    if nv < 0 or nf < 0:
        raise SceneError(f"{p}: OFF count line gives negative counts ({nv} vertices, {nf} faces)")
    if nv > max_points:
        raise SceneError(f"{p} has {nv:,} points, more than the limit of {max_points:,}; {TOO_MANY_POINTS_HINT}")
    if nf > MAX_FACES_PER_POINT * max(max_points, 1):
        raise SceneError(
            f"{p}: OFF header declares {nf:,} faces, more than the limit of {MAX_FACES_PER_POINT * max_points:,} "
            f"({MAX_FACES_PER_POINT} per allowed point; corrupt header, or {LIMIT_FLAG_HINT})"
        )
    if len(lines) < idx + nv + nf:
        raise SceneError(f"{p}: OFF file is truncated: expected {nv} vertices and {nf} faces after the header")
    if len(lines) > idx + nv + nf:
        raise SceneError(
            f"{p}: OFF file has more rows than its header declares ({nv:,} vertices, {nf:,} faces): "
            f"{len(lines) - idx - nv - nf:,} more non-empty lines, the first {lines[idx + nv + nf][:60]!r}; "
            "fix the counts or remove the extra rows"
        )
    vrows = [ln.split() for ln in lines[idx : idx + nv]]
    ncol = min(len(r) for r in vrows) if vrows else 3
    vals = np.asarray([r[:ncol] for r in vrows], dtype=np.float64)
    out: dict[str, Any] = {"points": vals[:, :3]}
    c = 3
    if has_normals:
        if ncol < 6:
            raise SceneError(f"{p}: {key} vertices need normals but have {ncol} values")
        out["normals"] = vals[:, 3:6]
        c = 6
    if has_colors and ncol >= c + 3:
        col = vals[:, c : c + 3]
        is_float = any(("." in t or "e" in t.lower()) for t in vrows[0][c : c + 3])
        # COFF colours are either integers 0..255 or floats 0..1 (decided by how the first row is written)
        out["colors"] = col.astype(np.float32) if is_float else np.clip(np.round(col), 0, 255).astype(np.uint8)
    polys = []
    for ln in lines[idx + nv : idx + nv + nf]:
        parts = ln.split()
        k = int(parts[0])
        if len(parts) < k + 1:
            raise SceneError(f"{p}: OFF face line {ln!r} lists fewer than {k} indices")
        polys.append(np.asarray(parts[1 : k + 1], dtype=np.int64))
    out["faces"] = triangulate(polys, p) if polys else None
    return out


def _fmt_rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    row = prefix + " ".join([fmt] * a.shape[1]) + "\n"
    return "".join(row % tuple(r) for r in a.tolist())


def save_obj(scene: Scene, tmp: Path, *, ascii: bool = True) -> None:
    """Write `v x y z r g b`, `vn` and `f a//a b//b c//c` lines (OBJ is text only: `ascii` is ignored)."""
    vc = np.concatenate([scene.points.astype(np.float64), scene.colors.astype(np.float64) / 255.0], axis=1)
    parts = [f"# efem-viz scene {scene.name}\n", _fmt_rows(vc, "v ", "%.7g"), _fmt_rows(scene.normals, "vn ", "%.6g")]
    if scene.faces is not None and len(scene.faces):
        f1 = scene.faces.astype(np.int64) + 1
        parts.append("".join(f"f {a}//{a} {b}//{b} {c}//{c}\n" for a, b, c in f1.tolist()))
    tmp.write_text("".join(parts), encoding="utf-8")


def save_off(scene: Scene, tmp: Path, *, ascii: bool = True) -> None:
    """Write CNOFF: `x y z nx ny nz r g b` vertex rows and `3 a b c` faces (OFF is text only: `ascii` is ignored)."""
    nf = len(scene.faces) if scene.faces is not None else 0
    vals = np.concatenate(
        [scene.points.astype(np.float64), scene.normals.astype(np.float64), scene.colors.astype(np.float64)], axis=1
    )
    lines = ["CNOFF\n", f"{scene.num_points} {nf} 0\n"]
    rows = "".join(
        "%.7g %.7g %.7g %.6g %.6g %.6g %d %d %d\n" % tuple(r) for r in vals.tolist()
    )
    lines.append(rows)
    if nf:
        lines.append("".join(f"3 {a} {b} {c}\n" for a, b, c in scene.faces.tolist()))  # type: ignore[union-attr]
    tmp.write_text("".join(lines), encoding="utf-8")

