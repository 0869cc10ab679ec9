"""Converter of the authors' released EFEM checkpoints (efem_viz.prior.convert, docs/design/efem-method.md §1.7).

Small random priors are written in the released layout (``network_dict.encoder.``/``network_dict.decoder.`` keys
inside ``{"model_state_dict", "optimizers_state_dict", "epoch", "batch"}``), converted, loaded with ``load_prior``
and compared in float64 with the original model and with a naive channels-first re-implementation of the
released forward pass that reads the released tensors by their released names.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from efem_viz import cli
from efem_viz.prior.convert import (
    convert_released_checkpoint,
    infer_released_config,
    map_released_keys,
    release_from_filename,
)
from efem_viz.prior.model import PickleRequired, PriorConfig, ShapePrior, load_prior

TINY: dict[str, Any] = {"widths": (8, 8, 16, 16), "down_blocks": (2,), "down_factors": (2,), "latent_dim": 16,
                        "center_hidden": 8, "n_pcl": 64, "k": 8, "decoder_hidden": 32, "decoder_blocks": 2}
TINY_ATT: dict[str, Any] = {**TINY, "widths": (8, 8, 32, 32), "attention_blocks": (2, 3)}  # 2 heads of 16
TINY_KW: dict[str, Any] = {"down_blocks": (2,), "down_factors": (2,), "n_pcl": 64, "k": 8, "check": False}


def random_prior(cfg: dict[str, Any], seed: int = 0) -> ShapePrior:
    """A float32 prior with every parameter random (also the zero-initialised decoder fc_1)."""
    torch.manual_seed(seed)
    prior = ShapePrior(PriorConfig(**cfg), name="orig")
    with torch.no_grad():
        for p in prior.parameters():
            p.uniform_(-1.0, 1.0).mul_(1.5 / math.sqrt(p.shape[-1]))
    return prior.eval()


def released_dict(prior: ShapePrior) -> dict[str, Any]:
    """The model in the released file layout."""
    state = {f"network_dict.{k}": v.detach().clone() for k, v in prior.state_dict().items()}
    return {"model_state_dict": state, "optimizers_state_dict": {}, "epoch": 7, "batch": 1234}


def write_released(tmp_path: Path, prior: ShapePrior, name: str = "released.pt", **edit: Any) -> Path:
    ckpt = released_dict(prior)
    ckpt.update(edit)
    path = tmp_path / name
    torch.save(ckpt, path)
    return path


# ------------------------------------------------------------------------------ naive released forward pass
def _lin(w: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """VN-Linear in the spec's layout: x (..., C_in, 3) -> (..., C_out, 3)."""
    return torch.einsum("oc,...cd->...od", w, x)


def _act(sd: dict[str, torch.Tensor], pre: str, x: torch.Tensor) -> torch.Tensor:
    """VN-LeakyReLU(0.2): keep the part orthogonal to the learned direction, leaky on the parallel length."""
    kdir = _lin(sd[pre + "lin_dir.weight"], x)
    kdir = kdir / kdir.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    par = (x * kdir).sum(-1, keepdim=True)
    return x - par * kdir + torch.nn.functional.leaky_relu(par, 0.2) * kdir


def _vnla(sd: dict[str, torch.Tensor], pre: str, x: torch.Tensor) -> torch.Tensor:
    return _act(sd, pre + "act.", _lin(sd[pre + "lin.weight"], x))


def _chnorm(x: torch.Tensor) -> torch.Tensor:
    """Per-channel direction times the channel length normalised across channels (release's formula)."""
    length = x.norm(dim=-1, keepdim=True)
    return x / length.clamp_min(1e-12) * (length / length.norm(dim=-2, keepdim=True).clamp_min(1e-12))


def _fps(pos: np.ndarray, n: int) -> np.ndarray:
    sel, dist = [0], np.full(len(pos), np.inf)
    for _ in range(n - 1):
        dist = np.minimum(dist, ((pos - pos[sel[-1]]) ** 2).sum(-1))
        sel.append(int(np.argmax(dist)))
    return np.asarray(sel)


def reference_encode(sd: dict[str, torch.Tensor], cfg: PriorConfig, pts: torch.Tensor) -> dict[str, torch.Tensor]:
    """One cloud (N, 3) float64 through the released encoder, written naively (edge features concatenated)."""
    centroid = pts.mean(0)
    pos = pts - centroid
    feat = pos[:, None, :]  # (N, C=1, 3)
    down = dict(zip(cfg.down_blocks, cfg.down_factors))
    for b in range(len(cfg.widths)):
        if b in down:
            sel = torch.as_tensor(_fps(pos.numpy(), len(pos) // down[b]))
            dst, pos = feat[sel], pos[sel]
        else:
            dst = feat
        d2 = ((dst.flatten(1)[:, None, :] - feat.flatten(1)[None, :, :]) ** 2).sum(-1)
        nbr = d2.argsort(dim=1)[:, : cfg.k]
        fj = feat[nbr]  # (Nd, k, C, 3)
        fi = dst[:, None].expand_as(fj)
        if b == 0:
            xhat = fi / fi.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            edge = torch.cat([torch.cross(xhat, fj, dim=-1), fj - fi, fi], dim=-2)
        else:
            edge = torch.cat([fj - fi, fi], dim=-2)
        v = _vnla(sd, f"V_list.{b}.", edge)
        if b in cfg.attention_blocks:
            key = _chnorm(_vnla(sd, f"K_list.{b}.", edge))  # (Nd, k, C, 3)
            qry = _chnorm(_vnla(sd, f"Q_list.{b}.", dst))  # (Nd, C, 3)
            qk = (key * qry[:, None]).sum(-1)  # (Nd, k, C)
            h = cfg.att_head_dim
            logits = qk.reshape(qk.shape[0], qk.shape[1], -1, h).sum(-1) / math.sqrt(3 * h)
            att = logits.softmax(dim=1).repeat_interleave(h, dim=-1)  # (Nd, k, C)
            out = (att[..., None] * v).sum(1)
        else:
            out = v.mean(1)
        if b >= cfg.global_from:
            glob = out.mean(0, keepdim=True).expand_as(out)
            out = _vnla(sd, f"global_conv_list.{b - cfg.global_from}.", torch.cat([out, glob], dim=-2))
        feat = out
    x = _vnla(sd, "conv_c.", feat).mean(0)  # (L, 3)
    R = _chnorm(x)
    scale = x.norm(dim=-1).mean() * cfg.scale_factor
    inv = (_chnorm(_lin(sd["fc_inv.weight"], x)) * R).sum(-1)
    hid = _vnla(sd, "fc_center.fc0.", x)
    y = _lin(sd["fc_center.lin1.weight"], hid) + _lin(sd["fc_center.shortcut.weight"], x)
    delta = _act(sd, "fc_center.act2.", y)[0]
    if cfg.center_times_sigma:
        delta = delta * cfg.scale_factor
    return {"R": R, "inv": inv, "center": centroid + delta, "scale": scale}


def reference_sdf(sd: dict[str, torch.Tensor], n_blocks: int, lat: dict[str, torch.Tensor],
                  x: torch.Tensor) -> torch.Tensor:
    """Released decoder: φ = [Θ_R q ; ‖q‖ ; Θ_inv] through fc_in, pre-activation ReLU blocks, fc_out."""
    relu = torch.relu
    q = (x - lat["center"]) / lat["scale"]
    phi = torch.cat([q @ lat["R"].T, q.norm(dim=-1, keepdim=True), lat["inv"].expand(len(q), -1)], dim=-1)
    h = phi @ sd["fc_in.weight"].T + sd["fc_in.bias"]
    for i in range(n_blocks):
        t = relu(h) @ sd[f"block{i}.fc_0.weight"].T + sd[f"block{i}.fc_0.bias"]
        h = h + relu(t) @ sd[f"block{i}.fc_1.weight"].T + sd[f"block{i}.fc_1.bias"]
    return (relu(h) @ sd["fc_out.weight"].T + sd["fc_out.bias"])[:, 0]


def _released_parts(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    state = torch.load(path, map_location="cpu", weights_only=True)["model_state_dict"]
    enc = {k[len("network_dict.encoder."):]: v.double() for k, v in state.items() if ".encoder." in k}
    dec = {k[len("network_dict.decoder."):]: v.double() for k, v in state.items() if ".decoder." in k}
    return enc, dec


# ------------------------------------------------------------------------------------------------------ tests
def _expected_released_keys(widths: tuple[int, ...], attention: tuple[int, ...]) -> dict[str, tuple[int, ...]]:
    """The released key/shape table (docs/design/efem-method.md §1.7, confirmed against the released module
    structure)."""
    out: dict[str, tuple[int, ...]] = {}
    e, d = "network_dict.encoder.", "network_dict.decoder."
    for b, c in enumerate(widths):
        c_in = 3 if b == 0 else 2 * widths[b - 1]
        out[f"{e}V_list.{b}.lin.weight"] = (c, c_in)
        out[f"{e}V_list.{b}.act.lin_dir.weight"] = (c, c)
        if b >= 2:
            out[f"{e}global_conv_list.{b - 2}.lin.weight"] = (c, 2 * c)
            out[f"{e}global_conv_list.{b - 2}.act.lin_dir.weight"] = (c, c)
        if b in attention:
            out[f"{e}Q_list.{b}.lin.weight"] = (c, widths[b - 1])
            out[f"{e}K_list.{b}.lin.weight"] = (c, 2 * widths[b - 1])
            out[f"{e}Q_list.{b}.act.lin_dir.weight"] = out[f"{e}K_list.{b}.act.lin_dir.weight"] = (c, c)
    out.update({f"{e}conv_c.lin.weight": (256, 512), f"{e}conv_c.act.lin_dir.weight": (1, 256),
                f"{e}fc_inv.weight": (256, 256), f"{e}fc_center.fc0.lin.weight": (128, 256),
                f"{e}fc_center.fc0.act.lin_dir.weight": (128, 128), f"{e}fc_center.lin1.weight": (1, 128),
                f"{e}fc_center.shortcut.weight": (1, 256), f"{e}fc_center.act2.lin_dir.weight": (1, 1),
                f"{d}fc_in.weight": (256, 513), f"{d}fc_in.bias": (256,),
                f"{d}fc_out.weight": (1, 256), f"{d}fc_out.bias": (1,)})
    for i in range(5):
        for j in (0, 1):
            out[f"{d}block{i}.fc_{j}.weight"], out[f"{d}block{i}.fc_{j}.bias"] = (256, 256), (256,)
    return out


@pytest.mark.parametrize("release", ["mugs", "chairs"])
def test_spec_prior_has_the_released_keys_and_config_is_inferred(release: str) -> None:
    attention = (2, 3, 4, 5, 6) if release == "chairs" else ()
    prior = ShapePrior(PriorConfig(attention_blocks=attention))
    widths = (32, 32, 64, 64, 128, 256, 512)
    state = released_dict(prior)["model_state_dict"]
    assert {k: tuple(v.shape) for k, v in state.items()} == _expected_released_keys(widths, attention)
    cfg = infer_released_config(map_released_keys(state), release=release)  # type: ignore[arg-type]
    assert cfg.widths == widths and cfg.attention_blocks == attention and cfg.global_from == 2
    assert (cfg.latent_dim, cfg.center_hidden, cfg.decoder_hidden, cfg.decoder_blocks) == (256, 128, 256, 5)
    assert cfg.use_qnorm and cfg.scale_factor == 64000.0 and cfg.k == 16 and cfg.down_blocks == (2, 4, 5)
    assert (cfg.n_pcl, cfg.down_factors) == ((1024, (4, 4, 4)) if release == "chairs" else (512, (2, 4, 4)))
    assert not cfg.center_times_sigma
    assert infer_released_config(map_released_keys(state), release="kit4cates").center_times_sigma


@pytest.mark.parametrize(("cfg", "release"), [(TINY, "mugs"), (TINY_ATT, "chairs")], ids=["mean", "attention"])
def test_converted_prior_matches_original_and_released_forward(tmp_path: Path, cfg: dict[str, Any],
                                                               release: str) -> None:
    orig = random_prior(cfg, seed=1)
    src = write_released(tmp_path, orig)
    dst = convert_released_checkpoint(src, tmp_path / "conv.pt", release=release, **TINY_KW)  # type: ignore[arg-type]
    conv = load_prior(dst)
    assert conv.config == orig.config and conv.name == {"mugs": "mug", "chairs": "chair"}[release]
    meta = conv.metadata["converted_from"]
    assert meta["release"] == release and meta["epoch"] == 7 and meta["batch"] == 1234
    assert len(meta["sha256"]) == 64
    orig, conv = orig.double(), conv.double()
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(2, 64, 3, generator=g, dtype=torch.float64) * torch.tensor([0.3, 0.2, 0.4]) + 0.5
    with torch.no_grad():
        la, lb = orig.encode(pts), conv.encode(pts)
        for a, b in zip(la, lb):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        # queries spread over the object in canonical units (random weights give Θ_s far from 1)
        q = lb.center[:, None] + lb.scale[:, None, None] * torch.randn(2, 50, 3, generator=g, dtype=torch.float64)
        torch.testing.assert_close(orig.sdf(q, la), conv.sdf(q, lb), rtol=0, atol=0)
        # against the naive released forward pass, tensor by released name
        enc, dec = _released_parts(src)
        for i in range(len(pts)):
            ref = reference_encode(enc, conv.config, pts[i])
            torch.testing.assert_close(lb.R[i], ref["R"], rtol=1e-9, atol=1e-12)
            torch.testing.assert_close(lb.inv[i], ref["inv"], rtol=1e-9, atol=1e-12)
            torch.testing.assert_close(lb.center[i], ref["center"], rtol=1e-9, atol=1e-12)
            torch.testing.assert_close(lb.scale[i], ref["scale"], rtol=1e-9, atol=1e-12)
            ref_sdf = reference_sdf(dec, conv.config.decoder_blocks, ref, q[i])
            torch.testing.assert_close(conv.sdf(q[i : i + 1], lb[i])[0], ref_sdf, rtol=1e-9, atol=1e-12)


def test_kit4cates_multiplies_delta_by_sigma(tmp_path: Path) -> None:
    orig = random_prior(TINY, seed=2)
    src = write_released(tmp_path, orig, name="kit4cates.pt")
    conv = load_prior(convert_released_checkpoint(src, tmp_path / "kit.pt", **TINY_KW)).double()
    assert conv.config.center_times_sigma and conv.name == "kit4cates"
    pts = torch.randn(1, 64, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with torch.no_grad():
        delta_kit = conv.encode(pts).center - pts.mean(1)
        delta_mug = orig.double().encode(pts).center - pts.mean(1)
    torch.testing.assert_close(delta_kit, delta_mug * 64000.0, rtol=1e-9, atol=0)


def test_release_from_filename() -> None:
    assert release_from_filename("weights/mugs.pt") == "mugs"
    assert release_from_filename("chairs.pt") == "chairs"
    assert release_from_filename("kit4cates.pt") == "kit4cates"
    assert release_from_filename("model.pt") is None


def _edited(prior: ShapePrior, fn: Any) -> dict[str, Any]:
    ckpt = released_dict(prior)
    fn(ckpt["model_state_dict"])
    return ckpt


@pytest.mark.parametrize(("edit", "pattern"), [
    (lambda s: s.pop("network_dict.encoder.fc_inv.weight"), r"missing keys: network_dict\.encoder\.fc_inv\.weight"),
    (lambda s: s.pop("network_dict.decoder.block1.fc_1.bias"), r"missing keys: network_dict\.decoder\.block1\.fc_1"),
    (lambda s: s.pop("network_dict.encoder.conv_c.lin.weight"), r"missing key network_dict\.encoder\.conv_c\.lin"),
    (lambda s: s.__setitem__("network_dict.encoder.fc_O.weight", torch.zeros(3, 16)),
     r"unexpected keys.*network_dict\.encoder\.fc_O\.weight"),
    (lambda s: s.__setitem__("network_dict.cls_head.0.weight", torch.zeros(4, 16)),
     r"unexpected keys.*network_dict\.cls_head\.0\.weight"),
    (lambda s: s.__setitem__("network_dict.encoder.V_list.1.act.lin_dir.weight", torch.zeros(8, 7)),
     r"shape mismatches: network_dict\.encoder\.V_list\.1\.act\.lin_dir\.weight \(8, 7\) \(expected \(8, 8\)\)"),
    (lambda s: s.__setitem__("network_dict.encoder.K_list.2.lin.weight", torch.zeros(16, 16)),
     r"missing keys: .*network_dict\.encoder\.Q_list\.2\.lin\.weight"),
])
def test_bad_checkpoints_name_the_key(tmp_path: Path, edit: Any, pattern: str) -> None:
    path = tmp_path / "bad.pt"
    torch.save(_edited(random_prior(TINY), edit), path)
    with pytest.raises(ValueError, match=pattern):
        convert_released_checkpoint(path, tmp_path / "out.pt", release="mugs", **TINY_KW)
    assert not (tmp_path / "out.pt").exists()


def test_not_a_released_file_and_overwrite(tmp_path: Path) -> None:
    prior = random_prior(TINY)
    bad = tmp_path / "plain.pt"
    torch.save({"state_dict": {}}, bad)
    with pytest.raises(ValueError, match="model_state_dict"):
        convert_released_checkpoint(bad, tmp_path / "out.pt", **TINY_KW)
    with pytest.raises(FileNotFoundError):
        convert_released_checkpoint(tmp_path / "missing.pt", tmp_path / "out.pt", **TINY_KW)
    src = write_released(tmp_path, prior)
    out = convert_released_checkpoint(src, tmp_path / "out.pt", release="mugs", **TINY_KW)
    with pytest.raises(FileExistsError):
        convert_released_checkpoint(src, out, release="mugs", **TINY_KW)
    convert_released_checkpoint(src, out, release="mugs", overwrite=True, **TINY_KW)
    with pytest.raises(ValueError, match="down-sampling schedule"):  # 4 blocks: the schedule is not the release's
        convert_released_checkpoint(src, tmp_path / "o2.pt", release="mugs", check=False)


def test_pickle_fallback_needs_the_flag(tmp_path: Path) -> None:
    src = write_released(tmp_path, random_prior(TINY), args=argparse.Namespace(lr=1e-4))  # not weights-only
    with pytest.raises(PickleRequired, match="allow_pickle.*--allow-pickle"):
        convert_released_checkpoint(src, tmp_path / "out.pt", release="mugs", **TINY_KW)
    out = convert_released_checkpoint(src, tmp_path / "out.pt", release="mugs", allow_pickle=True, **TINY_KW)
    assert load_prior(out).config.widths == TINY["widths"]


def test_corrupt_release_is_reported_as_corrupt(tmp_path: Path) -> None:
    src = write_released(tmp_path, random_prior(TINY))
    bad = tmp_path / "mugs_truncated.pt"
    bad.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    for allow in (False, True):  # a corrupt file is not a pickle question: no --allow-pickle hint, no unpickling
        with pytest.raises(ValueError, match="corrupt or truncated") as info:
            convert_released_checkpoint(bad, tmp_path / "out.pt", release="mugs", allow_pickle=allow, **TINY_KW)
        assert "--allow-pickle" not in str(info.value)
    assert not (tmp_path / "out.pt").exists()


def test_plausibility_check_runs_and_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    src = write_released(tmp_path, random_prior(TINY))  # no release in the name: assumed mugs, with a warning
    kw = {k: v for k, v in TINY_KW.items() if k != "check"}
    with caplog.at_level(logging.WARNING, logger="efem_viz.prior.convert"):
        out = convert_released_checkpoint(src, tmp_path / "out.pt", **kw)
    assert "assuming 'mugs'" in caplog.text
    check = load_prior(out).metadata["conversion_check"]
    assert set(check) == {"scale", "delta_norm"} and all(math.isfinite(v) for v in check.values())


def test_cli_convert_prior(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = write_released(tmp_path, random_prior(TINY), name="mugs.pt")
    args = ["convert-prior", str(src), "--down-blocks", "2", "--down-factors", "2", "--n-pcl", "64"]
    out = tmp_path / "conv.pt"
    assert cli.main([*args, "--out", str(out), "--no-codebook"]) == 0
    assert load_prior(out).codebook is None
    assert cli.main([*args, "--out", str(out), "--no-codebook"]) == 1  # exists
    assert "exists" in capsys.readouterr().err
    # default output name, with a tiny codebook built by the build-codebook code
    assert cli.main([*args, "--count", "2", "--n-store", "200"]) == 0
    prior = load_prior(tmp_path / "mugs_efemviz.pt")
    assert prior.codebook is not None and len(prior.codebook) == 2 and prior.codebook.meta["category"] == "mug"
