"""Loading priors and checkpoints safely: plain files load, code-carrying pickles are refused, corrupt files
give a clear error (never a raw unpickling traceback)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import torch

from efem_viz.prior.model import PriorConfig, ShapePrior, load_prior, read_checkpoint, save_prior

TINY = PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16, center_hidden=8,
                   n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=1)


def _saved(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    return save_prior(ShapePrior(TINY, name="tiny"), tmp_path / "tiny.pt", extra={"tau_out": 0.07})


def test_saved_prior_loads_without_unpickling(tmp_path: Path) -> None:
    p = _saved(tmp_path)
    raw = torch.load(p, weights_only=True)  # the format needs nothing beyond tensors and containers
    assert raw["metadata"]["tau_out"] == 0.07
    assert load_prior(p).metadata["tau_out"] == 0.07


def test_code_carrying_pickle_is_refused_unless_allowed(tmp_path: Path) -> None:
    p = _saved(tmp_path)
    ckpt = torch.load(p, weights_only=True)
    ckpt["extra"] = argparse.Namespace(a=1)  # a class outside the weights-only allowlist
    bad = tmp_path / "pickled.pt"
    torch.save(ckpt, bad)
    with pytest.raises(ValueError, match="full unpickle.*allow_pickle"):
        load_prior(bad)
    assert load_prior(bad, allow_pickle=True).metadata["tau_out"] == 0.07


@pytest.mark.parametrize("content", [b"", b"garbage" * 10, b"PK\x03\x04truncated zip"])
def test_corrupt_files_give_a_clear_error(tmp_path: Path, content: bytes) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(content)
    with pytest.raises(ValueError, match="not a readable torch checkpoint"):
        read_checkpoint(bad)
    with pytest.raises(ValueError, match="not a readable torch checkpoint"):
        load_prior(bad)


def test_corrupt_prior_through_the_cli_is_an_error_message(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz import cli
    from efem_viz.data.io import save_scene
    from efem_viz.prior.analytic import make_sphere_scene

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 64)
    sp = save_scene(make_sphere_scene(seed=1, radii=(0.05,)), tmp_path / "one.npz")
    assert cli.main(["segment", str(sp), "--prior", str(bad), "--out", str(tmp_path / "out")]) == 1
    assert "not a readable torch checkpoint" in capsys.readouterr().err
