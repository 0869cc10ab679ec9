"""Loading the priors of a solve by name: shipped weights, .pt files and the analytic priors.

The one place that knows every kind of prior, so that prior/model.py (trained priors) and prior/analytic.py
(closed-form priors) need not know each other.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from efem_viz.prior.model import load_prior

def _sphere() -> Any:
    from efem_viz.prior.analytic import make_sphere_prior

    return make_sphere_prior()


ANALYTIC_PRIORS: dict[str, Callable[[], Any]] = {"sphere": _sphere}
"""Closed-form priors by name (no weights file): name → factory. Register a new one here."""


def load_priors(specs: Sequence[str | os.PathLike[str]], *, device: str = "cpu") -> list[Any]:
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
    out: list[Any] = []
    for spec in specs:
        factory = ANALYTIC_PRIORS.get(str(spec))
        if factory is not None:
            out.append(factory().to(device))
        else:
            out.append(load_prior(spec, device=device))
    names = [p.category.name for p in out]
    if len(set(names)) != len(names):
        raise ValueError(f"two priors share a category name: {names}; give each prior its own category")
    return out
