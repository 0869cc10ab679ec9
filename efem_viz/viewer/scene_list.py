"""The viewer's scene browser: which scene files it may open (only inside the paths it was given) and where each
scene's saved result lies. The folders are walked by `efem_viz.data.files.find_scenes`, the one scene walk.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from efem_viz.data.files import RESULT_SUFFIX, find_scenes

LABELS_INFIX = ".labels"
"""`<scene>.labels.ply` is an annotated copy of `<scene>.ply` (annotator output) and may share its result."""
SEG_INFIX = ".seg"
"""`<scene>.seg.ply` is `efem-viz segment`'s coloured copy of `<scene>` and shares its result."""


@dataclass(frozen=True)
class SceneEntry:
    """One scene file the browser may open.

    Attributes:
        name: unique display name (file stem, with the parent folder added when stems collide).
        path: resolved absolute path, guaranteed to lie inside one of the roots given to `discover_scenes`.
        root: the resolved root (file or folder) it was found under.
    """

    name: str
    path: Path
    root: Path
    result_dirs: tuple[Path, ...] = ()
    """Folders of saved results (`efem-viz view --results DIR`, e.g. a `segment --out` folder), searched before
    the scene's own folder: a person who names a results folder asks to see those results."""

    @property
    def trace_path(self) -> Path:
        """The saved result to open with this scene, looked up when asked (a result written meanwhile is found):
        `<scene>.efem.npz` in each results folder, then next to the scene; for an annotated copy `<base>.labels.ply` or
        a `segment` output `<base>.seg.ply`, the result of `<base>` (same points). When none exists, the path next
        to the scene (where a run would be saved)."""
        stem = self.path.name[: -len(self.path.suffix)] if self.path.suffix else self.path.name
        stems = [stem] + [stem[: -len(infix)] for infix in (LABELS_INFIX, SEG_INFIX) if stem.endswith(infix)]
        folders = [*self.result_dirs, self.path.parent]
        for base in stems:
            for d in folders:
                cand = d / (base + RESULT_SUFFIX)
                if cand.is_file():
                    return cand
        return trace_path_for(self.path)


def trace_path_for(scene_path: Path) -> Path:
    """Path of the saved EM result of a scene: `<dir>/<stem>.efem.npz`.

    Args:
        scene_path: a scene file such as `sample_scenes/mugs_01.ply`.
    """
    name = scene_path.name
    if name.endswith(RESULT_SUFFIX):
        return scene_path
    return scene_path.with_name(scene_path.stem + RESULT_SUFFIX)


def is_inside(path: Path, roots: Sequence[Path]) -> bool:
    """True when `path` (resolved, symlinks followed) is one of `roots` or lies below a root folder."""
    try:
        rp = path.resolve(strict=False)
    except OSError:
        return False
    for r in roots:
        if rp == r or (r.is_dir() and rp.is_relative_to(r)):
            return True
    return False


def discover_scenes(
    paths: Sequence[str | os.PathLike[str]],
    *,
    recursive: bool = False,
    result_dirs: Sequence[str | os.PathLike[str]] = (),
) -> list[SceneEntry]:
    """List the scene files given directly or found inside the given folders.

    The folders are walked by `efem_viz.data.files.find_scenes` (the CLI's walk: same files, same errors). Only
    files inside the given paths are returned (symlinks are resolved and anything that points outside is
    dropped), so the viewer never opens a file the user did not hand it.

    Args:
        paths: scene files and/or folders.
        recursive: also search sub-folders of the given folders (default: only the folder itself).
        result_dirs: folders of saved results to look in for each scene's `<scene>.efem.npz`.

    Returns:
        Entries sorted by name, with unique names.

    Raises:
        FileNotFoundError: a results folder or a given path does not exist (for a scene path the
            `efem_viz.data.files.ScenePathNotFoundError`, also a `SceneError`).
        SceneError: a file given explicitly is not a scene file (an EFEM result, an unknown suffix).
    """
    rdirs: list[Path] = []
    for d in result_dirs:
        dd = Path(d).expanduser()
        if not dd.is_dir():
            raise FileNotFoundError(f"results folder does not exist: {dd}")
        rdirs.append(dd.resolve())
    given = [Path(p).expanduser() for p in paths]
    roots = [g.resolve() for g in given]
    found: list[tuple[Path, Path]] = []
    seen: set[Path] = set()
    for g, root in zip(given, roots):
        for c in find_scenes(g, recursive=recursive):
            rc = c.resolve()
            if rc in seen or not is_inside(rc, roots):
                continue
            seen.add(rc)
            found.append((rc, root))
    stems: dict[str, int] = {}
    for rc, _ in found:
        stems[rc.stem] = stems.get(rc.stem, 0) + 1
    entries: list[SceneEntry] = []
    used: set[str] = set()
    for rc, root in found:
        name = rc.stem if stems[rc.stem] == 1 else f"{rc.parent.name}/{rc.stem}"
        base, k = name, 2
        while name in used:
            name = f"{base} ({k})"
            k += 1
        used.add(name)
        entries.append(SceneEntry(name=name, path=rc, root=root, result_dirs=tuple(rdirs)))
    entries.sort(key=lambda e: e.name)
    return entries
