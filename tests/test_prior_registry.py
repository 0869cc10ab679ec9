"""`efem_viz.prior.registry.PriorSet`: each prior loaded once (also under concurrent asks), the prior of a trace or
of a proposal, the run priors, and the errors (analytic priors only: no weights needed)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from efem_viz.prior import registry
from efem_viz.prior.analytic import make_sphere_prior
from efem_viz.prior.config import ShapePriorLike
from efem_viz.prior.registry import PriorSet


@dataclass
class _Trace:
    prior_names: tuple[str, ...]
    row_R: Any
    prop_prior: tuple[int, ...] = ()

    def prior_index(self, proposal_id: int) -> int:
        return self.prop_prior[proposal_id] if self.prop_prior else 0


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Analytic priors "sphere" and "ball" (another category) whose loads are counted."""
    loads: list[str] = []

    def factory(name: str) -> Any:
        def make() -> Any:
            loads.append(name)
            p = make_sphere_prior()
            if name != "sphere":
                p.name = name
                p.metadata = {"category": {"name": name}}
            return p
        return make

    monkeypatch.setitem(registry.ANALYTIC_PRIORS, "sphere", factory("sphere"))
    monkeypatch.setitem(registry.ANALYTIC_PRIORS, "ball", factory("ball"))
    return loads


def test_each_prior_loads_once_even_when_asked_by_many_threads(counted: list[str]) -> None:
    priors = PriorSet("sphere")
    got: list[ShapePriorLike] = []
    threads = [threading.Thread(target=lambda: got.append(priors.get("sphere"))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert counted == ["sphere"] and all(p is got[0] for p in got)
    assert priors.primary() is got[0] and isinstance(got[0], ShapePriorLike)


def test_prior_of_a_trace_and_of_a_proposal(counted: list[str]) -> None:
    given = make_sphere_prior()
    priors = PriorSet("sphere", prior=given)
    one = _Trace(prior_names=("sphere",), row_R=np.zeros((2, 4, 3)))
    assert priors.for_trace(one) is given and priors.for_run(one) is given and counted == []
    mixed = _Trace(prior_names=("ball", "sphere"), row_R=np.zeros((2, 4, 3)), prop_prior=(1, 0))
    assert priors.for_trace(mixed, 1).name == "ball" and priors.for_trace(mixed, 0) is given
    run = priors.for_run(mixed)
    assert isinstance(run, list) and [p.name for p in run] == ["ball", "sphere"] and counted == ["ball"]
    with pytest.raises(RuntimeError, match="several priors"):
        priors.for_trace(mixed)
    with pytest.raises(RuntimeError, match="latent size 7"):  # another prior's run
        priors.for_trace(_Trace(prior_names=("mug",), row_R=np.zeros((2, 7, 3))))


def test_run_priors(counted: list[str]) -> None:
    assert PriorSet("sphere").run_priors() is None
    priors = PriorSet("sphere", extra=["ball"])
    run = priors.run_priors()
    assert run is not None and [p.name for p in run] == ["sphere", "ball"] and priors.run_priors() == run
    assert counted == ["sphere", "ball"]
    assert priors.named(["ball"])[0] is run[1]  # the run's priors decode their own proposals
    built = PriorSet.from_specs(["sphere", "ball"])
    assert built.run_priors() == [built.get("sphere"), built.get("ball")] and counted.count("ball") == 2
    with pytest.raises(ValueError, match="given twice"):
        PriorSet.from_specs(["sphere", "sphere"])


def test_errors(counted: list[str]) -> None:
    missing = PriorSet("no_such_prior_here")
    for _ in range(2):  # a failed load is remembered, with its reason
        with pytest.raises(RuntimeError, match="no_such_prior_here"):
            missing.primary()
    with pytest.raises(RuntimeError, match="unavailable"):
        missing.named(["no_such_prior_here"])
    with pytest.raises(FileNotFoundError):
        PriorSet().get("no_such_prior_here")


def test_resolve_device_takes_cuda_only_where_it_is(monkeypatch: pytest.MonkeyPatch) -> None:
    """auto is CUDA when the machine has it, else the CPU; cuda without CUDA and unknown names are one clear
    ValueError."""
    import torch

    from efem_viz.prior.registry import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("CPU") == "cpu"
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="unknown device 'tpu'"):
        resolve_device("tpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda" and resolve_device("cuda:1") == "cuda:1"


def test_a_one_prior_run_decodes_with_the_prior_it_recorded(counted: list[str]) -> None:
    """A viewer started with one prior that opens another category's run decodes it with that run's prior, not its
    own (both priors here have the same latent size, so nothing else would tell them apart)."""
    given = make_sphere_prior()
    priors = PriorSet("sphere", prior=given)
    assert priors.for_trace(_Trace(prior_names=("sphere",), row_R=np.zeros((2, 4, 3)))) is given
    other = priors.for_trace(_Trace(prior_names=("ball",), row_R=np.zeros((2, 4, 3))))
    assert other is not given and other.name == "ball" and counted == ["ball"]
    assert priors.for_run(_Trace(prior_names=("ball",), row_R=np.zeros((2, 4, 3)))) is other
    assert priors.for_trace(_Trace(prior_names=(), row_R=np.zeros((2, 4, 3)))) is given  # nothing recorded


def test_a_solve_for_another_category_takes_that_category_prior(counted: list[str]) -> None:
    given = make_sphere_prior()
    priors = PriorSet("sphere", prior=given)
    assert priors.solve_priors() == [given] and priors.solve_priors("sphere") == [given]
    (ball,) = priors.solve_priors("ball")
    assert ball.name == "ball" and counted == ["ball"]
    joint = PriorSet("sphere", prior=given, extra=["ball"])
    assert [p.name for p in joint.solve_priors("ball")] == ["sphere", "ball"]  # a joint solve is kept as asked
