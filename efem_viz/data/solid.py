"""What every procedural shape generator ends with: the solid checked, then moved into the canonical frame."""

from __future__ import annotations

import numpy as np
import trimesh


def finish_solid(
    mesh: trimesh.Trimesh, parts: list[np.ndarray], what: str
) -> tuple[trimesh.Trimesh, list[np.ndarray]]:
    """Check the solid, then move mesh and pieces into the canonical frame (bbox centre at the origin)."""
    if not mesh.is_watertight or mesh.volume <= 0:
        raise RuntimeError(
            f"{what} is not a watertight solid (watertight={mesh.is_watertight}, volume={mesh.volume})"
        )
    shift = -mesh.bounds.mean(axis=0)
    mesh.apply_translation(shift)
    return mesh, [np.asarray(q, np.float64) + shift for q in parts]
