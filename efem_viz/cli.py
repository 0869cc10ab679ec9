"""`efem-viz` command line: subcommands are typed dataclasses (tyro), imported lazily so start-up stays fast."""

from __future__ import annotations

import importlib
import logging
import sys

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "view": ("efem_viz.viewer.commands:ViewArgs", "open the viewer on scenes / folders (default: sample_scenes/)"),
    "info": ("efem_viz.data.commands:InfoArgs", "print what a scene file contains"),
    "generate": ("efem_viz.data.synth:GenerateArgs", "generate synthetic tabletop scans with ground truth"),
    "import-rgbd": ("efem_viz.data.commands:ImportRgbdArgs", "import a real RGB-D frame as a scene"),
    "train-prior": ("efem_viz.prior.train:TrainArgs", "train a SIM(3)-equivariant shape prior"),
    "build-codebook": ("efem_viz.prior.codebook:BuildCodebookArgs", "build the pose codebook of a prior"),
    "convert-prior": ("efem_viz.prior.convert:ConvertArgs",
                      "convert a released EFEM checkpoint (weights/mugs.pt) + build its +Z-up codebook"),
    "segment": ("efem_viz.em.commands:SegmentArgs", "run EFEM on scenes and save traces + results"),
    "calibrate-masks": ("efem_viz.em.commands:CalibrateMasksArgs",
                        "choose a prior's output-mask threshold tau_out on labelled tuning scenes"),
    "evaluate": ("efem_viz.eval.commands:EvaluateArgs", "compute AP / AP50 / AP25 against ground truth"),
}


def _usage() -> str:
    lines = ["usage: efem-viz COMMAND [--help] ...", "", "commands:"]
    for name, (_, doc) in SUBCOMMANDS.items():
        lines.append(f"  {name:<15} {doc}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `efem-viz` console script."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = args[0], args[1:]
    if name not in SUBCOMMANDS:
        print(f"efem-viz: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    import tyro

    target = SUBCOMMANDS[name][0]
    module_name, cls_name = target.split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    parsed = tyro.cli(cls, args=rest, prog=f"efem-viz {name}")
    try:
        return int(parsed.run() or 0)
    except (ValueError, FileNotFoundError, FileExistsError, PermissionError) as exc:
        print(f"efem-viz {name}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
