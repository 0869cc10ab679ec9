"""Tests of the chair scenes of the synthetic scan generator (`generate_scene(..., targets="chair")`, the paper's
SynChairs): chairs on a room floor, scanned from a few metres and fused with the floor stage's 1 cm voxel.
Two chairs and 320 x 240 cameras keep each scene to a few seconds."""

from __future__ import annotations

import shlex
from functools import lru_cache

import numpy as np
import pytest

from efem_viz.data.scene import Scene
from synth_helpers import distance_to, world_meshes
from efem_viz.data.synth import (
    FLOOR,
    PENETRATION_TOLERANCE,
    TABLETOP,
    GenerateArgs,
    contact_report,
    generate_scene,
    stage_for,
)

SMALL = dict(image_size=(320, 240), n_objects=2, targets="chair")
SEEDS = {"z": 0, "so3": 0, "pile": 1}
"""A seed per configuration (pile 1: the second chair lands on the first)."""


@lru_cache(maxsize=None)
def _chairs(config: str, seed: int) -> Scene:
    return generate_scene(config, seed=seed, **SMALL)  # type: ignore[arg-type]






@pytest.mark.parametrize("config", ["z", "so3", "pile"])
def test_chair_scene_labels_each_chair_on_its_surface_within_the_floor_crop(config: str) -> None:
    """Labels 1 and 2 are the two chairs (distractors are furniture blocks with label 0), each with thousands of
    points lying on its true surface; every point lies in the scan's crop on the floor; the poses rest on the
    floor or on each other without interpenetrating."""
    s = _chairs(config, SEEDS[config])
    p = s.provenance
    assert p["targets"] == "chair" and "--targets chair" in p["command"]
    assert p["floor"] == {"half_size": FLOOR.half_size, "top_z": 0.0} and "table" not in p
    assert p["voxel"] == FLOOR.voxel and p["label_tolerance"] == FLOOR.label_tolerance
    objs = p["objects"]
    assert [o["instance_id"] for o in objs if o["category"] == "chair"] == [1, 2]
    assert {o["category"] for o in objs if o["instance_id"] == 0} <= {"cabinet"}
    assert set(s.instance_ids().tolist()) == {1, 2} and s.categories == {1: "chair", 2: "chair"}
    meshes = world_meshes(s)
    for o, m in zip(objs, meshes):
        if o["instance_id"] == 0:
            continue
        lab = s.instance == o["instance_id"]
        assert lab.sum() > 2000, f"chair {o['instance_id']}: {lab.sum()} points"
        d = distance_to(m, s.points[lab])
        assert d.max() < FLOOR.label_tolerance + 1e-6
        assert np.median(d) < 0.5 * FLOOR.voxel, f"labelled points lie {np.median(d) * 1e3:.1f} mm from the chair"
    lo, hi = (np.asarray(c) for c in p["crop"])
    assert np.all(s.points >= lo - FLOOR.voxel - 1e-4) and np.all(s.points <= hi + FLOOR.voxel + 1e-4)
    assert np.abs(s.points[:, :2]).max() <= FLOOR.half_size and lo[2] >= -FLOOR.crop_below - 1e-6
    floor = (s.instance == 0) & (np.abs(s.points[:, 2]) < 0.03)
    assert floor.sum() > 5000, "the cameras see the floor"
    assert np.std(s.points[floor, 2]) < 0.01, "Kinect-like noise at 2-4 m leaves the fused floor within a cm"
    rep = contact_report(meshes, rays=3)
    assert rep["max_penetration"] <= PENETRATION_TOLERANCE
    assert rep["gap"].max() < 0.005, f"an object floats: {rep['gap']}"
    # the cameras stand 2-3.5 m from the chairs' centre, 1.2-1.7 m high
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, FLOOR.aim_height])
    eyes = np.array([np.asarray(c["T_world_camera"])[:3, 3] for c in p["cameras"]])
    assert np.all((eyes[:, 2] >= 1.2) & (eyes[:, 2] <= 1.7))
    dist = np.linalg.norm(eyes - centre, axis=1)
    assert np.all((dist > 2.0) & (dist < 3.5)), dist


def test_z_chairs_stand_upright_on_the_floor_with_disjoint_footprints() -> None:
    s = _chairs("z", SEEDS["z"])
    meshes = world_meshes(s)
    for o, m in zip(s.provenance["objects"], meshes):
        T = np.asarray(o["T_world_object"])
        assert np.allclose(T[:3, 2], [0, 0, 1], atol=1e-6), f"{o['category']} not upright"
        assert abs(m.bounds[0, 2]) < 1e-6, "not standing on the floor"
        if o["instance_id"] > 0:
            z_min = s.points[s.instance == o["instance_id"], 2].min()
            assert abs(z_min) < 0.02, f"chair {o['instance_id']}: lowest labelled point at {z_min * 1e3:.0f} mm"
    rep = contact_report(meshes, rays=3)
    assert rep["max_penetration"] < 1e-4
    pair = np.minimum(rep["pair_gap"], rep["pair_gap"].T)
    assert np.all(pair[~np.eye(len(meshes), dtype=bool)] > 0.005), "footprints overlap"


def test_so3_chairs_tip_over_and_pile_chairs_lean_on_each_other() -> None:
    so3 = _chairs("so3", SEEDS["so3"])
    ups = [np.asarray(o["T_world_object"])[2, 2] for o in so3.provenance["objects"] if o["instance_id"] > 0]
    assert min(ups) < 0.7, f"all chairs nearly upright: {np.round(ups, 2)}"
    pile = _chairs("pile", SEEDS["pile"])
    chairs = [m for o, m in zip(pile.provenance["objects"], world_meshes(pile)) if o["instance_id"] > 0]
    rep = contact_report(chairs, rays=3)
    assert min(rep["pair_gap"][0, 1], rep["pair_gap"][1, 0]) < 0.005, "the chairs do not touch"
    assert max(m.bounds[0, 2] for m in chairs) > 0.03, "no chair lies on another"


def test_chair_scene_is_deterministic() -> None:
    a = _chairs("pile", SEEDS["pile"])
    b = generate_scene("pile", seed=SEEDS["pile"], **SMALL)  # type: ignore[arg-type]
    assert a.faces is not None and b.faces is not None and a.instance is not None and b.instance is not None
    assert np.array_equal(a.points, b.points) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.instance, b.instance) and np.array_equal(a.colors, b.colors)
    assert a.provenance == b.provenance


def test_default_voxel_is_the_stages_and_the_command_repeats_the_scene() -> None:
    """1 cm for chairs, 4 mm for mugs when no voxel is given; the recorded command leaves the default out and
    parses back to the same arguments; a voxel of one's own is recorded and repeated."""
    import tyro

    assert stage_for("chair") is FLOOR and stage_for("mug") is TABLETOP and stage_for("kitchen") is TABLETOP
    assert (FLOOR.voxel, TABLETOP.voxel) == (0.01, 0.004)
    assert GenerateArgs().voxel is None
    chairs = _chairs("z", SEEDS["z"]).provenance
    assert chairs["voxel"] == 0.01 and "--voxel" not in chairs["command"]
    args = tyro.cli(GenerateArgs, args=shlex.split(chairs["command"])[2:])
    assert (args.config, args.seed, args.targets, args.objects, args.voxel) == ("z", 0, "chair", 2, None)
    mugs = generate_scene("z", seed=0, n_objects=1, distractors=False, image_size=(64, 48)).provenance
    assert mugs["voxel"] == 0.004 and mugs["label_tolerance"] == 0.01 and "--voxel" not in mugs["command"]
    assert "targets" not in mugs and mugs["table"]["half_size"] == TABLETOP.half_size
    own = generate_scene("z", seed=0, n_objects=1, distractors=False, image_size=(64, 48), voxel=0.006)
    assert own.provenance["voxel"] == 0.006 and "--voxel 0.006" in own.provenance["command"]


def test_structure_configs_refuse_chairs() -> None:
    for bad in ("tree", "box", "shelf"):
        with pytest.raises(ValueError, match="holds mugs only"):
            generate_scene(bad, seed=0, targets="chair")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown targets"):
        generate_scene("z", seed=0, targets="sofa")
