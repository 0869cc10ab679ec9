"""`bench.snapshots`: a run's snapshots found, calibrated with their own validation's offset, given a codebook;
bad requests refused with one line before any work."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from efem_viz.prior.model import load_prior
from efem_viz.prior.train import TrainArgs, train

from helpers import ROOT, bench_module


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny mug run of 4 iterations, validated and snapshotted every 2, on sensor inputs too."""
    tmp = tmp_path_factory.mktemp("snaps")
    args = TrainArgs(preset="tiny", n_train=3, n_val=2, out_dir=tmp / "run", export=tmp / "w" / "mug.pt",
                     cache_dir=tmp / "cache", batch_size=4, iterations=4, val_every=2, snapshot_every=2, threads=1,
                     progress=False, lr=1e-3, sensor_p=0.5)
    train(args)
    return Path(args.out_dir)


def test_snapshots_are_found_with_their_validations_and_sensor_offsets(run_dir: Path) -> None:
    mod = bench_module("snapshots")
    snaps = mod.snapshots(run_dir)
    assert list(snaps) == [2, 4]
    curve = mod.val_curve(run_dir)
    assert {2, 4} <= set(curve)
    v = dict(curve[2], iso_offset=0.0, sensor_iso_offset=0.0125, iou_cal=0.1, sensor_iou_cal=0.2)
    assert mod.calibrated(v) == (0.0125, 0.2)  # the run validated on sensor inputs: selected by them
    assert mod.calibrated({"iso_offset": -0.005, "iou_cal": 0.3}) == (-0.005, 0.3)


def test_a_prepared_snapshot_has_the_offset_folded_in_and_its_own_codebook(run_dir: Path, tmp_path: Path) -> None:
    mod = bench_module("snapshots")
    snap = mod.snapshots(run_dir)[2]
    path = mod.prepare(snap, 0.02, "mug", tmp_path / "snap_2", count=3, n_store=12)
    before, after = load_prior(snap, load_codebook=False), load_prior(path)
    assert after.codebook is not None and path.with_name("mug_codebook.npz").is_file()
    assert after.metadata["iso_offset"] == 0.02 and after.metadata["iteration"] == 2
    torch.manual_seed(0)
    pts = torch.rand(1, 64, 3) - 0.5
    q = torch.rand(1, 50, 3) - 0.5
    with torch.no_grad():
        lat = before.encode(pts)
        d0 = before.sdf(q, lat).numpy()
        d1 = after.sdf(q, lat).numpy()
    np.testing.assert_allclose(d1, d0 - 0.02, atol=2e-3)  # half precision storage


@pytest.mark.parametrize(("extra", "says"), [
    (["--seed0", "7000"], "fixed test set"),
    (["--seed0", "6995"], "fixed test set"),
    (["--iterations", "3"], "no snapshot at iteration [3]"),
])
def test_bad_requests_are_one_line_before_any_work(run_dir: Path, extra: list[str], says: str) -> None:
    r = subprocess.run([sys.executable, "-m", "bench.snapshots", str(run_dir), "--category", "mug", *extra],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and says in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (run_dir / "snapshot_scenes").exists()
