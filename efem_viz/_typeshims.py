"""Typed access to two third-party APIs whose shipped type information is missing or wrong.

Nothing here changes what runs: `cKDTree` *is* `scipy.spatial.cKDTree` and `o3d_tensor(x)` *is*
`open3d.core.Tensor(x)`; the module only gives pyright (run by tests/test_types.py) something to check.
scipy and open3d are imported on first use, as at the call sites before, so importing this module is cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

if TYPE_CHECKING:
    import open3d as o3d
    from numpy.typing import ArrayLike

    class cKDTree:
        """What pyright is told about `scipy.spatial.cKDTree`: scipy's signatures of the members used here.

        scipy ships no stub for its compiled `scipy.spatial._ckdtree`, so pyright cannot see the class at all
        ("unknown import symbol"). `KDTree`, its pure-Python subclass, is no stand-in: its `query` wraps
        scalar indices in np.intp. Query results are `Any`: scalar or array, list or array of lists,
        depending on the shape of the query. At run time the name is the real `scipy.spatial.cKDTree`.
        """

        def __init__(self, data: ArrayLike, leafsize: int = ..., compact_nodes: bool = ...,
                     copy_data: bool = ..., balanced_tree: bool = ...,
                     boxsize: ArrayLike | None = ...) -> None: ...

        def query(self, x: ArrayLike, k: int | Sequence[int] = ..., eps: float = ..., p: float = ...,
                  distance_upper_bound: float = ..., workers: int = ...) -> tuple[Any, Any]: ...

        def query_ball_point(self, x: ArrayLike, r: ArrayLike, p: float = ..., eps: float = ...,
                             workers: int = ..., return_sorted: bool | None = ...,
                             return_length: bool = ...) -> Any: ...

else:

    def __getattr__(name: str) -> Any:  # lazy: `scipy.spatial` is imported on first use, as before
        if name == "cKDTree":
            from scipy.spatial import cKDTree

            return cKDTree
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["cKDTree", "o3d_tensor"]


def o3d_tensor(data: np.ndarray | list[float]) -> o3d.core.Tensor:
    """`open3d.core.Tensor(data)`: dtype inferred from `data`, device CPU:0 (open3d's defaults).

    open3d's generated stubs (seen in 0.20) drop the defaults of the constructor's `dtype` and `device`
    arguments, so the documented one-argument call does not type-check; this wrapper keeps the workaround to
    one line.

    Args:
        data: a numpy array (copied) or a nested list of numbers.

    Returns:
        The open3d tensor.
    """
    import open3d as o3d

    # open3d stub bug (see above): `dtype` and `device` are typed as required although they have defaults.
    return o3d.core.Tensor(data)  # pyright: ignore[reportCallIssue]
