"""Reading and writing scenes: PLY (binary/ASCII), OBJ, OFF, GLB and the native NPZ, plus `atomic_write`.

Which format keeps what (a round trip through `save_scene` then `load_scene`):

| format | points | normals | colours | faces | instance labels | categories, provenance |
|--------|--------|---------|---------|-------|-----------------|------------------------|
| .ply   | yes    | yes     | yes     | yes   | yes (`instance` int vertex property) | yes (comment lines) |
| .npz   | yes    | yes     | yes     | yes   | yes             | yes                    |

(An `.npz` holding an RGB-D frame — `depth_mm` or `depth`, `K`, optional `rgb` — instead of a scene is imported
with `efem_viz.data.rgbd.import_rgbd_file` and its default settings.)
| .glb   | yes    | meshes  | yes     | yes   | yes (`_instance` vertex attribute, meshes; scene extras, point clouds) | yes (scene extras) |
| .obj   | yes    | yes     | yes (`v x y z r g b`) | yes | no  | no                     |
| .off   | yes    | yes (NOFF) | yes (COFF) | yes | no         | no                     |

OBJ and OFF have no place for per-vertex integer labels, so ground truth is dropped on save (with a warning) and
never present on load; use PLY or NPZ for labelled scenes. glTF is +Y up by specification: GLB files are converted
from our +Z-up world frame on save, `(x, y, z) -> (x, z, -y)`, and back on load. GLB point clouds have no normals
slot; their normals and labels travel in the scene's JSON extras.

PLY conventions (the same file the annotator writes, readable by MeshLab/CloudCompare): vertex properties
`x y z` (float), `nx ny nz` (float, optional), `red green blue` (uchar, optional), `instance` (int, optional,
0 = unlabelled); element `face` with list property `vertex_indices`. Categories and provenance are stored as
header comments `efem_categories {json}` and `efem_provenance {json}`.

Every write goes through `atomic_write`: a temporary file in the destination directory, fsync, then `os.replace`,
so a crash never leaves a half-written scene behind.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import re
import tempfile
import warnings
import zlib
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple, cast

import numpy as np

from efem_viz.data.npz import check_npz_headers
from efem_viz.data.scene import (
    DEFAULT_MAX_POINTS,
    LIMIT_FLAG_HINT,
    MAX_FACES_PER_POINT,
    SCENE_SCHEMA_VERSION,
    TOO_MANY_POINTS_HINT,
    Scene,
    SceneError,
)

log = logging.getLogger(__name__)

SCENE_SUFFIXES: tuple[str, ...] = (".ply", ".obj", ".off", ".glb", ".npz")
"""File suffixes `load_scene` understands (lower case)."""
RESULT_SUFFIX = ".efem.npz"
"""Suffix of EFEM result files (`EMResult.save`); `find_scenes` skips them."""
SEG_SUFFIX = ".seg.ply"
"""Suffix of `efem-viz segment`'s scene copies coloured by prediction: their per-vertex `instance` property holds
the *predicted* instances, not ground truth (`holds_predictions`)."""


def holds_predictions(path: str | os.PathLike[str]) -> bool:
    """Whether a scene file's instance labels are predictions (a `segment` output, `SEG_SUFFIX`), not ground
    truth."""
    return Path(path).name.endswith(SEG_SUFFIX)

_CATEGORIES_COMMENT = "efem_categories"
_PROVENANCE_COMMENT = "efem_provenance"
_GLB_EXTRAS_KEY = "efem"
_MAX_GLB_LABEL = 2**24  # float32 represents every integer up to 2^24 exactly



# ---------------------------------------------------------------------------------------------- atomic write
def atomic_write(path: str | os.PathLike[str], writer: Callable[[Path], Any]) -> Path:
    """Write a file atomically: `writer(tmp_path)` writes a temporary file in the same directory, then rename.

    The one atomic write of efem-viz and the annotator. The temporary file (``.<stem>.<random>.tmp<suffix>``)
    keeps the destination's suffix (so writers that infer the format from the name, or that append `.npz`,
    behave), is fsynced, gets the destination's permissions, and then replaces `path` with `os.replace` (atomic on
    POSIX and Windows); the directory is fsynced after the rename so that the rename itself survives a power
    cut (best effort: not every platform can). On any error the temporary file is removed and `path` is left
    untouched. An existing symbolic link at `path` is refused: it is never replaced or written through.

    Args:
        path: destination file; its parent directory is created if missing.
        writer: callable that writes the whole file to the `Path` it is given.

    Returns:
        The destination path.

    Raises:
        ValueError: `path` is a symbolic link.
    """
    dest = Path(path)
    if dest.is_symlink():
        raise ValueError(f"refusing to overwrite {dest}: it is a symbolic link")
    dest.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(dest.suffixes[-2:]) if dest.name.endswith(RESULT_SUFFIX) else dest.suffix
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=".tmp" + suffix, dir=dest.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        writer(tmp)
        if not tmp.exists():
            raise OSError(f"writer did not create the temporary file {tmp}")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode(dest))  # mkstemp makes 0600 files; give the usual permissions
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:  # make the rename itself durable (best effort; not possible on every platform)
        dir_fd = os.open(dest.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass
    return dest


def _file_mode(dest: Path) -> int:
    """The existing file's permissions, or 0666 minus the process umask for a new file."""
    try:
        return dest.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


def _umask() -> int:
    """The process umask, read without changing it (os.umask would race with other threads); 0o022 if unknown."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """`atomic_write` of a bytes payload (same guarantees and errors)."""
    return atomic_write(path, lambda p: p.write_bytes(data))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """`atomic_write` of a UTF-8 text payload (same guarantees and errors)."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


# ---------------------------------------------------------------------------------------------- discovery
class ScenePathNotFoundError(SceneError, FileNotFoundError):
    """A scene path that does not exist: both a `SceneError` (a user error the CLI reports in one line) and a
    `FileNotFoundError` (what the viewer's `discover_scenes` documents)."""


def is_scene_file(path: str | os.PathLike[str]) -> bool:
    """True for a file name with a scene suffix that is not an EFEM result (`*.efem.npz`) or a hidden file."""
    p = Path(path)
    return not p.name.startswith(".") and _has_scene_suffix(p)


def _has_scene_suffix(p: Path) -> bool:
    return not p.name.lower().endswith(RESULT_SUFFIX) and p.suffix.lower() in SCENE_SUFFIXES


def find_scenes(
    paths: str | os.PathLike[str] | Iterable[str | os.PathLike[str]], *, recursive: bool = False
) -> list[Path]:
    """Scene files among the given files and directories: the one folder walk of efem-viz (the CLI commands and
    the viewer's `discover_scenes` list scenes with it).

    Directories are listed (sub-folders too with `recursive`), keeping the files `is_scene_file` accepts (a
    scene suffix, not an EFEM result `*.efem.npz`, not hidden), sorted by path (by name within a folder). Files
    given explicitly are kept (in the order given) when they have a scene suffix and are not results (a hidden
    file named explicitly is kept). `~` is expanded. Duplicates (the same file after resolving symlinks) are
    removed; the paths are returned as found, not resolved.

    Args:
        paths: one path or several: files and/or directories.
        recursive: also list the sub-folders of the given directories.

    Returns:
        Scene file paths.

    Raises:
        ScenePathNotFoundError: a path does not exist (a `SceneError` and a `FileNotFoundError`).
        SceneError: a file given explicitly is an EFEM result or has no scene suffix.
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out: list[Path] = []
    seen: set[Path] = set()
    for item in items:
        p = Path(item).expanduser()
        if p.is_dir():
            it = p.rglob("*") if recursive else p.iterdir()
            found = sorted(c for c in it if c.is_file() and is_scene_file(c))
        elif p.is_file():
            if not _has_scene_suffix(p):
                if p.name.lower().endswith(RESULT_SUFFIX):
                    raise SceneError(f"{p} is an EFEM result file, not a scene")
                raise SceneError(
                    f"{p}: unknown scene format {p.suffix!r}; expected one of {', '.join(SCENE_SUFFIXES)}"
                )
            found = [p]
        else:
            raise ScenePathNotFoundError(f"{p}: no such file or directory")
        for f in found:
            key = f.resolve()
            if key not in seen:
                seen.add(key)
                out.append(f)
    return out


# ---------------------------------------------------------------------------------------------- load
def load_scene(
    path: str | os.PathLike[str],
    *,
    max_points: int = DEFAULT_MAX_POINTS,
    name: str | None = None,
) -> Scene:
    """Load a scene (mesh or point cloud) from .ply, .obj, .off, .glb or .npz.

    Missing normals are estimated on first use of `Scene.normals` (area-weighted face normals for meshes, PCA
    normals oriented consistently for point clouds; `Scene.normals_pending` tells), so a caller that never
    reads them (`efem-viz info`) never pays for them; missing colours become grey.

    Hostile or corrupt files fail with one `SceneError` in time and memory bounded by the file's real size:
    every count a header declares (PLY elements, OFF counts, GLB accessors, NPZ array headers) is checked
    against the bytes the file holds, `max_points` and `MAX_FACES_PER_POINT` before anything is allocated for
    it, and an ASCII PLY or OFF with data rows beyond its header's counts is refused.

    Args:
        path: the scene file.
        max_points: refuse files with more points than this.
        name: scene name; default: the file name without its suffix.

    Returns:
        The validated `Scene` (world frame, metres, +Z up).

    Raises:
        SceneError: missing file, a directory, unknown suffix, corrupt or truncated file, a header count the
            file cannot hold, rows beyond the header's counts, empty scene, NaN/Inf, mismatched array lengths,
            non-integer labels, more than `max_points` points or `MAX_FACES_PER_POINT * max_points` faces. The
            message names the path.
    """
    p = Path(path)
    if not p.exists():
        raise SceneError(f"{p}: no such file")
    if p.is_dir():
        raise SceneError(f"{p} is a directory, not a scene file (use find_scenes to list a folder)")
    if p.name.lower().endswith(RESULT_SUFFIX):
        raise SceneError(f"{p} is an EFEM result file (load it with EMResult.load), not a scene")
    suffix = p.suffix.lower()
    if suffix not in SCENE_SUFFIXES:
        raise SceneError(f"{p}: unknown scene format {suffix!r}; expected one of {', '.join(SCENE_SUFFIXES)}")
    if p.stat().st_size == 0:
        raise SceneError(f"{p}: file is empty (0 bytes)")
    scene_name = name if name is not None else p.name[: -len(p.suffix)]
    loaders = {".ply": _load_ply, ".obj": _load_obj, ".off": _load_off, ".glb": _load_glb, ".npz": _load_npz}
    try:
        kwargs = loaders[suffix](p, max_points)
    except SceneError as exc:
        msg = str(exc)
        raise SceneError(msg if str(p) in msg else f"{p}: {msg}") from exc
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # parser errors of plyfile / trimesh / numpy: corrupt or truncated file
        raise SceneError(f"{p}: could not read {suffix[1:].upper()} file ({type(exc).__name__}: {exc})") from exc
    kwargs.pop("name", None)  # the file name wins over a name stored inside the file
    try:
        return Scene.create(scene_name, max_points=max_points, **kwargs)
    except SceneError as exc:
        raise SceneError(f"{p}: {exc}") from exc


def scene_from_npz(data: Any, *, name: str | None = None, max_points: int = DEFAULT_MAX_POINTS) -> Scene:
    """Build a Scene from the arrays of a native scene `.npz` (as written by `Scene.to_npz_dict`).

    Args:
        data: a mapping of arrays (an open `np.load` result or a dict).
        name: override the stored name.
        max_points: refuse scenes with more points than this.

    Raises:
        SceneError: wrong or missing schema version, missing arrays.
    """
    kwargs = _npz_kwargs(data)
    stored = kwargs.pop("name", None)
    return Scene.create(name or stored or "scene", max_points=max_points, **kwargs)


def _npz_kwargs(data: Any) -> dict[str, Any]:
    keys = set(data.keys())
    if "schema_version" not in keys:
        raise SceneError("not a native scene .npz: no 'schema_version' array (expected keys points, normals, ...)")
    version = int(np.asarray(data["schema_version"]))
    if version != SCENE_SCHEMA_VERSION:
        raise SceneError(
            f"scene schema_version {version} is not supported (this efem-viz reads version {SCENE_SCHEMA_VERSION})"
        )
    if "points" not in keys:
        raise SceneError("scene .npz has no 'points' array")
    out: dict[str, Any] = {"points": data["points"]}
    for key in ("normals", "colors", "faces", "instance"):
        if key in keys:
            out[key] = data[key]
    if "name" in keys:
        out["name"] = str(np.asarray(data["name"]))
    if "categories_json" in keys:
        out["categories"] = _parse_categories(str(np.asarray(data["categories_json"])))
    if "provenance_json" in keys:
        out["provenance"] = json.loads(str(np.asarray(data["provenance_json"])))
    return out


def _load_npz(p: Path, max_points: int) -> dict[str, Any]:
    check_npz_headers(p, max_points)
    with np.load(p, allow_pickle=False) as data:
        keys = set(data.files)
        rgbd_frame = "schema_version" not in keys and "K" in keys and bool({"depth_mm", "depth"} & keys)
        if not rgbd_frame:
            kwargs = _npz_kwargs(data)
            # materialise the arrays before the file closes
            return {k: (np.array(v) if isinstance(v, np.ndarray) else v) for k, v in kwargs.items()}
    # an RGB-D frame (rgb, depth_mm or depth, K): import it with the default settings
    from efem_viz.data.rgbd import import_rgbd_file

    scene = import_rgbd_file(p)
    return {"points": scene.points, "normals": scene.normals, "colors": scene.colors,
            "provenance": dict(scene.provenance)}


def _parse_categories(text: str) -> dict[int, str]:
    raw = json.loads(text)
    if not isinstance(raw, dict):
        raise SceneError(f"categories must be a JSON object {{id: name}}, got {type(raw).__name__}")
    try:
        return {int(k): str(v) for k, v in raw.items()}
    except ValueError as exc:
        raise SceneError(f"category ids must be integers: {exc}") from exc


_PLY_HEADER_LIMIT = 4 << 20
"""Bytes searched for a PLY `end_header` line: a longer header is refused rather than parsed without checks."""
_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
_FACE_LISTS = ("vertex_indices", "vertex_index")
_ASCII_SPACE = b" \t\n\r\x0b\x0c"


class _PlyElementHead(NamedTuple):
    """One `element` of a PLY header, as far as bounds checks need it."""

    name: str
    count: int
    scalar_sizes: tuple[int, ...]
    """Byte size of each scalar property."""
    lists: tuple[tuple[str, int, int], ...]
    """(name, length-type size, value-type size) of each list property."""

    def min_bytes(self) -> int:
        """Fewest bytes one binary row can take."""
        return sum(self.scalar_sizes) + sum(ls + self._min_len(name) * vs for name, ls, vs in self.lists)

    def _min_len(self, list_name: str) -> int:
        return 3 if self.name == "face" and list_name in _FACE_LISTS else 0


class _PlyHead(NamedTuple):
    """A PLY header: format, elements in file order, and where the body starts."""

    ascii: bool
    elements: tuple[_PlyElementHead, ...]
    body_offset: int
    header_lines: int


def _read_ply_head(p: Path) -> _PlyHead | None:
    """Parse a PLY header for the bounds checks, reading at most `_PLY_HEADER_LIMIT` bytes.

    Returns None for what the readers report themselves (not a PLY file, an unknown format, type or keyword):
    plyfile then gives its own message.

    Raises:
        SceneError: no `end_header` within `_PLY_HEADER_LIMIT` bytes, or a negative element count.
    """
    with open(p, "rb") as fh:
        head = fh.read(_PLY_HEADER_LIMIT)
    if not head.startswith(b"ply"):
        return None
    # the header's line ending is the one after "ply" (LF, CR or CRLF), as plyfile reads it
    nl = b"\r\n" if head[3:5] == b"\r\n" else head[3:4]
    if nl not in (b"\n", b"\r", b"\r\n"):
        return None
    fmt: str | None = None
    elements: list[list[Any]] = []
    pos = 0
    n_lines = 0
    while True:
        end = head.find(nl, pos)
        if end < 0:
            if len(head) >= _PLY_HEADER_LIMIT:
                raise SceneError(
                    f"{p}: PLY header has no 'end_header' line in its first {_PLY_HEADER_LIMIT >> 20} MiB "
                    "(corrupt file, or not a PLY file)"
                )
            return None  # plyfile reports the missing end_header
        line = head[pos:end].strip()
        pos = end + len(nl)
        n_lines += 1
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == b"end_header":
            break
        if key == b"format" and len(words) >= 2:
            fmt = words[1].decode("ascii", "replace")
        elif key == b"element":
            if len(words) != 3:
                return None
            try:
                count = int(words[2])
            except ValueError:
                return None
            name = words[1].decode("ascii", "replace")
            if count < 0:
                raise SceneError(f"{p}: PLY header gives element {name!r} a negative count ({count})")
            elements.append([name, count, [], []])
        elif key == b"property":
            if not elements:
                return None
            types = [w.decode("ascii", "replace") for w in words[1:]]
            if len(types) == 4 and types[0] == "list" and types[1] in _PLY_SIZES and types[2] in _PLY_SIZES:
                elements[-1][3].append((types[3], _PLY_SIZES[types[1]], _PLY_SIZES[types[2]]))
            elif len(types) == 2 and types[0] in _PLY_SIZES:
                elements[-1][2].append(_PLY_SIZES[types[0]])
            else:
                return None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        return None
    elts = tuple(_PlyElementHead(n, c, tuple(sc), tuple(ls)) for n, c, sc, ls in elements)
    return _PlyHead(fmt == "ascii", elts, pos, n_lines)


def _check_ply_counts(p: Path, head: _PlyHead, max_points: int) -> None:
    """Refuse a PLY header whose element counts the file cannot hold, before any reader allocates for them.

    Vertex and face counts are checked against `max_points` (and `MAX_FACES_PER_POINT`); every element's
    count against the body: a binary row takes at least its scalars' bytes plus each list's length (and 3
    vertex indices for a face); an ASCII row takes at least one line. Time: a header parse, plus one chunked
    newline count of an ASCII body; memory: one 4 MiB chunk.

    Raises:
        SceneError: the first element that does not fit, named, with the numbers.
    """
    counts = {e.name: e.count for e in head.elements}
    n_vertex = counts.get("vertex", 0)
    if n_vertex > max_points:
        raise SceneError(
            f"{p} has {n_vertex:,} points, more than the limit of {max_points:,}; {TOO_MANY_POINTS_HINT}"
        )
    max_faces = MAX_FACES_PER_POINT * max(max_points, 1)
    if counts.get("face", 0) > max_faces:
        raise SceneError(
            f"{p}: PLY header declares {counts['face']:,} faces, more than the limit of {max_faces:,} "
            f"({MAX_FACES_PER_POINT} per allowed point; corrupt header, or {LIMIT_FLAG_HINT})"
        )
    size = p.stat().st_size
    body = max(size - head.body_offset, 0)
    if head.ascii:
        n_lines = _count_lines(p, head.body_offset)
        row0 = 0
        for e in head.elements:
            if row0 + e.count > n_lines:
                raise SceneError(
                    f"{p}: ASCII PLY file is truncated: element {e.name!r} has {e.count:,} rows in the header "
                    f"but the file ends after {max(n_lines - row0, 0):,} of them "
                    "(was it cut short while copying or writing?)"
                )
            row0 += e.count
        return
    need = 0
    for e in head.elements:
        need += e.count * e.min_bytes()
        if need > body:
            per_row = e.min_bytes()
            raise SceneError(
                f"{p}: binary PLY file is truncated or its header is wrong: element {e.name!r} has {e.count:,} "
                f"rows in the header ({per_row} bytes each at least), but the file holds {body:,} bytes after the "
                f"header, not the {need:,} the elements up to {e.name!r} need"
            )


def _iter_body_lines(p: Path, offset: int, chunk: int = 4 << 20) -> Iterator[bytes]:
    """The bytes after `offset` in chunks, CR and CRLF turned into LF (a CR that ends a chunk waits for the next)."""
    with open(p, "rb") as fh:
        fh.seek(offset)
        carry = b""
        while True:
            block = fh.read(chunk)
            if not block:
                if carry:
                    yield b"\n"
                return
            block = carry + block
            carry = b""
            if block.endswith(b"\r"):
                block, carry = block[:-1], b"\r"
            if b"\r" in block:
                block = block.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
            yield block


def _count_lines(p: Path, offset: int) -> int:
    """Lines after `offset` as plyfile's text reader sees them (LF, CR or CRLF; a last line without newline)."""
    n, last = 0, b"\n"
    for block in _iter_body_lines(p, offset):
        n += block.count(b"\n")
        last = block[-1:]
    return n + (0 if last == b"\n" else 1)


def _check_ply_no_extra_rows(p: Path, head: _PlyHead) -> None:
    """Refuse an ASCII PLY body with data after the rows its header declares (blank lines and spaces are fine).

    Raises:
        SceneError: names the first extra line (its number in the file and its text) and the header's counts.
    """
    rows = sum(e.count for e in head.elements)
    seen = 0  # body lines ended before the current block
    for block in _iter_body_lines(p, head.body_offset):
        start = 0
        n = block.count(b"\n")
        if seen < rows:
            if seen + n < rows:
                seen += n
                continue
            ends = np.flatnonzero(np.frombuffer(block, np.uint8) == 10)
            start = int(ends[rows - seen - 1]) + 1
            n -= rows - seen
            seen = rows
        rest = block[start:]
        if not rest.translate(None, _ASCII_SPACE):
            seen += n
            continue
        lines = rest.split(b"\n")
        k = next(i for i, ln in enumerate(lines) if ln.strip(_ASCII_SPACE))
        counts = ", ".join(f"{e.name} {e.count:,}" for e in head.elements)
        text = lines[k].strip(_ASCII_SPACE)[:60].decode("ascii", "replace")
        line_no = head.header_lines + seen + k + 1
        raise SceneError(
            f"{p}: ASCII PLY file has more rows than its header declares ({counts}): line {line_no:,} after "
            f"them holds {text!r}; fix the element counts in the header or remove the extra rows"
        )


def _load_ply(p: Path, max_points: int) -> dict[str, Any]:
    import plyfile

    head = _read_ply_head(p)
    if head is not None:
        _check_ply_counts(p, head, max_points)
    ply, tri_faces = _read_ply_fast(p)
    polys: tuple[np.ndarray, np.ndarray] | None = None
    if ply is None:
        ply, polys = _read_ply_ascii(p)
    if ply is None:
        ply = plyfile.PlyData.read(str(p))
    if head is not None and head.ascii:  # after the rows parsed: a bad row is the better message
        _check_ply_no_extra_rows(p, head)
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise SceneError(f"{p}: PLY file has no 'vertex' element (elements: {names})")
    v = ply["vertex"].data
    props = set(v.dtype.names or ())
    missing = {"x", "y", "z"} - props
    if missing:
        raise SceneError(f"{p}: PLY vertex element lacks {sorted(missing)} (has {sorted(props)})")
    out: dict[str, Any] = {"points": np.stack([v["x"], v["y"], v["z"]], axis=1)}
    if {"nx", "ny", "nz"} <= props:
        nrm = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float32)
        if np.all(np.abs(nrm).sum(axis=1) > 0):  # all-zero normals = "not set" in many exporters
            out["normals"] = nrm
    for rgb in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if set(rgb) <= props:
            col = np.stack([v[c] for c in rgb], axis=1)
            if col.dtype == np.uint16:  # 16-bit colour channels
                col = np.round(col / 257.0).astype(np.uint8)
            out["colors"] = col
            break
    if "instance" in props:
        out["instance"] = np.asarray(v["instance"])
    if "face" in names:
        fdata = ply["face"].data
        fprops = fdata.dtype.names or ()
        key = "vertex_indices" if "vertex_indices" in fprops else ("vertex_index" if "vertex_index" in fprops else None)
        if key is None:
            raise SceneError(f"{p}: PLY face element lacks a 'vertex_indices' list (has {list(fprops)})")
        if tri_faces is not None:
            out["faces"] = tri_faces
        elif polys is not None:
            out["faces"] = _triangulate_flat(*polys, p)
        else:
            out["faces"] = _triangulate([np.asarray(f) for f in fdata[key]], p)
    comments = list(ply.comments) + list(getattr(ply, "obj_info", []))
    for c in comments:
        c = c.strip()
        if c.startswith(_CATEGORIES_COMMENT + " "):
            out["categories"] = _parse_categories(c[len(_CATEGORIES_COMMENT) + 1 :])
        elif c.startswith(_PROVENANCE_COMMENT + " "):
            out["provenance"] = json.loads(c[len(_PROVENANCE_COMMENT) + 1 :])
    return out


def _read_ply_fast(p: Path) -> tuple[Any, np.ndarray | None]:
    """Binary triangle-mesh PLY via plyfile's fixed-length list path (None, None when it does not apply).

    plyfile parses list properties row by row (~17 s for 2M faces) unless told their length (`known_list_len`,
    ~0.03 s). It raises on a polygon that is not a triangle; then the caller falls back to the general reader.
    """
    import plyfile

    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    end = head.find(b"end_header")
    header = head[:end] if end > 0 else b""
    if not header.startswith(b"ply") or b"format binary" not in header or b"element face" not in header:
        return None, None
    key = "vertex_indices" if b"vertex_indices" in header else ("vertex_index" if b"vertex_index" in header else None)
    if key is None:
        return None, None
    try:
        ply = plyfile.PlyData.read(str(p), known_list_len={"face": {key: 3}})
        fdata = ply["face"].data[key]
        if fdata.dtype == object:
            return None, None
        faces = np.array(fdata, dtype=np.int64).reshape(-1, 3)
        # copy the vertex table out of the memory map so the file can be replaced while the scene lives
        ply["vertex"].data = np.array(ply["vertex"].data)
    except Exception:  # non-triangle faces or odd layouts: the general reader handles (or reports) them
        return None, None
    return ply, faces


_PLY_ASCII_BYTES = b"\t\n" + bytes(range(0x20, 0x7F))
"""Bytes of an ASCII PLY body that `_read_ply_ascii` parses itself: printable ASCII, tab and newline. A body
with any other byte (other whitespace such as \\v or \\x1c, control characters, non-ASCII) is left to plyfile,
whose decoding and `str.split` rules then decide, so that the two readers never disagree about such a file."""

_PLY_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                   "f4": "float", "f8": "double"}


def _read_ply_ascii(p: Path) -> tuple[Any, tuple[np.ndarray, np.ndarray] | None]:
    """ASCII PLY read with one `np.loadtxt` per element instead of plyfile's row-by-row parser (~10x faster).

    plyfile reads an ASCII body one row at a time and builds a numpy scalar per value (2-6 s for 200k
    points). This reader parses each element's block of rows with `np.loadtxt` into the same field types,
    following plyfile's rules: plyfile itself parses the header; each element takes the next `count` lines
    (LF, CR or CRLF); a row holds exactly its properties' values; a list property is a length followed by
    that many values. `np.loadtxt` accepts a subset of the tokens plyfile accepts (plyfile also takes `1_0`,
    or `-0` for an unsigned type) and reads them to the same values, float32 included. An element with one
    list property whose rows differ in length (a mesh mixing triangles and quads) is read grouping rows by
    length.

    What this reader does not settle returns (None, None); plyfile then reads the file and accepts or rejects
    it exactly as before: a header plyfile rejects, a body with a byte outside `_PLY_ASCII_BYTES`, an element
    without properties, several list properties whose lengths vary, or a block numpy refuses although no row
    breaks plyfile's rules.

    Args:
        p: the PLY file.

    Returns:
        (ply, polys): `ply` is a `PlyData` whose elements hold their rows in plyfile's dtype (list properties
        are object fields left as None: building one array per row is the slow part); `polys` is the face
        element's `vertex_indices` (or `vertex_index`) list flattened, (lens (F,) int64, indices (sum(lens),)
        of the list's value type), or None without such a list. (None, None) for a binary file or where this
        reader does not apply.

    Raises:
        SceneError: a body that plyfile rejects as well: truncated, a blank row, a row with too few or too
            many values, or a value that is not a number of its property's type. The message names element,
            row and line.
    """
    import plyfile

    parse_header = getattr(plyfile.PlyData, "_parse_header", None)  # private: if gone, plyfile reads the file
    if parse_header is None:
        return None, None
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or not re.search(rb"format\s+ascii", head[: max(end, 0)]):
            return None, None
        fh.seek(0)
        try:
            ply = parse_header(fh)
        except Exception:  # plyfile reports a bad header in its own words
            return None, None
        if not ply.text:
            return None, None
        n_head = fh.tell()
        body = fh.read()
    head_lines = len(head[:n_head].splitlines()) if n_head <= len(head) else None
    if b"\r" in body:  # plyfile reads the body with universal newlines
        body = body.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if body.translate(None, _PLY_ASCII_BYTES):
        return None, None
    text = body.decode("ascii")
    newlines = np.flatnonzero(np.frombuffer(body, np.uint8) == 10)
    n_lines = len(newlines) + (1 if body and not body.endswith(b"\n") else 0)
    line_start = np.concatenate([[0], newlines + 1])  # body line i is text[line_start[i] : line_end[i]]
    line_end = np.concatenate([newlines, [len(body)]])

    polys: tuple[np.ndarray, np.ndarray] | None = None
    row0 = 0  # body line of the current element's first row
    for elt in ply.elements:
        count, props = elt.count, elt.properties
        if count < 0 or (count and not props):
            return None, None
        if row0 + count > n_lines:
            raise SceneError(
                f"{p}: ASCII PLY file is truncated: element {elt.name!r} has {count:,} rows in the header "
                f"but the file ends after {max(n_lines - row0, 0):,} of them "
                "(was it cut short while copying or writing?)"
            )
        block = text[line_start[row0] : line_end[row0 + count - 1]] if count else ""
        parsed = _parse_ascii_block(props, block, count)
        if parsed is None:
            bad = _ascii_first_bad_row(props, block)
            if bad is None:  # numpy refused what plyfile accepts (e.g. `1_000`): plyfile reads the file
                return None, None
            k, why = bad
            where = f", line {head_lines + row0 + k + 1:,} of the file" if head_lines is not None else ""
            if row0 + k + 1 == n_lines and not body.endswith(b"\n"):
                why += " (the file ends in this row without a newline: was it cut short?)"
            raise SceneError(f"{p}: ASCII PLY element {elt.name!r}, row {k + 1:,} of {count:,}{where}: {why}")
        data, lists = parsed
        elt.data = data
        names = [q.name for q in props]
        key = next((k for k in ("vertex_indices", "vertex_index") if k in names), None)  # as _load_ply picks
        if elt.name == "face" and key is not None:
            if key not in lists:  # a scalar `vertex_indices`: the general reader reports it
                return None, None
            polys = lists[key]
        row0 += count
    return ply, polys


def _parse_ascii_block(
    props: tuple[Any, ...], block: str, count: int
) -> tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]] | None:
    """The rows of one ASCII PLY element, or None where numpy refuses them (`_ascii_first_bad_row` says why).

    Args:
        props: the element's plyfile properties.
        block: the element's `count` lines, joined by newlines (no final newline).
        count: number of rows.

    Returns:
        (data, lists): `data` is a (count,) structured array in plyfile's dtype for the element (list
        properties are object fields left as None); `lists` maps each list property to (lens (count,) int64,
        values flattened).
    """
    import plyfile

    dtype = np.dtype([(q.name, q.dtype()) for q in props])
    list_props = [q for q in props if isinstance(q, plyfile.PlyListProperty)]
    if count == 0:
        empty = {q.name: (np.zeros(0, np.int64), np.zeros(0, q.val_dtype)) for q in list_props}
        return np.empty(0, dtype), empty
    if re.search(r"\S", block) is None:  # only blank rows (np.loadtxt would warn "no data")
        return None
    if not list_props:
        arr = _loadtxt(block, dtype)
        return (arr, {}) if arr is not None and len(arr) == count else None  # fewer rows: blank lines skipped
    # every row laid out like the first (all triangles, say): one np.loadtxt
    lengths = _ascii_list_lengths(props, block.split("\n", 1)[0].split())
    if lengths is not None:
        arr = _loadtxt(block, _ascii_row_dtype(props, lengths))
        if (
            arr is not None
            and len(arr) == count
            and all(bool((arr[q.name + "\nlen"] == n).all()) for q, n in zip(list_props, lengths))
        ):
            data = np.empty(count, dtype)
            for q in props:
                if q not in list_props:
                    data[q.name] = arr[q.name]
            lists = {q.name: (np.full(count, n, np.int64), arr[q.name].reshape(-1))
                     for q, n in zip(list_props, lengths)}
            return data, lists
    if len(list_props) != 1:
        return None
    return _parse_ascii_ragged(props, list_props[0], block, count, dtype)


def _parse_ascii_ragged(
    props: tuple[Any, ...], lp: Any, block: str, count: int, dtype: np.dtype
) -> tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]] | None:
    """Rows of an element whose one list property `lp` varies in length (triangles and quads): one np.loadtxt
    per row length. Arguments and result as `_parse_ascii_block`."""
    raw = np.frombuffer(block.encode("ascii"), np.uint8)
    is_tok = raw > 32  # the body holds only printable ASCII, tab and newline
    tok_starts = np.flatnonzero(is_tok & ~np.concatenate([[False], is_tok[:-1]]))
    rows = np.searchsorted(np.flatnonzero(raw == 10), tok_starts)  # newlines before a value = its row
    lens = np.bincount(rows, minlength=count) - len(props)  # the row's values less the scalars and the length
    if len(lens) != count or (lens < 0).any():
        return None
    lines = block.split("\n")
    data = np.empty(count, dtype)
    first = np.cumsum(lens) - lens
    values = np.empty(int(lens.sum()), lp.val_dtype)
    for n in np.unique(lens).tolist():
        idx = np.flatnonzero(lens == n)
        arr = _loadtxt([lines[i] for i in idx.tolist()], _ascii_row_dtype(props, [n]))
        if arr is None or len(arr) != len(idx) or not (arr[lp.name + "\nlen"] == n).all():
            return None
        for q in props:
            if q is not lp:
                data[q.name][idx] = arr[q.name]
        if n:
            values[first[idx][:, None] + np.arange(n)] = arr[lp.name]
    return data, {lp.name: (lens.astype(np.int64), values)}


def _ascii_list_lengths(props: tuple[Any, ...], tokens: list[str]) -> list[int] | None:
    """Lengths of a row's list properties, read from its length values (None if the row does not lay out)."""
    import plyfile

    lengths, pos = [], 0
    for q in props:
        if isinstance(q, plyfile.PlyListProperty):
            try:
                n = int(tokens[pos])
            except (IndexError, ValueError):
                return None
            if n < 0:
                return None
            lengths.append(n)
            pos += 1 + n
        else:
            pos += 1
    return lengths if pos == len(tokens) else None


def _ascii_row_dtype(props: tuple[Any, ...], lengths: list[int]) -> np.dtype:
    """Structured dtype of one ASCII row: scalars in their type, a list as `name\\nlen` then `name` (n,)."""
    import plyfile

    fields: list[tuple[Any, ...]] = []
    it = iter(lengths)
    for q in props:
        if isinstance(q, plyfile.PlyListProperty):
            len_t, val_t = q.list_dtype()
            fields += [(q.name + "\nlen", len_t), (q.name, val_t, (next(it),))]
        else:
            fields.append((q.name, q.dtype()))
    return np.dtype(fields)


def _loadtxt(src: str | list[str], dtype: np.dtype) -> np.ndarray | None:
    """Whitespace-separated rows into a (N,) structured array; None where numpy refuses them."""
    try:
        return np.loadtxt(io.StringIO(src) if isinstance(src, str) else src, dtype=dtype, comments=None,
                          delimiter=None, quotechar=None, ndmin=1)
    except MemoryError:
        raise
    except Exception:  # a value numpy cannot parse, a row with another number of values
        return None


def _ascii_first_bad_row(props: tuple[Any, ...], block: str) -> tuple[int, str] | None:
    """The first row plyfile would reject, as (row index, reason), or None when plyfile accepts every row.

    A quick Python check passes most rows; a row it flags is judged by `_ascii_row_problem` (plyfile's rules).
    """
    import plyfile

    def quick(t: str) -> Callable[[str], Any]:
        if t[0] == "f":
            return float
        lo, hi = int(np.iinfo(t).min), int(np.iinfo(t).max)

        def in_range(tok: str) -> None:
            if not lo <= int(tok) <= hi:
                raise ValueError(tok)

        return in_range

    kinds = [
        (True, quick(q.list_dtype()[0][1:]), quick(q.val_dtype)) if isinstance(q, plyfile.PlyListProperty)
        else (False, quick(q.val_dtype), float)
        for q in props
    ]
    for k, line in enumerate(block.split("\n")):
        tokens = line.split()
        try:
            pos = 0
            for is_list, conv, val_conv in kinds:
                if is_list:
                    conv(tokens[pos])
                    n = int(tokens[pos])
                    vals = tokens[pos + 1 : pos + 1 + n]
                    if len(vals) < n:
                        raise ValueError
                    for t in vals:
                        val_conv(t)
                    pos += 1 + n
                else:
                    conv(tokens[pos])
                    pos += 1
            if pos == len(tokens):
                continue
        except (IndexError, ValueError, OverflowError):
            pass
        why = _ascii_row_problem(props, tokens)
        if why is not None:
            return k, why
    return None


def _ply_type_text(t: str) -> str:
    """'a uchar (an integer 0..255)' for the numpy type code 'u1'."""
    name = _PLY_TYPE_NAMES[t]
    if t[0] == "f":
        return f"a {name} (a number)"
    info = np.iinfo(t)
    return f"{'an' if name == 'int' else 'a'} {name} (an integer {info.min}..{info.max})"


def _ascii_row_problem(props: tuple[Any, ...], tokens: list[str]) -> str | None:
    """Why plyfile rejects this row of values (None: it accepts it), following `PlyElement._read_txt`."""
    import plyfile

    names = " ".join(q.name for q in props)
    n_tok = len(tokens)
    it = iter(tokens)
    for q in props:
        tok = next(it, None)
        if tok is None:
            what = "an empty row" if n_tok == 0 else f"only {n_tok} value{'s' if n_tok != 1 else ''}"
            return f"{what}, property {q.name!r} is missing (the properties are: {names})"
        if isinstance(q, plyfile.PlyListProperty):
            len_t, val_t = q.list_dtype()
            try:
                n = int(np.dtype(len_t).type(tok))
            except (ValueError, OverflowError):
                return f"list length {tok!r} of property {q.name!r} is not {_ply_type_text(len_t[1:])}"
            if n < 0:
                return f"list length {n} of property {q.name!r} is negative"
            vals = list(islice(it, n))
            if len(vals) < n:
                return f"property {q.name!r} has length {n} but the row has only {len(vals)} values after it"
            # plyfile reads list values with np.loadtxt, where `#` opens a comment: `#5` is no value
            for t in vals:
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # "input contained no data"
                        if len(np.loadtxt([t], val_t, ndmin=1)) == 1:
                            continue
                except (ValueError, OverflowError):
                    pass
                return f"{t!r} in list {q.name!r} is not {_ply_type_text(val_t[1:])}"
        else:
            try:
                np.dtype(q.dtype()).type(tok)
            except (ValueError, OverflowError):
                return f"{tok!r} for property {q.name!r} is not {_ply_type_text(q.val_dtype)}"
    extra = sum(1 for _ in it)
    if extra:
        return (f"{n_tok} values, {extra} more than the properties take ({names}); "
                "is a property missing from the header?")
    return None


def _triangulate(polys: list[np.ndarray], p: Path) -> np.ndarray | None:
    """Fan-triangulate polygon faces into (M, 3) int64 (None for no faces); see `_triangulate_flat`."""
    if not polys:
        return None
    lens = np.fromiter((len(f) for f in polys), dtype=np.int64, count=len(polys))
    return _triangulate_flat(lens, np.concatenate(polys), p)


def _triangulate_flat(lens: np.ndarray, flat: np.ndarray, p: Path) -> np.ndarray | None:
    """Fan-triangulate flattened polygons: polygon i is `flat[o_i : o_i + lens[i]]` with o_i = sum(lens[:i]).

    Polygon (v0, v1, ..., vn-1) becomes the triangles (v0, v1, v2), (v0, v2, v3), ..., in polygon order.

    Args:
        lens: (F,) int, vertices per polygon.
        flat: (sum(lens),) int (or the PLY list's value type), vertex indices of all polygons in order.
        p: the file, for the error message.

    Returns:
        (M, 3) int64 triangles, or None when there are no polygons.

    Raises:
        SceneError: a polygon has fewer than 3 vertices.
    """
    if len(lens) == 0:
        return None
    if (lens == 3).all():
        return flat.reshape(-1, 3).astype(np.int64)
    if (lens < 3).any():
        raise SceneError(f"{p}: {(lens < 3).sum()} faces have fewer than 3 vertices")
    n_tri = lens - 2
    first = np.repeat(np.cumsum(lens) - lens, n_tri)  # index in `flat` of each triangle's polygon's v0
    k = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)  # triangle's rank in polygon
    return np.stack([flat[first], flat[first + 1 + k], flat[first + 2 + k]], axis=1).astype(np.int64)


def _from_trimesh(geom: Any, p: Path) -> dict[str, Any]:
    """Arrays from a trimesh Trimesh or PointCloud."""
    import trimesh

    out: dict[str, Any] = {}
    if isinstance(geom, trimesh.PointCloud):
        out["points"] = np.asarray(geom.vertices)
        cols = getattr(geom, "colors", None)
        if cols is not None and len(cols) == len(geom.vertices):
            out["colors"] = np.asarray(cols)[:, :3]
        return out
    if not isinstance(geom, trimesh.Trimesh):
        raise SceneError(f"{p}: contains no mesh or point cloud (got {type(geom).__name__})")
    out["points"] = np.asarray(geom.vertices)
    faces = np.asarray(geom.faces)
    out["faces"] = faces if faces.size else None
    if "vertex_normals" in geom._cache:  # stored in the file; otherwise the Scene derives them on first use
        nrm = np.asarray(geom.vertex_normals)
        if len(nrm) == len(geom.vertices) and np.isfinite(nrm).all():
            out["normals"] = nrm
    # duck-typed on `kind`: ColorVisuals ("vertex"/"face") or TextureVisuals ("texture")
    visual: Any = geom.visual
    if getattr(visual, "kind", None) == "vertex":
        out["colors"] = np.asarray(visual.vertex_colors)[:, :3]
    elif getattr(visual, "kind", None) == "face":
        # ColorVisuals with per-face colours: trimesh averages them onto the vertices (to_color() is for textures)
        out["colors"] = np.asarray(visual.vertex_colors)[:, :3]
    elif getattr(visual, "kind", None) == "texture":
        try:
            out["colors"] = np.asarray(visual.to_color().vertex_colors)[:, :3]
        except Exception as exc:  # texture without UVs etc.: keep default grey
            log.warning("%s: could not convert the material/texture to vertex colours (%s)", p, exc)
    return out


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


def _load_obj(p: Path, max_points: int) -> dict[str, Any]:
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
    out = _from_trimesh(geom, p)
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


def _load_off(p: Path, max_points: int) -> dict[str, Any]:
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
    out["faces"] = _triangulate(polys, p) if polys else None
    return out


_GLTF_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLTF_ITEMSIZE = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}


def _check_glb(p: Path, max_points: int) -> None:
    """Check a GLB's chunk lengths and accessor counts against the file and `max_points` before trimesh reads it.

    trimesh allocates a zero array of an accessor's full `count` when the accessor has no buffer view, and
    builds meshes of the positions' counts; a corrupt header could ask for any size. What trimesh reports well
    itself (a wrong magic number, JSON it cannot parse) is left to it.

    Raises:
        SceneError: a chunk or buffer view that runs past the file, an accessor that runs past its buffer view
            (or, without one, is larger than any scene), more vertex positions than `max_points`.
    """
    import struct

    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return
        _, length, json_len, json_type = struct.unpack("<IIII", head[4:])
        if length > size:
            raise SceneError(f"{p}: GLB header says the file has {length:,} bytes, but it has {size:,} (truncated)")
        if json_type != 0x4E4F534A:  # "JSON"
            return
        if 20 + json_len > size:
            raise SceneError(f"{p}: GLB JSON chunk of {json_len:,} bytes runs past the end of the file ({size:,})")
        try:
            gltf = json.loads(fh.read(json_len))
        except (ValueError, UnicodeDecodeError):
            return
        bin_head = fh.read(8)  # the JSON chunk's length includes its padding
    if not isinstance(gltf, dict):
        return
    bin_len = struct.unpack("<I", bin_head[:4])[0] if len(bin_head) == 8 else 0
    if bin_len > max(size - 28 - json_len, 0):
        raise SceneError(f"{p}: GLB binary chunk of {bin_len:,} bytes runs past the end of the file ({size:,})")
    buffers = gltf.get("buffers", []) or []
    views = gltf.get("bufferViews", []) or []
    try:
        for i, view in enumerate(views):
            buf = buffers[int(view.get("buffer", 0))]
            buf_len = int(buf.get("byteLength", 0))
            if "uri" not in buf and buf_len > bin_len:
                raise SceneError(f"{p}: GLB buffer {view.get('buffer', 0)} claims {buf_len:,} bytes, but the "
                                 f"binary chunk holds {bin_len:,}")
            if int(view.get("byteOffset", 0)) + int(view["byteLength"]) > buf_len:
                raise SceneError(f"{p}: GLB bufferView {i} runs past the end of its buffer ({buf_len:,} bytes)")
        n_positions = 0
        position_ids = {
            int(prim["attributes"]["POSITION"])
            for mesh in gltf.get("meshes", []) or []
            for prim in mesh.get("primitives", []) or []
            if "POSITION" in (prim.get("attributes") or {})
        }
        for i, acc in enumerate(gltf.get("accessors", []) or []):
            count = int(acc["count"])
            comps = _GLTF_COMPONENTS[acc["type"]]
            itemsize = _GLTF_ITEMSIZE[int(acc["componentType"])]
            if count < 0:
                raise SceneError(f"{p}: GLB accessor {i} has a negative count ({count})")
            if i in position_ids:
                n_positions += count
            if "bufferView" in acc:
                view = views[int(acc["bufferView"])]
                elem = comps * itemsize
                stride = int(view.get("byteStride", elem)) or elem
                need = int(acc.get("byteOffset", 0)) + ((count - 1) * stride + elem if count else 0)
                if need > int(view["byteLength"]):
                    raise SceneError(
                        f"{p}: GLB accessor {i} claims {count:,} items ({need:,} bytes), more than its bufferView "
                        f"holds ({int(view['byteLength']):,} bytes): corrupt file"
                    )
            elif count * comps > 16 * max(max_points, 1):
                raise SceneError(
                    f"{p}: GLB accessor {i} has no data but claims {count:,} items, more than any scene this "
                    f"reader accepts (max_points {max_points:,})"
                )
    except SceneError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError):
        return  # a malformed glTF structure: trimesh reports it
    if n_positions > max_points:
        raise SceneError(
            f"{p} has {n_positions:,} vertex positions, more than the limit of {max_points:,}; "
            f"{TOO_MANY_POINTS_HINT}"
        )


def _load_glb(p: Path, max_points: int) -> dict[str, Any]:
    import trimesh

    _check_glb(p, max_points)
    loaded = trimesh.load(str(p), file_type="glb", process=False)
    extras: dict[str, Any] = {}
    if isinstance(loaded, trimesh.Scene):
        extras = dict(loaded.metadata.get(_GLB_EXTRAS_KEY, {}) or {})
        geoms = list(loaded.geometry.values())
        if not geoms:
            raise SceneError(f"{p}: GLB file has no geometry")
        if len(geoms) == 1 and len(loaded.graph.nodes_geometry) == 1:
            node = loaded.graph.nodes_geometry[0]
            T, gname = loaded.graph[node]
            src = loaded.geometry[gname]
            geom = src.copy()  # copy() drops trimesh's cached vertex normals: the file's NORMAL attribute
            geom.apply_transform(T)
            if isinstance(src, trimesh.Trimesh) and "vertex_normals" in src._cache:
                nrm = np.asarray(src.vertex_normals, np.float64) @ np.linalg.inv(np.asarray(T)[:3, :3])
                geom.vertex_normals = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        else:
            geom = loaded.to_geometry()
    else:
        geom = loaded
    out = _from_trimesh(geom, p)
    # glTF is +Y up: (x, y, z)_gltf -> (x, -z, y)_world
    for key in ("points", "normals"):
        if key in out and out[key] is not None:
            arr = np.asarray(out[key], dtype=np.float64)
            out[key] = np.stack([arr[:, 0], -arr[:, 2], arr[:, 1]], axis=1)
    attrs = getattr(geom, "vertex_attributes", {}) or {}
    for key in ("_instance", "instance"):
        if key in attrs:
            out["instance"] = np.asarray(attrs[key]).reshape(-1)
            break
    n_pts = len(out.get("points", ()))  # packed arrays hold one row per point: inflate no more than that
    if "instance_zb64" in extras and "instance" not in out:
        out["instance"] = _unpack_array(extras["instance_zb64"], np.int32, max_items=n_pts)
    if "normals_zb64" in extras and "normals" not in out:  # world frame
        out["normals"] = _unpack_array(extras["normals_zb64"], np.float32, max_items=3 * n_pts).reshape(-1, 3)
    if "categories" in extras:
        out["categories"] = {int(k): str(v) for k, v in dict(extras["categories"]).items()}
    if "provenance" in extras:
        out["provenance"] = dict(extras["provenance"])
    return out


def _pack_array(a: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(np.ascontiguousarray(a).tobytes(), 6)).decode("ascii")


def _unpack_array(s: str, dtype: Any, *, max_items: int) -> np.ndarray:
    """Inverse of `_pack_array`, inflating at most `max_items` items (a zlib bomb stops there).

    Raises:
        SceneError: the data inflates to more than `max_items` items.
    """
    limit = max(int(max_items), 0) * np.dtype(dtype).itemsize
    z = zlib.decompressobj()
    raw = z.decompress(base64.b64decode(s), limit + 1)
    if len(raw) > limit or z.unconsumed_tail:
        raise SceneError(f"packed array inflates to more than {max_items:,} items of {np.dtype(dtype)}")
    return np.frombuffer(raw, dtype=dtype).copy()


# ---------------------------------------------------------------------------------------------- save
def save_scene(scene: Scene, path: str | os.PathLike[str], *, ascii: bool = False) -> Path:
    """Save a scene; the format comes from the suffix (.ply, .obj, .off, .glb, .npz). Atomic.

    Args:
        scene: the scene.
        path: destination file.
        ascii: for .ply, write ASCII instead of binary little-endian.

    Returns:
        The destination path.

    Raises:
        SceneError: unknown suffix.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if p.name.lower().endswith(RESULT_SUFFIX):
        raise SceneError(f"{p}: the suffix {RESULT_SUFFIX} is reserved for EFEM results; choose another name")
    writers: dict[str, Callable[[Path], None]] = {
        ".ply": lambda t: _write_ply(scene, t, ascii=ascii),
        ".obj": lambda t: _write_obj(scene, t),
        ".off": lambda t: _write_off(scene, t),
        ".glb": lambda t: _write_glb(scene, t),
        # cast: numpy's stub would take a **dict[str, ndarray] to possibly fill `allow_pickle: bool`
        ".npz": lambda t: np.savez_compressed(t, **cast("dict[str, Any]", scene.to_npz_dict())),
    }
    if suffix not in writers:
        raise SceneError(f"{p}: unknown scene format {suffix!r}; expected one of {', '.join(SCENE_SUFFIXES)}")
    if suffix in (".obj", ".off") and scene.has_gt:
        log.warning("%s: %s cannot hold instance labels; they are not saved (use .ply or .npz)", p, suffix)
    return atomic_write(p, writers[suffix])


def _write_ply(scene: Scene, tmp: Path, *, ascii: bool) -> None:
    import plyfile

    n = scene.num_points
    fields: list[tuple[str, str]] = [
        ("x", "f4"), ("y", "f4"), ("z", "f4"),
        ("nx", "f4"), ("ny", "f4"), ("nz", "f4"),
        ("red", "u1"), ("green", "u1"), ("blue", "u1"),
    ]
    if scene.instance is not None:
        fields.append(("instance", "i4"))
    v = np.empty(n, dtype=fields)
    v["x"], v["y"], v["z"] = scene.points.T
    v["nx"], v["ny"], v["nz"] = scene.normals.T
    v["red"], v["green"], v["blue"] = scene.colors.T
    if scene.instance is not None:
        v["instance"] = scene.instance
    elements = [plyfile.PlyElement.describe(v, "vertex")]
    if scene.faces is not None and len(scene.faces):
        f = np.empty(len(scene.faces), dtype=[("vertex_indices", "i4", (3,))])
        f["vertex_indices"] = scene.faces
        elements.append(plyfile.PlyElement.describe(f, "face", len_types={"vertex_indices": "u1"}))
    comments = ["written by efem-viz"]
    if scene.categories:
        comments.append(f"{_CATEGORIES_COMMENT} " + json.dumps({str(k): v for k, v in scene.categories.items()}))
    if scene.provenance:
        comments.append(f"{_PROVENANCE_COMMENT} " + json.dumps(scene.provenance, default=str))
    for c in comments:
        if "\n" in c or "\r" in c:
            raise SceneError("PLY comment lines cannot contain newlines (categories/provenance)")
    if not ascii:
        plyfile.PlyData(elements, text=False, byte_order="<", comments=comments).write(str(tmp))
        return
    # ASCII: plyfile formats row by row (~30 s for 200k points); one %-format per row is ~50x faster
    head = ["ply", "format ascii 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}"]
    ply_type = {"f4": "float", "u1": "uchar", "i4": "int"}
    head += [f"property {ply_type[t]} {name}" for name, t in fields]
    nf = len(scene.faces) if scene.faces is not None else 0
    if nf:
        head += [f"element face {nf}", "property list uchar int vertex_indices"]
    head.append("end_header")
    cols = [scene.points.astype(np.float64), scene.normals.astype(np.float64), scene.colors.astype(np.float64)]
    fmt = "%.9g %.9g %.9g %.7g %.7g %.7g %d %d %d"
    if scene.instance is not None:
        cols.append(scene.instance.astype(np.float64)[:, None])
        fmt += " %d"
    vals = np.concatenate(cols, axis=1)
    fmt += "\n"
    body = "".join(fmt % tuple(r) for r in vals.tolist())
    if nf:
        body += "".join(f"3 {a} {b} {c}\n" for a, b, c in scene.faces.tolist())  # type: ignore[union-attr]
    tmp.write_text("\n".join(head) + "\n" + body, encoding="ascii", errors="strict")


def _fmt_rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    row = prefix + " ".join([fmt] * a.shape[1]) + "\n"
    return "".join(row % tuple(r) for r in a.tolist())


def _write_obj(scene: Scene, tmp: Path) -> None:
    vc = np.concatenate([scene.points.astype(np.float64), scene.colors.astype(np.float64) / 255.0], axis=1)
    parts = [f"# efem-viz scene {scene.name}\n", _fmt_rows(vc, "v ", "%.7g"), _fmt_rows(scene.normals, "vn ", "%.6g")]
    if scene.faces is not None and len(scene.faces):
        f1 = scene.faces.astype(np.int64) + 1
        parts.append("".join(f"f {a}//{a} {b}//{b} {c}//{c}\n" for a, b, c in f1.tolist()))
    tmp.write_text("".join(parts), encoding="utf-8")


def _write_off(scene: Scene, tmp: Path) -> None:
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


def _write_glb(scene: Scene, tmp: Path) -> None:
    import trimesh

    def to_gltf(a: np.ndarray) -> np.ndarray:  # world +Z up -> glTF +Y up
        a = np.asarray(a, dtype=np.float64)
        return np.stack([a[:, 0], a[:, 2], -a[:, 1]], axis=1)

    extras: dict[str, Any] = {
        "schema_version": SCENE_SCHEMA_VERSION,
        "name": scene.name,
        "categories": {str(k): v for k, v in scene.categories.items()},
        "provenance": json.loads(json.dumps(scene.provenance, default=str)),
    }
    rgba = np.concatenate([scene.colors, np.full((scene.num_points, 1), 255, np.uint8)], axis=1)
    if scene.is_mesh:
        geom = trimesh.Trimesh(
            vertices=to_gltf(scene.points),
            faces=scene.faces,
            vertex_normals=to_gltf(scene.normals),
            vertex_colors=rgba,
            process=False,
        )
        if scene.instance is not None:
            if scene.instance.max(initial=0) >= _MAX_GLB_LABEL:
                raise SceneError(f"GLB stores labels as float32; ids must be < {_MAX_GLB_LABEL}")
            geom.vertex_attributes["instance"] = scene.instance.astype(np.float32)
    else:
        geom = trimesh.PointCloud(to_gltf(scene.points), colors=rgba)
        extras["normals_zb64"] = _pack_array(scene.normals.astype(np.float32))
        if scene.instance is not None:
            extras["instance_zb64"] = _pack_array(scene.instance.astype(np.int32))
    tscene = trimesh.Scene(geom)
    tscene.metadata[_GLB_EXTRAS_KEY] = extras
    glb = tscene.export(file_type="glb")
    if not isinstance(glb, bytes):  # trimesh types export() as str | bytes | dict; GLB is always bytes
        raise TypeError(f"trimesh returned {type(glb).__name__} for a GLB export, expected bytes")
    tmp.write_bytes(glb)
