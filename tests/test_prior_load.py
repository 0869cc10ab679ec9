"""Loading priors and checkpoints safely: plain files load, code-carrying pickles are refused, corrupt files
give a clear error (never a raw unpickling traceback)."""

from __future__ import annotations

import argparse
import dataclasses
import resource
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from efem_viz.prior.model import (
    MAX_PRIOR_BLOCKS,
    MAX_PRIOR_PARAMETERS,
    PriorConfig,
    ShapePrior,
    count_parameters,
    load_prior,
    read_checkpoint,
    save_prior,
)

sys.path.insert(0, str(Path(__file__).parent))
from helpers import expanded_prior  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

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


# ---------------------------------------------------------------------------- hostile priors
def _limit_memory(mb: int) -> object:
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (mb << 20, mb << 20))

    return preexec


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="address-space limit (RLIMIT_AS) is Linux-only")
def test_a_tiny_file_declaring_a_huge_decoder_is_refused_by_the_cli(tmp_path: Path) -> None:
    """A few KB declaring a 20,000-wide decoder (billions of weights as zero-stride views) through `segment
    --prior`: one error line, under a 2 GB address-space limit (the loader once took 6.4 GiB on such a file)."""
    from efem_viz.data.io import save_scene
    from efem_viz.prior.analytic import make_sphere_scene

    cfg = dataclasses.replace(PriorConfig(), decoder_hidden=20_000)
    bad = expanded_prior(tmp_path / "hostile.pt", cfg)
    assert bad.stat().st_size < 64_000
    sp = save_scene(make_sphere_scene(seed=1, radii=(0.05,)), tmp_path / "one.npz")
    r = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(sp), "--prior", str(bad),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT,
                       timeout=300, preexec_fn=_limit_memory(2048))  # timeout: a hang guard only
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "declares" in lines[0] and f"{MAX_PRIOR_PARAMETERS:,}" in lines[0] and str(bad) in lines[0]
    assert "Traceback" not in r.stderr + r.stdout
    assert not list((tmp_path / "out").rglob("*.efem.npz"))


def test_weights_stored_as_views_are_refused_even_at_a_plausible_size(tmp_path: Path) -> None:
    """The declared count may be small; each stored tensor must still own exactly its bytes."""
    bad = expanded_prior(tmp_path / "views.pt", TINY)
    with pytest.raises(ValueError, match="stored as a view of 4 bytes"):
        load_prior(bad)


def test_a_weight_sliced_from_a_larger_storage_is_refused(tmp_path: Path) -> None:
    p = _saved(tmp_path)
    ckpt = torch.load(p, weights_only=True)
    key = "decoder.fc_out.bias"
    ckpt["state_dict"][key] = torch.zeros(1000)[:1]  # right shape and values, 4,000 stored bytes
    bad = tmp_path / "sliced.pt"
    torch.save(ckpt, bad)
    with pytest.raises(ValueError, match=f"{key}.*4,000 bytes"):
        load_prior(bad)


def test_parameter_and_block_bounds_are_checked_from_the_config(tmp_path: Path) -> None:
    deep = dataclasses.replace(TINY, decoder_blocks=MAX_PRIOR_BLOCKS + 1)
    ckpt = torch.load(_saved(tmp_path), weights_only=True)
    ckpt["config"] = deep.to_dict()
    bad = tmp_path / "deep.pt"
    torch.save(ckpt, bad)
    with pytest.raises(ValueError, match=f"at most {MAX_PRIOR_BLOCKS}"):
        load_prior(bad)
    # the bound is generous: the shipped prior is far below it, and it loads
    shipped = load_prior("mug", load_codebook=False)
    assert count_parameters(shipped) < MAX_PRIOR_PARAMETERS // 10


def test_a_small_prior_file_whose_records_inflate_to_gigabytes_is_refused_before_loading(tmp_path: Path) -> None:
    """the shipped prior plus a DEFLATE-compressed 1.5 GiB record, a few MB on disk, was
    inflated before any check. The zip directory is read first: one line, under a 2 GB address-space limit."""
    import shutil
    import zipfile

    from efem_viz.prior.model import MAX_CHECKPOINT_BYTES, WEIGHTS_DIR

    bad = tmp_path / "inflating.pt"
    shutil.copyfile(WEIGHTS_DIR / "mug.pt", bad)
    with zipfile.ZipFile(bad, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        name = zf.namelist()[0].split("/")[0] + "/data/99999"
        with zf.open(name, "w", force_zip64=True) as fh:
            chunk = bytes(64 << 20)
            for _ in range(24):  # 1.5 GiB of zeros
                fh.write(chunk)
    assert bad.stat().st_size < 20 << 20 and MAX_CHECKPOINT_BYTES < 24 * (64 << 20)
    from efem_viz.data.io import save_scene
    from efem_viz.prior.analytic import make_sphere_scene

    sp = save_scene(make_sphere_scene(seed=1, radii=(0.05,)), tmp_path / "one.npz")
    r = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(sp), "--prior", str(bad),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       preexec_fn=_limit_memory(2048))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "declare" in lines[0] and str(bad) in lines[0] and "refused before loading" in lines[0]


def test_the_shipped_kitchen_prior_names_its_members() -> None:
    """The shipped kitchen prior (one prior over mugs, bowls, bottles and cans) loads with the codebook built
    from its own weights, whose entries are classed by member, its calibrated mask band and its category."""
    from efem_viz.prior.model import WEIGHTS_DIR, load_prior

    if not (WEIGHTS_DIR / "kitchen.pt").is_file():
        pytest.skip("no shipped kitchen prior in this checkout")
    prior = load_prior("kitchen")
    cb = prior.codebook
    assert cb is not None and cb.matches(prior)
    assert cb.classes == ["mug", "bowl", "bottle", "can"]
    assert set(cb.class_id.tolist()) == {0, 1, 2, 3}
    assert prior.category.name == "kitchen" and 0.0 < prior.category.out_tau <= 0.2
