"""Shape priors: SIM(3)-equivariant encoder + invariant SDF decoder (torch; never imports viser).

Public names are re-exported lazily (``from efem_viz.prior import load_prior``) so that importing the package,
as the CLI does for ``efem_viz.prior.train``, stays free of torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from efem_viz.prior.config import CategorySettings as CategorySettings, PriorConfig as PriorConfig
    from efem_viz.prior.config import ShapePriorLike as ShapePriorLike
    from efem_viz.prior.model import Latent as Latent, ShapePrior as ShapePrior
    from efem_viz.prior.convert import convert_released_checkpoint as convert_released_checkpoint
    from efem_viz.prior.model import load_prior as load_prior, save_prior as save_prior
    from efem_viz.prior.registry import PriorSet as PriorSet, load_priors as load_priors

_LAZY = {
    "Latent": "efem_viz.prior.model",
    "PriorConfig": "efem_viz.prior.config",
    "CategorySettings": "efem_viz.prior.config",
    "ShapePriorLike": "efem_viz.prior.config",
    "load_priors": "efem_viz.prior.registry",
    "PriorSet": "efem_viz.prior.registry",
    "ShapePrior": "efem_viz.prior.model",
    "load_prior": "efem_viz.prior.model",
    "save_prior": "efem_viz.prior.model",
    "convert_released_checkpoint": "efem_viz.prior.convert",
}

__all__ = ["CategorySettings", "Latent", "PriorConfig", "ShapePriorLike", "PriorSet", "load_priors", "ShapePrior",
           "convert_released_checkpoint", "load_prior", "save_prior"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
