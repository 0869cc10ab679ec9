"""PLY scenes (binary and ASCII): the bounds-checked header reader, fast readers for triangle meshes and ASCII
bodies, and the writer.

Conventions (the same file the annotator writes, readable by MeshLab/CloudCompare): vertex properties `x y z`
(float), `nx ny nz` (float, optional), `red green blue` (uchar, optional), `instance` (int, optional, 0 =
unlabelled); element `face` with list property `vertex_indices`. Categories and provenance are stored as header
comments `efem_categories {json}` and `efem_provenance {json}` (`CATEGORIES_COMMENT`, `PROVENANCE_COMMENT`).

`read_ply_header` and `check_ply_counts` are public: the annotator's label reader runs the same bounds checks
before plyfile allocates anything.
"""

from __future__ import annotations

import io
import json
import re
import warnings
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np

from efem_viz.data.formats.common import (
    CATEGORIES_COMMENT,
    PROVENANCE_COMMENT,
    parse_categories,
    triangulate,
    triangulate_flat,
)
from efem_viz.data.scene import LIMIT_FLAG_HINT, MAX_FACES_PER_POINT, TOO_MANY_POINTS_HINT, Scene, SceneError

_PLY_HEADER_LIMIT = 4 << 20
"""Bytes searched for a PLY `end_header` line: a longer header is refused rather than parsed without checks."""
_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
_FACE_LISTS = ("vertex_indices", "vertex_index")
_ASCII_SPACE = b" \t\n\r\x0b\x0c"


class PlyElementHeader(NamedTuple):
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


class PlyHeader(NamedTuple):
    """A PLY header: format, elements in file order, and where the body starts."""

    ascii: bool
    elements: tuple[PlyElementHeader, ...]
    body_offset: int
    header_lines: int


def read_ply_header(p: Path) -> PlyHeader | None:
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
    elts = tuple(PlyElementHeader(n, c, tuple(sc), tuple(ls)) for n, c, sc, ls in elements)
    return PlyHeader(fmt == "ascii", elts, pos, n_lines)


def check_ply_counts(p: Path, head: PlyHeader, max_points: int) -> None:
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


def _check_ply_no_extra_rows(p: Path, head: PlyHeader) -> None:
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


def load(p: Path, max_points: int) -> dict[str, Any]:
    import plyfile

    head = read_ply_header(p)
    if head is not None:
        check_ply_counts(p, head, max_points)
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
            out["faces"] = triangulate_flat(*polys, p)
        else:
            out["faces"] = triangulate([np.asarray(f) for f in fdata[key]], p)
    comments = list(ply.comments) + list(getattr(ply, "obj_info", []))
    for c in comments:
        c = c.strip()
        if c.startswith(CATEGORIES_COMMENT + " "):
            out["categories"] = parse_categories(c[len(CATEGORIES_COMMENT) + 1 :])
        elif c.startswith(PROVENANCE_COMMENT + " "):
            out["provenance"] = json.loads(c[len(PROVENANCE_COMMENT) + 1 :])
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
    got = _ascii_header_and_body(p)
    if got is None:
        return None, None
    ply, body, head_lines = got
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


def _ascii_header_and_body(p: Path) -> tuple[Any, bytes, int | None] | None:
    """An ASCII PLY's header, parsed by plyfile, and its body (`_read_ply_ascii`).

    Returns:
        (ply, body, head_lines): the `PlyData` of the header (elements without data), the body with LF newlines,
        and the number of header lines (None when the header is longer than 64 KiB); None for a binary file, a
        header plyfile rejects, or a body with a byte outside `_PLY_ASCII_BYTES` (plyfile then reads the file).
    """
    import plyfile

    parse_header = getattr(plyfile.PlyData, "_parse_header", None)  # private: if gone, plyfile reads the file
    if parse_header is None:
        return None
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or not re.search(rb"format\s+ascii", head[: max(end, 0)]):
            return None
        fh.seek(0)
        try:
            ply = parse_header(fh)
        except Exception:  # plyfile reports a bad header in its own words
            return None
        if not ply.text:
            return None
        n_head = fh.tell()
        body = fh.read()
    head_lines = len(head[:n_head].splitlines()) if n_head <= len(head) else None
    if b"\r" in body:  # plyfile reads the body with universal newlines
        body = body.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if body.translate(None, _PLY_ASCII_BYTES):
        return None
    return ply, body, head_lines


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


def save(scene: Scene, tmp: Path, *, ascii: bool) -> None:
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
        comments.append(f"{CATEGORIES_COMMENT} " + json.dumps({str(k): v for k, v in scene.categories.items()}))
    if scene.provenance:
        comments.append(f"{PROVENANCE_COMMENT} " + json.dumps(scene.provenance, default=str))
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

