"""Tests of efem_viz.colors: one palette, and the same colour for the same instance in the viewer, the coloured
PLY export and the annotator (an EFEM instance with proposal id p → `instance_colors([p])` everywhere, unless a
neighbour's colour is too close: `result_colors`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from efem_viz.colors import instance_color, instance_colors


@pytest.fixture(scope="module")
def sphere_result() -> tuple[Any, Any]:
    """A small sphere scene and its EM result, with three instances whose confidences differ (0.3, 0.9, 0.6)."""
    from efem_viz.em import preset, run_em
    from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

    scene = make_sphere_scene(seed=11)
    res = run_em(scene, make_sphere_prior(), preset("fast").replace(proposals={"n_init": (16,)}), seed=5)
    inst = res.instances
    assert len(inst) >= 2
    # a third instance (a copy of the first, holding unassigned points) and confidences that make a threshold
    # drop the first instance
    k = len(inst)
    fields: dict[str, object] = {}
    for f in dataclasses.fields(inst):
        v = getattr(inst, f.name)
        if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == k:
            fields[f.name] = np.concatenate([v[:2], v[:1]])
        elif isinstance(v, list) and len(v) == k:
            fields[f.name] = [*v[:2], v[0]]
    free = np.setdiff1d(np.arange(scene.num_points), np.concatenate(inst.masks))[:200].astype(np.int32)
    fields["masks"] = [*inst.masks[:2], free]
    fields["ids"] = np.append(inst.ids[:2], next(i for i in range(res.trace.num_proposals) if i not in inst.ids))
    fields["confidence"] = np.array([0.3, 0.9, 0.6], inst.confidence.dtype)
    three = dataclasses.replace(inst, **fields)
    return scene, dataclasses.replace(res, instances=three)


def test_palette_is_deterministic_and_distinct() -> None:
    ids = np.arange(1, 21)
    a = instance_colors(ids)
    assert a.dtype == np.uint8 and a.shape == (20, 3)
    np.testing.assert_array_equal(a, instance_colors(ids))  # deterministic
    np.testing.assert_array_equal(a[::-1], instance_colors(ids[::-1]))  # a colour depends on its id only
    assert instance_colors([]).shape == (0, 3)
    # distinct: every pair of the first 20 ids is clearly apart in RGB
    d = np.linalg.norm(a[:, None].astype(float) - a[None].astype(float), axis=-1) + np.eye(20) * 1e9
    assert d.min() > 30.0
    for i in (0, 1, 7, 20, 12345):
        assert instance_color(i) == tuple(int(c) for c in instance_colors([i])[0])
        assert all(type(c) is int for c in instance_color(i))


@pytest.mark.parametrize("threshold", [0.0, 0.5])
def test_viewer_ply_export_and_annotator_agree(sphere_result: tuple, tmp_path: Path, threshold: float) -> None:
    from annotator.io import _read_efem
    from efem_viz.data.io import load_scene
    from efem_viz import colors as pal
    from efem_viz.colors import result_colors

    scene, res = sphere_result
    inst = res.instances
    n = scene.num_points
    shown = inst.above(threshold)
    labels = shown.label_array(n)  # the label k + 1 of the k-th shown instance, in every export
    assert len(shown) == (3 if threshold == 0 else 2)
    every = result_colors(inst)  # over the whole result: a cut changes no colour
    expected = {k + 1: tuple(int(c) for c in every[inst.kept(threshold)][k]) for k in range(len(shown))}
    assert len(set(expected.values())) == len(expected)

    # viewer: the points of each shown instance, and its mesh/box/swatch colour
    view = pal.instance_point_colors(scene.colors, inst, inst.kept(threshold))
    meshes = result_colors(inst)[inst.kept(threshold)]
    # the coloured PLY export (efem-viz segment --ply, the viewer's export) at the same threshold
    ply = load_scene(inst.to_colored_ply(scene, tmp_path / "seg.ply", threshold=threshold))
    np.testing.assert_array_equal(ply.instance, labels)
    # the annotator importing the EFEM result at the same threshold (as pre-labels numbered k + 1)
    imported = _read_efem(res.save(tmp_path / f"{scene.name}.efem.npz"), n, threshold=threshold)
    np.testing.assert_array_equal(imported.labels, labels)
    annotator = {r.id: r.color for r in imported.instances}
    for lab, col in expected.items():
        pts = labels == lab
        assert {tuple(int(c) for c in v) for v in view[pts]} == {col}
        assert tuple(int(c) for c in meshes[lab - 1]) == col
        assert {tuple(int(c) for c in v) for v in ply.colors[pts]} == {col}
        assert annotator[lab] == col


def test_annotator_new_instances_use_the_palette() -> None:
    from annotator.labels import LabelSet

    ls = LabelSet(10)
    for _ in range(3):
        d = ls.create_instance(category="mug")
        ls.apply(d)
    assert {i: info.color for i, info in ls.instances.items()} == {i: instance_color(i) for i in (1, 2, 3)}


def test_counts_read_as_words() -> None:
    """"result: 1 objects". One plural rule for every count a person reads."""
    from efem_viz.terminal import count

    assert count(1, "object") == "1 object" and count(0, "object") == "0 objects"
    assert count(1204, "point") == "1,204 points" and count(2, "vertex", "vertices") == "2 vertices"


def test_neighbouring_instances_get_clearly_different_colours(sphere_result: tuple) -> None:
    """Two touching instances whose proposal ids have near-identical palette colours (ids 150 and 294: 1.4 apart
    in RGB) are drawn clearly apart; an instance far from every other keeps its id's colour; the colours do not
    depend on which subset is shown (they are chosen over the whole result)."""
    from efem_viz.colors import NEIGHBOUR_COLOR_DISTANCE, result_colors

    _, res = sphere_result
    inst = res.instances
    assert np.linalg.norm(instance_colors([150])[0].astype(float) - instance_colors([294])[0]) < 5
    half = np.full((3, 3), 0.05)
    centers = np.array([[0.0, 0.0, 0.05], [0.09, 0.0, 0.05], [2.0, 2.0, 0.05]])  # two touch, one is far
    near = dataclasses.replace(inst, ids=np.array([150, 294, 151]), obb_center=centers, obb_half_extents=half)
    cols = result_colors(near).astype(float)
    assert np.linalg.norm(cols[0] - cols[1]) >= NEIGHBOUR_COLOR_DISTANCE
    np.testing.assert_array_equal(cols[[0, 2]], instance_colors([150, 151]))  # no neighbour in the way: its own
    far = dataclasses.replace(near, obb_center=centers * np.array([30.0, 1, 1]))  # the first two far apart too
    np.testing.assert_array_equal(result_colors(far), instance_colors([150, 294, 151]))
