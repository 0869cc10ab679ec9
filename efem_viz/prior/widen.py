"""Function-preserving growth of a trained prior's decoder (Net2Net-style).

`widen_decoder` returns a new `ShapePrior` whose decoder is wider (``hidden``) and/or deeper (``blocks``) and
computes exactly the function of the old one, so a fine-tune starts where the shipped prior is instead of from
scratch. How each new weight is set (``H`` old width, the new units after it):

- ``fc_in``: the old rows as they were; new rows freshly initialised (the new residual units carry a signal);
- every block's ``fc_0``: old rows read the old units only (zeros on the new inputs); new rows fresh;
- every block's ``fc_1``: old rows read the old inner units only (zeros on the new inner units); new rows as a
  fresh block has them (zero);
- ``fc_out``: zeros on the new units;
- appended blocks: fresh ``fc_0``, zero ``fc_1`` (weight and bias), so each starts as the identity.

Every new unit either reads a live signal or feeds an output through a weight that gets a gradient at once
(``fc_out``'s and ``fc_1``'s new columns see non-zero activations), so the grown network trains; random, not
copied, new rows break the symmetry that plain unit duplication would leave. The encoder is unchanged.
"""

from __future__ import annotations

import copy
import dataclasses

import torch

from efem_viz.prior.model import ShapePrior


def widen_decoder(prior: ShapePrior, *, hidden: int | None = None, blocks: int | None = None,
                  seed: int = 0) -> ShapePrior:
    """A copy of ``prior`` with a wider and/or deeper decoder that computes the same SDF.

    Args:
        prior: A trained prior (left untouched).
        hidden: New decoder width (``>=`` the current one; None keeps it).
        blocks: New number of residual blocks (``>=`` the current one; None keeps it).
        seed: Seed of the new units' initialisation.

    Returns:
        The grown prior (same dtype, device, name, metadata and codebook; config updated).

    Raises:
        ValueError: If ``hidden`` or ``blocks`` is smaller than the current size.
    """
    old = prior.config
    h_old, b_old = int(old.decoder_hidden), int(old.decoder_blocks)
    h_new = h_old if hidden is None else int(hidden)
    b_new = b_old if blocks is None else int(blocks)
    if h_new < h_old or b_new < b_old:
        raise ValueError(f"can only grow the decoder: {h_old}x{b_old} -> {h_new}x{b_new}")
    cfg = dataclasses.replace(old, decoder_hidden=h_new, decoder_blocks=b_new)
    gen_state = torch.get_rng_state()
    try:
        torch.manual_seed(seed)
        out = ShapePrior(cfg, name=prior.name).to(device=prior.device, dtype=prior.dtype)
    finally:
        torch.set_rng_state(gen_state)
    out.metadata = copy.deepcopy(prior.metadata)
    out.codebook = prior.codebook
    with torch.no_grad():
        out.encoder.load_state_dict(prior.encoder.state_dict())
        src, dst = prior.decoder, out.decoder
        dst.fc_in.weight[:h_old].copy_(src.fc_in.weight)
        dst.fc_in.bias[:h_old].copy_(src.fc_in.bias)
        for i in range(b_old):
            s, d = getattr(src, f"block{i}"), getattr(dst, f"block{i}")
            for name in ("fc_0", "fc_1"):
                ls, ld = getattr(s, name), getattr(d, name)
                ld.weight[:h_old, :h_old].copy_(ls.weight)
                ld.weight[:h_old, h_old:].zero_()
                ld.bias[:h_old].copy_(ls.bias)
            d.fc_1.weight[h_old:].zero_()
            d.fc_1.bias[h_old:].zero_()
        for i in range(b_old, b_new):  # appended blocks: the identity (a fresh fc_1 has a random bias)
            d = getattr(dst, f"block{i}")
            d.fc_1.weight.zero_()
            d.fc_1.bias.zero_()
        dst.fc_out.weight[:, :h_old].copy_(src.fc_out.weight)
        dst.fc_out.weight[:, h_old:].zero_()
        dst.fc_out.bias.copy_(src.fc_out.bias)
    out.train(prior.training)
    return out
