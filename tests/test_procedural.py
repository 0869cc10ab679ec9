"""Tests of the procedural shape generators (efem_viz.data.procedural)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
import trimesh

from efem_viz.data.procedural import (
    CATEGORIES,
    HANDLE_SHAPES,
    PROFILES,
    MugParams,
    make_mug,
    make_mug_with_parts,
    make_shape,
    make_shape_with_parts,
    sample_mug_params,
    split_seeds,
)


def _first_seed_per_combo(limit: int = 3000) -> dict[tuple[str, str], int]:
    found: dict[tuple[str, str], int] = {}
    for s in range(limit):
        p = sample_mug_params(s)
        found.setdefault((p.profile, p.handle), s)
        if len(found) == len(PROFILES) * len(HANDLE_SHAPES):
            break
    return found


def _assert_solid(m: trimesh.Trimesh, what: str) -> None:
    assert m.is_watertight, f"{what} not watertight"
    assert m.is_winding_consistent, f"{what} has inconsistent winding"
    assert m.volume > 0, f"{what} has volume {m.volume}"
    assert np.abs(m.bounds.mean(axis=0)).max() < 1e-9, f"{what} not centred at its bbox centre"


@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_mugs_watertight_over_seeds(split: str) -> None:
    seeds = split_seeds("mug", split)
    for s in list(seeds[:25]) + list(seeds[-5:]):
        m = make_mug(s)
        _assert_solid(m, f"mug {s}")
        assert m.body_count == 1, f"mug {s} has {m.body_count} bodies (handle not attached?)"
        assert 1500 <= len(m.faces) <= 7000, f"mug {s}: {len(m.faces)} faces"


def test_every_profile_and_handle_combination_occurs_and_is_solid() -> None:
    combos = _first_seed_per_combo()
    missing = set(itertools.product(PROFILES, HANDLE_SHAPES)) - set(combos)
    assert not missing, f"combinations never drawn: {sorted(missing)}"
    for (profile, handle), s in combos.items():
        m = make_mug(s)
        _assert_solid(m, f"mug {s} ({profile}, {handle})")
        assert m.body_count == 1


def test_handle_less_fraction_and_shape_variety() -> None:
    params = [sample_mug_params(s) for s in range(400)]
    frac_none = np.mean([p.handle == "none" for p in params])
    assert 0.08 <= frac_none <= 0.22, frac_none
    radii = np.array([p.radius for p in params])
    heights = np.array([p.height for p in params])
    walls = np.array([p.wall for p in params])
    assert radii.min() >= 0.03 and radii.max() <= 0.06 and np.ptp(radii) > 0.02
    assert heights.min() >= 0.06 and heights.max() <= 0.13 and np.ptp(heights) > 0.04
    assert walls.min() >= 0.003 and walls.max() <= 0.008


def test_mug_deterministic_and_seed_dependent() -> None:
    a, b, c = make_mug(123), make_mug(123), make_mug(124)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert sample_mug_params(123) == sample_mug_params(123)
    assert sample_mug_params(123) != sample_mug_params(124)
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


def test_canonical_frame_open_top_and_handle_on_plus_x() -> None:
    for s in range(200_000, 200_012):
        p = sample_mug_params(s)
        m = make_mug(s)
        lo, hi = m.bounds
        # height along +Z equals the body height; footprint matches the body radius (handle along +X)
        assert abs((hi[2] - lo[2]) - p.height) < 1e-3
        assert abs((hi[1] - lo[1]) / 2 - p.radius) < 2e-3
        # open top: just below the rim on the axis is empty space; just above the foot is solid (the bottom)
        x_axis = lo[0] + (hi[1] - lo[1]) / 2  # the body axis; the bbox centre is shifted towards the handle
        inside = m.contains(np.array([[x_axis, 0.0, hi[2] - 0.01], [x_axis, 0.0, lo[2] + p.bottom / 2]]))
        assert not inside[0] and inside[1], f"mug {s}: not an open cup with +Z up"
        if p.handle != "none":
            assert hi[0] - x_axis > x_axis - lo[0] + 0.01, f"mug {s}: handle not on +X"
        else:
            assert abs(x_axis) < 1e-3


def test_explicit_params_and_validation() -> None:
    p = sample_mug_params(7)
    q = dataclasses.replace(p, handle="none")
    m = make_mug(0, params=q)
    _assert_solid(m, "handle-less replacement")
    assert abs(m.extents[0] - m.extents[1]) < 1e-3  # rotationally symmetric without a handle
    with pytest.raises(ValueError, match="profile"):
        bad = MugParams(**{**dataclasses.asdict(p), "profile": "cone"})  # type: ignore[arg-type]
        bad.outer_radius(np.zeros(1))


def test_splits_disjoint_and_errors() -> None:
    for cat in CATEGORIES:
        r = {s: set(split_seeds(cat, s)) for s in ("train", "val", "test")}  # type: ignore[arg-type]
        assert not (r["train"] & r["val"]) and not (r["train"] & r["test"]) and not (r["val"] & r["test"])
        assert len(r["train"]) >= 10_000 and len(r["val"]) >= 500 and len(r["test"]) >= 500
    with pytest.raises(ValueError, match="split"):
        split_seeds("mug", "dev")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="category"):
        split_seeds("sofa", "train")
    with pytest.raises(ValueError, match="category"):
        make_shape("sofa", 0)


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_registry_categories_solid_and_sized(category: str) -> None:
    spec = CATEGORIES[category]
    lo, hi = spec.size_range
    for s in range(6):
        m = make_shape(category, s)
        _assert_solid(m, f"{category} {s}")
        assert lo - 0.01 <= m.extents.max() <= hi + 0.01, f"{category} {s}: size {m.extents}"
        assert np.array_equal(m.vertices, spec.generator(s).vertices)


@pytest.mark.parametrize("category", ["mug", "bowl", "bottle", "can"])
def test_collision_parts_lie_on_or_inside_the_solid(category: str) -> None:
    for s in (1, 2, 3):
        m, parts = make_shape_with_parts(category, s)
        pts = np.concatenate(parts)
        # trimesh: signed distance > 0 inside; allow the facetting error of the revolved surfaces
        sd = trimesh.proximity.signed_distance(m, pts)
        assert sd.min() > -1e-3, f"{category} {s}: collision piece {-sd.min() * 1e3:.2f} mm outside the mesh"
        # the pieces cover the object: its bounding box is (nearly) the pieces' bounding box
        assert np.allclose(pts.min(0), m.bounds[0], atol=3e-3)
        assert np.allclose(pts.max(0), m.bounds[1], atol=3e-3)


def test_mug_parts_frame_matches_mesh() -> None:
    m1 = make_mug(42)
    m2, parts = make_mug_with_parts(42)
    assert np.array_equal(m1.vertices, m2.vertices)
    assert len(parts) > 10


def test_the_chair_family_is_varied_watertight_and_canonical() -> None:
    """60 chairs of the train split: every base (four legs, stool, sled, cantilever, swivel), every back (solid,
    slatted, curved, none) and both arm variants appear; each chair is one watertight solid, +Z up with its
    bounding-box centre at the origin, its back toward +Y; the same seed gives the same chair."""
    from efem_viz.data.chairs import BACKS, BASES, chair_with_parts, sample_chair_params

    seen_bases, seen_backs, seen_arms = set(), set(), set()
    for seed in range(60):
        p = sample_chair_params(seed)
        mesh, parts = chair_with_parts(seed)
        seen_bases.add(p.base)
        seen_backs.add(p.back)
        seen_arms.add(p.arms)
        assert mesh.is_watertight and mesh.volume > 0 and len(mesh.split(only_watertight=False)) == 1, seed
        assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        assert 0.3 < mesh.extents[2] < 1.2 and max(mesh.extents[:2]) < 0.8, (seed, mesh.extents)
        assert all(len(q) >= 4 for q in parts)
        if p.back != "none":  # the back stands at +Y: the upper part of the chair lies behind the middle
            v = np.asarray(mesh.vertices)
            top = v[v[:, 2] > mesh.bounds[1, 2] - 0.1]
            assert top[:, 1].mean() > 0.0, seed
    assert seen_bases == set(BASES) and seen_backs == set(BACKS) and seen_arms == {True, False}
    again, _ = chair_with_parts(7)
    assert np.array_equal(again.vertices, chair_with_parts(7)[0].vertices)


def test_the_kitchen_family_interleaves_its_members_over_disjoint_splits() -> None:
    """A training family's objects: member i mod k with seed i div k, balanced in every prefix, the same
    disjoint splits as its members; a category is a family of itself; unknown names raise."""
    from efem_viz.data.procedural import FAMILIES, family_members, family_seeds
    from efem_viz.prior.data import procedural_sources

    assert family_members("kitchen") == FAMILIES["kitchen"] == ("mug", "bowl", "bottle", "can")
    assert family_members("mug") == ("mug",)
    train = family_seeds("kitchen", "train", 10)
    assert train[:5] == [("mug", 0), ("bowl", 0), ("bottle", 0), ("can", 0), ("mug", 1)]
    assert [c for c, _ in train].count("mug") == 3 and [c for c, _ in train].count("can") == 2
    val = family_seeds("kitchen", "val", 8)
    assert {s for _, s in val}.isdisjoint({s for _, s in family_seeds("kitchen", "train", 4000)})
    assert [n for n, _ in procedural_sources("kitchen", "val", 3)] == ["mug_100000", "bowl_100000", "bottle_100000"]
    mesh = procedural_sources("kitchen", "train", 3)[2][1]()
    assert mesh.is_watertight and mesh.extents[2] > 0.14  # a bottle: 15-26 cm tall
    with pytest.raises(ValueError, match="unknown category"):
        family_members("pantry")
    with pytest.raises(ValueError, match="asked for"):
        family_seeds("kitchen", "val", 4001)
    with pytest.raises(ValueError, match="handled_only"):
        procedural_sources("kitchen", "train", 4, handled_only=True)
