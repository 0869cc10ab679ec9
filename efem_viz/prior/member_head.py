"""Which member of a family an instance is: a linear classifier on the prior's invariant latent.

A family prior (the kitchen prior: mugs, bowls, bottles and cans in one network) completes every member's shape,
and the instance's category has to be read from its latent. `Codebook.category_of` votes with the codebook
entries its pose search retrieves; on the SynKit scenes that named about half of the well-fitted instances right
(cans taken for bottles and mugs, mugs for bowls). The member head reads the class from what the encoder says
about the shape itself: a softmax over Θ_inv, standardised, fitted on partial sensor-like views of the family's
training objects (`fit_member_head`, `efem-viz fit-member-head`). Θ_inv is invariant to rotation and scale, so the
head is too. (Θ_s is left out on purpose: the training objects are normalised to one size, so their scale says
nothing, and a scene's objects have their own sizes: a head with a log-scale feature named nearly every instance
of the SynKit scenes "bottle".)

The head lives in the prior file's metadata (key "member_head"), with a fingerprint of the encoder weights it was
fitted on: a head left over from other weights (a prior trained on from this one) is ignored with a warning.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

METADATA_KEY = "member_head"
MAX_CLASSES = 64


def encoder_fingerprint(prior: Any) -> str:
    """A short hash of the encoder's weights (what the head's features depend on)."""
    h = hashlib.sha1()
    for name, t in sorted(prior.encoder.state_dict().items()):
        h.update(name.encode())
        h.update(np.ascontiguousarray(t.detach().to("cpu").float().numpy()).tobytes())
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class MemberHead:
    """A softmax classifier over the invariant latent Θ_inv of one prior."""

    classes: tuple[str, ...]
    mean: np.ndarray
    """(F,) feature mean (standardisation)."""
    std: np.ndarray
    """(F,) feature standard deviation."""
    weight: np.ndarray
    """(K, F) logits weight."""
    bias: np.ndarray
    """(K,) logits bias."""
    fingerprint: str
    """`encoder_fingerprint` of the prior it was fitted on."""
    report: Mapping[str, Any]
    """How it was fitted and its held-out accuracy (free-form, JSON-able)."""

    def probabilities(self, inv: np.ndarray) -> np.ndarray:
        """(N, K) class probabilities of N latents' Θ_inv (N, C)."""
        x = (np.asarray(inv, np.float64).reshape(-1, len(self.mean)) - self.mean) / self.std
        z = x @ self.weight.T + self.bias
        z -= z.max(axis=1, keepdims=True)
        p = np.exp(z)
        return p / p.sum(axis=1, keepdims=True)

    def classify(self, inv: np.ndarray) -> str:
        """The class of one latent's Θ_inv (C,)."""
        return self.classes[int(np.argmax(self.probabilities(np.asarray(inv)[None])[0]))]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (the prior file's metadata entry)."""
        return {"classes": list(self.classes), "mean": self.mean.tolist(), "std": self.std.tolist(),
                "weight": self.weight.tolist(), "bias": self.bias.tolist(), "fingerprint": self.fingerprint,
                "report": dict(self.report)}

    @classmethod
    def from_dict(cls, d: Any, *, width: int) -> MemberHead:
        """Inverse of `to_dict` for a prior of latent width `width`; ValueError (one line) on anything else."""
        if not isinstance(d, Mapping):
            raise ValueError(f"member head must be a dict, got {type(d).__name__}")
        classes = d.get("classes")
        if (not isinstance(classes, (list, tuple)) or not 2 <= len(classes) <= MAX_CLASSES
                or not all(isinstance(c, str) and 0 < len(c) <= 64 for c in classes)
                or len(set(classes)) != len(classes)):
            raise ValueError(f"member head classes must be 2..{MAX_CLASSES} distinct names")
        k, f = len(classes), int(width)

        def arr(name: str, shape: tuple[int, ...]) -> np.ndarray:
            try:
                a = np.asarray(d.get(name), np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"member head {name} is not numeric") from exc
            if a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"member head {name} must be finite with shape {shape}, got {a.shape}")
            return a

        std = arr("std", (f,))
        if (std <= 0).any():
            raise ValueError("member head std must be > 0")
        fp = d.get("fingerprint")
        if not isinstance(fp, str) or len(fp) > 64:
            raise ValueError("member head fingerprint must be a short string")
        report = d.get("report") or {}
        return cls(classes=tuple(classes), mean=arr("mean", (f,)), std=std, weight=arr("weight", (k, f)),
                   bias=arr("bias", (k,)), fingerprint=fp, report=dict(report) if isinstance(report, Mapping) else {})


def member_head_of(prior: Any) -> MemberHead | None:
    """The member head stored with `prior` (metadata "member_head"), or None: none stored, or one that does not
    fit (damaged, another latent width, fitted on other encoder weights; each said once in a warning)."""
    meta = getattr(prior, "metadata", None) or {}
    d = meta.get(METADATA_KEY)
    if d is None:
        return None
    cached = getattr(prior, "_member_head_cache", None)
    if cached is not None and cached[0] is d:
        return cached[1]
    head: MemberHead | None = None
    try:
        width = int(prior.config.latent_dim)
        head = MemberHead.from_dict(d, width=width)
        if head.fingerprint != encoder_fingerprint(prior):
            log.warning("%s: its member head was fitted on other encoder weights; ignored (fit it again: "
                        "efem-viz fit-member-head)", getattr(prior, "name", "prior"))
            head = None
    except (ValueError, AttributeError) as exc:
        log.warning("%s: member head ignored (%s)", getattr(prior, "name", "prior"), exc)
        head = None
    try:
        object.__setattr__(prior, "_member_head_cache", (d, head))
    except (AttributeError, TypeError):
        pass
    return head


def fit_member_head(prior: Any, family: str, *, n_train: int = 400, n_val: int = 96, views: int = 4,
                    seed: int = 0, cache_dir: Any = None, epochs: int = 400, weight_decay: float = 1e-4
                    ) -> MemberHead:
    """Fit a member head for `prior` on its family's procedural objects.

    Each training object gives `views` partial input clouds (1-12 of its rendered depth views, `data.input_cloud`),
    encoded by the prior (inputs as the prior's training makes them, with the depth-sensor model and a scene's
    clutter, were measured worse on the SynKit-like scenes: per-class AP50 z 61.0 -> 55.5, so3 32.3 -> 21.5); a
    multinomial logistic regression (Adam, full batch, `epochs` steps) is fitted on their standardised features. The val
    split's objects, encoded the same way, give the held-out accuracy and the confusion table (the report).

    Args:
        prior: a trained family prior (`prior.encoder`).
        family: a training family (`procedural.FAMILIES`, e.g. "kitchen").
        n_train, n_val: objects of the train and val splits (the members interleaved).
        views: input clouds per object.
        seed: RNG seed of the views and the fit.
        cache_dir: the per-object data cache (`train-prior --cache-dir`; default runs/cache).

    Raises:
        ValueError: not a family, or too few objects.
    """
    import torch

    from efem_viz.data.procedural import FAMILIES, family_members
    from efem_viz.prior.train import TrainArgs, load_objects

    if family not in FAMILIES:
        raise ValueError(f"{family!r} is not a training family; known: {sorted(FAMILIES)}")
    members = family_members(family)
    if min(n_train, n_val) < len(members) or views < 1:
        raise ValueError(f"need at least one object per member in each split and views >= 1 (got n_train "
                         f"{n_train}, n_val {n_val}, views {views})")
    kw: dict[str, Any] = {"category": family, "n_train": n_train, "n_val": n_val, "seed": 12345}
    if cache_dir is not None:
        from pathlib import Path

        kw["cache_dir"] = Path(cache_dir)
    args = TrainArgs(**kw)  # type: ignore[arg-type]
    train_x, train_y = _encoded_views(prior, load_objects(args, "train"), len(members), views, seed)
    val_x, val_y = _encoded_views(prior, load_objects(args, "val"), len(members), views, seed + 1)
    mean = train_x.mean(axis=0)
    std = train_x.std(axis=0) + 1e-6
    gen = torch.Generator().manual_seed(seed)
    lin = torch.nn.Linear(train_x.shape[1], len(members), dtype=torch.float64)
    with torch.no_grad():
        lin.weight.copy_(0.01 * torch.randn(lin.weight.shape, generator=gen, dtype=torch.float64))
        lin.bias.zero_()
    xt = torch.as_tensor((train_x - mean) / std)
    yt = torch.as_tensor(train_y)
    opt = torch.optim.Adam(lin.parameters(), lr=1e-2, weight_decay=weight_decay)
    for _ in range(int(epochs)):
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(lin(xt), yt)
        loss.backward()
        opt.step()
    head = MemberHead(classes=tuple(members), mean=mean, std=std, weight=lin.weight.detach().numpy().copy(),
                      bias=lin.bias.detach().numpy().copy(), fingerprint=encoder_fingerprint(prior), report={})
    pred_t = head.probabilities(train_x).argmax(axis=1)
    pred_v = head.probabilities(val_x).argmax(axis=1)
    confusion = np.zeros((len(members), len(members)), np.int64)
    np.add.at(confusion, (val_y, pred_v), 1)
    report = {"family": family, "n_train": n_train, "n_val": n_val, "views": views, "epochs": int(epochs),
              "train_accuracy": float(np.mean(pred_t == train_y)), "val_accuracy": float(np.mean(pred_v == val_y)),
              "val_confusion": confusion.tolist(), "final_loss": float(loss.detach())}
    return dataclasses.replace(head, report=report)


def _encoded_views(prior: Any, objs: list[Any], n_classes: int, views: int, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Θ_inv (N, C) and classes (N,) of `views` input clouds of each object (object i is member
    i mod n_classes, as `procedural.family_seeds` interleaves them)."""
    import torch

    from efem_viz.prior.data import SampleConfig, input_cloud

    rng = np.random.default_rng(seed)
    cfg = SampleConfig(n_pcl=int(prior.config.n_pcl), min_views=1)
    clouds = [input_cloud(o, cfg, rng) for o in objs for _ in range(views)]
    labels = np.repeat(np.arange(len(objs)) % n_classes, views)
    feats: list[np.ndarray] = []
    dtype = next(prior.parameters()).dtype
    with torch.no_grad():
        for b in range(0, len(clouds), 64):
            x = torch.as_tensor(np.stack(clouds[b:b + 64]), dtype=dtype)
            enc = _encode(prior, x - x.mean(dim=1, keepdim=True))
            feats.append(enc.inv.double().numpy())
    return np.concatenate(feats), labels


def _encode(prior: Any, x: torch.Tensor) -> Any:
    was = prior.training
    prior.eval()
    try:
        return prior.encoder(x)
    finally:
        prior.train(was)


__all__ = ["METADATA_KEY", "MemberHead", "encoder_fingerprint", "fit_member_head", "member_head_of"]
