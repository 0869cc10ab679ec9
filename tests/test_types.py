"""Static checks: pyright (basic mode, via basedpyright) reports no errors, as STYLE.md asks of CI.

The settings are the repository's pyrightconfig.json. basedpyright is a PyPI build of pyright that bundles
Node, so the test extra is all it needs. Set EFEM_SKIP_TYPES=1 to skip (e.g. for a quick local loop); a
missing basedpyright is a failure, not a skip, so that CI cannot pass without running the check.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _basedpyright() -> list[str]:
    if importlib.util.find_spec("basedpyright") is not None:  # the one installed with this interpreter
        return [sys.executable, "-m", "basedpyright"]
    exe = shutil.which("basedpyright")
    if exe is None:
        pytest.fail("basedpyright is not installed: run `bash scripts/setup.sh --test` "
                    "(or set EFEM_SKIP_TYPES=1 to skip the type check)")
    return [exe]


def _format(diag: dict) -> str:
    """`path:line:col severity [rule]: message`, path relative to the repository."""
    path = diag.get("file", "?")
    if path.startswith(str(ROOT) + os.sep):
        path = path[len(str(ROOT)) + 1:]
    start = diag.get("range", {}).get("start", {})
    rule = f" [{diag['rule']}]" if diag.get("rule") else ""
    line, col = start.get("line", -1) + 1, start.get("character", -1) + 1
    return f"{path}:{line}:{col} {diag.get('severity')}{rule}: {diag.get('message', '')}"


@pytest.mark.slow  # about 20-25 s of CPU
@pytest.mark.skipif(os.environ.get("EFEM_SKIP_TYPES") == "1", reason="EFEM_SKIP_TYPES=1")
def test_pyright_reports_no_errors() -> None:
    cmd = [*_basedpyright(), "--outputjson", "--project", str(ROOT / "pyrightconfig.json"),
           "--pythonpath", sys.executable]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    try:
        report = json.loads(out.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"basedpyright gave no JSON report (exit {out.returncode}):\n{out.stdout}\n{out.stderr}")
    summary = report["summary"]
    diags = report.get("generalDiagnostics", [])
    errors = [d for d in diags if d.get("severity") == "error"]
    assert summary["filesAnalyzed"] > 0, f"basedpyright analysed no files:\n{out.stdout}\n{out.stderr}"
    assert summary["errorCount"] == 0 and not errors, (
        f"basedpyright: {summary['errorCount']} errors, {summary['warningCount']} warnings\n"
        + "\n".join(_format(d) for d in diags)
    )


def test_prior_all_matches_lazy_exports() -> None:
    """efem_viz.prior spells `__all__` out (pyright cannot follow `sorted(_LAZY)`); keep it in sync."""
    import efem_viz.prior as prior

    assert sorted(prior.__all__) == sorted(prior._LAZY)
