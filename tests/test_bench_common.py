"""The benches as a package (`bench/`): every bench imports as ``bench.NAME`` (what ``python -m bench.NAME`` runs), and
`bench.common` writes results where docs/BENCHMARKS.md says, keeping the record a new run replaces."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCHES = sorted(p.stem for p in (ROOT / "bench").glob("*.py") if p.stem not in ("__init__", "common"))


def test_every_bench_imports_as_a_module_of_the_package() -> None:
    assert len(BENCHES) >= 20
    code = "import importlib, sys\nfor n in sys.argv[1:]:\n    importlib.import_module('bench.' + n)\nprint('ok')"
    out = subprocess.run([sys.executable, "-c", code, *BENCHES], cwd=ROOT, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_results_go_to_one_folder_per_bench(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT))
    try:
        from bench.common import RESULTS, result_path, write_result
    finally:
        sys.path.remove(str(ROOT))
    assert result_path("real") == RESULTS / "real" / "latest.json"
    assert result_path("real", "fs_final") == RESULTS / "real" / "real_fs_final.json"
    # every record in the folder belongs to a bench that exists
    for folder in RESULTS.iterdir():
        assert folder.is_dir() and folder.name in BENCHES, folder

    latest = tmp_path / "speed" / "latest.json"
    write_result(latest, {"run": 1, "median": np.float32(2.5), "rows": np.arange(3)})
    assert json.loads(latest.read_text()) == {"run": 1, "median": 2.5, "rows": [0, 1, 2]}
    day = "2026-12-01"
    stamp = time.mktime(time.strptime(day + " 12", "%Y-%m-%d %H"))
    os.utime(latest, (stamp, stamp))
    write_result(latest, {"run": 2})  # the first run is kept, named by its date
    archived = tmp_path / "speed" / f"speed_{day}.json"
    assert json.loads(archived.read_text())["run"] == 1 and json.loads(latest.read_text()) == {"run": 2}
    os.utime(latest, (stamp, stamp))
    write_result(latest, {"run": 3})  # a second run of the same day: kept too, the first not overwritten
    second = tmp_path / "speed" / f"speed_{day}_2.json"
    assert json.loads(archived.read_text())["run"] == 1 and json.loads(second.read_text())["run"] == 2
    write_result(latest, {"run": 4}, archive=False)  # a bench that updates sections of its record in place
    assert json.loads(latest.read_text()) == {"run": 4}
    assert sorted(p.name for p in latest.parent.iterdir()) == ["latest.json", f"speed_{day}.json", second.name]


def test_gemm_ceiling_is_per_thread_tiles_and_leaves_the_thread_setting_alone() -> None:
    """The speed bench's ceiling at T threads is T one-thread tiles (the decoder runs one tile per thread); the
    measurement runs on one thread and gives the caller's thread count back, even when it is interrupted."""
    code = (
        "import torch, bench.speed as s\n"
        "torch.set_num_threads(2)\n"
        "seen = []\n"
        "real = torch.nn.functional.linear\n"
        "def spy(*a):\n"
        "    seen.append(torch.get_num_threads())\n"
        "    if len(seen) > 5: raise KeyboardInterrupt\n"
        "    return real(*a)\n"
        "torch.nn.functional.linear = spy\n"
        "try:\n"
        "    s.gemm_peak(32, rows=64)\n"
        "except KeyboardInterrupt:\n"
        "    pass\n"
        "torch.nn.functional.linear = real\n"
        "assert set(seen) == {1}, seen\n"
        "assert torch.get_num_threads() == 2\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_family_scenes_are_also_scored_class_agnostic() -> None:
    """`bench.em`'s class-agnostic measure of a family's scenes (every run path records it): two objects found
    with exact masks but each named the other's member score AP50 0 per member and 1 class-agnostic."""
    import dataclasses

    sys.path.insert(0, str(ROOT))
    try:
        from bench.em import agnostic_prediction, agnostic_truth
    finally:
        sys.path.remove(str(ROOT))
    from efem_viz.em.results import Instances
    from efem_viz.eval import SceneGroundTruth, evaluate

    inst_ids = np.repeat([0, 1, 2, 0], 300)  # objects large enough to count (the evaluation's minimum size)
    gt = SceneGroundTruth(name="s", instance=inst_ids, categories={1: "mug", 2: "can"})
    found = dataclasses.replace(Instances.empty(), ids=np.array([1, 2]),
                                masks=[np.arange(300, 600, dtype=np.int32), np.arange(600, 900, dtype=np.int32)],
                                confidence=np.array([0.9, 0.8]), category=np.array(["can", "mug"]))

    class Result:
        instances = found

    from efem_viz.eval import prediction_from_instances

    named = prediction_from_instances(found, name="s", class_names=("mug", "can"))
    assert evaluate([named], [gt], class_names=("mug", "can")).ap50 == 0.0
    any_gt = agnostic_truth(gt)
    assert set(any_gt.categories.values()) == {"object"} and gt.categories[1] == "mug"  # the input is not changed
    ev = evaluate([agnostic_prediction(Result(), "s")], [any_gt], class_names=("object",))
    assert ev.ap50 == 1.0
