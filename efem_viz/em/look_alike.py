"""Mug or look-alike? A small learned score on a fit's review features.

A completed shape that passed the review can still be a cup, a can, a box or part of the table. The review already
measures what tells them apart (`bench/ranking.py`, `bench/learned_confidence.py`): how still the fit is, how much of
the shape the points cover, how well its pose matches a training pose, its size, its tilt, how much of it lies in
front of the observed depth, and how many points it claims. `LookAlikeModel` is a logistic regression on those eight
numbers (standardised); `EMConfig.confidence.look_alike` names a shipped one (`efem_viz/em/models/<name>.json`),
and the solver multiplies each accepted fit's confidence by its probability of being a mug.

Models are fitted by `bench/learned_confidence.py` on saved runs of *tune* frames only and written with `save`;
`load_model` reads only shipped names and checks every number (a model file is data, never code).
"""

from __future__ import annotations

import functools
import json
import math
import os
import stat
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.prior.config import LOOK_ALIKE_NAME

FEATURES = ("log stationary", "log coverage", "pose score", "radius (cm)", "half height (cm)", "cos up angle",
            "seen-through", "log mask size")
"""The review features a model may use, in this order."""

MODELS = Path(__file__).with_name("models")
"""Where the shipped models live."""

_MAX_BYTES = 64 * 1024


def review_features(*, stationary: float, coverage: float, pose: float, radius: float, half_height: float,
                    up_angle: float, seen_through: float, mask_size: int) -> dict[str, float]:
    """A fit's review features as the model sees them (missing measurements get neutral values: no pose score
    0.4, no free-space check 0, no up angle cos 90°).

    Args:
        stationary: its stationary score.
        coverage: its coverage.
        pose: its codebook pose score (NaN: none).
        radius: horizontal radius of the completed shape (m).
        half_height: half height of the completed shape (m).
        up_angle: angle between its axis and the scene's up (degrees; NaN: unknown).
        seen_through: seen-through fraction of the free-space check (NaN: not measured).
        mask_size: points in its mask.
    """
    def finite(x: float, default: float = 0.0) -> float:
        return float(x) if math.isfinite(float(x)) else default

    return {
        "log stationary": math.log(max(finite(stationary), 1e-4)),
        "log coverage": math.log(max(finite(coverage), 1e-4)),
        "pose score": finite(pose, 0.4),
        "radius (cm)": 100.0 * finite(radius),
        "half height (cm)": 100.0 * finite(half_height),
        "cos up angle": math.cos(math.radians(up_angle)) if math.isfinite(up_angle) else 0.0,
        "seen-through": float(seen_through) if math.isfinite(seen_through) else 0.0,
        "log mask size": math.log(max(int(mask_size), 1)),
    }


@dataclass(frozen=True)
class LookAlikeModel:
    """p(mug | features) = sigmoid(bias + Σ weight_i · (x_i − mean_i) / scale_i)."""

    names: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    weights: tuple[float, ...]
    bias: float
    trained_on: str = ""
    """Where it was fitted (frames, runs, the command)."""
    times_confidence: bool = True
    """The fit's confidence is the solver's confidence times p(mug) (True) or p(mug) alone (False)."""
    category: str = "mug"
    """The category it scores: a joint solve's other priors keep their confidence."""

    def __post_init__(self) -> None:
        n = len(self.names)
        if (not 0 < n <= len(FEATURES) or not all(isinstance(x, str) for x in self.names)
                or len(set(self.names)) != n or any(x not in FEATURES for x in self.names)):
            raise ValueError(f"look-alike model features must be distinct names from {FEATURES}, got {self.names}")
        if not isinstance(self.category, str) or not LOOK_ALIKE_NAME.fullmatch(self.category):
            raise ValueError(f"look-alike model category must be a plain name, got {self.category!r}")
        if not (len(self.mean) == len(self.scale) == len(self.weights) == n):
            raise ValueError("look-alike model: mean, scale and weights need one value per feature")
        nums = (*self.mean, *self.scale, *self.weights, self.bias)
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) < 1e6 and math.isfinite(v)
                   for v in nums):  # abs first: a 400-digit int is a size error, not an OverflowError
            raise ValueError("look-alike model: every number must be finite and below 1e6 in size")
        if not all(s >= 1e-6 for s in self.scale):
            raise ValueError("look-alike model: every scale must be >= 1e-6 (a smaller one divides features into "
                             "inf / NaN confidences)")
        if not isinstance(self.times_confidence, bool):
            raise ValueError("look-alike model: times_confidence must be true or false")

    def confidence(self, confidence: float, features: dict[str, float]) -> float:
        """A fit's final confidence: `confidence` x p(mug), or p(mug) alone (`times_confidence`)."""
        p = self.prob(features)
        return float(confidence) * p if self.times_confidence else p

    def prob(self, features: dict[str, float]) -> float:
        """The probability that a fit with these features is a mug."""
        z = self.bias + sum(w * (features[n] - m) / s
                            for n, m, s, w in zip(self.names, self.mean, self.scale, self.weights))
        return 1.0 / (1.0 + math.exp(-min(max(z, -60.0), 60.0)))

    def probs(self, x: np.ndarray) -> np.ndarray:
        """(M,) probabilities of an (M, F) matrix with the columns of `names`."""
        z = self.bias + ((np.asarray(x, np.float64) - np.asarray(self.mean)) / np.asarray(self.scale)) @ np.asarray(
            self.weights)
        return 1.0 / (1.0 + np.exp(-np.clip(z, -60.0, 60.0)))

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (atomically)."""
        from efem_viz.data.io import atomic_write_text

        atomic_write_text(Path(path), json.dumps(asdict(self), indent=1))


def fit_logistic(x: np.ndarray, y: np.ndarray, names: tuple[str, ...] | list[str], *, l2: float = 1.0,
                 trained_on: str = "", times_confidence: bool = True) -> LookAlikeModel:
    """Fit an L2-regularised logistic regression (Newton steps; the bias is not regularised).

    Args:
        x: (M, F) features, columns as `names`.
        y: (M,) 1 for a mug, 0 for a look-alike.
        names: the feature names.
        l2: the penalty on the standardised weights.
        trained_on: provenance text kept with the model.
        times_confidence: how the model's probability makes the confidence (`LookAlikeModel.times_confidence`).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    mu, sd = x.mean(0), x.std(0) + 1e-9
    z = np.c_[np.ones(len(x)), (x - mu) / sd]
    w = np.zeros(z.shape[1])
    reg = np.full(z.shape[1], float(l2))
    reg[0] = 1e-6
    for _ in range(100):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ w, -60.0, 60.0)))
        g = z.T @ (p - y) + reg * w
        h = (z * (p * (1 - p))[:, None]).T @ z + np.diag(reg)
        step = np.linalg.solve(h, g)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return LookAlikeModel(tuple(names), tuple(map(float, mu)), tuple(map(float, sd)), tuple(map(float, w[1:])),
                          float(w[0]), trained_on, times_confidence)


def check_name(name: object) -> None:
    """A model name as a config may hold it (the file is looked up when a run starts, so that a result naming a
    model that was since removed still loads).

    Raises:
        ValueError: not a plain name.
    """
    if not isinstance(name, str) or not LOOK_ALIKE_NAME.fullmatch(name):
        raise ValueError(f"look-alike model name must be a plain name ([A-Za-z0-9_-], <= 64), got {name!r}")


def available_models() -> list[str]:
    """Names of the shipped models (plain files `<name>.json`; links and folders are not models)."""
    return sorted(p.stem for p in MODELS.glob("*.json") if p.is_file() and not p.is_symlink())


@functools.lru_cache(maxsize=8)
def load_model(name: str) -> LookAlikeModel:
    """A shipped model by name (`efem_viz/em/models/<name>.json`), read once.

    Raises:
        ValueError: not a shipped name, or a file that is not a valid model (one line saying why).
    """
    if not isinstance(name, str) or not LOOK_ALIKE_NAME.fullmatch(name) or name not in available_models():
        raise ValueError(f"unknown look-alike model {name!r}; shipped: {available_models()}")
    path = MODELS / f"{name}.json"
    try:
        with open(path, "rb") as fh:  # at most the cap is ever read, whatever the file claims to be
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise ValueError(f"look-alike model {name!r} is not a regular file")
            raw = fh.read(_MAX_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"look-alike model {name!r} cannot be read: {type(exc).__name__}: {exc}") from None
    if len(raw) > _MAX_BYTES:
        raise ValueError(f"look-alike model {name!r} is larger than {_MAX_BYTES} bytes")
    try:
        d: Any = json.loads(raw)
        return LookAlikeModel(tuple(d["names"]), tuple(d["mean"]), tuple(d["scale"]), tuple(d["weights"]),
                              d["bias"], str(d.get("trained_on", "")), d.get("times_confidence", True),
                              d.get("category", "mug"))
    except (ValueError, KeyError, TypeError, RecursionError, OverflowError) as exc:
        raise ValueError(f"look-alike model {name!r} is not valid: {type(exc).__name__}: "
                         f"{str(exc)[:200]}") from exc
