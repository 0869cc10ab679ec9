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

The members' metric sizes do tell them apart (a bottle stands 15-26 cm, a can 6-15 cm), and the latent of a partial
fit often does not: on SynKit-like tuning scenes most misnamed bottles were completed as the can their visible part
resembles. So the head also keeps each member's size model, a Gaussian over the log horizontal radius and log
half-height of its training objects as made (metres), and `classify` adds its log-likelihood of the completed
shape's measured size to the latent's logits when it is given one (`MemberHead.size_mean`, `size_cov`).

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
    size_mean: np.ndarray | None = None
    """(K, 2) per member, the mean of log(horizontal radius), log(half-height) of its training objects in metres
    (None: the head names by the latent alone)."""
    size_cov: np.ndarray | None = None
    """(K, 2, 2) their covariances (positive definite)."""

    def probabilities(self, inv: np.ndarray, radii: np.ndarray | None = None) -> np.ndarray:
        """(N, K) class probabilities of N latents' Θ_inv (N, C); with `radii` (N, 2) the completed shapes' measured
        (horizontal radius, half-height) in metres and a size model, weighed by each member's size likelihood
        (rows with a non-finite or non-positive size by the latent alone)."""
        x = (np.asarray(inv, np.float64).reshape(-1, len(self.mean)) - self.mean) / self.std
        z = x @ self.weight.T + self.bias
        if radii is not None:
            z = z + self.size_log_likelihood(radii)
        z -= z.max(axis=1, keepdims=True)
        p = np.exp(z)
        return p / p.sum(axis=1, keepdims=True)

    def size_log_likelihood(self, radii: np.ndarray) -> np.ndarray:
        """(N, K) log-density of each member's size model at N measured sizes (N, 2) (metres); 0 where a size is
        not finite and positive, or without a size model."""
        r = np.asarray(radii, np.float64).reshape(-1, 2)
        out = np.zeros((len(r), len(self.classes)))
        if self.size_mean is None or self.size_cov is None:
            return out
        ok = np.isfinite(r).all(axis=1) & (r > 0).all(axis=1)
        if not ok.any():
            return out
        d = np.log(r[ok])[:, None, :] - self.size_mean[None]  # (n, K, 2)
        inv_cov = np.linalg.inv(self.size_cov)
        maha = np.einsum("nki,kij,nkj->nk", d, inv_cov, d)
        out[ok] = -0.5 * maha - 0.5 * np.log(np.linalg.det(self.size_cov))[None]
        return out

    def classify(self, inv: np.ndarray, radii: np.ndarray | None = None) -> str:
        """The class of one latent's Θ_inv (C,), with its completed shape's (radius, half-height) when given."""
        r = None if radii is None else np.asarray(radii, np.float64).reshape(1, 2)
        return self.classes[int(np.argmax(self.probabilities(np.asarray(inv)[None], r)[0]))]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (the prior file's metadata entry)."""
        d = {"classes": list(self.classes), "mean": self.mean.tolist(), "std": self.std.tolist(),
             "weight": self.weight.tolist(), "bias": self.bias.tolist(), "fingerprint": self.fingerprint,
             "report": dict(self.report)}
        if self.size_mean is not None and self.size_cov is not None:
            d["size_mean"], d["size_cov"] = self.size_mean.tolist(), self.size_cov.tolist()
        return d

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
        size_mean = size_cov = None
        if d.get("size_mean") is not None or d.get("size_cov") is not None:
            size_mean, size_cov = arr("size_mean", (k, 2)), arr("size_cov", (k, 2, 2))
            sym = np.allclose(size_cov, size_cov.transpose(0, 2, 1))
            if not sym or (np.linalg.eigvalsh(size_cov) <= 1e-9).any() or (np.abs(size_mean) > 20).any():
                raise ValueError("member head size model must have symmetric positive-definite covariances and "
                                 "log sizes within ±20")
        return cls(classes=tuple(classes), mean=arr("mean", (f,)), std=std, weight=arr("weight", (k, f)),
                   bias=arr("bias", (k,)), fingerprint=fp, report=dict(report) if isinstance(report, Mapping) else {},
                   size_mean=size_mean, size_cov=size_cov)


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
    size_mean, size_cov = member_size_model(family, "train", n_train)
    head = MemberHead(classes=tuple(members), mean=mean, std=std, weight=lin.weight.detach().numpy().copy(),
                      bias=lin.bias.detach().numpy().copy(), fingerprint=encoder_fingerprint(prior), report={},
                      size_mean=size_mean, size_cov=size_cov)
    pred_t = head.probabilities(train_x).argmax(axis=1)
    pred_v = head.probabilities(val_x).argmax(axis=1)
    val_sizes = np.repeat(object_sizes(family, "val", n_val), views, axis=0)
    pred_vs = head.probabilities(val_x, val_sizes).argmax(axis=1)
    confusion = np.zeros((len(members), len(members)), np.int64)
    np.add.at(confusion, (val_y, pred_v), 1)
    report = {"family": family, "n_train": n_train, "n_val": n_val, "views": views, "epochs": int(epochs),
              "train_accuracy": float(np.mean(pred_t == train_y)), "val_accuracy": float(np.mean(pred_v == val_y)),
              "val_accuracy_with_size": float(np.mean(pred_vs == val_y)),
              "val_confusion": confusion.tolist(), "final_loss": float(loss.detach())}
    return dataclasses.replace(head, report=report)


def object_sizes(family: str, split: str, n: int) -> np.ndarray:
    """(n, 2) (horizontal radius, half-height) in metres of the first `n` objects of a family's split as made
    (`procedural.family_seeds`; the mesh's bounding-box centre at the origin, +Z up), the measure the solver's
    review takes of a completed shape around its centre."""
    from efem_viz.data.procedural import family_seeds, make_shape

    out = np.empty((n, 2))
    for i, (cat, seed) in enumerate(family_seeds(family, split, n)):  # type: ignore[arg-type]
        v = np.asarray(make_shape(cat, seed).vertices, np.float64)
        out[i] = np.linalg.norm(v[:, :2], axis=1).max(), np.abs(v[:, 2]).max()
    return out


def member_size_model(family: str, split: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each member's Gaussian over log(horizontal radius), log(half-height) of the first `n` objects of a family's
    split (object i is member i mod k): ((k, 2) means, (k, 2, 2) covariances with a 1e-4 ridge)."""
    from efem_viz.data.procedural import family_members

    k = len(family_members(family))
    logs = np.log(object_sizes(family, split, n))
    member = np.arange(n) % k
    if np.bincount(member, minlength=k).min() < 3:
        raise ValueError(f"a size model needs at least 3 objects per member (got {n} for {k} members)")
    mean = np.stack([logs[member == j].mean(axis=0) for j in range(k)])
    cov = np.stack([np.cov(logs[member == j].T) + 1e-4 * np.eye(2) for j in range(k)])
    return mean, cov


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


__all__ = ["METADATA_KEY", "MemberHead", "encoder_fingerprint", "fit_member_head", "member_head_of",
           "member_size_model", "object_sizes"]
