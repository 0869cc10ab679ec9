"""Files on disk: the one atomic write of efem-viz and the annotator, and the one scene walk (`find_scenes`).

Every write goes through `atomic_write`: a temporary file in the destination directory, fsync, then `os.replace`,
so a crash never leaves a half-written file behind. `find_scenes` lists the scene files (the suffixes of the
format table `FORMATS` in efem_viz/data/formats/) among files and folders, skipping EFEM results
(`RESULT_SUFFIX`).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

from efem_viz.data.formats import FORMATS
from efem_viz.data.scene import SceneError

RESULT_SUFFIX = ".efem.npz"
NO_SCENES_GIVEN = f"no scenes given: name scene files ({', '.join(FORMATS)}) or folders of them"
"""The one line of a command called without any scene."""
BATCH_FILE = "batch.json"
"""The record `efem-viz segment --out DIR` keeps of its scenes (written and read in full by `efem_viz.batch`)."""
MAX_BATCH_FILE_BYTES = 64 << 20
"""Largest `batch.json` read (a record is about 500 bytes: room for 100,000 scenes)."""
"""Suffix of EFEM result files (`EMResult.save`); `find_scenes` skips them. (Its owner is the result file,
efem_viz/em/results.py, which imports it from here for now: data/ sits below em/.)"""
SEG_SUFFIX = ".seg.ply"
"""Suffix of `efem-viz segment`'s scene copies coloured by prediction: their per-vertex `instance` property holds
the *predicted* instances, not ground truth (`holds_predictions`)."""


def recorded_scene_paths(folder: str | os.PathLike[str]) -> dict[str, Path]:
    """Scene name -> scene file, as the `batch.json` of a results folder records them ({} when it has none, or
    an unreadable or oversized one); for apps that open a batch's results with their scenes."""
    import json

    p = Path(folder) / BATCH_FILE
    try:
        if not p.is_file() or p.stat().st_size > MAX_BATCH_FILE_BYTES:
            return {}
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return {}
    scenes = data.get("scenes") if isinstance(data, dict) and data.get("kind") == "efem-batch" else None
    out: dict[str, Path] = {}
    for r in scenes if isinstance(scenes, list) else []:
        if isinstance(r, dict) and isinstance(r.get("name"), str) and isinstance(r.get("path"), str):
            out[r["name"]] = Path(r["path"])
    return out


def holds_predictions(path: str | os.PathLike[str]) -> bool:
    """Whether a scene file's instance labels are predictions (a `segment` output, `SEG_SUFFIX`), not ground
    truth."""
    return Path(path).name.endswith(SEG_SUFFIX)


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
    return not p.name.lower().endswith(RESULT_SUFFIX) and p.suffix.lower() in FORMATS


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
                    stem = p.name[: -len(RESULT_SUFFIX)]
                    near = [c for c in (p.with_name(f"{stem}.seg.ply"), *(p.with_name(stem + s)
                                                                        for s in FORMATS)) if c.is_file()]
                    hint = (f"; open {near[0]}" + (" (its coloured segmentation)" if near[0].name.endswith(".seg.ply")
                                                   else "") + " instead, or view both with `efem-viz view "
                            f"{p.parent}`") if near else "; `efem-viz view --results` shows it over its scene"
                    raise SceneError(f"{p} is an EFEM result file, not a scene{hint}")
                raise SceneError(
                    f"{p}: unknown scene format {p.suffix!r}; expected one of {', '.join(FORMATS)}"
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

