"""Loading the priors of a solve by name (shipped weights, .pt files, the analytic priors) and keeping them.

The one place that knows every kind of prior, so that prior/model.py (trained priors) and prior/analytic.py
(closed-form priors) need not know each other; and the one home of a run's loaded priors (`PriorSet`): the viewer,
the annotator's click-to-segment, the batch worker and the static export all ask a `PriorSet`, which loads each
prior once and finds the prior of a trace or of one of its proposals.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from efem_viz.prior.config import DEFAULT_PRIOR, ShapePriorLike, prior_category


class TraceLike(Protocol):
    """What `PriorSet` reads of a recorded run (`efem_viz.em.trace.EMTrace` is one; typed here by a protocol so
    that prior/ does not import em/, even for type checking)."""

    @property
    def prior_names(self) -> tuple[str, ...]:
        """Category names of the run's priors in the run's order (one or none for a one-prior run)."""
        ...

    @property
    def row_R(self) -> Any:
        """(K, C, 3) Θ_R of every stored latent row: C is the latent size of the prior that made it."""
        ...

    def prior_index(self, proposal_id: int) -> int:
        """Index into `prior_names` of a proposal's prior."""
        ...


def _sphere() -> ShapePriorLike:
    from efem_viz.prior.analytic import make_sphere_prior

    return make_sphere_prior()


ANALYTIC_PRIORS: dict[str, Callable[[], ShapePriorLike]] = {"sphere": _sphere}
"""Closed-form priors by name (no weights file): name → factory. Register a new one here."""


def available_priors() -> list[str]:
    """Every prior name a solve accepts: the priors shipped in ``efem_viz/weights/`` (``<name>.pt``; training
    resume states excluded) and the analytic ones (`ANALYTIC_PRIORS`), sorted."""
    from efem_viz.prior.model import WEIGHTS_DIR

    shipped = {p.stem for p in WEIGHTS_DIR.glob("*.pt") if not p.stem.endswith("_resume")}
    return sorted(shipped | set(ANALYTIC_PRIORS))


DEVICES = ("auto", "cpu", "cuda")
"""Where the apps and `segment` run the networks: "auto" is CUDA when this machine has it, else the CPU."""


def resolve_device(name: str) -> str:
    """The torch device for a `--device` choice: "auto" → "cuda" when CUDA is available, else "cpu"; "cpu";
    "cuda" or "cuda:N" only when CUDA is available.

    Raises:
        ValueError: an unknown name, or CUDA asked for on a machine without it (one line).
    """
    import torch

    d = str(name).strip().lower()
    if d == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if d == "cpu":
        return "cpu"
    if re.fullmatch(r"cuda(:\d+)?", d):
        if not torch.cuda.is_available():
            raise ValueError(f"--device {d}: CUDA is not available on this machine (torch {torch.__version__}); "
                             "use --device cpu or auto")
        return d
    raise ValueError(f"unknown device {name!r}: use one of {', '.join(DEVICES)} (or cuda:N)")


def check_prior_name(spec: str | os.PathLike[str]) -> None:
    """Refuse a bare prior name that is neither shipped nor analytic, in one line that lists the valid names (a
    path is left to the loader).

    Raises:
        FileNotFoundError: an unknown name.
    """
    s = str(spec)
    if s.endswith(".pt") or os.sep in s or "/" in s:
        return
    names = available_priors()
    if s not in names:
        raise FileNotFoundError(f"unknown shape prior {s!r}: give one of {', '.join(names)} or a .pt file")


def load_prior_spec(spec: str | os.PathLike[str], *, device: str = "cpu") -> ShapePriorLike:
    """Load one prior: a name of `ANALYTIC_PRIORS`, a name under ``efem_viz/weights/`` or a ``.pt`` path.

    Raises:
        FileNotFoundError: a weights file is missing.
        ValueError: the file is not a prior.
    """
    factory = ANALYTIC_PRIORS.get(str(spec))
    if factory is not None:
        return factory().to(device)
    check_prior_name(spec)
    from efem_viz.prior.model import load_prior

    return load_prior(spec, device=device)


def load_priors(specs: Sequence[str | os.PathLike[str]], *, device: str = "cpu") -> list[ShapePriorLike]:
    """Load the priors of a multi-category solve (`run_em(scene, priors=...)`), each once.

    Args:
        specs: each a name of `ANALYTIC_PRIORS` (``"sphere"``, efem_viz/prior/analytic.py), a name under
            ``efem_viz/weights/`` (``"mug"``) or a ``.pt`` path.
        device: target device.

    Returns:
        The priors in the order given (each satisfies `ShapePriorLike`).

    Raises:
        ValueError: no specs, the same spec twice, or two priors with the same category name.
        FileNotFoundError: a weights file is missing.
    """
    if not specs:
        raise ValueError("give at least one prior")
    seen = [str(s) for s in specs]
    if len(set(seen)) != len(seen):
        raise ValueError(f"a prior is given twice: {seen}")
    out = [load_prior_spec(spec, device=device) for spec in specs]
    _check_distinct_categories(out)
    return out


def _check_distinct_categories(priors: Sequence[ShapePriorLike]) -> None:
    names = [prior_category(p).name for p in priors]
    if len(set(names)) != len(names):
        raise ValueError(f"two priors share a category name: {names}; give each prior its own category")


class PriorSet:
    """The priors of one app or run, each loaded once; thread-safe (viser callbacks and workers share one).

    A set has a primary prior (`primary()`: the one-prior runs and the decoding of one-prior traces), optional
    extra run priors (`run_priors()`: a joint solve over the primary and these), and finds any other prior a saved
    multi-prior trace names by its category name (loaded by that name on first use).

    Args:
        primary: spec of the primary prior (an `ANALYTIC_PRIORS` name, a name under ``efem_viz/weights/`` or a
            ``.pt`` path), loaded on first use unless `prior` is given.
        prior: the primary prior, already loaded (then `primary` only names it in messages).
        extra: specs of more priors for runs started with this set (`run_priors()`).
        device: device the priors are loaded on.

    Example:
        >>> priors = PriorSet("sphere")
        >>> priors.primary() is priors.primary()  # loaded once
        True
    """

    def __init__(self, primary: str | os.PathLike[str] = DEFAULT_PRIOR, *, prior: ShapePriorLike | None = None,
                 extra: Sequence[str | os.PathLike[str]] = (), device: str = "cpu") -> None:
        self.primary_spec = str(primary)
        """Spec of the primary prior."""
        self.extra_specs = tuple(str(s) for s in extra)
        """Specs of the extra run priors."""
        self.device = device
        """Device the priors are loaded on."""
        self._lock = threading.RLock()
        self._spec_locks: dict[str, threading.Lock] = {}
        self._by_spec: dict[str, ShapePriorLike] = {}
        self._by_category: dict[str, ShapePriorLike] = {}
        self._primary: ShapePriorLike | None = prior
        self._primary_error: str | None = None
        self._extras: list[ShapePriorLike] | None = None
        if prior is not None:
            self.add(prior)

    @classmethod
    def from_specs(cls, specs: Sequence[str | os.PathLike[str]], *, device: str = "cpu") -> PriorSet:
        """A set of the priors of a solve, all loaded now (`load_priors`): the first is the primary.

        Raises:
            ValueError, FileNotFoundError: as `load_priors`.
        """
        loaded = load_priors(specs, device=device)
        out = cls(specs[0], prior=loaded[0], extra=specs[1:], device=device)
        with out._lock:
            out._by_spec[str(specs[0])] = loaded[0]
            for spec, p in zip(specs[1:], loaded[1:]):
                out._by_spec[str(spec)] = p
                out.add(p)
            out._extras = loaded[1:]
        return out

    def add(self, prior: ShapePriorLike) -> None:
        """Register a loaded prior under its category name (the first one registered for a name stays)."""
        with self._lock:
            self._by_category.setdefault(prior_category(prior).name, prior)

    def get(self, spec: str | os.PathLike[str]) -> ShapePriorLike:
        """The prior of a spec, loaded on first use (a second thread asking for it meanwhile waits for that load).

        Raises:
            FileNotFoundError: a weights file is missing.
            ValueError: the file is not a prior.
        """
        key = str(spec)
        with self._lock:
            if key in self._by_spec:
                return self._by_spec[key]
            spec_lock = self._spec_locks.setdefault(key, threading.Lock())
        with spec_lock:
            with self._lock:
                if key in self._by_spec:
                    return self._by_spec[key]
            prior = load_prior_spec(spec, device=self.device)  # outside the set's lock: lookups go on meanwhile
            with self._lock:
                self._by_spec[key] = prior
                self.add(prior)
            return prior

    def primary(self) -> ShapePriorLike:
        """The primary prior (loaded on first use; a failed load is not retried).

        Raises:
            RuntimeError: the primary prior is unavailable (the message says why).
        """
        with self._lock:
            if self._primary is not None:
                return self._primary
            if self._primary_error is not None:
                raise RuntimeError(self._primary_error)
        try:
            prior = self.get(self.primary_spec)
        except Exception as exc:  # noqa: BLE001 - any failure to load makes the prior unavailable
            with self._lock:
                self._primary_error = f"shape prior {self.primary_spec!r} unavailable: {exc}"
            raise RuntimeError(self._primary_error) from exc
        with self._lock:
            if self._primary is None:
                self._primary = prior
            return self._primary

    def run_priors(self) -> list[ShapePriorLike] | None:
        """The priors of a run started with this set: None for the primary alone (no extra specs), else
        [primary, *extras] (the extras loaded once; they then also decode the proposals of their categories).

        Raises:
            RuntimeError: the primary prior is unavailable.
            ValueError, FileNotFoundError: an extra prior cannot be loaded (as `load_priors`).
        """
        if not self.extra_specs:
            return None
        primary = self.primary()
        with self._lock:
            if self._extras is None:
                self._extras = [self.get(s) for s in _distinct(self.extra_specs)]
                _check_distinct_categories(self._extras)
            return [primary, *self._extras]

    def solve_priors(self, category: str | None = None) -> list[ShapePriorLike]:
        """The priors a solve started with this set passes to `run_em(priors=...)`: `run_priors()`, or the primary
        alone (the one place that decides; `run_em` treats `priors=[p]` as `prior=p`). With `category` (the prior a
        scene was made for, `efem_viz.em.config.suggested_prior`), a one-prior set whose primary is of another
        category solves with that category's prior instead (`named`).

        Raises:
            RuntimeError: the primary prior is unavailable, or the category's.
            ValueError, FileNotFoundError: an extra prior cannot be loaded (as `load_priors`).
        """
        if category is not None and self._replaced_by(category):
            return self.named([category])
        return self.run_priors() or [self.primary()]

    def solve_category(self, category: str | None = None) -> str:
        """The category of the prior `solve_priors(category)` leads with, without loading a scene's own prior (the
        preset follows it: `efem_viz.em.config.suggested_preset`).

        Raises:
            RuntimeError: the primary prior is unavailable.
        """
        if category is not None and self._replaced_by(category):
            return category
        return prior_category(self.primary()).name

    def _replaced_by(self, category: str) -> bool:
        """Whether a solve for a scene made for ``category`` replaces a one-prior set's primary with that category's
        prior (`solve_priors`)."""
        return not self.extra_specs and prior_category(self.primary()).name != category

    def named(self, names: Sequence[str]) -> list[ShapePriorLike]:
        """The priors of a multi-prior run by category name: the priors loaded here where the name matches, the
        others loaded by that name once.

        Raises:
            RuntimeError: one is unavailable.
        """
        with self._lock:
            if self._primary is not None:
                self.add(self._primary)
            missing = [n for n in names if n not in self._by_category]
        try:
            for n in missing:
                p = self.get(n)
                with self._lock:
                    self._by_category.setdefault(n, p)
        except (OSError, ValueError) as exc:
            raise RuntimeError(f"the priors of this run {list(names)} are unavailable: {exc}") from exc
        with self._lock:
            return [self._by_category[n] for n in names]

    def for_trace(self, trace: TraceLike, pid: int | None = None) -> ShapePriorLike:
        """The prior of a trace's proposal `pid`: for a one-prior run the primary prior when the run's recorded
        category is the primary's (or none is recorded), else the prior of that category (`named`: a chair run
        opened in a viewer started with the mug prior decodes with the chair prior), checked against the latent
        size recorded in the trace; for a multi-prior run the prior of the proposal's category.

        Raises:
            RuntimeError: no prior, the run's prior unavailable, one whose latent size differs from the trace's
                (another prior's run), or a multi-prior run asked without `pid`.
        """
        names = tuple(trace.prior_names or ())
        if len(names) > 1:
            if pid is None:
                raise RuntimeError(f"this run used several priors {list(names)}: shapes are decoded per proposal")
            return self.named(names)[trace.prior_index(int(pid))]
        prior = self.primary()
        if names and prior_category(prior).name != names[0]:
            prior = self.named(names)[0]
        c_trace = int(np.asarray(trace.row_R).shape[1]) if len(trace.row_R) else None
        c_prior = getattr(getattr(prior, "config", None), "latent_dim", None)  # analytic priors have no config
        if c_trace is not None and c_prior is not None and int(c_prior) != c_trace:
            raise RuntimeError(
                f"this trace was recorded with a prior of latent size {c_trace}, but the prior "
                f"{prior.name!r} has latent size {c_prior}; give the prior used for the run (--prior)"
            )
        return prior

    def for_run(self, trace: TraceLike) -> ShapePriorLike | list[ShapePriorLike]:
        """What the replay functions take as a run's priors (`PriorArg`): the prior of a one-prior run
        (`for_trace`), or the list of priors of a multi-prior run in the run's order (`named`).

        Raises:
            RuntimeError: as `for_trace` and `named`.
        """
        names = tuple(trace.prior_names or ())
        return self.named(names) if len(names) > 1 else self.for_trace(trace)


def _distinct(specs: Sequence[str]) -> list[str]:
    if len(set(specs)) != len(specs):
        raise ValueError(f"a prior is given twice: {list(specs)}")
    return list(specs)
