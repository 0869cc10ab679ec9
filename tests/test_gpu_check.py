"""The prepared GPU check (`scripts/gpu_check.sh`, `bench/gpu_check.py`) as it runs on the GPU machine, here on the
CPU: without open3d, pybullet, viser or rich, from a carried scene folder, CPU against CPU (the same seed gives the
same masks), its JSON and log in the output folder; a missing carry is one line."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _device_like_site(folder: Path) -> Path:
    """A sitecustomize that makes what the GPU machine lacks unimportable (`importlib.util.find_spec` says None,
    as for an absent package)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(
        "import sys\n"
        "for n in ('open3d', 'viser', 'pybullet', 'manifold3d', 'rich', 'ray', 'pymeshlab', 'tyro', 'plotly'):\n"
        "    sys.modules[n] = None\n")
    return folder


def test_gpu_check_runs_without_open3d_and_compares_the_devices(tmp_path: Path) -> None:
    from efem_viz.data.io import load_scene, save_scene

    carry = tmp_path / "carry"
    (carry / "gpu_check").mkdir(parents=True)
    save_scene(load_scene(ROOT / "sample_scenes" / "syn_z_1.ply"), carry / "gpu_check" / "z_7000.npz")
    env = {**os.environ, "EFEM_CARRY": str(carry), "EFEM_CHECK_DEVICE": "cpu", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": str(_device_like_site(tmp_path / "site"))}
    out = tmp_path / "out"
    run = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), str(out), "--scenes", "z_7000",
                          "--proposals", "8", "--repeats", "2", "--threads", "1"],
                         env=env, capture_output=True, text=True, timeout=1800, cwd=tmp_path)
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    rec = json.loads((out / "gpu_check.json").read_text())
    row = rec["scenes"]["z_7000"]
    assert rec["machine"]["device"] == "cpu" and rec["proposals"] == 8 and rec["agree"] == 1
    assert row["mask_iou_cpu_to_device"] == 1.0 and row["max_confidence_gap"] == 0.0
    assert row["instances"]["cpu"] == row["instances"]["device"] and row["ap50"]["cpu"] == row["ap50"]["device"]
    assert row["cpu_phases"] and row["device_phases"]
    log = (out / "gpu_check.log").read_text()
    assert "1 of 1 scenes with the same masks" in log and "undecimated" in log
    missing = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), str(tmp_path / "none")],
                             env={**env, "EFEM_CARRY": str(tmp_path / "nothing")}, capture_output=True, text=True,
                             timeout=60)
    assert missing.returncode == 1 and missing.stderr.count("\n") == 1 and "--prepare" in missing.stderr
    assert not (tmp_path / "none").exists()
