"""Instance AP (docs/design/efem-method.md §5): hand-worked cases, duplicate/size/class rules, a naive §5.4 reference,
IO, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from efem_viz.eval import (
    IOU_THRESHOLDS,
    SceneGroundTruth,
    ScenePrediction,
    average_precision,
    evaluate,
    evaluate_instances,
    evaluate_scene,
    load_scannet_predictions,
    match_instances,
    write_scannet_predictions,
)
from efem_viz.eval.matching import ClassMatches, match_scene_class, scene_overlaps

N = 2000


def rng_mask(lo: int, hi: int, n: int = N) -> np.ndarray:
    m = np.zeros(n, bool)
    m[lo:hi] = True
    return m


def two_gt() -> np.ndarray:
    """GT 1 = points [0, 200), GT 2 = points [200, 400), the rest unlabelled."""
    gt = np.zeros(N, np.int32)
    gt[:200] = 1
    gt[200:400] = 2
    return gt


# ---------------------------------------------------------------------------------------------- §5.4 by hand
def test_ap_hand_case_duplicate_fp_and_miss() -> None:
    # GT 1 and GT 2 (200 points each). p0 = GT 1 exactly (IoU 1, conf 0.9); p1 = 180 points of GT 1 (IoU 0.9,
    # conf 0.8): a duplicate of the matched GT -> FP with min(0.9, 0.8) = 0.8; p2 covers no GT -> FP 0.7.
    # GT 2 is missed -> 1 hard FN. Entries sorted by score: (F .7), (F .8), (T .9); T = 1, n = 3, H = 1.
    #   .7: k=0, cum=0: tp=1 fp=2 fn=1 -> p=1/3, r=1/2
    #   .8: k=1, cum=0: tp=1 fp=1 fn=1 -> p=1/2, r=1/2
    #   .9: k=2, cum=0: tp=1 fp=0 fn=1 -> p=1,   r=1/2
    #   end: p=1, r=0.  Widths: (r0-r1)/2=0, (r0-r2)/2=0, (r1-r3)/2=1/4, (r2-0)/2=1/4  ->  AP = 1/4 + 1/4 = 1/2
    res = evaluate_scene([rng_mask(0, 200), rng_mask(0, 180), rng_mask(500, 700)], [0.9, 0.8, 0.7], two_gt())
    assert res.ap50 == pytest.approx(0.5)
    # p1's IoU 0.9 is not > 0.9, but then it is an unmatched FP with the same score: AP is 1/2 at every threshold
    assert np.allclose(res.ap_table, 0.5)
    assert res.ap == pytest.approx(0.5) and res.ap25 == pytest.approx(0.5)
    prec, rec = res.pr[("mug", 0.5)]
    np.testing.assert_allclose(prec, [1 / 3, 1 / 2, 1, 1])
    np.testing.assert_allclose(rec, [1 / 2, 1 / 2, 1 / 2, 0])
    assert res.recall_table[0, 0] == pytest.approx(0.5)


def test_ap_hand_case_fp_ranked_first() -> None:
    # p0 = GT 1 (conf .6), p1 = FP on no object (conf .9), p2 = GT 2 (conf .3). Entries: (T .3) (T .6) (F .9), H=0.
    #   .3: k=0 cum=0: tp=2 fp=1 fn=0 -> p=2/3 r=1
    #   .6: k=1 cum=1: tp=1 fp=1 fn=1 -> p=1/2 r=1/2
    #   .9: k=2 cum=2: tp=0 fp=1 fn=2 -> p=0   r=0
    #   end p=1 r=0. Widths: (1-.5)/2=1/4, (1-0)/2=1/2, (.5-0)/2=1/4, (0-0)/2=0
    #   AP = 2/3*1/4 + 1/2*1/2 + 0 + 0 = 1/6 + 1/4 = 5/12
    res = evaluate_scene([rng_mask(0, 200), rng_mask(600, 800), rng_mask(200, 400)], [0.6, 0.9, 0.3], two_gt())
    assert res.ap50 == pytest.approx(5 / 12)


def test_duplicate_with_higher_score_keeps_the_higher_score() -> None:
    # p0 (conf .3, IoU 0.9) is matched first (prediction order); p1 (conf .8, IoU 0.95) is a duplicate:
    # the GT keeps max = .8 as its score, the FP gets min = .3. Entries (F .3) (T .8), H = 1 (GT 2 missed).
    #   .3: k=0 cum=0: tp=1 fp=1 fn=1 -> p=1/2 r=1/2;  .8: k=1 cum=0: tp=1 fp=0 fn=1 -> p=1 r=1/2;  end p=1 r=0
    #   Widths: 0, (1/2-0)/2 = 1/4, (1/2-0)/2 = 1/4  ->  AP = 1/4 + 1/4 = 1/2
    gt = two_gt()
    preds = [rng_mask(0, 180), rng_mask(0, 190)]
    res = evaluate_scene(preds, [0.3, 0.8], gt)
    assert res.ap50 == pytest.approx(0.5)
    ov = scene_overlaps(ScenePrediction("s", preds, np.array([0.3, 0.8])), SceneGroundTruth("s", gt))
    acc = ClassMatches()
    match_scene_class(ov, 1, 0.5, acc)
    assert sorted(zip(acc.y_true, acc.y_score)) == [(False, 0.3), (True, 0.8)]
    assert acc.hard_fn == 1
    # with the scores swapped the naive ordering would matter; the duplicate rule makes AP the same
    assert evaluate_scene(preds, [0.8, 0.3], gt).ap50 == pytest.approx(0.5)


def test_ties_count_everything_at_or_above_the_threshold() -> None:
    # One TP and one FP with the same score 0.5, H = 0: one distinct score, k=0: tp=1 fp=1 fn=0 -> p=1/2 r=1;
    # end p=1 r=0. Widths: (r0-r1)/2 = 1/2, (r0-0)/2 = 1/2  ->  AP = 1/2*1/2 + 1*1/2 = 3/4
    ap, prec, rec = average_precision([True, False], [0.5, 0.5], 0)
    assert ap == pytest.approx(0.75)
    np.testing.assert_allclose(prec, [0.5, 1.0])
    np.testing.assert_allclose(rec, [1.0, 0.0])


def test_rounding_to_four_decimals_creates_ties() -> None:
    # GT 1 found by p0 (conf .12341), p1 = FP (conf .12344). Unrounded: (T .12341) (F .12344):
    #   k=0: tp=1 fp=1 fn=0 -> p=1/2 r=1; k=1 cum=1: tp=0 fp=1 fn=1 -> p=0 r=0; end p=1 r=0
    #   widths (1-0)/2, (1-0)/2, (0-0)/2 -> AP = 1/4
    # Rounded to 4 decimals both are .1234: the tie case above -> AP = 3/4
    gt = np.zeros(N, np.int32)
    gt[:200] = 1
    preds = [rng_mask(0, 200), rng_mask(1000, 1200)]
    assert evaluate_scene(preds, [0.12341, 0.12344], gt, decimals=None).ap50 == pytest.approx(0.25)
    assert evaluate_scene(preds, [0.12341, 0.12344], gt).ap50 == pytest.approx(0.75)


def test_perfect_predictions_score_one() -> None:
    res = evaluate_scene([rng_mask(0, 200), rng_mask(200, 400)], [0.5, 0.7], two_gt())
    assert res.ap == pytest.approx(1.0) and res.ap50 == pytest.approx(1.0) and res.ap25 == pytest.approx(1.0)


def test_empty_predictions_give_zero_and_no_gt_gives_nan() -> None:
    res = evaluate_scene([], [], two_gt())
    assert res.ap == 0.0 and res.ap50 == 0.0 and res.ap25 == 0.0
    res = evaluate_scene([rng_mask(0, 200)], [0.5], np.zeros(N, np.int32))
    assert math.isnan(res.ap) and math.isnan(res.ap50) and math.isnan(res.ap25)
    assert math.isnan(evaluate_scene([], [], np.zeros(N, np.int32)).ap)


def test_size_filters() -> None:
    gt = np.zeros(N, np.int32)
    gt[:99] = 1  # too small: not evaluated
    gt[200:400] = 2
    # a 99-point prediction of GT 2's points is dropped (not even an FP)
    small_pred = rng_mask(200, 299)
    res = evaluate_scene([small_pred], [0.9], gt)
    assert res.n_pred[0] == 0 and res.n_gt[0] == 1 and res.ap50 == 0.0
    # a prediction that matches only the small GT is silently ignored: the only entry is GT 2's TP -> AP 1
    on_small = rng_mask(0, 110)  # IoU with GT 1 = 99 / 110 > 0.5
    res = evaluate_scene([on_small, rng_mask(200, 400)], [0.9, 0.5], gt)
    assert res.ap50 == pytest.approx(1.0)
    # ... but at IoU > 0.90 (> 99/110 = 0.9) it is an ordinary FP, ranked above the TP: AP < 1
    col = int(np.flatnonzero(np.isclose(IOU_THRESHOLDS, 0.9))[0])
    assert res.ap_table[0, col] < 1.0


def test_strict_iou_comparison() -> None:
    gt = np.zeros(N, np.int32)
    gt[:200] = 1
    # IoU exactly 0.5: 100 points inside GT 1 + 0 outside -> 100 / 200 = 0.5, not > 0.5
    res = evaluate_scene([rng_mask(0, 100)], [0.9], gt)
    assert res.ap50 == 0.0
    assert res.ap25 == pytest.approx(1.0)


def test_categories_select_the_evaluated_class() -> None:
    gt = two_gt()
    cats = {1: "mug", 2: "bowl"}
    # the bowl is not a GT instance of class 'mug': a prediction on it is a false positive
    res = evaluate_scene([rng_mask(0, 200), rng_mask(200, 400)], [0.4, 0.9], gt, gt_categories=cats)
    # entries (T .4) (F .9), H = 0: k=0: p=1/2 r=1; k=1: cum=1: tp=0 -> p=0 r=0; end (1, 0)
    # widths (1-0)/2, (1-0)/2, 0 -> AP = 1/4
    assert res.n_gt[0] == 1 and res.ap50 == pytest.approx(0.25)
    # two classes: each scores 1
    res2 = evaluate_scene(
        [rng_mask(0, 200), rng_mask(200, 400)], [0.4, 0.9], gt, labels=np.array([1, 2]),
        gt_categories=cats, class_names=("mug", "bowl"),
    )
    assert np.allclose(res2.ap_table, 1.0)
    assert set(res2.per_class()) == {"mug", "bowl"}


def test_evaluate_accumulates_over_scenes_and_checks_names() -> None:
    gt_a = SceneGroundTruth("a", two_gt())
    gt_b = SceneGroundTruth("b", two_gt())
    pa = ScenePrediction("a", [rng_mask(0, 200)], np.array([0.9]))
    pb = ScenePrediction("b", [rng_mask(200, 400), rng_mask(900, 1100)], np.array([0.8, 0.95]))
    # entries: a: (T .9), GT a2 missed (H); b: (T .8), (F .95), GT b1 missed (H). T=2, H=2, n=3
    #   .8: k=0 cum=0: tp=2 fp=1 fn=2 -> p=2/3 r=1/2;  .9: k=1 cum=1: tp=1 fp=1 fn=3 -> p=1/2 r=1/4
    #   .95: k=2 cum=2: tp=0 fp=1 fn=4 -> p=0 r=0;  end p=1 r=0
    #   widths: (1/2-1/4)/2 = 1/8, (1/2-0)/2 = 1/4, (1/4-0)/2 = 1/8, 0 -> AP = 2/3/8 + 1/2/4 = 1/12 + 1/8 = 5/24
    res = evaluate([pb, pa], [gt_a, gt_b])
    assert res.ap50 == pytest.approx(5 / 24)
    assert res.scenes == ["a", "b"]
    with pytest.raises(ValueError, match="differ"):
        evaluate([pa], [gt_a, gt_b])
    assert evaluate([pa], [gt_a, gt_b], strict=False).n_gt[0] == 4
    with pytest.raises(ValueError, match="points"):
        evaluate([ScenePrediction("a", [np.ones(10, bool)], np.array([1.0]))], [gt_a])
    with pytest.raises(ValueError, match="confidences"):
        ScenePrediction("a", [np.ones(10, bool)], np.array([1.0, 2.0]))


# ---------------------------------------------------------------------------------------------- naive reference
def naive_ap(y_true: list[bool], y_score: list[float], hard_fn: int) -> float:
    """§5.4 written out literally: one PR point per distinct score (everything scoring >= it counts)."""
    if not y_true:
        return 0.0
    precisions, recalls = [], []
    total_true = sum(y_true)
    for s in sorted(set(y_score)):
        tp = sum(1 for t, sc in zip(y_true, y_score) if t and sc >= s)
        fp = sum(1 for t, sc in zip(y_true, y_score) if not t and sc >= s)
        fn = (total_true - tp) + hard_fn
        precisions.append(tp / (tp + fp))
        recalls.append(tp / (tp + fn))
    precisions.append(1.0)
    recalls.append(0.0)
    u = len(precisions) - 1
    ap = 0.0
    for i in range(u + 1):
        left = recalls[i - 1] if i >= 1 else recalls[0]
        right = recalls[i + 1] if i + 1 <= u else 0.0
        ap += precisions[i] * (left - right) / 2
    return ap


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.booleans(), st.integers(0, 6)), min_size=0, max_size=25),
    st.integers(0, 5),
)
def test_average_precision_matches_naive_reference(entries: list[tuple[bool, int]], hard_fn: int) -> None:
    y_true = [t for t, _ in entries]
    y_score = [s / 6 for _, s in entries]  # few distinct values: many ties
    if not any(y_true) and hard_fn == 0:
        hard_fn = 1
    ap, prec, rec = average_precision(y_true, y_score, hard_fn)
    assert ap == pytest.approx(naive_ap(y_true, y_score, hard_fn), abs=1e-12)
    assert -1e-12 <= ap <= 1 + 1e-12
    assert prec[-1] == 1.0 and rec[-1] == 0.0
    assert np.all(np.diff(rec) <= 1e-12)  # recall never increases with the score threshold


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_random_scenes_bounds_and_perfect_copy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 3000
    gt = np.zeros(n, np.int32)
    k = int(rng.integers(1, 6))
    cuts = np.sort(rng.choice(np.arange(1, n), size=2 * k, replace=False))
    for i in range(k):
        gt[cuts[2 * i] : cuts[2 * i + 1]] = i + 1
    masks = [rng.random(n) < rng.uniform(0.02, 0.3) for _ in range(int(rng.integers(0, 6)))]
    for i in range(1, k + 1):  # noisy copies of some GTs
        if rng.random() < 0.6:
            m = gt == i
            flip = rng.random(n) < 0.02
            masks.append(m ^ flip)
    conf = rng.random(len(masks))
    res = evaluate_scene(masks, conf, gt)
    for v in (res.ap, res.ap50, res.ap25):
        assert math.isnan(v) or 0.0 <= v <= 1.0
    exact = [gt == i for i in range(1, k + 1) if (gt == i).sum() >= 100]
    if exact:
        perfect = evaluate_scene(exact, np.linspace(0.5, 0.9, len(exact)), gt)
        assert perfect.ap == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------- viewer helpers
def test_match_instances_tp_fp_fn() -> None:
    gt = two_gt()
    preds = [rng_mask(0, 200), rng_mask(0, 190), rng_mask(1000, 1300)]
    res = match_instances(preds, gt, iou=0.5, confidences=np.array([0.5, 0.9, 0.1]))
    tp, fp, fn = res  # unpacks as three lists
    assert tp == [1] and fp == [0, 2] and fn == [2]  # the more confident duplicate wins
    assert res.pairs[0][:2] == (1, 1) and res.pairs[0][2] == pytest.approx(0.95)
    tp, fp, fn = match_instances(preds, gt)  # prediction order
    assert tp == [0] and fp == [1, 2] and fn == [2]
    idx_masks = [np.arange(200, 400)]  # int index arrays work too
    assert list(match_instances(idx_masks, gt)) == [[0], [], [1]]


def test_evaluate_instances_from_an_instances_like_object() -> None:
    inst = SimpleNamespace(
        masks=[np.arange(0, 200, dtype=np.int32), np.arange(200, 400, dtype=np.int32)],
        confidence=np.array([0.9, 0.2], np.float32),
        category=np.array(["mug", "mug"]),
    )
    scene = SimpleNamespace(name="s", instance=two_gt(), categories={})
    assert evaluate_instances(inst, scene).ap == pytest.approx(1.0)
    assert evaluate_instances(inst, scene, threshold=0.5).ap50 == pytest.approx(0.5)  # GT 2 now missed
    res = evaluate_instances(inst, scene)
    assert "mug @ IoU 0.50" in res.pr_curves
    json.dumps(res.to_dict())  # JSON-friendly


# ---------------------------------------------------------------------------------------------- files and CLI
def test_scannet_layout_round_trip(tmp_path: Path) -> None:
    gt = SceneGroundTruth("scene0", two_gt())
    pred = ScenePrediction("scene0", [rng_mask(0, 200), np.arange(200, 380)], np.array([0.91234, 0.5]))
    write_scannet_predictions(tmp_path, pred, num_points=N)
    txt = (tmp_path / "scene0.txt").read_text().splitlines()
    assert txt[0] == "pred_mask/scene0_000.txt 1 0.9123"
    assert (tmp_path / "pred_mask" / "scene0_000.txt.npy").is_file()
    (loaded,) = load_scannet_predictions(tmp_path)
    assert loaded.name == "scene0" and len(loaded.masks) == 2
    np.testing.assert_array_equal(loaded.masks[1], rng_mask(200, 380))
    assert evaluate([loaded], [gt]).ap50 == pytest.approx(evaluate([pred], [gt]).ap50)
    # text masks (ScanNet / `Instances.to_scannet`) under a scannet/ subfolder
    write_scannet_predictions(tmp_path / "res" / "scannet", pred, num_points=N, npy=False)
    (loaded2,) = load_scannet_predictions(tmp_path / "res")
    np.testing.assert_array_equal(loaded2.masks[0], loaded.masks[0])
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.txt").write_text("pred_mask/missing.txt 1 0.5\n")
    with pytest.raises(ValueError, match="not found"):
        load_scannet_predictions(tmp_path / "bad")


def test_evaluate_cli(tmp_path: Path) -> None:
    from efem_viz.cli import main
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(0)
    gts_dir = tmp_path / "gt"
    for name in ("a", "b"):
        scene = Scene.create(
            name, rng.random((N, 3)), normals=np.tile([0, 0, 1.0], (N, 1)), instance=two_gt(),
            categories={1: "mug", 2: "mug"},
        )
        save_scene(scene, gts_dir / f"{name}.ply")
        pred = ScenePrediction(name, [rng_mask(0, 200), rng_mask(900, 1100)], np.array([0.9, 0.1]))
        write_scannet_predictions(tmp_path / "res", pred, num_points=N)
    out = tmp_path / "ev.json"
    assert main(["evaluate", str(tmp_path / "res"), "--gt", str(gts_dir), "--json-out", str(out)]) == 0
    data = json.loads(out.read_text())
    # per scene: (T .9), (F .1), H = 1; two scenes: T=2, n=4, H=2
    #   .1: k=0 cum=0: tp=2 fp=2 fn=2 -> p=1/2 r=1/2; .9: k=2 cum=0: tp=2 fp=0 fn=2 -> p=1 r=1/2; end (1, 0)
    #   widths 0, 1/4, 1/4 -> AP = 1/2
    assert data["ap50"] == pytest.approx(0.5)
    assert data["per_class"]["mug"]["n_gt"] == 4
    assert main(["evaluate", str(tmp_path / "res"), "--gt", str(gts_dir / "a.ply")]) == 1  # strict: b unmatched


def test_the_viewer_comparison_reports_each_class_of_a_family_scene() -> None:
    """A kitchen scene (a mug and two bowls): an instance named "bowl" on the mug is a false positive of "bowl"
    and leaves the mug missed; the comparison gives AP50 per class (with the objects each has) and the panel
    text shows them; a one-class scene shows no per-class line."""
    from types import SimpleNamespace

    from efem_viz.data.scene import Scene
    from efem_viz.eval.comparison import gt_metrics
    from efem_viz.viewer.texts import gt_markdown

    inst = np.repeat(np.array([1, 2, 3], np.int32), 100)
    scene = Scene.create("kit", np.random.default_rng(0).random((300, 3)).astype(np.float32), instance=inst,
                         categories={1: "mug", 2: "bowl", 3: "bowl"})
    masks = [np.arange(0, 100), np.arange(100, 200), np.arange(200, 300)]

    class Shown(SimpleNamespace):
        def above(self, t: float) -> "Shown":
            return self

    pred = Shown(masks=masks, confidence=np.array([0.9, 0.8, 0.7], np.float32),
                 category=np.array(["bowl", "bowl", "bowl"]))
    m = gt_metrics(pred, scene, 0.0)
    per = {name: (ap50, n) for name, ap50, n in m.per_class}
    assert per["mug"] == (0.0, 1) and per["bowl"][1] == 2 and 0.0 < per["bowl"][0] < 1.0
    assert m.ap50 == pytest.approx((per["mug"][0] + per["bowl"][0]) / 2)
    text = gt_markdown(3, 0.0, m)
    assert "AP50 per class: bowl" in text and "mug 0.000 (1)" in text
    one = Scene.create("one", scene.points, instance=inst, categories={1: "mug", 2: "mug", 3: "mug"})
    pred.category = np.array(["mug", "mug", "mug"])
    single = gt_metrics(pred, one, 0.0)
    assert single.per_class == () and "per class" not in gt_markdown(3, 0.0, single)


def test_evaluate_takes_its_classes_from_the_labelled_scenes(tmp_path: Path) -> None:
    """Without --classes, `evaluate` scores the categories the labelled scenes name (a chair scene is scored as
    chairs, not as zero mugs); a scene naming two categories gives a row each, the predictions matched by category;
    --classes still decides when given."""
    import dataclasses

    from efem_viz.cli import main
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.em import EMResult

    repo = Path(__file__).resolve().parents[1]
    scene = load_scene(repo / "sample_scenes" / "syn_pile_0.ply")
    res = EMResult.load(repo / "sample_scenes" / "syn_pile_0.efem.npz")
    ids = [int(i) for i in np.unique(scene.instance) if i > 0]
    assert len(ids) == 5

    def run(folder: str, categories: dict[int, str], pred_category: Any, *args: str) -> dict[str, Any]:
        d = tmp_path / folder
        save_scene(dataclasses.replace(scene, categories=categories), d / "syn_pile_0.ply")
        cats = pred_category(res) if callable(pred_category) else np.full(len(res.instances), pred_category)
        dataclasses.replace(res, instances=dataclasses.replace(res.instances, category=cats)).save(
            d / "syn_pile_0.efem.npz")
        assert main(["evaluate", str(d), "--gt", str(d), "--json-out", str(d / "ev.json"), *args]) == 0
        return json.loads((d / "ev.json").read_text())

    chairs = run("chairs", {i: "chair" for i in ids}, "chair")
    assert set(chairs["per_class"]) == {"chair"} and chairs["per_class"]["chair"]["n_gt"] == 5
    mugs = run("mugs", {i: "mug" for i in ids}, "mug")
    assert chairs["ap50"] == pytest.approx(mugs["ap50"]) and mugs["ap50"] > 0.5  # the same masks, either name

    # two categories: each instance's prediction named after the object it covers best
    two = {i: ("chair" if i in ids[:2] else "mug") for i in ids}

    def named(r: Any) -> np.ndarray:
        best = [np.bincount(scene.instance[np.asarray(m)], minlength=max(ids) + 1)[1:].argmax() + 1
                for m in r.instances.masks]
        return np.array([two[int(b)] for b in best])

    both = run("two", two, named)
    assert {k: v["n_gt"] for k, v in both["per_class"].items()} == {"chair": 2, "mug": 3}
    only_mug = run("given", two, named, "--classes", "mug")
    assert {k: v["n_gt"] for k, v in only_mug["per_class"].items()} == {"mug": 3}
