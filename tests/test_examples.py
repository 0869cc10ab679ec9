"""Smoke tests of examples/: every example runs with its small defaults, exits 0 and prints what it found.

Each example is run as its own process (as a reader would run it), with `--out` in a temporary folder and the
working directory an empty folder that must stay empty (examples write only under `--out`). A broken example
fails here; a new example without an entry in `EXPECTED` fails `test_every_example_is_smoke_tested`.
"""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
TIMEOUT_S = 300
"""Per example; the defaults run in well under a minute on one thread (the whole file in about 2 minutes)."""

EXPECTED: dict[str, tuple[list[str], list[str]]] = {
    # example: (substrings its output must contain, files its --out folder must hold)
    "run_efem_and_read_trace": (
        ["preset 'fast' with 40 proposals", "instances: ", "deaths by reason: ", "review after step",
         "replay proposal #", "replayed weights agree"],
        ["syn_z_1.efem.npz"],
    ),
    "add_category_prior": (
        ["ShapePriorLike True", "joint solve: ", "of priors ['mug', 'sphere']", "instances by category: mug ",
         "AP50 per category", "reloaded categories ['mug', 'sphere']", "categories: ['sphere', 'bowl']"],
        ["syn_z_1+spheres.efem.npz", "bowl-v1.pt"],
    ),
    "add_elimination_rule": (
        ["'stationary near zero'", "'low coverage'",
         "on a hand-made context: kills [(1, 'stationary near zero')]", "deaths by reason: ",
         "reloaded trace: reason names"],
        ["syn_pile_0.efem.npz"],
    ),
    "embed_viewer": (
        ["ran EFEM on spheres", "viewer at http://127.0.0.1:", "inspecting proposal #", "scene nodes (",
         "/scene/points", "/results/mesh/k0", "/inspect/samples"],
        ["spheres.ply", "exported"],
    ),
    "viewer_session": (
        ["scenes: [", "opened syn_z_1: ", "live proposals, top [", "threshold 0.3 keeps ", " mug confidence ",
         "ground truth: ", "exported results to "],
        ["exported/syn_z_1.txt", "exported/pred_mask"],
    ),
    "annotator_session": (
        ["opened real_tabletop_6.ply: ", "imported ", "accepted ", "after undo 0; after redo ",
         "reopened from the journal: labels identical True"],
        ["real_tabletop_6.labels.ply", "real_tabletop_6.annotate"],
    ),
    "add_annotator_tool": (
        ["'lift'", "**U** Lift", "IoU with true object", "(Lift)", "after undo", "exported "],
        ["syn_z_1_unlabelled.ply", "syn_z_1_unlabelled.labels.ply"],
    ),
    "add_scene_format": (
        [".laz, .xyz", "find_scenes lists: ['spheres.xyz']", "same points, normals and labels: True",
         "not numeric columns", "more than the limit of 10", "EFEM on spheres.xyz: 3 instances"],
        ["spheres.xyz", "spheres.efem.npz"],
    ),
    "add_batch_backend": (
        ["'thread'", "on thread-", "same instances on both backends: True",
         "resumes: counts {'ok': 0, 'skipped': 3"],
        ["thread/batch.json", "local/batch.json"],
    ),
}
SLOW = {"run_efem_and_read_trace", "add_category_prior"}  # runs of the mug prior, about 20-40 s each


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _run(name: str, tmp_path: Path, *extra: str) -> tuple[str, Path, Path]:
    out, cwd = tmp_path / "out", tmp_path / "cwd"
    cwd.mkdir()
    proc = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), "--out", str(out), *extra], cwd=cwd,
                          env=_env(), capture_output=True, text=True, timeout=TIMEOUT_S)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{name} exited with {proc.returncode}:\n{text[-4000:]}"
    return text, out, cwd


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n
                                  for n in EXPECTED])
def test_example_runs(name: str, tmp_path: Path) -> None:
    text, out, cwd = _run(name, tmp_path)
    lines, files = EXPECTED[name]
    missing = [s for s in lines if s not in text]
    assert not missing, f"{name}: output lacks {missing}:\n{text[-4000:]}"
    absent = [f for f in files if not (out / f).exists()]
    assert not absent, f"{name}: --out lacks {absent} (has {sorted(p.name for p in out.iterdir())})"
    assert not any(cwd.iterdir()), f"{name} wrote into its working directory: {sorted(cwd.iterdir())}"


def test_embed_viewer_serves_until_ctrl_c(tmp_path: Path) -> None:
    """`--serve` keeps the server up (the URL is printed) and Ctrl+C stops it cleanly (exit 0)."""
    cmd = [sys.executable, str(EXAMPLES / "embed_viewer.py"), "--serve", "--out", str(tmp_path)]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert proc.stdout is not None
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("serving http://127.0.0.1:"):
                proc.send_signal(signal.SIGINT)
                break
        rc = proc.wait(timeout=60)
        rest = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert any(s.startswith("serving ") for s in seen), "".join(seen)[-3000:]
    assert rc == 0, "".join(seen)[-2000:] + rest[-2000:]


def test_every_example_is_smoke_tested() -> None:
    """Each examples/*.py has an entry here, a docstring saying what it shows, and an --out option."""
    found = sorted(p.stem for p in EXAMPLES.glob("*.py"))
    assert found == sorted(EXPECTED), f"examples {found} vs smoke-tested {sorted(EXPECTED)}"
    for name in found:
        src = (EXAMPLES / f"{name}.py").read_text(encoding="utf-8")
        doc = ast.get_docstring(ast.parse(src))
        assert doc and len(doc.splitlines()) > 3, f"{name} needs a docstring saying what it shows"
        assert '"--out"' in src, f"{name} needs an --out folder option"
