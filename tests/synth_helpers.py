"""Ground-truth geometry of generated scenes, for the scene generator's tests."""

from __future__ import annotations

import numpy as np

from efem_viz.data.scene import Scene


def world_meshes(scene: Scene) -> list:
    """The scene's objects (labelled and distractors) rebuilt from its provenance, posed in the world."""
    from efem_viz.data.procedural import make_shape

    out = []
    for o in scene.provenance["objects"]:
        m = make_shape(o["category"], o["seed"])
        m.apply_transform(np.asarray(o["T_world_object"]))
        out.append(m)
    return out


def distance_to(mesh, pts: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance of points to a mesh's surface."""
    import open3d as o3d

    from efem_viz._typeshims import o3d_tensor

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d_tensor(np.asarray(mesh.vertices, np.float32)), o3d_tensor(np.asarray(mesh.faces, np.uint32)))
    return rc.compute_distance(o3d_tensor(pts.astype(np.float32))).numpy()
