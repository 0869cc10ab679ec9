"""Convert the authors' released EFEM shape priors into efem-viz prior files (docs/design/efem-method.md §1.7).

The MIT release (repository ``JiahuiLei/EFEM``) ships ``weights/{mugs,chairs,kit4cates}.pt``: pickled dicts with
the keys ``model_state_dict``, ``optimizers_state_dict``, ``epoch`` and ``batch``. Every state-dict key is
prefixed ``network_dict.encoder.`` or ``network_dict.decoder.``; after the prefix the names are the ones our
``VNDGCNNEncoder`` / ``SDFDecoder`` use (``V_list.{b}.lin.weight``, ``V_list.{b}.act.lin_dir.weight``,
``global_conv_list.{j}.…``, ``Q_list.{b}``/``K_list.{b}`` for attention blocks, ``conv_c``, ``fc_inv``,
``fc_center.{fc0,lin1,shortcut,act2}``, ``fc_in``, ``block{i}.fc_{0,1}``, ``fc_out``), with the same
``(C_out, C_in)`` weight shapes. :func:`convert_released_checkpoint` maps them one to one, infers the
:class:`~efem_viz.prior.model.PriorConfig` from the tensor shapes, checks that every tensor is used and every
parameter is filled, and writes a file that :func:`~efem_viz.prior.model.load_prior` reads.

What the tensor shapes cannot tell, and how it is chosen (override any of it):

* the **down-sampling schedule** and the encoder **input size**: blocks (2, 4, 5) with factors (2, 4, 4) and
  512 points for mugs and kit4cates, factors (4, 4, 4) and 1024 points for chairs;
* whether the centre offset δ is **multiplied by σ**: the kit4cates prior does (its config sets
  ``center_pred_scale``), mugs and chairs do not. Mugs and kit4cates have identical tensor shapes, so the
  release is taken from the ``release`` argument, else from the file name (``mugs``/``chairs``/``kit4cates``),
  else from the shapes (attention blocks present: chairs; otherwise mugs, with a warning). A plausibility check
  (below) flags the usual mistake;
* ``scale_factor`` σ = 64000, k = 16 neighbours and 16 channels per attention head (all three releases).

**Canonical frame.** The released priors were trained on ShapeNet objects with **+Y up**; efem-viz uses **+Z
up** everywhere. The encoder is SO(3)-equivariant and the decoder invariant, so the weights are used unchanged
and compute the same function in any frame. What is frame-dependent is the pose codebook (latents of canonical
objects): the released ``cache/*.npz`` codebooks are in the +Y-up frame (and in another format) and must not be
used. Rebuild the codebook from efem-viz's +Z-up procedural meshes with ``efem-viz build-codebook --prior
<converted>.pt`` (``efem-viz convert-prior`` does so unless ``--no-codebook``); the pose estimates then come out
in efem-viz's +Z-up canonical frame.

**Fidelity.** The converted network computes what the released network computes, to rounding, with these
exceptions (details in docs/INTERFACES.md):

* the release's block-0 cross product ``torch.cross`` is called without ``dim``, so for a batch of exactly 3
  clouds it crosses along the batch axis; efem-viz always crosses the xyz axis (the intended behaviour);
* kNN and FPS ties, and sub-1e-12 vector lengths in the normalisations, may resolve differently;
* the released solver runs the encoder in float64 (``use_double``) and the decoder in float32; a loaded
  efem-viz prior is float32 (call ``prior.double()`` for the release's encoder precision).

A plausibility check encodes a unit-size procedural mug in float64 after conversion and warns when Θ_s is far
from 1 or |δ| is implausible; its numbers are stored in the metadata (``conversion_check``).

This module's top is light (no torch). `efem-viz convert-prior` is `efem_viz.prior.commands.ConvertArgs`.
"""

from __future__ import annotations

import hashlib
import logging
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Mapping

if TYPE_CHECKING:
    from efem_viz.prior.model import PriorConfig, ShapePrior

logger = logging.getLogger(__name__)

__all__ = [
    "RELEASES",
    "ReleaseName",
    "convert_released_checkpoint",
    "infer_released_config",
    "load_released_state_dict",
    "map_released_keys",
]

ReleaseName = Literal["mugs", "chairs", "kit4cates"]

RELEASES: dict[str, dict[str, Any]] = {
    "mugs": {"name": "mug", "n_pcl": 512, "down_blocks": (2, 4, 5), "down_factors": (2, 4, 4),
             "center_times_sigma": False, "category": "mug"},
    "kit4cates": {"name": "kit4cates", "n_pcl": 512, "down_blocks": (2, 4, 5), "down_factors": (2, 4, 4),
                  "center_times_sigma": True, "category": "mug"},
    "chairs": {"name": "chair", "n_pcl": 1024, "down_blocks": (2, 4, 5), "down_factors": (4, 4, 4),
               "center_times_sigma": False, "category": None},
}
"""What each released prior's training config sets beyond the tensor shapes (lib_shape_prior/configs/*.yaml),
plus the efem-viz defaults used for it (display ``name``, procedural codebook ``category``; chairs have none)."""

RELEASED_PREFIX = "network_dict."
"""Prefix of every key of the released ``model_state_dict`` (``network_dict.encoder.…``/``network_dict.decoder.…``)."""

_RELEASED_BLOCKS = 7
_SOURCE = "EFEM release (github.com/JiahuiLei/EFEM, MIT): model_state_dict with network_dict.{encoder,decoder}"

# Parameter-name patterns of the released encoder/decoder (after ``network_dict.``); our ShapePrior uses the same
# names under ``encoder.``/``decoder.``. Anything else (``cls_head``, ``pe_projector``, ``fc_O``, …) belongs to a
# released option efem-viz does not implement and is rejected.
_KEY_PATTERNS = [re.compile(p) for p in (
    r"encoder\.V_list\.\d+\.(lin\.weight|act\.lin_dir\.weight)",
    r"encoder\.global_conv_list\.\d+\.(lin\.weight|act\.lin_dir\.weight)",
    r"encoder\.[QK]_list\.\d+\.(lin\.weight|act\.lin_dir\.weight)",
    r"encoder\.conv_c\.(lin\.weight|act\.lin_dir\.weight)",
    r"encoder\.fc_inv\.weight",
    r"encoder\.fc_center\.(fc0\.lin\.weight|fc0\.act\.lin_dir\.weight|lin1\.weight|shortcut\.weight"
    r"|act2\.lin_dir\.weight)",
    r"decoder\.fc_in\.(weight|bias)",
    r"decoder\.block\d+\.fc_[01]\.(weight|bias)",
    r"decoder\.fc_out\.(weight|bias)",
)]


def _released_name(key: str) -> str:
    """Our parameter name -> the released state-dict key (for messages)."""
    return RELEASED_PREFIX + key


def _fmt_keys(keys: list[str], limit: int = 12) -> str:
    shown = ", ".join(keys[:limit])
    return shown + (f", … ({len(keys) - limit} more)" if len(keys) > limit else "")


def load_released_state_dict(src: str | Path, *,
                             allow_pickle: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """Read a released checkpoint's ``model_state_dict``.

    The file is read with `read_checkpoint`: ``torch.load(weights_only=True)``, which cannot run code. Only if
    the file needs Python objects beyond tensors and ``allow_pickle`` is set is it unpickled in full (a pickle
    can run arbitrary code: do this only for files you trust).

    Args:
        src: The released ``.pt`` file (e.g. ``weights/mugs.pt``).
        allow_pickle: Fall back to a full unpickle when the weights-only load fails.

    Returns:
        ``(state, info)``: the ``model_state_dict`` as ``{key: tensor}`` (on CPU, keys as stored) and
        ``{"epoch", "batch"}`` (None where absent).

    Raises:
        FileNotFoundError: If ``src`` does not exist.
        ValueError: If the file is corrupt, needs a full unpickle without ``allow_pickle``, or is not a released
            checkpoint.
    """
    import torch

    from efem_viz.prior.model import PickleRequired, read_checkpoint

    src = Path(src)
    if not src.is_file():
        raise FileNotFoundError(f"released checkpoint not found: {src}")
    try:
        ckpt = read_checkpoint(src, allow_pickle=allow_pickle)
    except PickleRequired as exc:
        raise PickleRequired(f"{exc} (CLI: efem-viz convert-prior ... --allow-pickle)") from exc
    if not isinstance(ckpt, dict) or "model_state_dict" not in ckpt:
        keys = sorted(map(str, ckpt)) if isinstance(ckpt, dict) else type(ckpt).__name__
        hint = " (this looks like an efem-viz prior already)" if isinstance(ckpt, dict) and "config" in ckpt else ""
        raise ValueError(f"{src} is not a released EFEM checkpoint: expected a dict with 'model_state_dict', "
                         f"got {keys}{hint}")
    state = ckpt["model_state_dict"]
    if not isinstance(state, Mapping) or not state:
        raise ValueError(f"{src}: model_state_dict is empty or not a mapping ({type(state).__name__})")
    bad = [str(k) for k, v in state.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise ValueError(f"{src}: model_state_dict entries that are not tensors: {_fmt_keys(bad)}")
    info = {k: (ckpt.get(k) if isinstance(ckpt.get(k), (int, float)) else None) for k in ("epoch", "batch")}
    return {str(k): v for k, v in state.items()}, info


def map_released_keys(state: Mapping[str, Any]) -> dict[str, Any]:
    """Map released state-dict keys to efem-viz ``ShapePrior`` parameter names.

    ``network_dict.encoder.X`` becomes ``encoder.X`` and ``network_dict.decoder.X`` becomes ``decoder.X`` (a
    leading ``module.`` from ``DataParallel`` is dropped first). The names after the prefix are the same in both
    implementations.

    Args:
        state: Released ``{key: tensor}``.

    Returns:
        ``{efem-viz key: tensor}``.

    Raises:
        ValueError: Listing every key that does not belong to the released encoder/decoder (e.g. a
            classification head, a positional-encoding projector or a rotation-matrix head, which efem-viz does
            not implement), or two keys that map to the same name.
    """
    out: dict[str, Any] = {}
    unexpected: list[str] = []
    for key, tensor in state.items():
        k = key[len("module."):] if key.startswith("module.") else key
        if not k.startswith(RELEASED_PREFIX):
            unexpected.append(key)
            continue
        k = k[len(RELEASED_PREFIX):]
        if not any(p.fullmatch(k) for p in _KEY_PATTERNS):
            unexpected.append(key)
            continue
        if k in out:
            raise ValueError(f"released keys map twice to {k!r} (duplicate with and without 'module.')")
        out[k] = tensor
    if unexpected:
        raise ValueError(f"unexpected keys in the released checkpoint (not part of the encoder/decoder efem-viz "
                         f"implements; the released use_cls / use_pe / z_so3_as_Omtx options are not supported): "
                         f"{_fmt_keys(sorted(unexpected))}")
    return out


def _indices(state: Mapping[str, Any], pattern: str) -> list[int]:
    rx = re.compile(pattern)
    return sorted({int(m.group(1)) for k in state if (m := rx.fullmatch(k))})


def _need(state: Mapping[str, Any], key: str, what: str) -> Any:
    if key not in state:
        raise ValueError(f"missing key {_released_name(key)} (needed to infer {what})")
    t = state[key]
    if t.ndim != 2:
        raise ValueError(f"{_released_name(key)} must be 2-D, got shape {tuple(t.shape)}")
    return t


def release_from_filename(path: str | Path) -> ReleaseName | None:
    """The release a file name points at (``mugs.pt`` -> "mugs", ``kit4cates.pt`` -> "kit4cates", …), or None."""
    stem = Path(path).stem.lower()
    if "kit4cates" in stem or "kitchen" in stem:
        return "kit4cates"
    if "chair" in stem:
        return "chairs"
    if "mug" in stem:
        return "mugs"
    return None


def _backbone_widths(state: Mapping[str, Any]) -> tuple[int, ...]:
    """The widths of the encoder's backbone blocks (``V_list.{b}.lin.weight`` rows), blocks numbered 0..n-1.

    Raises:
        ValueError: no backbone block, or a block missing from the numbering.
    """
    blocks = _indices(state, r"encoder\.V_list\.(\d+)\.lin\.weight")
    if not blocks:
        raise ValueError(f"missing keys {_released_name('encoder.V_list.{b}.lin.weight')}: no backbone blocks")
    if blocks != list(range(len(blocks))):
        missing = sorted(set(range(max(blocks) + 1)) - set(blocks))
        raise ValueError("missing key(s) " + ", ".join(_released_name(f"encoder.V_list.{b}.lin.weight")
                                                      for b in missing) + " (backbone blocks must be 0..n-1)")
    return tuple(int(_need(state, f"encoder.V_list.{b}.lin.weight", f"the width of block {b}").shape[0])
                 for b in blocks)


def _down_schedule(n_blocks: int, rel: Mapping[str, Any], *, down_blocks: tuple[int, ...] | None,
                   down_factors: tuple[int, ...] | None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The encoder's down-sampling schedule: as given, else the release's (``rel``, a `RELEASES` entry) when the
    backbone has the released block count.

    Raises:
        ValueError: another block count without a schedule, factors without blocks, or down-sampling before
            block 0.
    """
    if down_blocks is None:
        if n_blocks != _RELEASED_BLOCKS:
            raise ValueError(f"the checkpoint has {n_blocks} backbone blocks, not the released "
                             f"{_RELEASED_BLOCKS}: its down-sampling schedule cannot be known, pass down_blocks "
                             "and down_factors (CLI: --down-blocks, --down-factors)")
        down_blocks = tuple(rel["down_blocks"])
        if down_factors is None:
            down_factors = tuple(rel["down_factors"])
    if down_factors is None:
        raise ValueError("down_factors must be given together with down_blocks")
    if 0 in tuple(down_blocks):
        raise ValueError("block 0 cannot be preceded by down-sampling in the released network")
    return tuple(down_blocks), tuple(down_factors)


def infer_released_config(
    state: Mapping[str, Any],
    *,
    release: ReleaseName,
    n_pcl: int | None = None,
    down_blocks: tuple[int, ...] | None = None,
    down_factors: tuple[int, ...] | None = None,
    center_times_sigma: bool | None = None,
    k: int = 16,
    att_head_dim: int = 16,
    scale_factor: float = 64000.0,
) -> PriorConfig:
    """Infer the ``PriorConfig`` of a released network from its tensor shapes (keys already mapped).

    Read from the shapes: block count and widths (``V_list.{b}.lin.weight`` rows), attention blocks (the
    ``Q_list`` indices), the first global-fusion block (block count − number of ``global_conv_list`` entries),
    latent width (``conv_c.lin.weight`` rows), centre-head width (``fc_center.fc0.lin.weight`` rows), decoder
    width / blocks and whether φ carries ‖q‖ (``fc_in.weight`` has 2L+1 or 2L columns). Taken from ``release``
    unless given: ``n_pcl``, ``down_blocks``/``down_factors``, ``center_times_sigma`` (see ``RELEASES``).

    Args:
        state: ``{efem-viz key: tensor}`` from :func:`map_released_keys`.
        release: Which released prior this is.
        n_pcl: Encoder input size override.
        down_blocks: Down-sampled blocks override (required when the block count is not the released 7).
        down_factors: Down-sampling factors override (same length as ``down_blocks``).
        center_times_sigma: δ-times-σ override.
        k: kNN size (16 in every release).
        att_head_dim: Channels per attention head (16 in every release).
        scale_factor: σ (64000 in every release).

    Returns:
        The inferred config. Every tensor's shape is checked afterwards by :func:`convert_released_checkpoint`.

    Raises:
        ValueError: If a key needed for inference is missing or malformed, or the schedule cannot be known.
    """
    from efem_viz.prior.config import PriorConfig

    if release not in RELEASES:
        raise ValueError(f"unknown release {release!r}; known: {sorted(RELEASES)}")
    rel = RELEASES[release]
    widths = _backbone_widths(state)
    n_blocks = len(widths)
    attention = tuple(sorted(set(_indices(state, r"encoder\.Q_list\.(\d+)\.lin\.weight"))
                             | set(_indices(state, r"encoder\.K_list\.(\d+)\.lin\.weight"))))
    n_global = len(_indices(state, r"encoder\.global_conv_list\.(\d+)\.lin\.weight"))
    latent = int(_need(state, "encoder.conv_c.lin.weight", "the latent width").shape[0])
    center_hidden = int(_need(state, "encoder.fc_center.fc0.lin.weight", "the centre-head width").shape[0])
    fc_in = _need(state, "decoder.fc_in.weight", "the decoder width")
    dec_blocks = _indices(state, r"decoder\.block(\d+)\.fc_0\.weight")
    if dec_blocks != list(range(len(dec_blocks))):
        raise ValueError(f"decoder blocks must be numbered 0..n-1, found block indices {dec_blocks}")
    if int(fc_in.shape[1]) == 2 * latent + 1:
        use_qnorm = True
    elif int(fc_in.shape[1]) == 2 * latent:
        use_qnorm = False
    else:
        raise ValueError(f"{_released_name('decoder.fc_in.weight')} has shape {tuple(fc_in.shape)}: expected "
                         f"(H, {2 * latent + 1}) for latent width {latent} (projections, ‖q‖, invariant code)")
    down_blocks, down_factors = _down_schedule(n_blocks, rel, down_blocks=down_blocks, down_factors=down_factors)
    cts = bool(rel["center_times_sigma"]) if center_times_sigma is None else bool(center_times_sigma)
    return PriorConfig(
        widths=widths, k=int(k), n_pcl=int(n_pcl if n_pcl is not None else rel["n_pcl"]),
        down_blocks=tuple(down_blocks), down_factors=tuple(down_factors), global_from=n_blocks - n_global,
        attention_blocks=attention, att_head_dim=int(att_head_dim), latent_dim=latent,
        center_hidden=center_hidden, scale_factor=float(scale_factor), center_times_sigma=cts,
        negative_slope=0.2, decoder_hidden=int(fc_in.shape[0]), decoder_blocks=len(dec_blocks),
        use_qnorm=use_qnorm, decoder_proj_gain=1.0, decoder_inv_gain=1.0,
    )


def _fill(prior: ShapePrior, mapped: Mapping[str, Any]) -> None:
    """Copy ``mapped`` into ``prior`` after checking keys and shapes; one ValueError lists every problem."""
    import torch

    own = prior.state_dict()
    missing = sorted(set(own) - set(mapped))
    unexpected = sorted(set(mapped) - set(own))
    shapes = sorted(f"{_released_name(k)} {tuple(mapped[k].shape)} (expected {tuple(own[k].shape)})"
                    for k in set(own) & set(mapped) if tuple(mapped[k].shape) != tuple(own[k].shape))
    problems = []
    if missing:
        problems.append("missing keys: " + _fmt_keys([_released_name(k) for k in missing]))
    if unexpected:
        problems.append("unexpected keys: " + _fmt_keys([_released_name(k) for k in unexpected]))
    if shapes:
        problems.append("shape mismatches: " + _fmt_keys(shapes))
    if problems:
        raise ValueError("the released checkpoint does not match the inferred architecture "
                         f"(widths {list(prior.config.widths)}, attention {list(prior.config.attention_blocks)}, "
                         f"latent {prior.config.latent_dim}): " + "; ".join(problems))
    nonfinite = sorted(_released_name(k) for k, v in mapped.items() if not bool(torch.isfinite(v).all()))
    if nonfinite:
        raise ValueError(f"non-finite values in {_fmt_keys(nonfinite)}")
    with torch.no_grad():
        prior.load_state_dict({k: v.detach().to(torch.float32) for k, v in mapped.items()}, strict=True)


def _plausibility_check(prior: ShapePrior) -> dict[str, float]:
    """Encode a unit-size procedural mug (float64) and return Θ_s and |δ| (canonical units)."""
    import copy

    import numpy as np
    import torch

    from efem_viz.data.procedural import make_shape
    from efem_viz.geometry.sampling import sample_surface
    from efem_viz.prior.data import normalize_mesh

    mesh = normalize_mesh(make_shape("mug", 0))
    pts = sample_surface(mesh, int(prior.config.n_pcl), seed=np.random.default_rng(0), empty="raise").points
    net = copy.deepcopy(prior).double()
    with torch.no_grad():
        x = torch.as_tensor(pts, dtype=torch.float64)[None]
        lat = net.encode(x)
    delta = (lat.center[0] - x[0].mean(dim=0)).norm()
    return {"scale": float(lat.scale[0]), "delta_norm": float(delta)}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def convert_released_checkpoint(
    src: str | Path,
    dst: str | Path,
    *,
    name: str | None = None,
    release: ReleaseName | None = None,
    center_times_sigma: bool | None = None,
    n_pcl: int | None = None,
    down_blocks: tuple[int, ...] | None = None,
    down_factors: tuple[int, ...] | None = None,
    k: int = 16,
    att_head_dim: int = 16,
    scale_factor: float = 64000.0,
    allow_pickle: bool = False,
    overwrite: bool = False,
    check: bool = True,
) -> Path:
    """Convert a released EFEM checkpoint (``weights/mugs.pt`` …) into an efem-viz prior file.

    The weights are copied unchanged (the released canonical frame is +Y up, efem-viz's +Z up; the networks
    are SO(3)-equivariant, so only the codebook depends on the frame and it must be rebuilt from efem-viz's
    +Z-up meshes: ``efem-viz build-codebook --prior dst``). See the module docstring for what is inferred and
    for the known differences from the released code.

    Args:
        src: The released ``.pt`` file.
        dst: The efem-viz prior file to write (``.pt``); ``load_prior(dst)`` reads it.
        name: Display name of the prior (default: "mug", "chair" or "kit4cates" from the release).
        release: "mugs", "chairs" or "kit4cates" (default: from the file name, else from the shapes:
            attention blocks -> chairs, none -> mugs). Sets the input size, the down-sampling schedule and
            whether δ is multiplied by σ (kit4cates only).
        center_times_sigma: Override: multiply the centre offset δ by σ.
        n_pcl: Override: encoder input size (512 mugs/kit4cates, 1024 chairs).
        down_blocks: Override: blocks preceded by farthest-point down-sampling (released: 2, 4, 5).
        down_factors: Override: their factors (released: 2, 4, 4 or chairs 4, 4, 4).
        k: kNN size.
        att_head_dim: Channels per attention head.
        scale_factor: σ.
        allow_pickle: If the safe weights-only load fails, unpickle in full (trusted files only).
        overwrite: Replace an existing ``dst``.
        check: Run the plausibility check (encode a unit-size procedural mug; warn on an implausible Θ_s or δ).

    Returns:
        ``dst``.

    Raises:
        FileNotFoundError: If ``src`` is missing.
        FileExistsError: If ``dst`` exists and ``overwrite`` is False.
        ValueError: If the file is not a released checkpoint, cannot be loaded safely, has missing or unexpected
            keys or wrong shapes (the message names each key), or the architecture cannot be inferred.
    """
    path, _ = convert_with_release(src, dst, name=name, release=release, center_times_sigma=center_times_sigma,
                       n_pcl=n_pcl, down_blocks=down_blocks, down_factors=down_factors, k=k, att_head_dim=att_head_dim,
                       scale_factor=scale_factor, allow_pickle=allow_pickle, overwrite=overwrite, check=check)
    return path


def convert_with_release(src: str | Path, dst: str | Path, *, name: str | None, release: ReleaseName | None,
             center_times_sigma: bool | None, n_pcl: int | None, down_blocks: tuple[int, ...] | None,
             down_factors: tuple[int, ...] | None, k: int, att_head_dim: int, scale_factor: float,
             allow_pickle: bool, overwrite: bool, check: bool) -> tuple[Path, ReleaseName]:
    """``convert_released_checkpoint`` that also returns the release it resolved."""
    from efem_viz.prior.model import ShapePrior, save_prior

    src, dst = Path(src), Path(dst)
    if dst.suffix != ".pt":
        raise ValueError(f"the output must be a .pt file, got {dst}")
    if dst.exists() and dst.resolve() == src.resolve():
        raise ValueError(f"the output {dst} is the input file")
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    raw, info = load_released_state_dict(src, allow_pickle=allow_pickle)
    mapped = map_released_keys(raw)
    has_attention = any(key.startswith(("encoder.Q_list.", "encoder.K_list.")) for key in mapped)
    if release is None:
        release = release_from_filename(src)
        if release is None:
            release = "chairs" if has_attention else "mugs"
            logger.warning("%s: release not given and not in the file name; assuming %r from the tensor shapes "
                           "(mugs and kit4cates have the same shapes: pass release='kit4cates' for the kitchen "
                           "prior, whose centre offset is multiplied by σ)", src, release)
    if release not in RELEASES:
        raise ValueError(f"unknown release {release!r}; known: {sorted(RELEASES)}")
    if has_attention != (release == "chairs"):
        logger.warning("%s: release %r but the checkpoint %s attention blocks (the released chairs prior has them, "
                       "mugs and kit4cates do not); check --release", src, release,
                       "has" if has_attention else "has no")
    config = infer_released_config(mapped, release=release, n_pcl=n_pcl, down_blocks=down_blocks,
                                   down_factors=down_factors, center_times_sigma=center_times_sigma, k=k,
                                   att_head_dim=att_head_dim, scale_factor=scale_factor)
    prior = ShapePrior(config, name=name or str(RELEASES[release]["name"]))
    _fill(prior, mapped)
    prior.eval()
    dtypes = sorted({str(v.dtype).replace("torch.", "") for v in raw.values()})
    meta: dict[str, Any] = {
        "converted_from": {
            "file": src.name, "sha256": _sha256(src), "format": _SOURCE, "release": release,
            "epoch": info["epoch"], "batch": info["batch"], "dtypes": dtypes,
            "converted_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
        "trained_on": f"ShapeNet ({release}, authors' release)",
        "canonical_frame": "weights are frame-free (SO(3)-equivariant); the released +Y-up codebook is not used, "
                           "the efem-viz codebook is built from +Z-up procedural meshes",
    }
    if check:
        res = _plausibility_check(prior)
        meta["conversion_check"] = res
        s, d = res["scale"], res["delta_norm"]
        if not 0.2 <= s <= 5.0:
            logger.warning("plausibility check: Θ_s = %.4g for a unit-size mug (expected ~1); check the "
                           "checkpoint and scale_factor (σ = %g)", s, config.scale_factor)
        if d > 0.5:
            logger.warning("plausibility check: |δ| = %.4g canonical units for a unit-size mug (expected < 0.5)%s",
                           d, "; this prior multiplies δ by σ: is it really the kit4cates prior?"
                           if config.center_times_sigma else "")
        elif d < 1e-3 and not config.center_times_sigma:
            logger.warning("plausibility check: |δ| = %.3g is ~0 for a unit-size mug; if this is the kit4cates "
                           "prior, convert with release='kit4cates' (δ times σ)", d)
        logger.info("plausibility check (unit-size procedural mug, float64): Θ_s = %.4f, |δ| = %.4f", s, d)
    if "float64" in dtypes:
        logger.info("%s stores float64 tensors; efem-viz prior files are float32", src)
    path = save_prior(prior, dst, extra=meta)
    stale = path.with_name(f"{path.stem}_codebook.npz")
    if stale.is_file():
        logger.warning("%s exists and was built for other weights: rebuild it (efem-viz build-codebook --prior %s)",
                       stale, path)
    logger.info("converted %s (%s, epoch %s) -> %s: widths %s, attention %s, latent %d, n_pcl %d, δ×σ %s",
                src, release, info["epoch"], path, list(config.widths), list(config.attention_blocks),
                config.latent_dim, config.n_pcl, config.center_times_sigma)
    return path, release
