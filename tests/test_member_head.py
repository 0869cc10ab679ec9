"""The member head: which member of a family prior an instance is, read from its invariant latent."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from efem_viz.prior.member_head import (
    METADATA_KEY,
    MemberHead,
    encoder_fingerprint,
    fit_member_head,
    member_head_of,
    member_size_model,
    object_sizes,
)
from efem_viz.prior.model import WEIGHTS_DIR, load_prior

KITCHEN = WEIGHTS_DIR / "kitchen.pt"


def _head(width: int, *, favour: int = 1, fingerprint: str = "x") -> MemberHead:
    k = 4
    bias = np.zeros(k)
    bias[favour] = 50.0
    return MemberHead(classes=("mug", "bowl", "bottle", "can"), mean=np.zeros(width), std=np.ones(width),
                      weight=np.zeros((k, width)), bias=bias, fingerprint=fingerprint, report={"val_accuracy": 1.0})


def _sized_head(width: int) -> MemberHead:
    """A head whose latent leans a little to "bowl" and whose size model knows the four members' sizes."""
    head = _head(width, favour=1)
    sizes = np.log([[0.056, 0.047], [0.075, 0.029], [0.038, 0.103], [0.035, 0.051]])
    cov = np.stack([np.diag([0.02, 0.03])] * 4)
    return dataclasses.replace(head, bias=np.array([0.0, 1.0, 0.0, 0.0]), size_mean=sizes, size_cov=cov)


def test_a_size_model_names_the_member_whose_size_fits_and_round_trips() -> None:
    """Σ log p: the latent's logits plus each member's log size density; no size, or a size that is not finite
    and positive, leaves the latent alone."""
    head = _sized_head(8)
    inv = np.zeros(8)
    assert head.classify(inv) == "bowl"  # the latent alone
    assert head.classify(inv, radii=np.array([0.038, 0.11])) == "bottle"  # tall and thin
    assert head.classify(inv, radii=np.array([0.034, 0.05])) == "can"
    assert head.classify(inv, radii=np.array([0.08, 0.03])) == "bowl"
    for bad in ([np.nan, 0.05], [0.0, 0.05], [-1.0, 0.05], [np.inf, 1.0]):
        assert head.classify(inv, radii=np.array(bad)) == "bowl"
    p = head.probabilities(np.zeros((3, 8)), np.array([[0.038, 0.11], [np.nan, 1.0], [0.034, 0.05]]))
    assert np.allclose(p.sum(axis=1), 1.0) and p[1].argmax() == 1
    # the size term by hand: a member's Gaussian in log size
    d = np.log([0.038, 0.11]) - head.size_mean[2]
    cov = head.size_cov[2]
    want = -0.5 * d @ np.linalg.solve(cov, d) - 0.5 * np.log(np.linalg.det(cov))
    assert head.size_log_likelihood(np.array([0.038, 0.11]))[0, 2] == pytest.approx(want, rel=1e-12)
    back = MemberHead.from_dict(head.to_dict(), width=8)
    assert np.array_equal(back.size_mean, head.size_mean) and np.array_equal(back.size_cov, head.size_cov)
    assert back.classify(inv, radii=np.array([0.038, 0.11])) == "bottle"
    assert MemberHead.from_dict(_head(8).to_dict(), width=8).size_mean is None  # a head without a size model
    d0 = head.to_dict()
    for changes, pattern in [({"size_cov": [[[1.0, 0.0], [0.0, -1.0]]] * 4}, "positive"),
                             ({"size_cov": [[[1.0, 0.5], [0.0, 1.0]]] * 4}, "symmetric"),
                             ({"size_mean": [[1e6, 0.0]] * 4}, "within"),
                             ({"size_mean": [[0.0, 0.0]] * 3}, "shape"),
                             ({"size_cov": None}, "shape"),
                             ({"size_mean": [[float("nan"), 0.0]] * 4}, "finite")]:
        with pytest.raises(ValueError, match=pattern):
            MemberHead.from_dict({**d0, **changes}, width=8)


def test_the_kitchen_size_model_orders_the_members_as_they_are_made() -> None:
    """Bottles stand tallest, bowls are widest and flattest; per member (k, 2) means and (k, 2, 2) covariances."""
    mean, cov = member_size_model("kitchen", "train", 40)
    radius, half_height = np.exp(mean).T  # mug, bowl, bottle, can
    assert half_height[2] == half_height.max() and radius[1] == radius.max() and half_height[1] == half_height.min()
    assert cov.shape == (4, 2, 2) and (np.linalg.eigvalsh(cov) > 0).all()
    sizes = object_sizes("kitchen", "val", 8)
    assert sizes.shape == (8, 2) and (sizes > 0.01).all() and (sizes < 0.2).all()
    with pytest.raises(ValueError, match="at least 3"):
        member_size_model("kitchen", "train", 8)


def test_a_head_round_trips_and_a_hostile_one_is_refused() -> None:
    head = _head(8)
    back = MemberHead.from_dict(head.to_dict(), width=8)
    assert back.classes == head.classes and np.array_equal(back.weight, head.weight)
    assert back.classify(np.zeros(8)) == "bowl"
    assert np.allclose(back.probabilities(np.zeros((3, 8))).sum(axis=1), 1.0)
    bad: list[tuple[dict[str, Any], str]] = [
        ({**head.to_dict(), "weight": [[float("nan")] * 8] * 4}, "finite"),
        ({**head.to_dict(), "bias": [0.0] * 3}, "shape"),
        ({**head.to_dict(), "std": [0.0] * 8}, "std"),
        ({**head.to_dict(), "classes": ["a"] * 4}, "distinct"),
        ({**head.to_dict(), "classes": [f"c{i}" for i in range(65)]}, "distinct"),
        ({**head.to_dict(), "mean": "1e9" * 10}, "shape|numeric"),
    ]
    for d, pattern in bad:
        with pytest.raises(ValueError, match=pattern):
            MemberHead.from_dict(d, width=8)
    with pytest.raises(ValueError, match="shape"):
        MemberHead.from_dict(head.to_dict(), width=16)  # another prior's latent width


@pytest.mark.skipif(not KITCHEN.is_file(), reason="needs the shipped kitchen prior")
def test_a_head_fitted_on_other_weights_or_damaged_is_ignored_with_a_warning(caplog: pytest.LogCaptureFixture
                                                                             ) -> None:
    prior = load_prior(KITCHEN, load_codebook=False)
    width = prior.config.latent_dim
    prior.metadata = {**prior.metadata, METADATA_KEY: _head(width, fingerprint=encoder_fingerprint(prior)).to_dict()}
    assert member_head_of(prior) is not None
    prior.metadata = {**prior.metadata, METADATA_KEY: _head(width, fingerprint="0123").to_dict()}
    with caplog.at_level(logging.WARNING):
        assert member_head_of(prior) is None
    assert "other encoder weights" in caplog.text
    prior.metadata = {**prior.metadata, METADATA_KEY: {"classes": "mug"}}
    assert member_head_of(prior) is None


def test_the_solver_names_a_family_instance_by_its_head_before_the_codebook_vote() -> None:
    """`Solver._category`: the head's class when the prior has one; else the codebook vote; else the name."""
    from efem_viz.em.solver import Solver

    class Codebook:
        def category_of(self, rows: Any, default: str, *, weights: Any = None) -> str:
            return "can"

    prior = SimpleNamespace(name="kitchen", metadata={}, codebook=Codebook(), config=SimpleNamespace(latent_dim=8))
    fake = SimpleNamespace(categories=["kitchen"], table=SimpleNamespace(priors=[prior]), pose_votes={})
    rev = SimpleNamespace(prior=0, proposal_id=3, neighbours=np.zeros(0, np.int32), radii=np.array([0.04, 0.05]))
    lat = {"inv": np.zeros(8, np.float32), "scale": np.float32(0.1)}
    assert Solver._category(fake, rev, lat) == "can"  # type: ignore[arg-type]
    prior.metadata = {METADATA_KEY: _head(8, favour=1).to_dict()}
    prior.encoder = SimpleNamespace(state_dict=lambda: {})  # the fingerprint of an encoder without weights
    prior.metadata[METADATA_KEY]["fingerprint"] = encoder_fingerprint(prior)
    assert Solver._category(fake, rev, lat) == "bowl"  # type: ignore[arg-type]
    # with a size model, the completed shape's measured size weighs in: a can-sized shape the latent barely calls
    # a bowl is named a can
    sized = dataclasses.replace(_sized_head(8), fingerprint=prior.metadata[METADATA_KEY]["fingerprint"])
    prior.metadata = {METADATA_KEY: sized.to_dict()}
    assert Solver._category(fake, rev, lat) == "can"  # type: ignore[arg-type]
    prior.codebook = None
    prior.metadata = {}
    assert Solver._category(fake, rev, lat) == "kitchen"  # type: ignore[arg-type]


@pytest.mark.skipif(not KITCHEN.is_file(), reason="needs the shipped kitchen prior")
def test_fit_member_head_names_held_out_members_and_the_cli_writes_it(tmp_path: Path) -> None:
    """Fitted on 6 objects per member (2 views each), the head names held-out objects' members far above chance
    (1 in 4); `fit-member-head --write` stores it in the prior file, where EFEM finds it."""
    prior = load_prior(KITCHEN, load_codebook=False)
    head = fit_member_head(prior, "kitchen", n_train=24, n_val=16, views=2, cache_dir=tmp_path / "cache")
    assert head.classes == ("mug", "bowl", "bottle", "can")
    assert head.report["val_accuracy"] >= 0.75, head.report
    assert head.report["val_accuracy_with_size"] >= 0.75, head.report
    assert head.size_mean is not None and head.size_mean.shape == (4, 2)
    assert np.asarray(head.report["val_confusion"]).sum() == 16 * 2
    with pytest.raises(ValueError, match="not a training family"):
        fit_member_head(prior, "mug")
    from efem_viz.cli import main

    copy = tmp_path / "kitchen.pt"
    shutil.copy(KITCHEN, copy)
    assert main(["fit-member-head", "--prior", str(copy), "--n-train", "24", "--n-val", "16", "--views", "2",
                 "--cache-dir", str(tmp_path / "cache"), "--write"]) == 0
    stored = member_head_of(load_prior(copy, load_codebook=False))
    assert stored is not None and stored.report["val_accuracy"] >= 0.75
