"""The batch backend registry: name -> factory (`local`, `process`, `ray`); `make_backend` builds one.

Add a backend by writing a class that implements `efem_viz.batch.backends.Backend` and registering its factory in
`BACKENDS`: `run_batch(..., backend=make_backend(NAME))` runs on it, and `efem-viz segment --backend NAME` accepts
it in any process that imported the registering module (see examples/add_batch_backend.py).
"""

from __future__ import annotations

from collections.abc import Callable

from efem_viz.batch.backends import Backend, BackendOptions, BatchError, LocalBackend, ProcessBackend
from efem_viz.batch.ray_backend import RayBackend

BackendFactory = Callable[[BackendOptions], Backend]
"""Builds a backend from the CLI's options (raises `BatchError` for options it cannot honour)."""

BACKENDS: dict[str, BackendFactory] = {
    "local": LocalBackend,
    "process": ProcessBackend,
    "ray": RayBackend,
}
"""Backend registry: name -> factory."""


def make_backend(name: str, options: BackendOptions | None = None) -> Backend:
    """The backend registered under `name`.

    Raises:
        BatchError: unknown name, or bad options for it (Ray not installed, ...).
    """
    if name not in BACKENDS:
        raise BatchError(f"unknown batch backend {name!r}; choose one of {sorted(BACKENDS)}")
    return BACKENDS[name](options or BackendOptions())
