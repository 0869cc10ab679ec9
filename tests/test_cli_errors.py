"""Damaged `<scene>.efem.npz` files and bad CLI arguments: a ValueError naming the file on load, and one line on
stderr (never a traceback unless `--debug`) from `efem-viz evaluate` / `calibrate-masks` and `efem-annotate`.

The results come from a bundled sample (`sample_scenes/syn_pile_0.efem.npz`, copied and damaged in tmp_path), so
no test here runs EM. Most cases call `efem_viz.cli.main` in-process; a few run the real console
entry in a subprocess to show what a user sees.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from efem_viz.em.results import REQUIRED_RESULT_KEYS, EMResult, ResultFileError

REPO = Path(__file__).resolve().parents[1]
SAMPLE = "syn_pile_0"
"""The smallest bundled scene with a saved result (19,656 points)."""


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The sample result's arrays, its ground truth saved as a fast-loading .npz, and its point count."""
    from efem_viz.data.io import load_scene, save_scene

    base = tmp_path_factory.mktemp("sample")
    scene = load_scene(REPO / "sample_scenes" / f"{SAMPLE}.ply")
    assert scene.instance is not None
    gt = save_scene(scene, base / "gt" / f"{SAMPLE}.npz")
    with np.load(REPO / "sample_scenes" / f"{SAMPLE}.efem.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return {"arrays": arrays, "gt": gt, "n": scene.num_points}


def write_result(folder: Path, arrays: dict[str, np.ndarray], damage: Callable[[dict[str, np.ndarray]], None]) -> Path:
    """`<folder>/syn_pile_0.efem.npz` holding the sample's arrays after `damage(arrays)` (on a copy)."""
    data = dict(arrays)
    damage(data)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{SAMPLE}.efem.npz"
    np.savez(path, **data)  # type: ignore[arg-type]
    return path


def drop(key: str) -> Callable[[dict[str, np.ndarray]], None]:
    def go(d: dict[str, np.ndarray]) -> None:
        del d[key]
    return go


def setter(key: str, value: Any) -> Callable[[dict[str, np.ndarray]], None]:
    return lambda d: d.__setitem__(key, np.asarray(value))


def edit(key: str, fn: Callable[[np.ndarray], None]) -> Callable[[dict[str, np.ndarray]], None]:
    """Damage a copy of one array in place with `fn`."""
    def go(d: dict[str, np.ndarray]) -> None:
        a = np.array(d[key])
        fn(a)
        d[key] = a
    return go


def nan_first_confidence(a: np.ndarray) -> None:
    a[0] = np.nan


def mask_index_at_num_points(n: int) -> Callable[[np.ndarray], None]:
    def go(a: np.ndarray) -> None:
        a[3] = n
    return go


def negative_mask_index(a: np.ndarray) -> None:
    a[0] = -1


def wrong_num_points(n: int) -> Callable[[dict[str, np.ndarray]], None]:
    """A self-consistent file computed on n points (masks still in range): only the ground truth can catch it."""
    def go(d: dict[str, np.ndarray]) -> None:
        d["num_points"] = np.array(n, np.int64)
        d["trace/num_points"] = np.array(n, np.int64)
    return go


def damages(n: int) -> dict[str, tuple[Callable[[dict[str, np.ndarray]], None], str]]:
    """Case name -> (damage, a regex the error message must match)."""
    return {
        "no config_json": (drop("config_json"), "config_json"),
        "no num_points": (drop("num_points"), "num_points"),
        "no schema_version": (drop("schema_version"), "schema_version"),
        "no masks": (drop("instances/masks"), "instances/masks"),
        "no mask offsets": (drop("instances/masks_offsets"), "instances/masks_offsets"),
        "no trace config": (drop("trace/config_json"), "trace/config_json"),
        "unknown schema": (setter("schema_version", np.int32(99)), "schema_version 99"),
        "nan confidence": (edit("instances/confidence", nan_first_confidence), "confidence nan"),
        "confidence > 1": (edit("instances/confidence", lambda a: a.__setitem__(1, 1.5)), "confidence 1.5"),
        "mask index = num_points": (edit("instances/masks", mask_index_at_num_points(n)), "outside"),
        "negative mask index": (edit("instances/masks", negative_mask_index), "outside"),
        "num_points vs trace": (setter("num_points", np.int64(n + 7)), "disagrees"),
        "short confidence": (lambda d: d.__setitem__("instances/confidence", d["instances/confidence"][:-1]),
                             "instances/confidence must be"),
        "bad offsets": (edit("instances/masks_offsets", lambda a: a.__setitem__(-1, a[-1] + 5)), "offsets"),
        "face index": (edit("instances/mesh_faces", lambda a: a.__setitem__((0, 0), 10**6)), "mesh_faces"),
        "proposal id": (edit("instances/ids", lambda a: a.__setitem__(0, 10**6)), "proposal ids"),
        "config not json": (setter("config_json", "{not json"), "config_json"),
        "float num_points": (setter("num_points", 1.5), "num_points must be one integer"),
    }


# ---------------------------------------------------------------------------------------------- EMResult.load
def test_the_sample_result_loads_unchanged(sample: dict[str, Any], tmp_path: Path) -> None:
    path = write_result(tmp_path, sample["arrays"], lambda d: None)
    res = EMResult.load(path)
    assert res.num_points == sample["n"] and len(res.instances) == len(sample["arrays"]["instances/ids"])


def test_load_refuses_each_damage_naming_the_file(sample: dict[str, Any], tmp_path: Path) -> None:
    for i, (case, (damage, pattern)) in enumerate(damages(sample["n"]).items()):
        path = write_result(tmp_path / f"c{i}", sample["arrays"], damage)
        with pytest.raises(ResultFileError) as info:
            EMResult.load(path)
        msg = str(info.value)
        assert str(path) in msg and "\n" not in msg, case
        assert re.search(pattern, msg), f"{case}: {msg}"
        assert isinstance(info.value, ValueError)


def test_load_refuses_every_missing_required_key(sample: dict[str, Any], tmp_path: Path) -> None:
    assert set(REQUIRED_RESULT_KEYS) <= set(sample["arrays"]), "the writer writes every required key"
    for key in REQUIRED_RESULT_KEYS:
        path = write_result(tmp_path, sample["arrays"], drop(key))
        with pytest.raises(ValueError, match=str(path)) as info:
            EMResult.load(path)
        # the key is named, except where the file no longer says it is a result at all
        assert key in str(info.value) or (key == "kind" and "not an EFEM result" in str(info.value)), key


# ---------------------------------------------------------------------------------------------- in-process CLI
def one_error_line(capsys: pytest.CaptureFixture[str], prog: str) -> str:
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


@pytest.mark.parametrize("command", ["evaluate", "calibrate-masks"])
def test_cli_refuses_damaged_results_in_one_line(command: str, sample: dict[str, Any], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli

    n = sample["n"]
    cases = damages(n)
    cases["wrong num_points"] = (wrong_num_points(n + 3), f"{n + 3} points .* has {n}")
    cases["fewer num_points"] = (wrong_num_points(n - 1), f"{n - 1}|outside")
    for i, (case, (damage, pattern)) in enumerate(cases.items()):
        folder = tmp_path / f"c{i}"
        path = write_result(folder, sample["arrays"], damage)
        out = tmp_path / f"c{i}.json"
        before = sorted(folder.iterdir())
        rc = cli.main([command, str(folder if command == "evaluate" else path), "--gt", str(sample["gt"]),
                       "--json-out", str(out)])
        line = one_error_line(capsys, f"efem-viz {command}")
        assert rc == 1, case
        assert f"{SAMPLE}.efem.npz" in line, f"{case}: {line}"
        assert re.search(pattern, line), f"{case}: {line}"
        assert not out.exists() and sorted(folder.iterdir()) == before, f"{case}: something was written"


def test_evaluate_accepts_the_undamaged_copy(sample: dict[str, Any], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli

    folder = tmp_path / "ok"
    write_result(folder, sample["arrays"], lambda d: None)
    out = tmp_path / "ev.json"
    assert cli.main(["evaluate", str(folder), "--gt", str(sample["gt"]), "--json-out", str(out)]) == 0
    assert out.is_file()


@pytest.mark.parametrize("command", ["evaluate", "calibrate-masks"])
def test_json_out_a_folder_is_refused_before_any_work(command: str, sample: dict[str, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli

    folder = tmp_path / "res"
    write_result(folder, sample["arrays"], lambda d: None)
    target = tmp_path / "a_folder"
    target.mkdir()
    rc = cli.main([command, str(folder), "--gt", str(sample["gt"]), "--json-out", str(target)])
    line = one_error_line(capsys, f"efem-viz {command}")
    assert rc == 1 and "--json-out" in line and "folder" in line
    assert list(target.iterdir()) == [] and capsys.readouterr().out == ""


def test_missing_paths_are_one_line(sample: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli

    nope = tmp_path / "nope"
    for args in (["evaluate", str(nope), "--gt", str(sample["gt"])],
                 ["evaluate", str(tmp_path), "--gt", str(nope)],
                 ["calibrate-masks", str(nope), "--gt", str(sample["gt"])],
                 ["calibrate-masks", str(tmp_path), "--gt", str(nope / "x.ply")]):
        assert cli.main(args) == 1, args
        assert "nope" in one_error_line(capsys, f"efem-viz {args[0]}")


def test_debug_flag_reraises(sample: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from efem_viz import cli

    folder = tmp_path / "res"
    write_result(folder, sample["arrays"], drop("config_json"))
    args = [str(folder), "--gt", str(sample["gt"])]
    with pytest.raises(ResultFileError, match="config_json"):
        cli.main(["--debug", "evaluate", *args])
    with pytest.raises(ResultFileError):
        cli.main(["evaluate", *args, "--debug"])  # after the subcommand too
    monkeypatch.setenv("EFEM_DEBUG", "1")
    with pytest.raises(ResultFileError):
        cli.main(["evaluate", *args])
    monkeypatch.setenv("EFEM_DEBUG", "0")
    assert cli.main(["evaluate", *args]) == 1


def test_run_reporting_errors_classes(capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz.cli import EXIT_INTERRUPTED, run_reporting_errors

    def raiser(exc: BaseException) -> Callable[[], int]:
        def go() -> int:
            raise exc
        return go

    cases: list[tuple[BaseException, int, str]] = [
        (IsADirectoryError(21, "Is a directory", "/x/out.json"), 1, "p: error: Is a directory: /x/out.json"),
        (KeyError("config_json"), 1, "p: error: missing key 'config_json'"),
        (ValueError("two\n  lines"), 1, "p: error: two lines"),
        (FileNotFoundError("scene not found: a.ply"), 1, "p: error: scene not found: a.ply"),
        (ModuleNotFoundError("No module named 'viser'"), 1, "p: error: No module named 'viser'"),
        (KeyboardInterrupt(), EXIT_INTERRUPTED, "p: interrupted"),
        (RuntimeError("boom"), 1, "p: internal error: RuntimeError: boom (rerun with --debug for the traceback)"),
    ]
    for exc, rc, line in cases:
        assert run_reporting_errors("p", raiser(exc)) == rc
        assert capsys.readouterr().err == line + "\n"
        with pytest.raises(type(exc)):
            run_reporting_errors("p", raiser(exc), debug=True)
    with pytest.raises(SystemExit):  # tyro's argument errors and --help pass through
        run_reporting_errors("p", raiser(SystemExit(2)))
    assert run_reporting_errors("p", lambda: None) == 0


def test_annotator_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from annotator.__main__ import main  # viser is a dependency: an import error fails here, it does not skip

    missing = tmp_path / "missing.ply"
    assert main([str(missing), "--port", "0"]) == 1
    assert "missing.ply" in one_error_line(capsys, "efem-annotate")
    with pytest.raises(ValueError, match="no such file"):  # LabelIOError
        main([str(missing), "--port", "0", "--debug"])


# ---------------------------------------------------------------------------------------------- real processes
def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("EFEM_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "efem_viz.cli", *args], capture_output=True, text=True, cwd=REPO,
                          env=env, timeout=120)


def test_console_errors_have_no_traceback(sample: dict[str, Any], tmp_path: Path) -> None:
    nan = write_result(tmp_path / "nan", sample["arrays"], edit("instances/confidence", nan_first_confidence))
    no_cfg = write_result(tmp_path / "nocfg", sample["arrays"], drop("config_json"))
    (tmp_path / "dir").mkdir()
    gt = str(sample["gt"])
    cases = [
        (["evaluate", str(nan.parent), "--gt", gt, "--json-out", str(tmp_path / "a.json")], "confidence nan"),
        (["calibrate-masks", str(no_cfg), "--gt", gt, "--json-out", str(tmp_path / "b.json")], "config_json"),
        (["evaluate", str(REPO / "sample_scenes"), "--gt", str(REPO / "sample_scenes" / f"{SAMPLE}.ply"),
          "--no-strict", "--json-out", str(tmp_path / "dir")], "--json-out"),
    ]
    for args, needle in cases:
        proc = run_cli(*args)
        lines = proc.stderr.splitlines()
        assert proc.returncode == 1 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert lines[0].startswith(f"efem-viz {args[0]}: error: ") and needle in lines[0], proc.stderr
    assert (sorted(p.name for p in tmp_path.iterdir()) == ["dir", "nan", "nocfg"]
            and not any((tmp_path / "dir").iterdir()))
    proc = run_cli("--debug", "calibrate-masks", str(no_cfg), "--gt", gt)
    assert proc.returncode == 1 and "Traceback" in proc.stderr and "ResultFileError" in proc.stderr


def test_version_flag(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    from efem_viz.cli import main

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"efem-viz {version('efem-viz')}"


# ----------------------------------------------------------------------------------------------
def test_view_refuses_what_it_cannot_show_before_serving(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """`efem-viz view corrupt.ply` (and a folder without scenes, a scene over --max-points) says why in one line and
    exits 1 without starting a server (it used to serve "(1 scenes)" and only log a warning)."""
    from efem_viz import cli
    from efem_viz.data.io import save_scene
    from efem_viz.viewer import app as viewer_app

    started: list[object] = []

    def no_server(*args: object, **kwargs: object) -> None:
        started.append(args)
        raise AssertionError("a server was started")

    monkeypatch.setattr(viewer_app.ViewerApp, "__init__", no_server)
    corrupt = tmp_path / "corrupt.ply"
    corrupt.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
                        b"end_header\n\x00")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no scenes here\n")
    big = tmp_path / "big"
    big.mkdir()
    import trimesh

    from efem_viz.data.scene import Scene

    save_scene(Scene.create("ball", trimesh.creation.icosphere(subdivisions=2).vertices), big / "ball.ply")
    for args, needle in (([str(corrupt)], "corrupt.ply"), ([str(empty)], "no scene files"),
                         ([str(big / "ball.ply"), "--max-points", "100"], "--max-points")):
        assert cli.main(["view", *args, "--port", "0"]) == 1, args
        assert needle in one_error_line(capsys, "efem-viz view"), args
    assert started == []


def test_efem_annotate_version(capsys: pytest.CaptureFixture[str]) -> None:
    """`efem-annotate --version` prints the version (it said "Missing value for argument 'scan'")."""
    from importlib.metadata import version

    from annotator.__main__ import main

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"efem-annotate {version('efem-viz')}"


def test_the_point_limit_message_names_the_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A scan over the limit is refused with the option that raises it, `--max-points` (the message said "raise
    max_points"), from every reader."""
    import trimesh

    from annotator.__main__ import main
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.data.scene import Scene, SceneError

    m = trimesh.creation.icosphere(subdivisions=2)  # 162 vertices
    scene = Scene.create("ball", m.vertices, faces=m.faces)
    paths = [save_scene(scene, tmp_path / f"ball.{ext}") for ext in ("ply", "npz", "obj", "off", "glb")]
    for p in paths:
        with pytest.raises(SceneError) as info:
            load_scene(p, max_points=100)
        assert "--max-points" in str(info.value) and "raise max_points" not in str(info.value), (p, info.value)
    with pytest.raises(SceneError, match="--max-points"):
        Scene.create("ball", m.vertices, max_points=100)
    assert main([str(paths[0]), "--max-points", "100", "--port", "0", "--out", str(tmp_path / "o")]) == 1
    line = one_error_line(capsys, "efem-annotate")
    assert "more than the limit of 100" in line and "--max-points" in line


def test_info_calls_a_segment_outputs_labels_predictions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`efem-viz info` on `<scene>.seg.ply` (segment's output, its `instance` = predictions) says "predicted
    instances", never "ground truth"; its JSON says no ground truth. A scene with real labels still says ground
    truth."""
    import json

    import trimesh

    from efem_viz import cli
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene

    m = trimesh.creation.icosphere(subdivisions=2)
    labels = (np.arange(len(m.vertices)) % 3).astype(np.int32)
    scene = Scene.create("ball", m.vertices, faces=m.faces, instance=labels, categories={1: "mug", 2: "mug"})
    seg = save_scene(scene, tmp_path / "ball.seg.ply")
    gt = save_scene(scene, tmp_path / "gt" / "ball.ply")
    assert cli.main(["info", str(seg)]) == 0
    out = capsys.readouterr().out
    assert "predicted instances" in out and "ground truth" not in out, out
    assert cli.main(["info", str(seg), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["has_ground_truth"] is False and summary["labels"].startswith("predicted")
    assert cli.main(["info", str(gt)]) == 0
    out = capsys.readouterr().out
    assert "ground truth" in out and "predicted" not in out


BAD_OPTIONS = {
    # option: (value for efem-viz view, value for efem-annotate, what the one line says)
    "--port": ("99999", "-1", "--port must be 0-65535"),
    "--device": ("cuda", "cuda", "CUDA is not available on this machine"),
}


@pytest.mark.parametrize("option", sorted(BAD_OPTIONS))
@pytest.mark.parametrize("prog", ["efem-viz", "efem-annotate"])
def test_a_bad_option_is_one_line_and_exit_2_before_anything_starts(prog: str, option: str, tmp_path: Path) -> None:
    """`--port 99999` printed viser's traceback from its server thread and then hung; `--device cuda` on a machine
    without CUDA (skipped where CUDA exists) names the choices. Each is one line, exit 2, before a scene or scan is
    read."""
    if option == "--device":
        import torch

        if torch.cuda.is_available():
            pytest.skip("this machine has CUDA")
    view_value, annotate_value, says = BAD_OPTIONS[option]
    if prog == "efem-viz":
        cmd = [sys.executable, "-m", "efem_viz.cli", "view", str(REPO / "sample_scenes"), option, view_value]
    else:
        cmd = [sys.executable, "-m", "annotator", str(REPO / "sample_scenes" / "real_tabletop_8.ply"),
               option, annotate_value, "--out", str(tmp_path / "ann")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert says in lines[0] and lines[0].startswith(f"{prog}") and "error:" in lines[0]
    assert not (tmp_path / "ann").exists()  # nothing was started or written


def test_info_summarises_and_escapes_what_a_file_says(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """and `info` summarises by default (--full for every provenance entry),
    prints a scene's own strings inert (no raw terminal escapes, no rich markup), and points from a result file
    to its scene."""
    from efem_viz import cli
    from efem_viz.data.io import load_scene, save_scene

    scene = load_scene(REPO / "sample_scenes" / "real_tabletop_8.ply")
    evil = "\x1b[2J\x1b]0;owned\x07[bold red]fake[/bold red]\nsecond line"
    path = save_scene(scene.replace(provenance={**dict(scene.provenance), "note": evil}), tmp_path / "s.ply")
    assert cli.main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\n second" not in out
    assert "\\x1b[2J" in out and "red]fake[/bold red]" in out  # shown inert, the markup literal (cells may wrap)
    assert "T_world_camera" not in out and "capture camera" in out and "--full" in out
    assert cli.main(["info", str(path), "--full"]) == 0
    assert "T_world_camera" in capsys.readouterr().out
    # a fused scan's camera list: how many can check free space, and what is wrong with the others
    prov = {k: v for k, v in dict(scene.provenance).items() if k not in ("K", "T_world_camera", "image_size")}
    cam = {k: scene.provenance[k] for k in ("K", "T_world_camera", "image_size")}
    fused = save_scene(scene.replace(provenance={**prov, "cameras": [cam, {**cam, "K": [[1]]}, cam]}),
                       tmp_path / "fused.ply")
    assert cli.main(["info", str(fused)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "2 recorded" in out and "1 unusable: camera 2 of 3" in out
    proc = run_cli("info", str(REPO / "sample_scenes" / "real_tabletop_6.efem.npz"))
    assert proc.returncode == 1 and "real_tabletop_6.ply" in proc.stderr and "instead" in proc.stderr


def test_an_unused_member_of_a_result_file_is_never_inflated(sample: dict[str, Any], tmp_path: Path) -> None:
    """a small result file with an extra, highly compressed member cost its inflated size in
    every reader. `EMResult.load` reads the format's keys only (memory measured with tracemalloc, which numpy
    reports its arrays to)."""
    import tracemalloc

    path = tmp_path / f"{SAMPLE}.efem.npz"
    np.savez_compressed(path, **sample["arrays"], junk=np.zeros(300 << 20, np.uint8))  # type: ignore[arg-type]
    assert path.stat().st_size < 20 << 20
    tracemalloc.start()
    try:
        res = EMResult.load(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(res.instances) == len(EMResult.load(REPO / "sample_scenes" / f"{SAMPLE}.efem.npz").instances)
    assert peak < 150 << 20, f"{peak / 2**20:.0f} MB traced while loading"


def _with_config(key: str, value: Any) -> Callable[[dict[str, np.ndarray]], None]:
    """Damage: the saved run's config (both copies) with ``key`` set to ``value``."""
    def go(d: dict[str, np.ndarray]) -> None:
        for k in ("config_json", "trace/config_json"):
            cfg = json.loads(str(d[k]))
            cfg[key] = value
            d[k] = np.array(json.dumps(cfg))
    return go


@pytest.mark.parametrize(("key", "value", "says"), [
    ("mesh_resolution", 600, "mesh_resolution must be in [8, 128]"),
    ("r_init", 1e309, "r_init = inf: must be float"),
    ("n_init", [100000], "at most 2000"),
])
def test_a_results_file_declaring_unbounded_work_is_refused_in_one_line(
        key: str, value: Any, says: str, sample: dict[str, Any], tmp_path: Path) -> None:
    """A results file's solver settings are bounded like a run's own (a mesh_resolution of 600 took the viewer's
    Step slider to 1.9 GB and minutes per shape): the loader and `evaluate` refuse it in one line."""
    path = write_result(tmp_path, sample["arrays"], _with_config(key, value))
    with pytest.raises(ValueError, match=re.escape(says)):
        EMResult.load(path)
    proc = run_cli("evaluate", str(path.parent), "--gt", str(sample["gt"]))
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert proc.returncode == 1 and len(errors) == 1 and says in errors[0], proc.stderr[-2000:]


def test_segment_refuses_more_proposals_than_it_can_hold_before_any_work(tmp_path: Path) -> None:
    proc = run_cli("segment", str(REPO / "sample_scenes" / f"{SAMPLE}.ply"), "--proposals", "20000", "--out",
                   str(tmp_path / "out"))
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert proc.returncode in (1, 2) and len(errors) == 1 and "at most 2000" in errors[0], proc.stderr[-2000:]
    assert not (tmp_path / "out" / f"{SAMPLE}.efem.npz").exists()


def test_segment_names_the_valid_priors_and_an_empty_call_says_what_to_give(tmp_path: Path) -> None:
    """A prior typo is one line that lists the valid names, before any scene work or display (no blank line
    first); a call without scenes says what to give instead of "no scene files found in []"."""
    proc = run_cli("segment", str(REPO / "sample_scenes" / f"{SAMPLE}.ply"), "--prior", "mugg", "--out",
                   str(tmp_path / "o"))
    assert proc.returncode == 1 and proc.stdout == "", proc.stdout
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "unknown shape prior 'mugg'" in lines[0] and "mug, sphere" in lines[0], lines
    assert not (tmp_path / "o").exists()
    empty = run_cli("segment")
    assert empty.returncode == 1 and empty.stdout == ""
    assert empty.stderr.strip() == ("efem-viz segment: error: no scenes given: name scene files (.ply, .obj, .off, "
                                    ".glb, .npz, .pcd, .las, .laz) or folders of them")  # the format table's order


def test_tables_written_to_a_file_keep_long_paths_whole(tmp_path: Path) -> None:
    """Output to a file or pipe was cut at rich's 80 columns (paths truncated with "…", rows wrapped): tables
    written there are 200 columns wide unless COLUMNS says otherwise."""
    import shutil

    deep = tmp_path / ("a_rather_long_folder_name_for_scans_" * 2) / "another_level_of_folders"
    deep.mkdir(parents=True)
    scene = shutil.copy(REPO / "sample_scenes" / f"{SAMPLE}.ply", deep / f"{SAMPLE}.ply")
    proc = run_cli("segment", str(scene), "--prior", "sphere", "--preset", "fast", "--proposals", "8", "--out",
                   str(deep / "out"), "--no-scannet", "--no-ply")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert str(deep / "out" / "batch.json") in proc.stdout and "…" not in proc.stdout, proc.stdout
