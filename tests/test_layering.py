"""Architecture rules: the compute core never imports viser; the CLI dispatcher stays light and helpful."""

from __future__ import annotations

import subprocess
import sys

import pytest

from efem_viz import cli

CORE_MODULES = [
    "efem_viz.geometry",
    "efem_viz.data.scene",
    "efem_viz.data.io",
    "efem_viz.data.procedural",
    "efem_viz.data.synth",
    "efem_viz.data.rgbd",
    "efem_viz.prior",
    "efem_viz.prior.model",
    "efem_viz.prior.meshing",
    "efem_viz.prior.pose",
    "efem_viz.prior.codebook",
    "efem_viz.em",
    "efem_viz.eval",
    "annotator.labels",
    "annotator.selection",
    "annotator.journal",
]


@pytest.mark.parametrize("module", CORE_MODULES)
def test_core_module_does_not_import_viser(module: str) -> None:
    code = f"import sys, importlib; importlib.import_module({module!r}); print('viser' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False", f"{module} pulled in viser"


def test_cli_dispatcher_is_light() -> None:
    code = "import sys; import efem_viz.cli; print(sorted(m for m in ('torch','open3d','viser') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_cli_usage_and_unknown_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    assert "segment" in capsys.readouterr().out
    assert cli.main(["no-such-command"]) == 2
    assert "unknown command" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(cli.SUBCOMMANDS))
def test_every_subcommand_resolves(name: str) -> None:
    import importlib

    module_name, cls_name = cli.SUBCOMMANDS[name][0].split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    assert callable(getattr(cls, "run", None)), f"{cls_name} has no run()"
