"""Checking an `.npz` archive before numpy reads it: every array header against the bytes the archive holds and
against the size limits, so a corrupt or hostile file costs neither memory nor time. Used by every `.npz` reader
(scenes, RGB-D frames, labels, results, codebooks)."""

from __future__ import annotations

import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from efem_viz.data.scene import MAX_FACES_PER_POINT, TOO_MANY_POINTS_HINT, SceneError

_NPZ_ROWS_PER_POINT = {"points": 1, "normals": 1, "colors": 1, "instance": 1, "faces": MAX_FACES_PER_POINT}
"""Rows a native scene array may have per allowed point (`max_points`)."""
_NPZ_BYTES_PER_ROW = 64
"""Bytes a scene array may take per allowed row (float64 points are 24, RGBA float64 colours 32)."""
_NPZ_OTHER_BYTES = 256 << 20
"""Bytes any other array (an RGB-D frame's depth and colour images, names, JSON) may take, at least."""


NPY_HEADER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError, OSError, EOFError, SyntaxError, NotImplementedError, tokenize.TokenError, zlib.error,
    zipfile.BadZipFile,
)
"""What reading a damaged `.npy` header inside a zip raises: numpy's parser (ValueError, SyntaxError and
tokenize.TokenError from its literal parsing), zipfile (BadZipFile; NotImplementedError for an unsupported "zip
file version"), zlib and the file itself."""


def check_npz_headers(p: Path, max_points: int) -> dict[str, tuple[int, ...]]:
    """Check every array header of an `.npz` against the archive and the limits before numpy allocates.

    `np.load` allocates an array's full size from its `.npy` header before reading the data, so a header
    claiming 10^12 points would cost memory (or raise MemoryError) before the file is found short. Each
    member's claimed size must equal the bytes the zip directory says it holds (zipfile never inflates more
    than that), and scene arrays must fit `max_points`.

    Returns:
        The declared shape of every array (key -> shape), for format-specific bounds before loading.

    Raises:
        SceneError: not a zip archive; a header that disagrees with its member's size; an array over the limits.
    """
    shapes: dict[str, tuple[int, ...]] = {}

    try:  # zipfile raises NotImplementedError for an entry that needs a newer zip version than it reads
        zf = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, OSError, NotImplementedError, ValueError) as exc:
        raise SceneError(f"{p}: not a valid .npz (zip) archive ({exc})") from exc
    with zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            key = info.filename[: -len(".npy")]
            try:
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                        np.lib.format.read_array_header_2_0
                    shape, _, dtype = read(fh)
                    header_len = fh.tell()
            except NPY_HEADER_ERRORS as exc:
                raise SceneError(f"{p}: array {key!r} has a corrupt .npy header ({str(exc)[:160]})") from exc
            shapes[key] = tuple(int(x) for x in shape)
            if dtype.hasobject:
                continue  # np.load(allow_pickle=False) refuses it with its own message
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize if shape else dtype.itemsize
            held = info.file_size - header_len
            if nbytes != held:
                raise SceneError(
                    f"{p}: array {key!r} claims shape {tuple(shape)} {dtype} ({nbytes:,} bytes) but the archive "
                    f"holds {held:,} bytes for it (corrupt or truncated file)"
                )
            if key in _NPZ_ROWS_PER_POINT:
                rows_limit = _NPZ_ROWS_PER_POINT[key] * max(max_points, 1)
                rows = int(shape[0]) if shape else 1
                if rows > rows_limit or nbytes > _NPZ_BYTES_PER_ROW * rows_limit:
                    what = "points" if key != "faces" else "faces"
                    raise SceneError(
                        f"{p}: array {key!r} has shape {tuple(shape)} {dtype}: more {what} than the limit of "
                        f"{rows_limit:,} (point limit {max_points:,}); {TOO_MANY_POINTS_HINT}"
                    )
            elif nbytes > max(_NPZ_OTHER_BYTES, _NPZ_BYTES_PER_ROW * max_points):
                raise SceneError(
                    f"{p}: array {key!r} has shape {tuple(shape)} {dtype} ({nbytes:,} bytes), larger than any "
                    "scene or RGB-D frame this reader accepts"
                )
    return shapes
