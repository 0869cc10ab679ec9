"""Reading values that clients send: every GUI value that feeds computation passes one of these helpers.

A browser's GUI limits (slider ranges, the options of a dropdown) are only hints: any client can send any value
over the WebSocket. The helpers here re-check a control's value on the server against what the server declared
for that control (`min`/`max` of sliders and numbers, `options` of dropdowns; `efem_viz.serve.guard` keeps
clients from rewriting those): numbers are clamped into range and must be finite, choices must be one of the
options, text is bounded, colours are 0-255 triples. Paths typed into the GUI must resolve inside a folder chosen
at start (`resolve_inside_root`), and so must every folder and file an export then writes there (`confine_writes`:
a symbolic link inside the output folder cannot lead a write out of it).

Out-of-range numbers are clamped (and the clamped value is written back through `write_back`, so every client
shows what is used); values that cannot be used (NaN, text in a number, an unknown option) raise
`ClientValueError` with one line for the status line.
"""

from __future__ import annotations

import logging
import math
import os
import unicodedata
from pathlib import Path
from typing import Any, Callable, Iterable

logger = logging.getLogger(__name__)

MAX_TEXT = 1024
"""Longest text accepted from a text field (names, categories, paths)."""

WriteBack = Callable[[Any, Any], None]
"""`write_back(handle, value)`: show the value actually used in the GUI (the app's own quiet setter)."""


class ClientValueError(ValueError):
    """A value from a client that cannot be used (the message is one line for the user)."""


def _label(handle: Any) -> str:
    return str(getattr(handle, "label", "") or "value")


def _fix(handle: Any, value: Any, write_back: WriteBack | None) -> None:
    logger.info("%s: client value %r replaced by %r", _label(handle), handle.value, value)
    if write_back is not None:
        write_back(handle, value)


def read_number(handle: Any, *, write_back: WriteBack | None = None) -> float:
    """The finite value of a slider / number control, clamped to its declared `min`/`max`.

    Args:
        handle: a viser slider or number handle (or anything with `value`, optional `min`, `max`, `label`).
        write_back: called with the clamped value when it differs from the sent one.

    Returns:
        The value as a float, within [min, max] where those are declared.

    Raises:
        ClientValueError: not a number, NaN or infinite.
    """
    raw = handle.value
    if isinstance(raw, bool):
        raise ClientValueError(f"{_label(handle)}: expected a number, got {raw!r}")
    try:
        x = float(raw)
    except (TypeError, ValueError, OverflowError):
        raise ClientValueError(f"{_label(handle)}: expected a number, got {raw!r}") from None
    if not math.isfinite(x):
        raise ClientValueError(f"{_label(handle)}: {raw!r} is not a finite number")
    lo, hi = getattr(handle, "min", None), getattr(handle, "max", None)
    y = x
    if lo is not None and y < float(lo):
        y = float(lo)
    if hi is not None and y > float(hi):
        y = float(hi)
    if y != x:
        _fix(handle, type(raw)(y) if isinstance(raw, int) else y, write_back)
    return y


def read_int(handle: Any, *, write_back: WriteBack | None = None) -> int:
    """`read_number`, rounded to the nearest integer inside the declared range.

    Raises:
        ClientValueError: not a number, NaN or infinite.
    """
    x = read_number(handle)
    lo, hi = getattr(handle, "min", None), getattr(handle, "max", None)
    n = int(round(x))
    if lo is not None and n < lo:
        n = math.ceil(lo)
    if hi is not None and n > hi:
        n = math.floor(hi)
    if n != handle.value:
        _fix(handle, n, write_back)
    return n


def read_choice(handle: Any) -> str:
    """The value of a dropdown, checked to be one of its (server-declared) options.

    Raises:
        ClientValueError: the value is not one of the options.
    """
    value = handle.value
    options = tuple(getattr(handle, "options", ()))
    if not isinstance(value, str) or value not in options:
        shown = value if len(str(value)) <= 60 else str(value)[:57] + "..."
        raise ClientValueError(f"{_label(handle)}: {shown!r} is not one of the options")
    return value


def read_bool(handle: Any) -> bool:
    """The value of a checkbox.

    Raises:
        ClientValueError: not a boolean.
    """
    value = handle.value
    if not isinstance(value, bool):
        raise ClientValueError(f"{_label(handle)}: expected true/false, got {value!r}")
    return value


def read_text(handle: Any, *, max_len: int = MAX_TEXT) -> str:
    """The value of a text field: one line of at most `max_len` characters, without control characters.

    Every text field of the apps is a single line (names, categories, paths); a newline, ESC or NUL in one can
    only come from a client bypassing the GUI, and would reach file names, logs and terminals.

    Raises:
        ClientValueError: not a string, too long, or containing a control character (NUL, newline, ESC, ...).
    """
    value = handle.value
    if not isinstance(value, str):
        raise ClientValueError(f"{_label(handle)}: expected text, got {type(value).__name__}")
    if len(value) > max_len:
        raise ClientValueError(f"{_label(handle)}: text longer than {max_len} characters")
    bad = next((c for c in value if unicodedata.category(c) == "Cc"), None)
    if bad is not None:
        name = "NUL" if bad == "\x00" else bad.encode("unicode_escape").decode("ascii")
        raise ClientValueError(f"{_label(handle)}: text contains a control character ({name}); not used")
    return value


def uncastable_value(current: Any, value: Any) -> str | None:
    """Why a client's `value` cannot take the type of a control's `current` value, or None when it can.

    viser casts every value a client sends to the type of the control's current value (`int(value)` for an integer
    control, element-wise for a colour) before any callback runs, so a NaN, an infinity or text sent for an integer
    or colour control fails inside viser, with a traceback in the server log. `efem_viz.serve.guard` drops such
    values first, with this one-line reason. (A NaN for a float control casts; `read_number` refuses it.)

    Args:
        current: the control's current value (its type is the control's).
        value: the value the client sent.
    """
    if isinstance(current, tuple) and current:
        typ: type = type(current[0])
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            return f"expected {len(current)} values, got {_short(value)}"
        items = list(value)
    else:
        typ, items = type(current), [value]
    for v in items:
        try:
            typ(v)
        except (TypeError, ValueError, OverflowError, ArithmeticError):
            kind = {int: "a finite integer", float: "a number"}.get(typ, typ.__name__)
            return f"expected {kind}, got {_short(value)}"
    return None


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def read_rgb(handle: Any, *, write_back: WriteBack | None = None) -> tuple[int, int, int]:
    """The value of a colour control: three integers clamped to 0-255.

    Raises:
        ClientValueError: not three finite numbers.
    """
    value = handle.value
    try:
        parts = [float(c) for c in value]
    except (TypeError, ValueError):
        raise ClientValueError(f"{_label(handle)}: expected an RGB colour, got {value!r}") from None
    if len(parts) != 3 or not all(math.isfinite(c) for c in parts):
        raise ClientValueError(f"{_label(handle)}: expected three finite RGB components, got {value!r}")
    rgb = tuple(int(min(max(round(c), 0), 255)) for c in parts)
    if rgb != tuple(value):
        _fix(handle, rgb, write_back)
    return rgb  # type: ignore[return-value]


def resolve_inside(
    text: str | os.PathLike[str],
    roots: Iterable[str | os.PathLike[str]],
    *,
    what: str = "path",
    allow_dotdot: bool = True,
    error: type[ValueError] = ClientValueError,
) -> Path:
    """Resolve a user- or client-given path (following symlinks) and check that it lies inside one of `roots`: the
    one path-confinement rule of both apps. Relative paths are taken relative to the first root.

    Args:
        text: the path typed into the GUI or given on the command line.
        roots: the allowed folders (the folders the app was given at start).
        what: noun for the error message ("output folder", "label file").
        allow_dotdot: accept `..` components when the result still resolves inside a root.
        error: the ValueError subclass to raise (each app's own error type).

    Returns:
        The resolved absolute path, a root itself or below one.

    Raises:
        `error`: empty, NUL, longer than `MAX_TEXT`, a `..` component when not allowed, no roots, or a path that
            resolves outside every root (an absolute path elsewhere, or a symlink pointing out).
    """
    s = os.fspath(text).strip()
    if not s or "\x00" in s:
        raise error(f"invalid {what}: {s!r}")
    if len(s) > MAX_TEXT:
        raise error(f"invalid {what}: longer than {MAX_TEXT} characters")
    root_list = [Path(r).expanduser().resolve() for r in roots]
    if not root_list:
        raise error("no allowed directories configured")
    p = Path(s).expanduser()
    if not allow_dotdot and ".." in p.parts:
        raise error(f"refusing {what} {s!r}: '..' is not allowed")
    resolved = (p if p.is_absolute() else root_list[0] / p).resolve()
    for r in root_list:
        if resolved == r or r in resolved.parents:
            return resolved
    where = (f"the folder {root_list[0]}" if len(root_list) == 1
             else f"the allowed folders {[str(r) for r in root_list]}")
    raise error(f"refusing {what} {s!r}: it resolves to {resolved}, outside {where}")


def resolve_inside_root(text: str | os.PathLike[str], root: str | os.PathLike[str], *, what: str = "path") -> Path:
    """Resolve a client-given path inside `root` (relative paths are taken relative to `root`; no `..`).

    Raises:
        ClientValueError: see `resolve_inside`.
    """
    return resolve_inside(text, [root], what=what, allow_dotdot=False)



def confine_writes(
    paths: Iterable[str | os.PathLike[str]],
    root: str | os.PathLike[str],
    *,
    what: str = "export",
    error: type[ValueError] = ClientValueError,
) -> list[Path]:
    """Check, before anything is written, that every folder and file an export will write lies inside `root`
    after following symbolic links (`resolve_inside`), and that no file it will write is itself a symbolic link.

    The output folder alone is not enough: a link further down (a sub-folder such as `pred_mask/`, or one file)
    can point outside. A file-level link is refused even when it points inside `root`: atomic writes never write
    through a link, so the export would stop half-way. A folder that is a link into `root` is accepted.

    Args:
        paths: the folders and files the export will create or replace (absolute, or relative to `root`).
        root: the output root chosen at start.
        what: noun for the error message.
        error: the ValueError subclass to raise.

    Returns:
        The resolved paths, in the given order.

    Raises:
        `error`: naming the first path that resolves outside `root` or is a link to a file.
    """
    out = []
    for p in paths:
        path = Path(p) if Path(p).is_absolute() else Path(root).expanduser().resolve() / p
        try:
            resolved = resolve_inside(path, [root], what=f"{what} path", error=error)
        except error as exc:
            raise error(f"{exc}; nothing was written") from None
        if path.is_symlink() and not path.is_dir():
            raise error(f"refusing {what}: {path} is a symbolic link (to {resolved}); nothing was written")
        out.append(resolved)
    return out
