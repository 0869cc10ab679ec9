"""EFEM per-step rules on hand-made cases: eliminations, schedule, energies, sampling, confidence."""

from __future__ import annotations


import json

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from efem_viz.em.config import EMConfig, ProposalSettings, category_fields, preset, resolve_for_prior
from efem_viz.em.estep import energy_weights, schedule
from efem_viz.em.proposals import AvailableTree, Ragged, init_crops, lookup, sample_independent, sample_joint
from efem_viz.em.rules import (
    REASON_DUPLICATE,
    REASON_INCLUDED,
    REASON_INCLUDES_BETTER,
    REASON_TOO_SMALL,
    find_duplicates,
    find_inclusions,
    find_too_small,
    STEP_RULES,
    Kill,
    StepContext,
    StepRule,
    apply_step_rules,
    capped_confidence,
    explained_decay,
    first_failed_review,
    reason_names,
    set_matrix,
)
from efem_viz.em.solver import confidence
from efem_viz.prior.config import KNOWN_CATEGORIES, CategorySettings, category_settings

N = 100


def sets_from(lists: list[list[int]], n: int = N) -> sp.csr_matrix:
    rag = Ragged.from_lists([np.array(sorted(x), np.int64) for x in lists])
    return set_matrix(rag, np.ones(len(rag.idx), bool), n)


# ---------------------------------------------------------------------------------------------- too small
def test_too_small_kills_exactly_rows_below_min_size() -> None:
    kills = find_too_small(np.array([299, 300, 0, 1000]), 300)
    assert [k.row for k in kills] == [0, 2]
    assert all(k.reason == REASON_TOO_SMALL for k in kills)
    assert [k.ratio for k in kills] == [299.0, 0.0]


# ---------------------------------------------------------------------------------------------- duplicates
def test_duplicates_keep_highest_stationary_score_in_group() -> None:
    a = list(range(0, 20))
    b = list(range(1, 20))  # IoU(a, b) = 19/20
    c = list(range(50, 70))
    kills = find_duplicates(sets_from([a, b, c]), np.array([0.5, 0.9, 0.1]), 0.7)
    assert [(k.row, k.partner) for k in kills] == [(0, 1)]
    assert kills[0].reason == REASON_DUPLICATE
    assert kills[0].ratio == pytest.approx(19 / 20, abs=1e-5)


def test_duplicates_argmax_restricted_to_group_when_scores_are_zero() -> None:
    # rows 0 and 2 are duplicates with score 0; row 1 is unrelated with a high score: it must not be chosen,
    # and the group keeps its first member (the release's quirk would pick row 1).
    a = list(range(0, 20))
    b = list(range(50, 70))
    kills = find_duplicates(sets_from([a, b, a]), np.array([0.0, 0.9, 0.0]), 0.7)
    assert [(k.row, k.partner) for k in kills] == [(2, 0)]


def test_duplicates_below_threshold_survive_and_inactive_rows_ignored() -> None:
    a = list(range(0, 20))
    b = list(range(10, 30))  # IoU 10/30
    kills = find_duplicates(sets_from([a, b]), np.array([0.1, 0.2]), 0.7)
    assert kills == []
    # an inactive identical row does not take part
    kills = find_duplicates(sets_from([a, a]), np.array([0.1, 0.2]), 0.7, active=np.array([True, False]))
    assert kills == []


def test_duplicate_groups_are_per_visited_row() -> None:
    # chain a ~ b ~ c with IoU(a, c) below threshold: visiting a forms {a, b}; b wins (higher score);
    # visiting b then forms {b, c}: c wins. a and b die, c survives.
    a = list(range(0, 20))
    b = list(range(2, 22))
    c = list(range(4, 24))
    scores = np.array([0.1, 0.5, 0.9])
    kills = find_duplicates(sets_from([a, b, c]), scores, 0.75)
    assert [(k.row, k.partner) for k in kills] == [(0, 1), (1, 2)]


def naive_duplicates(sets: list[set[int]], scores: np.ndarray, thr: float) -> list[tuple[int, int]]:
    alive = [True] * len(sets)
    out = []
    for i in range(len(sets)):
        if not alive[i]:
            continue
        group = []
        for k in range(len(sets)):
            if alive[k]:
                inter = len(sets[i] & sets[k])
                union = len(sets[i] | sets[k])
                if inter / (union + 1e-6) >= thr:
                    group.append(k)
        if len(group) > 1:
            win = max(group, key=lambda k: (scores[k], -k))
            for k in group:
                if k != win:
                    alive[k] = False
                    out.append((k, win))
    return out


def naive_inclusions(sets: list[set[int]], thr: float) -> list[tuple[int, int]]:
    alive = [True] * len(sets)
    out = []
    for i in range(len(sets)):
        if not alive[i]:
            continue
        best, bk = -1.0, -1
        for k in range(len(sets)):
            if k != i and alive[k]:
                r = len(sets[i] & sets[k]) / (len(sets[i]) + 1e-6)
                if r > best:
                    best, bk = r, k
        if bk >= 0 and best > thr:
            alive[i] = False
            out.append((i, bk))
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_sparse_rules_match_naive_loops(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = int(rng.integers(2, 12))
    sets = []
    for _ in range(p):
        lo = int(rng.integers(0, 40))
        hi = lo + int(rng.integers(0, 30))
        s = set(range(lo, hi)) - set(rng.integers(0, 80, size=3).tolist())
        sets.append(s)
    scores = rng.integers(0, 4, size=p) / 4.0
    mat = sets_from([sorted(s) for s in sets], 80)
    dup = find_duplicates(mat, scores, 0.7)
    assert [(k.row, k.partner) for k in dup] == naive_duplicates(sets, scores, 0.7)
    inc = find_inclusions(mat, 0.8)
    assert [(k.row, k.partner) for k in inc] == naive_inclusions(sets, 0.8)


# ---------------------------------------------------------------------------------------------- inclusion
def test_inclusion_is_pairwise_not_union() -> None:
    x = list(range(0, 20))
    left = list(range(0, 10)) + list(range(40, 60))
    right = list(range(10, 20)) + list(range(60, 80))
    # x is covered by left ∪ right but only half by each: it survives
    assert find_inclusions(sets_from([x, left, right]), 0.8) == []


def test_inclusion_kills_the_included_set_with_partner_and_ratio() -> None:
    big = list(range(0, 50))
    small = list(range(5, 15)) + [90]  # 10 of 11 inside big
    kills = find_inclusions(sets_from([big, small]), 0.8)
    assert [(k.row, k.partner) for k in kills] == [(1, 0)]
    assert kills[0].ratio == pytest.approx(10 / 11, abs=1e-5)
    assert kills[0].reason == REASON_INCLUDED  # its own reason, no longer filed as a duplicate


def test_inclusion_kill_takes_effect_immediately() -> None:
    a = list(range(0, 20))
    # two identical sets include each other; only the first visited dies, the second then has no partner
    kills = find_inclusions(sets_from([a, a]), 0.8)
    assert [(k.row, k.partner) for k in kills] == [(0, 1)]
    # inactive rows are never partners
    assert find_inclusions(sets_from([a, a]), 0.8, active=np.array([True, False])) == []


def test_inclusion_modes_decide_by_the_stationary_score() -> None:
    """a fit wider than its object (two mugs, a mug and the table) includes a better fit of one of them;
    the paper kills the better one. "score" keeps both unless the includer scores at least as high, "swap" kills
    the includer instead."""
    big = list(range(0, 50))
    small = list(range(5, 15)) + [90]  # 10 of 11 inside big
    mat = sets_from([big, small])
    better_small, better_big = np.array([0.3, 0.7]), np.array([0.7, 0.3])
    assert [(k.row, k.partner) for k in find_inclusions(mat, 0.8, scores=better_small)] == [(1, 0)]  # paper
    assert find_inclusions(mat, 0.8, scores=better_small, mode="score") == []
    swapped = find_inclusions(mat, 0.8, scores=better_small, mode="swap")
    assert [(k.row, k.partner, k.reason) for k in swapped] == [(0, 1, REASON_INCLUDES_BETTER)]
    assert swapped[0].ratio == pytest.approx(10 / 11, abs=1e-5)
    for mode in ("score", "swap"):  # an includer that scores at least as high still wins, ties included
        assert [(k.row, k.partner) for k in find_inclusions(mat, 0.8, scores=better_big, mode=mode)] == [(1, 0)]
        assert [k.row for k in find_inclusions(mat, 0.8, scores=np.array([0.5, 0.5]), mode=mode)] == [1]
    # a swapped-out includer is no partner for later rows: a third set inside big only survives
    third = list(range(20, 30))
    kills = find_inclusions(sets_from([big, small, third]), 0.8, scores=np.array([0.3, 0.7, 0.1]), mode="swap")
    assert [(k.row, k.partner) for k in kills] == [(0, 1)]
    with pytest.raises(ValueError, match="needs the rows' scores"):
        find_inclusions(mat, 0.8, mode="swap")
    with pytest.raises(ValueError, match="one of paper, score, swap"):
        find_inclusions(mat, 0.8, scores=better_big, mode="bigger")


# ---------------------------------------------------------------------------------------------- registry
def _ctx(phase: int, inliers: list[int], rows: list[list[int]], stationary: list[float]) -> StepContext:
    rag = Ragged.from_lists([np.array(r, np.int64) for r in rows])
    return StepContext(phase=phase, step=0, local_step=0 if phase == 1 else 15, cfg=preset("fast"),
                       inliers=np.array(inliers), stationary=np.array(stationary),
                       d=np.zeros(len(rag.idx), np.float32), rag=rag, n_points=N, min_size=3,
                       owner=np.zeros(len(rows), np.int64),
                       coverage=np.full(len(rows), 0.4) if phase == 2 else None)  # phase 2 rows have a review


def test_too_small_with_patience_waits_for_steps_in_a_row() -> None:
    """`elimination.min_size_patience`: 1 kills a row the step it falls under the threshold (the method); 2 spares
    it once, and kills it when it was under the threshold the step before too. The rule marks every row under
    the threshold in `ctx.small`, spared or not, for the runner's streak."""
    rows = [list(range(0, 20)), list(range(40, 42)), list(range(60, 62))]
    ctx = _ctx(1, [20, 2, 2], rows, [0.5, 0.5, 0.5])
    assert [k.row for k in apply_step_rules(ctx)] == [1, 2] and ctx.small.tolist() == [False, True, True]
    ctx = _ctx(1, [20, 2, 2], rows, [0.5, 0.5, 0.5])
    ctx.cfg = ctx.cfg.replace(elimination={"min_size_patience": 2})
    ctx.small_streak = np.array([0, 1, 0])  # row 1 was under the threshold at the step before, row 2 was not
    kills = apply_step_rules(ctx)
    assert [(k.row, k.reason) for k in kills] == [(1, REASON_TOO_SMALL)]
    assert ctx.small.tolist() == [False, True, True] and ctx.active.tolist() == [True, False, True]
    ctx = _ctx(1, [20, 2, 2], rows, [0.5, 0.5, 0.5])
    ctx.cfg = ctx.cfg.replace(elimination={"min_size_patience": 2})  # no streak yet: nobody dies
    assert apply_step_rules(ctx) == []
    # per row (a joint solve's priors each with their own): row 2's prior kills at once
    ctx = _ctx(1, [20, 2, 2], rows, [0.5, 0.5, 0.5])
    ctx.patience = np.array([2, 2, 1])
    assert [k.row for k in apply_step_rules(ctx)] == [2]
    # the kitchen family waits two steps (its tumbled bowls flip), the others none; an explicit value wins
    from efem_viz.em.config import resolve_for_prior

    class Prior:
        def __init__(self, name: str) -> None:
            self.name, self.metadata = name, {}

    assert resolve_for_prior(preset("synthetic"), Prior("kitchen")).elimination.min_size_patience == 2
    assert resolve_for_prior(preset("real"), Prior("kitchen")).elimination.min_size_patience == 2
    assert resolve_for_prior(preset("synthetic"), Prior("mug")).elimination.min_size_patience == 1
    own = preset("synthetic").replace(elimination={"min_size_patience": 1})
    assert resolve_for_prior(own, Prior("kitchen")).elimination.min_size_patience == 1
    for bad in (0, 2.0, True, 101):
        with pytest.raises(ValueError, match="min_size_patience"):
            preset("fast").replace(elimination={"min_size_patience": bad}).validate()


def test_step_rules_run_in_order_and_each_kill_hides_the_row_from_later_rules() -> None:
    a, b = list(range(0, 20)), list(range(0, 19))
    small = list(range(40, 42))
    # phase 1: row 2 is too small; rows 0 and 1 are duplicates (IoU 0.95): the better-scored row 1 survives
    ctx = _ctx(1, [20, 19, 2], [a, b, small], [0.1, 0.9, 1.0])
    kills = apply_step_rules(ctx)
    assert [(k.row, k.reason) for k in kills] == [(2, REASON_TOO_SMALL), (0, REASON_DUPLICATE)]
    assert ctx.active.tolist() == [False, True, False]
    # phase 2 with a duplicate threshold above 1: no duplicate, but b lies inside a (19/19 > 0.8)
    ctx = _ctx(2, [20, 19], [a, b], [0.1, 0.9])
    ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01})
    assert [(k.row, k.partner, k.reason) for k in apply_step_rules(ctx)] == [(0, 1, REASON_INCLUDED)]


def test_the_inclusion_mode_of_the_config_reaches_the_step_rule() -> None:
    """`EMConfig.elimination.inclusion` through `apply_step_rules`: b (19 points) lies inside a (20) and a inside
    b; a is visited first and scores higher. The paper kills a; "score" spares it and b dies inside a; "swap" kills b
    as the includer of a better fit, and that reason is in the name table."""
    a, b = list(range(0, 20)), list(range(0, 19))
    got = {}
    for mode in ("paper", "score", "swap"):
        ctx = _ctx(2, [20, 19], [a, b], [0.9, 0.1])
        ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01, "inclusion": mode})
        got[mode] = [(k.row, k.partner, k.reason) for k in apply_step_rules(ctx)]
    assert got == {"paper": [(0, 1, REASON_INCLUDED)], "score": [(1, 0, REASON_INCLUDED)],
                   "swap": [(1, 0, REASON_INCLUDES_BETTER)]}
    assert REASON_INCLUDES_BETTER in reason_names()
    with pytest.raises(ValueError, match="inclusion must be one of"):
        preset("fast").replace(elimination={"inclusion": "largest"}).validate()


def test_capped_confidence_is_the_papers_confidence() -> None:
    """§3.10 by hand: 0.5 · min(0.2, 0.4) / 0.4 = 0.25; coverage above the cap counts as the cap."""
    got = capped_confidence(np.array([0.5, 0.5, 0.8]), np.array([0.2, 0.6, 0.0]), 0.4)
    np.testing.assert_allclose(got, [0.25, 0.5, 0.0])
    assert confidence(0.5, 0.2) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="cap must be > 0"):
        capped_confidence(0.5, 0.2, 0.0)


def test_explained_decay_by_hand() -> None:
    """Three fits on 100 points. a = 0..39 (0.9), b = 20..59 (0.8: half of it inside a), c = 60..79 (0.5, alone).
    With p = 1: a keeps 0.9; b falls to 0.8 · (1 − 20/40) = 0.4; c, which nobody overlaps, keeps 0.5 and is
    now taken before b. With p = 2, b falls to 0.8 · 0.25 = 0.2. p = 0 changes nothing."""
    a, b, c = np.arange(0, 40), np.arange(20, 60), np.arange(60, 80)
    conf = np.array([0.9, 0.8, 0.5])
    np.testing.assert_allclose(explained_decay(conf, [a, b, c], N, 1.0), [0.9, 0.4, 0.5])
    np.testing.assert_allclose(explained_decay(conf, [a, b, c], N, 2.0), [0.9, 0.2, 0.5])
    np.testing.assert_array_equal(explained_decay(conf, [a, b, c], N, 0.0), conf)
    # disjoint masks keep their confidences whatever the power
    np.testing.assert_array_equal(explained_decay(conf, [a, c, np.arange(80, 100)], N, 3.0), conf)


def test_explained_decay_takes_the_lowered_order() -> None:
    """The union grows in the order of the lowered confidences, not the raw ones. a = 0..39 (1.0); w = 30..69
    (0.9, a quarter inside a) falls to 0.9 · 0.75 = 0.675 with p = 1, below t = 60..79 (0.7, alone), which is
    taken first; w then also loses the 10 points it shares with t: 0.9 · (1 − 20/40) = 0.45. A raw-order pass
    would give w 0.675 and t 0.7 · 0.5 = 0.35."""
    a, w, t = np.arange(0, 40), np.arange(30, 70), np.arange(60, 80)
    got = explained_decay(np.array([1.0, 0.9, 0.7]), [a, w, t], N, 1.0)
    np.testing.assert_allclose(got, [1.0, 0.45, 0.7])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 90), st.integers(1, 30), st.floats(0.01, 1.0)), min_size=1, max_size=8),
       st.sampled_from([0.5, 1.0, 2.0]))
def test_explained_decay_properties(fits: list, power: float) -> None:
    """On random interval masks: no confidence rises; the highest keeps its value; a fit that shares no point
    with any other keeps its value; a loop over the greedy order by hand gives the same numbers."""
    masks = [np.arange(a, min(a + w, N)) for a, w, _ in fits]
    conf = np.array([c for *_, c in fits])
    got = explained_decay(conf, masks, N, power)
    assert (got <= conf + 1e-12).all()
    assert got[int(np.argmax(conf))] == pytest.approx(conf.max())
    for j, m in enumerate(masks):
        others = [k for k in range(len(masks)) if k != j]
        if not any(np.intersect1d(m, masks[k]).size for k in others):
            assert got[j] == pytest.approx(conf[j])
    taken, left, want = np.zeros(N, bool), list(range(len(conf))), np.zeros(len(conf))
    while left:
        vals = [conf[j] * (1 - taken[masks[j]].mean()) ** power for j in left]
        j = left.pop(int(np.argmax(vals)))
        want[j] = max(vals)
        taken[masks[j]] = True
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_explained_decay_rejects_bad_input() -> None:
    assert explained_decay(np.array([]), [], N, 1.0).shape == (0,)
    with pytest.raises(ValueError, match="2 masks but 1 confidences"):
        explained_decay(np.array([0.5]), [np.arange(3), np.arange(3)], N, 1.0)
    with pytest.raises(ValueError, match="power"):
        explained_decay(np.array([0.5]), [np.arange(3)], N, -1.0)
    with pytest.raises(ValueError, match="outside the scene"):
        explained_decay(np.array([0.5]), [np.array([N])], N, 1.0)
    with pytest.raises(ValueError, match="integer point indices"):
        explained_decay(np.array([0.5]), [np.ones(N, bool)], N, 1.0)
    with pytest.raises(ValueError, match="finite and >= 0"):
        explained_decay(np.array([-0.5]), [np.arange(3)], N, 1.0)
    with pytest.raises(ValueError, match="explained_decay"):
        preset("synthetic").replace(confidence={"explained_decay": -0.5}).validate()


def test_confidence_inclusion_spares_a_tight_fit_inside_a_wide_one() -> None:
    """(tree and box scenes): a fit over two mugs (a, 30 points, stationary 0.9) holds all of a tight
    fit of one of them (b, 19 points, stationary 0.6; a holds only 19/30 of a's own points in b, so a is not
    included in b). By stationary score b dies in every mode. The wide fit's completed shape is mostly
    unobserved (coverage 0.05 against 0.35), so by confidence (0.9 · 0.05/0.4 = 0.11 against 0.6 · 0.35/0.4 =
    0.525) "score" keeps both and "swap" kills a as the includer of a better fit; the paper compares nothing."""
    a, b = list(range(0, 30)), list(range(0, 19))
    got = {}
    for mode in ("paper", "score", "swap"):
        for by in ("stationary", "confidence"):
            ctx = _ctx(2, [30, 19], [a, b], [0.9, 0.6])
            ctx.coverage = np.array([0.05, 0.35])
            ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01, "inclusion": mode, "inclusion_by": by})
            got[mode, by] = [(k.row, k.partner, k.reason) for k in apply_step_rules(ctx)]
    assert got == {("paper", "stationary"): [(1, 0, REASON_INCLUDED)],
                   ("paper", "confidence"): [(1, 0, REASON_INCLUDED)],
                   ("score", "stationary"): [(1, 0, REASON_INCLUDED)],
                   ("score", "confidence"): [],
                   ("swap", "stationary"): [(1, 0, REASON_INCLUDED)],
                   ("swap", "confidence"): [(0, 1, REASON_INCLUDES_BETTER)]}
    # the same pair with the coverages swapped: the wide fit is also the better explained one and wins
    ctx = _ctx(2, [30, 19], [a, b], [0.9, 0.6])
    ctx.coverage = np.array([0.35, 0.05])
    ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01, "inclusion": "swap", "inclusion_by": "confidence"})
    assert [(k.row, k.partner) for k in apply_step_rules(ctx)] == [(1, 0)]
    # a context without review coverage cannot decide by confidence: one clear error, not a silent fallback
    ctx = _ctx(2, [30, 19], [a, b], [0.9, 0.6])
    ctx.coverage = None
    ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01, "inclusion": "score", "inclusion_by": "confidence"})
    with pytest.raises(ValueError, match="needs the rows' review coverage"):
        apply_step_rules(ctx)
    with pytest.raises(ValueError, match="inclusion_by must be one of"):
        preset("fast").replace(elimination={"inclusion_by": "coverage"}).validate()


def test_score_memory_lets_a_fit_keep_its_pairs_through_one_bad_step() -> None:
    """`elimination.score_memory`: the pair rules compare each fit's best stationary score of its last steps. The
    kitchen pile case by hand: a tight fit b (19 points, coverage 0.32) inside a wide fit a (30 points, coverage
    0.25) scores 0.83, 0.84, then dips to 0.48 at the step it is compared; a scores 0.89, 0.69, 0.82. By this step's
    confidence b dies inside a (0.48 · 0.8 = 0.38 against 0.82 · 0.625 = 0.51); by the best of 3 steps it is the
    better one (0.84 · 0.8 = 0.67 against 0.89 · 0.625 = 0.56) and "score" keeps both. A duplicate pair alike."""
    from efem_viz.em.solver import ProposalPool

    a, b = list(range(0, 30)), list(range(0, 19))
    pool = ProposalPool(ids=np.array([0, 1]), rag=Ragged.from_lists([np.array(a), np.array(b)]),
                        w=np.ones(49, np.float32), owner=np.zeros(2, np.int64))
    assert pool.remember(np.array([0.89, 0.83]), 1) is None  # the method: this step's scores
    for scores in ([0.89, 0.83], [0.69, 0.84]):
        pool.remember(np.array(scores), 3)
    best = pool.remember(np.array([0.82, 0.48]), 3)
    np.testing.assert_allclose(best, [0.89, 0.84])
    got = {}
    for memory, recent in ((1, None), (3, best)):
        ctx = _ctx(2, [30, 19], [a, b], [0.82, 0.48])
        ctx.coverage, ctx.recent_best = np.array([0.25, 0.32]), recent
        ctx.cfg = ctx.cfg.replace(elimination={"joint_dup_iou": 1.01, "inclusion": "score",
                                               "inclusion_by": "confidence", "score_memory": memory})
        got[memory] = [(k.row, k.partner, k.reason) for k in apply_step_rules(ctx)]
    assert got == {1: [(1, 0, REASON_INCLUDED)], 3: []}
    # duplicates: the pair's survivor is the one with the better recent best, not this step's score
    ctx = _ctx(1, [20, 19], [list(range(20)), list(range(19))], [0.9, 0.5])
    ctx.recent_best = np.array([0.9, 0.95])
    assert [(k.row, k.reason) for k in apply_step_rules(ctx)] == [(0, REASON_DUPLICATE)]
    # a row that leaves the pool takes its history with it; the rest keep theirs, newest last
    pool.keep(np.array([1]))
    np.testing.assert_allclose(pool.remember(np.array([0.5]), 3), [0.84])
    np.testing.assert_allclose(pool.remember(np.array([0.5]), 2), [0.5])  # a shorter memory forgets the oldest
    for bad in (0, 21, 2.0, True):
        with pytest.raises(ValueError, match="score_memory"):
            preset("fast").replace(elimination={"score_memory": bad}).validate()


def test_a_registered_rule_runs_and_its_reason_enters_the_name_table() -> None:
    def odd_rows(ctx: StepContext) -> list[Kill]:
        return [Kill(int(r), "odd") for r in np.flatnonzero(ctx.active) if r % 2]

    rules = (*STEP_RULES, StepRule("odd", odd_rows))
    ctx = _ctx(1, [10, 10, 10], [[1, 2], [30, 31], [60, 61]], [0.5, 0.5, 0.5])
    assert [(k.row, k.reason) for k in apply_step_rules(ctx, rules)] == [(1, "odd")]
    names = reason_names(rules)
    assert names[-1] == "survive" and "odd" in names and len(set(names)) == len(names)
    with pytest.raises(ValueError, match="survive"):
        reason_names((StepRule("survive", odd_rows),))

    def kills_dead_row(ctx: StepContext) -> list[Kill]:
        return [Kill(0, "again")]

    ctx = _ctx(1, [0, 10], [[1], [2]], [0.5, 0.5])  # row 0 dies as too small first
    with pytest.raises(ValueError, match="already dead"):
        apply_step_rules(ctx, (*STEP_RULES, StepRule("again", kills_dead_row)))


def test_review_rules_first_failure_wins() -> None:
    from efem_viz.em.rules import ReviewRecord

    z3 = np.zeros(3)
    rec = ReviewRecord(step=0, phase=1, proposal_id=0, R=np.eye(3), R_raw=np.eye(3), scale_sel=1.0, db_sim=0.0,
                       coverage=0.5, radii=np.array([0.2, 0.1]), scale_pass=False, up_angle=30.0, pose_pass=False,
                       obb_center=z3, obb_axes=np.eye(3), obb_half_extents=z3, mask=np.zeros(0, np.int32),
                       mesh_vertices=np.zeros((0, 3)), mesh_faces=np.zeros((0, 3), np.int32),
                       neighbours=np.zeros(0, np.int32))
    assert first_failed_review(rec, None) == ("scale-fail", 0.2)
    assert first_failed_review(rec._replace(scale_pass=True), None) == ("pose-fail", 30.0)
    assert first_failed_review(rec._replace(scale_pass=True, pose_pass=True), None) is None
    # the free-space check: unmeasured (NaN) passes; above the config's limit fails with the fraction
    from efem_viz.em import preset

    cfg = preset("real").replace(free_space={"margin": 0.01, "max_seen_through": 0.2, "final": False})
    ok = rec._replace(scale_pass=True, pose_pass=True)
    assert first_failed_review(ok._replace(seen_through=0.2), cfg) is None
    assert first_failed_review(ok._replace(seen_through=0.35), cfg) == ("seen-through", 0.35)
    assert first_failed_review(ok._replace(seen_through=float("nan")), cfg) is None
    # seen_through_final: the independent phase's review measures only, the joint phase's (the last) removes
    final = cfg.replace(free_space={"final": True})
    assert first_failed_review(ok._replace(seen_through=0.35), final) is None
    assert first_failed_review(ok._replace(seen_through=0.35, phase=2), final) == ("seen-through", 0.35)
    assert first_failed_review(ok._replace(seen_through=0.35), final.replace(steps={"t2": 0})) == ("seen-through", 0.35)


def test_the_planar_check_kills_box_edges_only_where_the_category_asks_for_it() -> None:
    """`review.max_planar`: a fit whose mask normals three directions hold above the limit fails as "planar";
    unset (most categories, every single-view frame) or unmeasured (NaN, older traces) passes. The kitchen
    family sets it for fused scans only."""
    from efem_viz.em import preset
    from efem_viz.em.config import resolve_for_prior
    from efem_viz.em.rules import ReviewRecord
    from efem_viz.prior.config import KNOWN_CATEGORIES, CategorySettings

    z3 = np.zeros(3)
    rec = ReviewRecord(step=0, phase=1, proposal_id=0, R=np.eye(3), R_raw=np.eye(3), scale_sel=1.0, db_sim=0.0,
                       coverage=0.5, radii=np.array([0.04, 0.05]), scale_pass=True, up_angle=0.0, pose_pass=True,
                       obb_center=z3, obb_axes=np.eye(3), obb_half_extents=z3, mask=np.zeros(0, np.int32),
                       mesh_vertices=np.zeros((0, 3)), mesh_faces=np.zeros((0, 3), np.int32),
                       neighbours=np.zeros(0, np.int32), planar=0.7)
    assert np.isnan(ReviewRecord(*rec[:-1]).planar)  # the default: not measured

    class Prior:
        def __init__(self, name: str) -> None:
            self.name, self.metadata = name, {}

    kitchen_syn = resolve_for_prior(preset("synthetic"), Prior("kitchen"))
    assert kitchen_syn.review.max_planar == 0.5
    assert first_failed_review(rec, kitchen_syn) == ("planar", 0.7)
    assert first_failed_review(rec._replace(planar=0.5), kitchen_syn) is None
    assert first_failed_review(rec._replace(planar=float("nan")), kitchen_syn) is None
    # single-view frames and the other categories are not checked; an explicit value wins over the category's
    assert resolve_for_prior(preset("real"), Prior("kitchen")).review.max_planar is None
    mug_syn = resolve_for_prior(preset("synthetic"), Prior("mug"))
    assert mug_syn.review.max_planar is None and first_failed_review(rec, mug_syn) is None
    own = resolve_for_prior(preset("synthetic").replace(review={"max_planar": 0.8}), Prior("kitchen"))
    assert own.review.max_planar == 0.8 and first_failed_review(rec, own) is None
    with pytest.raises(ValueError, match="max_planar"):
        preset("synthetic").replace(review={"max_planar": 1.5}).validate()
    # the category's limit travels with a prior's metadata; a category saved before it takes the known one's
    cat = KNOWN_CATEGORIES["kitchen"]
    assert CategorySettings.from_dict(cat.to_dict()) == cat
    from efem_viz.prior.config import category_settings

    old = {k: v for k, v in cat.to_dict().items() if k not in ("max_planar", "min_size_patience")}
    assert category_settings("kitchen", {"category": old}).max_planar == {"synthetic": 0.5}
    for bad in ({"synthetic": 0.0}, {"synthetic": "0.5"}, {"synthetic": True}, {"lab": 0.5}):
        with pytest.raises(ValueError, match="max_planar"):
            CategorySettings.from_dict({**cat.to_dict(), "max_planar": bad})
    assert category_settings("kitchen", {"category": old}).min_size_patience == 2
    for bad_patience in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match="min_size_patience"):
            CategorySettings.from_dict({**cat.to_dict(), "min_size_patience": bad_patience})


# ---------------------------------------------------------------------------------------------- schedule
@pytest.mark.parametrize(
    "t, expected",
    [
        (0, (3.0, 0.1, 0.003, 90.0)),
        (5, (16.5, 0.085, 0.0045, 75.0)),
        (10, (30.0, 0.07, 0.006, 60.0)),
        (15, (30.0, 0.07, 0.006, 60.0)),
    ],
)
def test_schedule_real_paper(t: int, expected: tuple[float, ...]) -> None:
    assert schedule(preset("real_paper"), t) == pytest.approx(expected)


def test_real_preset_is_the_paper_one_with_the_measured_changes() -> None:
    """`real` = §3.12's real settings (`real_paper`) + the changes for noisy single-view frames (a free-space check
    that ignores depth edges and widens with the range) + the learned mug-vs-look-alike confidence + the inclusion
    rule that spares the better fit (by stationary score; the synthetic presets compare the confidence) + 120
    proposals spread over the frame above its table instead of 400 uniform ones."""
    real, paper = preset("real"), preset("real_paper")
    assert real.replace(name="real_paper", steps={"tau_d": paper.steps.tau_d, "tau_n": paper.steps.tau_n,
                                                   "m_step_replace": True},
                        free_space=paper.free_space, confidence={"look_alike": None},
                        elimination={"inclusion": "paper"}, proposals=paper.proposals) == paper
    assert real.proposals.n_init == (120,) and real.proposals.anchors == "spread" and paper.proposals.n_init == (400,)
    assert real.proposals.anchor_min_height == 0.015 and paper.proposals.anchor_min_height is None
    assert (real.free_space.edge, real.free_space.range_growth, real.free_space.final) == (0.02, 0.01, True)
    # the look-alike model is the category's: the mug prior's for real frames, none for a chair or in synthetic scenes
    assert real.confidence.look_alike == "category" and paper.confidence.look_alike is None
    assert resolve_for_prior(real, _Named("mug")).confidence.look_alike == "mug_uois_tune"
    assert resolve_for_prior(real, _Named("chair")).confidence.look_alike is None
    assert resolve_for_prior(real.replace(domain="synthetic"), _Named("mug")).confidence.look_alike is None
    assert resolve_for_prior(real.replace(confidence={"look_alike": "mug_uois_tune"}),
                             _Named("chair")).confidence.look_alike == "mug_uois_tune"  # named: as given
    assert real.confidence.pose_weight == 0.0
    assert (real.elimination.inclusion, real.elimination.inclusion_by) == ("score", "stationary")
    assert paper.elimination.inclusion == "paper"
    for name in ("synthetic", "fast"):  # the better-explained fit is spared
        assert (preset(name).elimination.inclusion, preset(name).elimination.inclusion_by) == ("score", "confidence")
    assert schedule(real, 0) == pytest.approx((3.0, 0.15, 0.003, 180.0))
    assert not real.steps.m_step_replace and real.free_space.margin == 0.01 and real.free_space.max_seen_through == 0.15


def test_the_free_space_switch_adds_or_removes_the_real_presets_check() -> None:
    """`SolveSettings.free_space`: auto keeps each preset's check (real: on), on adds the fused scans' check to
    a preset without one (looser than a single frame's: several cameras see every side of an imperfect fit), off
    removes it; anything else is refused."""
    from efem_viz.em.config import FREE_SPACE, FREE_SPACE_FUSED, SolveSettings

    real, syn = preset("real"), preset("synthetic")
    assert SolveSettings(preset="real").config() == real
    assert SolveSettings(preset="synthetic").config() == syn and syn.free_space.margin is None
    on = SolveSettings(preset="synthetic", free_space="on").config()
    assert on == syn.replace(free_space=FREE_SPACE_FUSED)
    assert on.free_space.margin > real.free_space.margin
    assert on.free_space.max_seen_through > real.free_space.max_seen_through
    assert SolveSettings(preset="real", free_space="on").config() == real
    assert real.free_space == FREE_SPACE.replace(final=True)
    off = SolveSettings(preset="real", free_space="off").config()
    assert off.free_space.margin is None and off.replace(free_space={"margin": 0.01}) == real
    with pytest.raises(ValueError, match="free_space"):
        SolveSettings(preset="real", free_space="maybe").config()  # type: ignore[arg-type]


def test_schedule_synthetic_keeps_tau_d_and_phase2_uses_end_values() -> None:
    cfg = preset("synthetic")
    assert schedule(cfg, 5)[1] == pytest.approx(0.1)
    long = cfg.replace(steps={"end_step": 30})  # phase 2 must use the end values even if annealing is not finished
    assert schedule(long, 15) == pytest.approx((30.0, 0.1, 0.006, 60.0))
    assert schedule(long, 14)[0] < 30.0


def test_presets_follow_the_spec_table() -> None:
    syn, real, fast = preset("synthetic"), preset("real_paper"), preset("fast")
    assert preset("synthetic_mugs") == syn and preset("real_mugs") == preset("real")  # the old names still work
    assert syn.proposals.n_init == (400,) and syn.elimination.min_size == 300
    # crop radii are the category's (spec: mugs 0.07 / 0.11 m, synthetic chairs 0.5 / 0.8 m); explicit values win
    assert syn.proposals.r_init is None and syn.proposals.r_err is None
    mug = category_fields(syn, KNOWN_CATEGORIES["mug"])
    chair = category_fields(syn, KNOWN_CATEGORIES["chair"])
    assert mug["proposals"] == {"r_init": 0.07, "r_err": 0.11} and chair["proposals"] == {"r_init": 0.5, "r_err": 0.8}
    assert category_fields(syn.replace(proposals={"r_init": 0.2}), KNOWN_CATEGORIES["chair"])["proposals"] == {
        "r_err": 0.8}
    assert (syn.confidence.stat_tau, syn.confidence.stat_gamma, syn.confidence.cov_tau,
            syn.confidence.cov_gamma) == (0.04, 45.0, 0.04, 45.0)
    assert (real.confidence.stat_tau, real.confidence.stat_gamma, real.confidence.cov_tau,
            real.confidence.cov_gamma) == (0.03, 30.0, 0.03, 30.0)
    # sizes are the category's, per capture domain: the presets leave them to the prior
    assert real.review.scale_horizontal is None and syn.review.scale_height is None and real.domain == "real"
    mug = category_settings("mug")
    real_mug, syn_mug = resolve_for_prior(real, _Named("mug")), resolve_for_prior(syn, _Named("mug"))
    assert real_mug.review.scale_horizontal == (0.03, 0.08) and real_mug.review.scale_height == (0.015, 0.10)
    assert syn_mug.review.scale_horizontal == (0.03, 0.08) and syn_mug.review.scale_height == (0.015, 0.30)
    assert syn_mug.review.up_range == mug.up_range == (0.0, 180.0) and syn_mug.output.tau_out == 0.04
    # an explicit value in the config wins over the category's
    assert resolve_for_prior(real.replace(review={"scale_horizontal": (0.01, 0.5)}),
                             _Named("mug")).review.scale_horizontal == (0.01, 0.5)
    # an unknown category checks no size; metadata can carry its settings
    free = resolve_for_prior(syn, _Named("teapot"))
    assert free.review.scale_horizontal == (0.0, float("inf"))
    meta = {"category": CategorySettings("teapot", scale_horizontal=(0.05, 0.2)).to_dict(), "tau_out": 0.06}
    tea = resolve_for_prior(syn, _Named("teapot", meta))
    assert tea.review.scale_horizontal == (0.05, 0.2) and tea.review.scale_height == (0.0, float("inf"))
    assert tea.output.tau_out == 0.06
    assert (syn.steps.t1, syn.steps.t2, syn.steps.omega, syn.elimination.joint_incl) == (15, 5, 1e-4, 0.8)
    assert 50 <= fast.proposals.n_init[0] <= 100
    with pytest.raises(ValueError, match="unknown EM preset"):
        preset("sofas")
    # the synthetic-chairs column of the spec's table (300 proposals anchored above the floor, cropped at the real
    # chairs' 0.35 m, instead of its 200 anywhere at 0.5 m); the chair prior's category brings the 0.8 m reach
    chairs = resolve_for_prior(preset("chairs"), _Named("chair"))
    assert (chairs.proposals.n_init, chairs.steps.alpha_d, chairs.steps.tau_d, chairs.steps.tau_n) == (
        (300,), (5.0, 20.0), (0.2, 0.15), (120.0, 80.0))
    assert chairs.proposals.anchor_min_height == 0.05 and syn.proposals.anchor_min_height is None
    assert chairs.proposals.min_point_height == 0.01  # the floor joins no chair (a deviation, docs/BENCHMARKS.md)
    assert all(preset(n).proposals.min_point_height is None for n in ("synthetic", "real", "real_paper", "fast"))
    assert (chairs.elimination.min_size, chairs.elimination.dup_iou, chairs.proposals.r_init,
            chairs.proposals.r_err) == (1000, 0.8, 0.35, 0.8)
    assert resolve_for_prior(syn, _Named("chair")).proposals.radii() == (0.5, 0.8)  # the category's own
    assert EMConfig.from_json(real.to_json()) == real
    assert syn.with_proposals(64).proposals.n_init == (64,)


class _Named:
    """The part of a prior that the config resolution reads: a name and metadata."""

    def __init__(self, name: str, metadata: dict | None = None) -> None:
        self.name = name
        self.metadata = metadata or {}


def test_category_settings_round_trip_and_validation() -> None:
    cat = category_settings("mug", {"tau_out": 0.07})
    back = CategorySettings.from_dict(json.loads(json.dumps(cat.to_dict())))
    assert back == cat and back.sizes("real") == ((0.03, 0.08), (0.015, 0.10))
    assert back.look_alike == {"real": "mug_uois_tune"}
    # a mug category saved before categories carried their look-alike model keeps the known mug's
    old = {k: v for k, v in cat.to_dict().items() if k != "look_alike"}
    assert category_settings("mug", {"category": old}).look_alike == {"real": "mug_uois_tune"}
    assert category_settings("mug", {"category": {**old, "look_alike": {}}}).look_alike == {}
    assert CategorySettings.from_dict(CategorySettings("x").to_dict()).scale_height == (0.0, float("inf"))
    for bad in ({"name": "x", "scale_height": [0.2, 0.1]}, {"name": "x", "colour": 1},
                {"name": "x", "domain_sizes": {"mars": [[0, 1], [0, 1]]}}, {"name": ""},
                {"name": "x", "domain_sizes": {"real": [[0, 1]]}}, {"name": "x", "domain_sizes": {"real": 5}},
                {"name": "x", "look_alike": {"mars": "m"}}, {"name": "x", "look_alike": {"real": "../etc/passwd"}},
                {"name": "x", "look_alike": ["real"]}):
        with pytest.raises(ValueError):
            CategorySettings.from_dict(bad)


# ---------------------------------------------------------------------------------------------- energies
def test_energy_weights_truncation_and_inliers() -> None:
    sched = (30.0, 0.1, 0.006, 60.0)
    d = np.array([0.0, 0.05, -0.05, 0.2, 0.0, np.nan], np.float32)
    g = np.array([0.0, 10.0, 10.0, 0.0, 70.0, 0.0], np.float32)
    w, inl = energy_weights(d, g, sched)
    assert w[0] == pytest.approx(1.0)
    assert w[1] == pytest.approx(np.exp(-30 * 0.05 - 0.006 * 10), rel=1e-5)
    assert w[2] == pytest.approx(w[1])  # |d|
    assert w[3] < 1e-40 and w[4] < 1e-40  # a truncated term costs U = 100
    assert w[5] == 0.0  # NaN -> out
    assert inl.tolist() == [True, True, True, False, False, False]


def test_confidence_formula() -> None:
    assert confidence(0.8, 0.2) == pytest.approx(0.8 * 0.2 / 0.4)
    assert confidence(0.8, 0.9) == pytest.approx(0.8)  # coverage saturates at 0.4
    assert confidence(0.0, 1.0) == 0.0
    with pytest.raises(ValueError):
        confidence(0.5, 0.5, cap=0.0)
    # the pose-score factor: min(1, pose / ref)^w, off without a pose score or with w = 0
    assert confidence(0.8, 0.2, pose=0.3, pose_weight=2.0, pose_ref=0.6) == pytest.approx(0.4 * 0.25)
    assert confidence(0.8, 0.2, pose=0.9, pose_weight=2.0, pose_ref=0.6) == pytest.approx(0.4)
    assert confidence(0.8, 0.2, pose=-0.2, pose_weight=2.0) == 0.0
    assert confidence(0.8, 0.2, pose=float("nan"), pose_weight=2.0) == pytest.approx(0.4)
    assert confidence(0.8, 0.2, pose=0.3) == pytest.approx(0.4)
    both = confidence(0.8, 0.2, seen_through=0.5, pose=0.3, pose_weight=1.0, pose_ref=0.6)
    assert both == pytest.approx(0.4 * 0.5 * 0.5)


# ---------------------------------------------------------------------------------------------- sampling
def test_independent_sampling_stays_in_support_and_follows_weights() -> None:
    rng = np.random.default_rng(0)
    rag = Ragged.from_lists([np.array([3, 5, 7]), np.array([10, 11]), np.array([20])])
    w = np.array([1.0, 0.5, 0.0, 1.0, 1e-9, 0.0])
    s = sample_independent(rag, w, 4000, 1e-4, rng, fallback=np.arange(50, 60))
    assert set(np.unique(s[0])) <= {3, 5}
    frac = (s[0] == 3).mean()
    assert 0.6 < frac < 0.73  # ≈ 2/3
    assert set(np.unique(s[1])) == {10}  # 1e-9 << ω drops out
    assert set(np.unique(s[2])) <= set(range(50, 60))  # zero weight -> whole available scene


def test_joint_sampling_one_owner_per_point() -> None:
    rng = np.random.default_rng(1)
    rows = [np.arange(0, 60), np.arange(30, 90), np.arange(200, 210)]
    rag = Ragged.from_lists(rows)
    w = np.ones(len(rag.idx))
    scores = np.array([1.0, 1.0, 0.5])
    s, claimed = sample_joint(rag, w, scores, 256, 1e-4, rng, fallback=np.arange(300))
    owners: dict[int, int] = {}
    for r in range(3):
        pts = rag.idx[rag.row_slice(r)][claimed[rag.row_slice(r)]]
        for p in pts:
            assert p not in owners, "a point was claimed twice"
            owners[int(p)] = r
        assert set(np.unique(s[r])) <= set(pts.tolist())
    shared = [owners.get(p) for p in range(30, 60)]
    assert 0 in shared and 1 in shared  # contested points are split between the two proposals
    assert all(owners.get(p) == 0 for p in range(0, 30))  # uncontested points (ω tiny) go to their owner


def test_joint_sampling_empty_claim_gets_best_background_point() -> None:
    rng = np.random.default_rng(2)
    rag = Ragged.from_lists([np.arange(0, 10), np.arange(0, 10)])
    w = np.r_[np.ones(10), np.full(10, 1e-12)]
    s, claimed = sample_joint(rag, w, np.array([1.0, 1.0]), 16, 1e-4, rng, fallback=np.arange(10))
    assert claimed[10:].sum() == 1  # the weak proposal is given exactly one point
    assert len(np.unique(s[1])) == 1


def test_init_crops_anchors_among_available_only() -> None:
    rng = np.random.default_rng(3)
    pts = np.random.default_rng(0).uniform(-1, 1, (500, 3)).astype(np.float32)
    avail = np.zeros(500, bool)
    avail[:100] = True
    anchors, crops = init_crops(pts, avail, 50, 0.3, rng)
    assert anchors.max() < 100
    assert crops.idx.max() < 100
    for r in range(50):
        sl = crops.row_slice(r)
        d = np.linalg.norm(pts[crops.idx[sl]] - pts[anchors[r]], axis=1)
        assert (d < 0.3).all()
        brute = np.flatnonzero(avail & (np.linalg.norm(pts - pts[anchors[r]], axis=1) < 0.3))
        assert np.array_equal(np.sort(crops.idx[sl]), brute)


def test_init_crops_anchor_mask_restricts_anchors_not_crops() -> None:
    rng = np.random.default_rng(4)
    pts = np.random.default_rng(1).uniform(-1, 1, (400, 3)).astype(np.float32)
    avail = np.ones(400, bool)
    avail[300:] = False
    mask = np.zeros(400, bool)
    mask[[5, 17, 350]] = True  # 350 is not available: never an anchor
    anchors, crops = init_crops(pts, avail, 40, 0.5, rng, anchor_mask=mask)
    assert set(anchors.tolist()) <= {5, 17}
    assert len(set(anchors.tolist())) == 2  # both drawn among 40 (with replacement)
    for r in range(40):  # the crops still hold every available point in the ball
        brute = np.flatnonzero(avail & (np.linalg.norm(pts - pts[anchors[r]], axis=1) < 0.5))
        assert np.array_equal(np.sort(crops.idx[crops.row_slice(r)]), brute)
    with pytest.raises(ValueError, match="no available points"):
        init_crops(pts, avail, 4, 0.5, rng, anchor_mask=np.eye(1, 400, 350, dtype=bool)[0])
    with pytest.raises(ValueError, match="anchor_mask has shape"):
        init_crops(pts, avail, 4, 0.5, rng, anchor_mask=np.ones(10, bool))


def test_spread_anchors_cover_space_not_density() -> None:
    """A dense blob (90 % of the points in a 4 cm cube) beside a sparse 1 m table: random anchors go mostly to the
    blob, spread anchors to every part of the table, one per grid cell at most; among available points only,
    deterministic for a seed, with `anchor_mask` honoured."""
    from efem_viz.em.proposals import spread_anchors

    g = np.random.default_rng(0)
    blob = g.uniform(0, 0.04, (9000, 3))
    table = np.column_stack([g.uniform(-0.5, 0.5, 1000), g.uniform(-0.5, 0.5, 1000), np.zeros(1000)])
    pts = np.concatenate([blob, table]).astype(np.float32)
    avail = np.ones(len(pts), bool)
    avail[-100:] = False
    a_rand, _ = init_crops(pts, avail, 100, 0.05, np.random.default_rng(1))
    a_spread, crops = init_crops(pts, avail, 100, 0.05, np.random.default_rng(1), spread=True)
    in_blob = lambda a: float((a < 9000).mean())  # noqa: E731
    assert in_blob(a_rand) > 0.8 and in_blob(a_spread) < 0.1
    assert len(a_spread) == 100 and avail[a_spread].all() and len(crops.offsets) == 101
    quads = np.sign(pts[a_spread][:, :2]).astype(int)
    assert len({tuple(q) for q in quads.tolist()}) == 4  # all four quarters of the table
    again, _ = init_crops(pts, avail, 100, 0.05, np.random.default_rng(1), spread=True)
    assert np.array_equal(again, a_spread)
    idx = spread_anchors(pts[:9000], 30, np.random.default_rng(2))  # the blob alone: spread within it
    cells = {tuple(c) for c in np.floor(pts[idx] / 0.01).astype(int).tolist()}
    assert len(idx) == 30 and len(cells) > 15
    mask = np.zeros(len(pts), bool)
    mask[[3, 9500]] = True
    masked, _ = init_crops(pts, avail, 10, 0.05, np.random.default_rng(3), anchor_mask=mask, spread=True)
    assert set(masked.tolist()) == {3, 9500}
    assert spread_anchors(pts[:0], 5, np.random.default_rng(0)).shape == (0,)
    with pytest.raises(ValueError, match="anchors must be"):
        EMConfig(proposals=ProposalSettings(anchors="grid"))  # type: ignore[arg-type]


def test_cylinder_neighbourhood_ignores_height() -> None:
    pts = np.array([[0, 0, 0], [0, 0, 5], [0.5, 0, 0], [0.05, 0, -3]], np.float32)
    tree = AvailableTree(pts, np.ones(4, bool), crop="cylinder")
    rag = tree.query(np.zeros((1, 3)), 0.1)
    assert rag.idx.tolist() == [0, 1, 3]


def test_lookup_and_take_rows() -> None:
    rag = Ragged.from_lists([np.array([1, 4, 9]), np.array([2, 4])])
    pos = lookup(rag, np.array([0, 0, 1, 1]), np.array([4, 2, 4, 9]))
    assert pos.tolist() == [1, -1, 4, -1]
    sub, posk = rag.take_rows(np.array([1]))
    assert sub.idx.tolist() == [2, 4] and posk.tolist() == [3, 4]


def test_nan_centre_owns_no_points() -> None:
    pts = np.random.default_rng(0).uniform(-1, 1, (200, 3)).astype(np.float32)
    tree = AvailableTree(pts, np.ones(200, bool))
    rag = tree.query(np.array([[np.nan, 0, 0], [0, 0, 0]]), 0.5)
    assert rag.lengths[0] == 0 and rag.lengths[1] > 0


def test_review_rules_decide_from_the_measures() -> None:
    """The size and up verdicts are the rules': with a resolved config the rule decides from the
    record's radii and up angle, whatever verdict the record carries; without a config it keeps the stored one."""
    from efem_viz.em.rules import ReviewRecord, size_passes, up_passes

    cfg = resolve_for_prior(preset("real"), _Named("mug"))
    z3 = np.zeros(3)
    good_r = np.array([0.05, 0.05])
    rec = ReviewRecord(step=0, phase=1, proposal_id=0, R=np.eye(3), R_raw=np.eye(3), scale_sel=1.0, db_sim=0.0,
                       coverage=0.5, radii=good_r, scale_pass=False, up_angle=5.0, pose_pass=False,
                       obb_center=z3, obb_axes=np.eye(3), obb_half_extents=z3, mask=np.zeros(0, np.int32),
                       mesh_vertices=np.zeros((0, 3)), mesh_faces=np.zeros((0, 3), np.int32),
                       neighbours=np.zeros(0, np.int32))
    assert size_passes(good_r, cfg) and up_passes(5.0, cfg)
    assert first_failed_review(rec, cfg) is None  # the measures pass: the stale stored flags do not decide
    assert first_failed_review(rec, None) == ("scale-fail", 0.05)  # no config: the stored verdict
    big = rec._replace(radii=np.array([0.2, 0.05]), scale_pass=True)
    assert first_failed_review(big, cfg) == ("scale-fail", 0.2)
    tilted = rec._replace(up_angle=80.0, pose_pass=True)
    upright = cfg.replace(review={"up_range": (0.0, 30.0)})
    assert up_passes(80.0, cfg)  # real captures leave the up axis free
    assert not up_passes(80.0, upright) and first_failed_review(tilted, upright) == ("pose-fail", 80.0)
    with pytest.raises(ValueError, match="unresolved"):
        size_passes(good_r, preset("real"))
