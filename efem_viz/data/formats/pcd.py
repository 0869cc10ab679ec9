"""PCD point clouds (the Point Cloud Library's format, what ROS and many robot stacks write): ``ascii``, ``binary``
and ``binary_compressed`` bodies.

Read: `x y z` (any float or integer type), `normal_x normal_y normal_z` (optional), colour as `rgb` / `rgba` (the
packed 4-byte form PCL writes, whatever TYPE the header gives it), instance labels from `instance` or `label`
(optional; 0 = unlabelled); other fields (`curvature`, intensities, ...) are skipped. Organised clouds (HEIGHT > 1)
keep their valid points only: rows with a non-finite coordinate are dropped, as every PCL consumer does. Categories
and provenance live in header comments `# efem_categories {json}` / `# efem_provenance {json}` (as in our PLY
files; PCL skips comment lines).

Every count the header declares is checked against the bytes the file holds and `max_points` before anything is
allocated for it; the LZF decoder of ``binary_compressed`` stops at the size the header declares.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.formats.common import CATEGORIES_COMMENT, PROVENANCE_COMMENT, parse_categories
from efem_viz.data.scene import LIMIT_FLAG_HINT, TOO_MANY_POINTS_HINT, Scene, SceneError

_HEADER_LIMIT = 1 << 20
"""Bytes searched for the `DATA` line: a longer header is refused."""
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_DTYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "<i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
           ("U", 1): "<u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}
_LABEL_FIELDS = ("instance", "label")
_MAX_FIELDS = 256


def _header(p: Path) -> tuple[dict[str, list[str]], dict[str, str], int]:
    """(header keys -> values, efem comments -> text, byte offset of the body)."""
    with open(p, "rb") as fh:
        head = fh.read(_HEADER_LIMIT)
    keys: dict[str, list[str]] = {}
    comments: dict[str, str] = {}
    pos = 0
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise SceneError(f"no DATA line within the first {_HEADER_LIMIT >> 20} MB: "
                             "not a PCD file or a damaged header")
        line = head[pos:end].decode("utf-8", errors="replace").strip()
        pos = end + 1
        if not line:
            continue
        if line.startswith("#"):
            tag, _, rest = line[1:].strip().partition(" ")
            if tag in (CATEGORIES_COMMENT, PROVENANCE_COMMENT):
                comments[tag] = rest
            continue
        word, *vals = line.split()
        if word.upper() not in _KEYS:
            raise SceneError(f"unknown PCD header line {line[:60]!r}: not a PCD file or a damaged header")
        keys[word.upper()] = vals
        if word.upper() == "DATA":
            return keys, comments, pos


def _int(keys: dict[str, list[str]], key: str) -> int:
    try:
        (value,) = keys[key]
        out = int(value)
    except (KeyError, ValueError):
        raise SceneError(f"PCD header: {key} must be one integer, got {keys.get(key)}") from None
    if out < 0:
        raise SceneError(f"PCD header: negative {key} ({out})")
    return out


def _layout(keys: dict[str, list[str]], max_points: int) -> tuple[list[str], np.dtype, int, str]:
    """(field names, one row's structured dtype (every COUNT expanded), points, data kind), checked."""
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in keys:
            raise SceneError(f"PCD header has no {key} line")
    fields, sizes, types = keys["FIELDS"], keys["SIZE"], keys["TYPE"]
    counts = keys.get("COUNT", ["1"] * len(fields))
    if not 0 < len(fields) <= _MAX_FIELDS or not len(fields) == len(sizes) == len(types) == len(counts):
        raise SceneError(f"PCD header: FIELDS, SIZE, TYPE and COUNT disagree ({len(fields)}, {len(sizes)}, "
                         f"{len(types)}, {len(counts)} entries)")
    names: list[str] = []
    cols: list[tuple[str, str]] = []
    for name, size, kind, count in zip(fields, sizes, types, counts):
        try:
            n, s = int(count), int(size)
        except ValueError:
            raise SceneError(f"PCD header: field {name!r} has SIZE {size!r} / COUNT {count!r}") from None
        dt = _DTYPES.get((kind.upper(), s))
        if dt is None or not 0 < n <= 4096:
            raise SceneError(f"PCD header: field {name!r} of TYPE {kind} SIZE {size} COUNT {count} is not supported")
        if name in names:
            raise SceneError(f"PCD header: field {name!r} is declared twice")
        names.append(name)
        cols += [(name if n == 1 else f"{name}__{i}", dt) for i in range(n)]
    if not {"x", "y", "z"} <= set(names):
        raise SceneError(f"PCD file has no x y z fields (fields: {' '.join(names[:12])})")
    points = _int(keys, "POINTS") if "POINTS" in keys else _int(keys, "WIDTH") * _int(keys, "HEIGHT")
    if points == 0:
        raise SceneError("PCD file holds no points (POINTS 0)")
    if points > max_points:
        raise SceneError(f"PCD header declares {points:,} points, more than the limit {max_points:,} "
                         f"({TOO_MANY_POINTS_HINT}{LIMIT_FLAG_HINT})")
    kind = keys["DATA"][0].lower() if keys["DATA"] else ""
    if kind not in ("ascii", "binary", "binary_compressed"):
        raise SceneError(f"PCD DATA {kind!r} is not ascii, binary or binary_compressed")
    return names, np.dtype(cols), points, kind


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decode LZF (liblzf's format, used by PCD's ``binary_compressed``) into exactly ``size`` bytes.

    Raises:
        SceneError: a back reference before the start, output beyond ``size``, or a short result.
    """
    out = bytearray(size)
    i = o = 0
    n = len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if i + length > n or o + length > size:
                raise SceneError("damaged compressed PCD body (a literal runs past the end)")
            out[o:o + length] = data[i:i + length]
            i += length
            o += length
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                raise SceneError("damaged compressed PCD body (truncated back reference)")
            length += data[i]
            i += 1
        if i >= n:
            raise SceneError("damaged compressed PCD body (truncated back reference)")
        ref = o - ((ctrl & 0x1F) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0 or o + length > size:
            raise SceneError("damaged compressed PCD body (a back reference outside the data)")
        if ref + length <= o:
            out[o:o + length] = out[ref:ref + length]
        else:  # overlapping copy repeats the pattern
            for k in range(length):
                out[o + k] = out[ref + k]
        o += length
    if o != size:
        raise SceneError(f"damaged compressed PCD body ({o} of {size} bytes decoded)")
    return bytes(out)


def _body(p: Path, offset: int, row: np.dtype, points: int, kind: str) -> np.ndarray:
    """The (points,) structured array of the body, bounds-checked against the file's size."""
    file_size = p.stat().st_size
    body_bytes = file_size - offset
    names: tuple[str, ...] = tuple(row.names or ())
    fields: dict[str, Any] = {str(k): v for k, v in (row.fields or {}).items()}
    if kind == "ascii":
        if body_bytes < 2 * points * len(names) - 1:  # every value takes at least a digit and a separator
            raise SceneError(f"PCD header declares {points:,} points but the file holds {body_bytes:,} bytes of text")
        with open(p, "rb") as fh:
            fh.seek(offset)
            text = fh.read()
        try:  # parsed straight into one float64 array (no per-token Python objects); junk stops it with a warning
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                flat = np.fromstring(text.decode("ascii", errors="replace").replace("\ufffd", "?"), sep=" ")
        except (ValueError, DeprecationWarning):
            raise SceneError("the PCD body holds a value that is not a number: damaged file") from None
        width = len(names)
        if len(flat) != points * width:
            raise SceneError(f"PCD body holds {len(flat):,} values, the header declares {points:,} x {width}")
        vals = flat.reshape(points, width)
        arr = np.zeros(points, dtype=row)
        for j, name in enumerate(names):
            arr[name] = vals[:, j]
        return arr
    need = points * row.itemsize
    with open(p, "rb") as fh:
        fh.seek(offset)
        if kind == "binary":
            if body_bytes < need:
                raise SceneError(f"PCD header declares {points:,} points ({need:,} bytes) but the body has "
                                 f"{body_bytes:,}: truncated file")
            return np.frombuffer(fh.read(need), dtype=row, count=points).copy()
        sizes = np.frombuffer(fh.read(8), dtype="<u4")
        if len(sizes) != 2:
            raise SceneError("truncated compressed PCD body")
        packed, unpacked = int(sizes[0]), int(sizes[1])
        if unpacked != need:
            raise SceneError(f"compressed PCD body unpacks to {unpacked:,} bytes, the header declares {need:,}")
        if packed > body_bytes - 8:
            raise SceneError(f"compressed PCD body of {packed:,} bytes but the file holds {body_bytes - 8:,}: "
                             "truncated file")
        raw = lzf_decompress(fh.read(packed), unpacked)
    # binary_compressed stores the fields one after another (column-major)
    arr = np.zeros(points, dtype=row)
    pos = 0
    for name in names:
        dt = fields[name][0]
        arr[name] = np.frombuffer(raw, dtype=dt, count=points, offset=pos)
        pos += points * dt.itemsize
    return arr


def load(p: Path, max_points: int) -> dict[str, Any]:
    """The `Scene.create` arguments of a PCD file (see the module docstring)."""
    keys, comments, offset = _header(p)
    names, row, points, kind = _layout(keys, max_points)
    arr = _body(p, offset, row, points, kind)
    xyz = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
    valid = np.isfinite(xyz).all(axis=1)
    if not valid.any():
        raise SceneError("PCD file holds no valid points (every row has a NaN or infinite coordinate)")
    out: dict[str, Any] = {"points": xyz[valid]}
    if {"normal_x", "normal_y", "normal_z"} <= set(names):
        nrm = np.stack([arr["normal_x"], arr["normal_y"], arr["normal_z"]], axis=1).astype(np.float64)[valid]
        if np.isfinite(nrm).all() and (np.linalg.norm(nrm, axis=1) > 0).all():
            out["normals"] = nrm
    for colour in ("rgb", "rgba"):
        if colour in names and dict(row.fields or {})[colour][0].itemsize == 4:
            packed = arr[colour].view("<u4")[valid]
            out["colors"] = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255],
                                     axis=1).astype(np.uint8)
            break
    for label in _LABEL_FIELDS:
        if label in names:
            lab = np.asarray(arr[label])[valid]
            if lab.dtype.kind == "f":
                if not (np.isfinite(lab).all() and (lab == np.round(lab)).all()):
                    raise SceneError(f"PCD field {label!r} holds non-integer instance labels")
            out["instance"] = lab.astype(np.int64)
            break
    if CATEGORIES_COMMENT in comments:
        out["categories"] = parse_categories(comments[CATEGORIES_COMMENT])
    if PROVENANCE_COMMENT in comments:
        prov = json.loads(comments[PROVENANCE_COMMENT])
        if not isinstance(prov, dict):
            raise SceneError("PCD provenance comment is not a JSON object")
        out["provenance"] = prov
    return out


def save(scene: Scene, tmp: Path, *, ascii: bool = False) -> None:
    """Write a PCD (v0.7) file: x y z, normals when the scene has them, packed rgb, `instance` labels when the scene
    has ground truth; binary unless ``ascii``. Meshes are written as their vertices (PCD has no faces)."""
    cols: list[tuple[str, str, np.ndarray]] = [(c, "<f4", scene.points[:, i]) for i, c in enumerate("xyz")]
    if not scene.normals_pending:
        cols += [(f"normal_{c}", "<f4", scene.normals[:, i]) for i, c in enumerate("xyz")]
    rgb = scene.colors.astype(np.uint32)
    cols.append(("rgb", "<u4", (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]))
    if scene.instance is not None:
        cols.append(("instance", "<i4", scene.instance))
    row = np.dtype([(name, dt) for name, dt, _ in cols])
    arr = np.empty(scene.num_points, dtype=row)
    for name, _, values in cols:
        arr[name] = values
    head = ["# .PCD v0.7 - Point Cloud Data file format (efem-viz)"]
    if scene.categories:
        head.append(f"# {CATEGORIES_COMMENT} {json.dumps({str(k): v for k, v in scene.categories.items()})}")
    if scene.provenance:
        head.append(f"# {PROVENANCE_COMMENT} {json.dumps(dict(scene.provenance), default=str)}")
    types = {"<f4": "F", "<u4": "U", "<i4": "I"}
    head += ["VERSION 0.7", "FIELDS " + " ".join(n for n, _, _ in cols), "SIZE " + " ".join("4" for _ in cols),
             "TYPE " + " ".join(types[dt] for _, dt, _ in cols), "COUNT " + " ".join("1" for _ in cols),
             f"WIDTH {scene.num_points}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {scene.num_points}",
             f"DATA {'ascii' if ascii else 'binary'}"]
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode())
        if not ascii:
            fh.write(arr.tobytes())
            return
        fmt = " ".join("%.9g" if dt == "<f4" else "%d" for _, dt, _ in cols)
        np.savetxt(fh, np.stack([arr[n].astype(np.float64) for n, _, _ in cols], axis=1), fmt=fmt)
