"""`efem-viz` command line: subcommands are typed dataclasses (tyro), imported lazily so start-up stays fast."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from pathlib import Path

from efem_viz.terminal import log_to_terminal, terminal_text

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "view": ("efem_viz.viewer.commands:ViewArgs", "open the viewer on scenes / folders (default: sample_scenes/)"),
    "info": ("efem_viz.data.commands:InfoArgs", "print what a scene file contains"),
    "generate": ("efem_viz.data.synth:GenerateArgs",
                 "generate synthetic scans with ground truth (mugs on a table, chairs on a floor)"),
    "import-rgbd": ("efem_viz.data.commands:ImportRgbdArgs", "import a real RGB-D frame as a scene"),
    "import-scan": ("efem_viz.data.commands:ImportScanArgs",
                    "bring your own scan (any units, any up axis) into the scene frame"),
    "train-prior": ("efem_viz.prior.train:TrainArgs", "train a SIM(3)-equivariant shape prior"),
    "build-codebook": ("efem_viz.prior.commands:BuildCodebookArgs", "build the pose codebook of a prior"),
    "fit-member-head": ("efem_viz.prior.commands:FitMemberHeadArgs",
                        "fit a family prior's member classifier (which of mug, bowl, bottle, can)"),
    "pack-meshes": ("efem_viz.prior.commands:PackMeshesArgs",
                    "pack training meshes into one .npz for a machine without trimesh/open3d"),
    "convert-prior": ("efem_viz.prior.commands:ConvertArgs",
                      "convert a released EFEM checkpoint (weights/mugs.pt) + build its +Z-up codebook"),
    "segment": ("efem_viz.batch.commands:SegmentArgs", "run EFEM on scenes and save traces + results"),
    "calibrate-masks": ("efem_viz.eval.commands:CalibrateMasksArgs",
                        "choose a prior's output-mask threshold tau_out on labelled tuning scenes"),
    "evaluate": ("efem_viz.eval.commands:EvaluateArgs", "compute AP / AP50 / AP25 against ground truth"),
}


def _usage() -> str:
    lines = ["usage: efem-viz COMMAND [--help] ...", "", "commands:"]
    for name, (_, doc) in SUBCOMMANDS.items():
        lines.append(f"  {name:<15} {doc}")
    return "\n".join(lines)


DEBUG_FLAG = "--debug"
"""Global flag (before or after the subcommand): show the traceback of an error instead of its one-line message."""
DEBUG_ENV = "EFEM_DEBUG"
"""Environment variable with the same effect as --debug (any value but empty or 0)."""
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, KeyError, ImportError)
"""Errors that mean bad input or a bad environment (the project's own error types are ValueErrors): reported as
`<prog>: error: <message>`. Anything else is a bug and is reported with a hint to rerun with --debug."""
EXIT_ERROR = 1
"""Exit status of a command that failed (argument parsing errors exit 2, as with argparse)."""
EXIT_INTERRUPTED = 130
"""Exit status after Ctrl+C (128 + SIGINT)."""
EXIT_USAGE = 2
"""Exit status of a bad option value (as argparse's argument errors)."""


class OptionError(ValueError):
    """A command-line option with a value the command cannot use, found before anything starts: reported as
    `<prog>: error: <message>` with exit status 2 (`EXIT_USAGE`)."""

    exit_status = EXIT_USAGE


def check_port(port: int, *, option: str = "--port") -> int:
    """Refuse a TCP port outside 0-65535 (0 = any free port) before a server is built.

    Raises:
        OptionError: naming the option and the value.
    """
    if not 0 <= int(port) <= 65535:
        raise OptionError(f"{option} must be 0-65535 (0: any free port), got {port}")
    return int(port)


def check_device(name: str) -> str:
    """The torch device for a `--device` choice (`efem_viz.prior.registry.resolve_device`), checked before a
    server is built.

    Raises:
        OptionError: an unknown name, or CUDA asked for on a machine without it.
    """
    from efem_viz.prior.registry import resolve_device

    try:
        return resolve_device(name)
    except ValueError as exc:
        raise OptionError(str(exc)) from None


def pop_debug_flag(args: list[str]) -> tuple[list[str], bool]:
    """Remove `--debug` from command-line arguments (so subcommands must not define a `--debug` of their own).

    Args:
        args: arguments of a command (after the program name).

    Returns:
        The arguments without `--debug` (up to a `--` separator, after which nothing is touched) and whether
        debugging was asked for, by the flag or by EFEM_DEBUG.
    """
    debug = os.environ.get(DEBUG_ENV, "").strip() not in ("", "0")
    out: list[str] = []
    for i, a in enumerate(args):
        if a == "--":
            out += args[i:]
            break
        if a == DEBUG_FLAG:
            debug = True
        else:
            out.append(a)
    return out, debug


def error_message(exc: BaseException) -> str:
    """One line for an exception: its message with line breaks folded; OSErrors as `<reason>: <file>`, KeyErrors as
    `missing key '<k>'`; other control characters escaped (`terminal_text`)."""
    if isinstance(exc, OSError) and exc.strerror:
        files = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        msg = f"{exc.strerror}: {' -> '.join(files)}" if files else exc.strerror
    elif isinstance(exc, KeyError) and len(exc.args) == 1:
        msg = f"missing key {exc.args[0]!r}"
    else:
        msg = str(exc)
    return terminal_text(" ".join(msg.split())) or type(exc).__name__


def run_reporting_errors(prog: str, command: Callable[[], int | None], *, debug: bool = False) -> int:
    """Run a command and turn its errors into one line on stderr (the traceback only with `debug`).

    Args:
        prog: the program name the message starts with (`efem-viz evaluate`).
        command: runs the command; returns its exit status (None = 0).
        debug: re-raise instead, so that Python prints the traceback.

    Returns:
        The command's exit status; EXIT_ERROR after an error, EXIT_INTERRUPTED after Ctrl+C. A `SystemExit` (tyro's
        argument errors, `--help`) passes through.
    """
    try:
        return int(command() or 0)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except EXPECTED_ERRORS as exc:
        if debug:
            raise
        print(f"{prog}: error: {error_message(exc)}", file=sys.stderr)
        # by attribute, not isinstance: under `python -m efem_viz.cli` this module is also `__main__`
        return int(getattr(exc, "exit_status", EXIT_ERROR))
    except Exception as exc:  # a bug: still one line, with the way to see more
        if debug:
            raise
        print(f"{prog}: internal error: {type(exc).__name__}: {error_message(exc)} "
              f"(rerun with {DEBUG_FLAG} for the traceback)", file=sys.stderr)
        return EXIT_ERROR


def check_output_file(path: str | os.PathLike[str], *, option: str) -> Path:
    """Refuse an output file path that cannot be a file (an existing folder), before any work is done.

    Args:
        path: where a command will write a file.
        option: the option that named it, for the message (`--json-out`).

    Returns:
        The path.

    Raises:
        ValueError: `path` is an existing directory.
    """
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {p} is a folder; give a file path such as {p / 'result.json'}")
    return p


def package_version() -> str:
    """The installed package version (`--version` of both console scripts)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("efem-viz")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without installing
        return "unknown (not installed)"


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `efem-viz` console script.

    `efem-viz [--debug] COMMAND ARGS...`; errors print one line `efem-viz COMMAND: error: ...` on stderr and exit 1
    (2 for argument errors, 130 after Ctrl+C); `--debug` (or EFEM_DEBUG=1) shows the traceback instead.
    """
    args, debug = pop_debug_flag(list(sys.argv[1:] if argv is None else argv))
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if args[0] in ("--version", "-V", "version"):
        print(f"efem-viz {package_version()}")
        return 0
    name, rest = args[0], args[1:]
    from efem_viz.cpu import configure_openmp

    configure_openmp()  # before torch is imported: OpenMP threads sleep at barriers (sharing busy cores)
    if name not in SUBCOMMANDS:
        print(f"efem-viz: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    prog = f"efem-viz {name}"

    def command() -> int:
        import tyro

        module_name, cls_name = SUBCOMMANDS[name][0].split(":")
        cls = getattr(importlib.import_module(module_name), cls_name)
        log_to_terminal()
        parsed = tyro.cli(cls, args=rest, prog=prog)
        return int(parsed.run() or 0)

    return run_reporting_errors(prog, command, debug=debug)

if __name__ == "__main__":
    sys.exit(main())
