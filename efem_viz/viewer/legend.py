"""What the viewer says about the final instances: their colours, scene labels, category counts and the legend.

`color_key_html` is the key of the point colours of each colour mode (TP/FP/FN, the weight colour bar).
`instance_table_markdown` is the Results tab's instance table (its dropdown's options, `instance_options`, are a
headless text in `efem_viz.viewer.texts`; both are built like the annotator's instance list, from
`efem_viz.serve.table`).

Pure functions of an `efem_viz.em.Instances` (no viser): the live viewer and the static demo both draw their
instance nodes with `result_colors` and `instance_label`, and the Results tab shows `result_summary_markdown` and
`legend_html`. A result may hold several categories (one per prior of a joint solve, e.g. "mug" and "sphere"):
each category has one colour (`category_color`, stable across scenes and runs) for its name in the legend, while
each instance keeps its own colour (the one of its points, mesh and box) for its swatch.
"""

from __future__ import annotations

import html
import zlib
from typing import TYPE_CHECKING, Sequence

import numpy as np

from efem_viz.colors import (DEAD_COLOR, FN_COLOR, FP_COLOR, HEAT_RGB, HEAT_STOPS, TP_COLOR, dim, hex_color,
                             instance_colors, result_colors)
from efem_viz.eval.comparison import GTMetrics
from efem_viz.serve.table import cell, swatch
from efem_viz.viewer.texts import md_escape
from efem_viz.terminal import count

if TYPE_CHECKING:
    from efem_viz.em.results import Instances

MAX_LEGEND_ROWS = 40
"""The legend lists at most this many instances (highest confidence first), then says how many more."""
MAX_TABLE_ROWS = 60
"""The instance table lists at most this many instances (highest confidence first), then says how many more."""


def category_color(category: str) -> tuple[int, int, int]:
    """The colour of a category name: `instance_colors` of the name's CRC-32, so the same name has the same
    colour in every scene and run (independent of which other categories a result holds)."""
    r, g, b = (int(c) for c in instance_colors([zlib.crc32(str(category).encode("utf-8")) & 0x7FFFFFFF])[0])
    return r, g, b


def instance_label(instances: Instances, k: int) -> str:
    """Text of instance k's label in the scene: category, proposal id and confidence (e.g. "mug #12 · 0.87")."""
    return f"{instances.category[k]} #{int(instances.ids[k])} · {float(instances.confidence[k]):.2f}"


def category_counts(categories: Sequence[str] | np.ndarray) -> dict[str, int]:
    """Instances per category, in order of first appearance.

    Args:
        categories: (K,) str, e.g. `Instances.category[keep]`.
    """
    out: dict[str, int] = {}
    for c in np.asarray(categories, dtype=str).reshape(-1).tolist():
        out[c] = out.get(c, 0) + 1
    return out


def category_summary(categories: Sequence[str] | np.ndarray) -> str:
    """Plain text "mug 2 · sphere 1" of `category_counts` ("" for no instances)."""
    return " · ".join(f"{c} {k}" for c, k in category_counts(categories).items())


def result_summary_markdown(instances: Instances, keep: np.ndarray, *, threshold: float, out_tau: float,
                            hidden_by_hand: int = 0) -> str:
    """The Results tab's summary: how many instances the threshold keeps and how many it hides, per category,
    and the mask band.

    Args:
        instances: `efem_viz.em.Instances` (confidence (K,), category (K,)).
        keep: (K,) bool, the instances kept by the threshold (`Instances.kept`).
        threshold: the confidence threshold.
        out_tau: the output masks' SDF band τ_out (canonical units).
        hidden_by_hand: kept instances hidden in the instance table.
    """
    keep = np.asarray(keep, bool).reshape(-1)
    conf = np.asarray(instances.confidence, float)
    below = int(keep.size - keep.sum())
    lines = [
        f"**{int(keep.sum())} of {count(keep.size, 'instance')}** with confidence ≥ {threshold:.2f}"
        + (f" (max {conf.max():.2f})" if conf.size else "")
        + (f" · **{below} hidden** below the cut (the slider at 0 shows them)" if below else "")
        + (f" · {hidden_by_hand} hidden in the table" if hidden_by_hand else "")
    ]
    all_counts = category_counts(np.asarray(instances.category, dtype=str))
    if all_counts:
        kept_counts = category_counts(np.asarray(instances.category, dtype=str)[keep])
        lines.append(" · ".join(f"{md_escape(c)}: {kept_counts.get(c, 0)} of {n}" for c, n in all_counts.items()))
    lines.append(f"masks: points with decoded \\|SDF\\| < {out_tau:g} (τ_out, canonical units)")
    return "\n\n".join(lines)


def legend_html(instances: Instances, keep: np.ndarray) -> str:
    """The instance legend: one row per kept instance (highest confidence first) with its colour swatch, id,
    category (in the category's colour) and confidence. Text from the result file is escaped.

    Args:
        instances: `efem_viz.em.Instances`.
        keep: (K,) bool, the instances kept by the threshold.

    Returns:
        An HTML fragment ("" when no instance is kept).
    """
    keep = np.asarray(keep, bool).reshape(-1)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return ""
    conf = np.asarray(instances.confidence, float)
    order = idx[np.argsort(-conf[idx], kind="stable")]
    cols = result_colors(instances)
    rows = []
    for k in order[:MAX_LEGEND_ROWS]:
        cat = str(instances.category[k])
        rows.append(
            f'<div><span style="color:{hex_color(cols[k])}">&#9632;</span> #{int(instances.ids[k])} '
            f'<b style="color:{hex_color(category_color(cat))}">{html.escape(cat)}</b> {conf[k]:.2f}</div>'
        )
    if order.size > MAX_LEGEND_ROWS:
        rows.append(f"<div>… {order.size - MAX_LEGEND_ROWS} more</div>")
    return '<div style="font-size:0.85em;line-height:1.5">' + "".join(rows) + "</div>"


GREY_SWATCH = hex_color(dim(np.array([[128, 128, 128]], np.uint8))[0])
"""The grey of points that no shown prediction covers (`efem_viz.colors.dim`)."""


def _swatch(color: str, text: str) -> str:
    return f'<div><span style="color:{color}">&#9632;</span> {text}</div>'


def color_key_html(mode: str) -> str:
    """The key of the point colours in a colour mode, shown under the Colour control.

    Args:
        mode: the colour mode in effect: "gt_match" (TP / FP / FN, boxes too), "instances", "weights" (the
            inspected proposal's weight heat map: a colour bar), "step" (one EM step on screen: the samples' and
            shapes' colours) or "rgb" (scene colours: no key).

    Returns:
        An HTML fragment ("" for scene colours).
    """
    if mode == "gt_match":
        rows = [
            _swatch(hex_color(TP_COLOR), "<b>TP</b>: a prediction matched to a ground-truth object (IoU ≥ 0.5)"),
            _swatch(hex_color(FP_COLOR), "<b>FP</b>: a prediction that matches none"),
            _swatch(hex_color(FN_COLOR), "<b>FN</b>: a ground-truth object no prediction found"),
            _swatch(GREY_SWATCH, "grey: no prediction (boxes are green / red as TP / FP)"),
        ]
    elif mode == "instances":
        rows = [_swatch(GREY_SWATCH, "grey: no instance shown; each instance in its colour (legend: Results tab)")]
    elif mode == "weights":
        stops = ", ".join(f"{hex_color(c)} {100 * p:.0f}%" for c, p in zip(HEAT_RGB.astype(np.uint8), HEAT_STOPS))
        rows = [
            f'<div style="height:0.8em;border-radius:2px;background:linear-gradient(to right, {stops})"></div>',
            '<div style="display:flex;justify-content:space-between"><span>0</span>'
            "<span>weight of the point in the inspected proposal</span><span>1</span></div>",
            _swatch(GREY_SWATCH, "grey: weight ≤ 0.001"),
        ]
    elif mode == "step":
        rows = [
            "<div>One EM step on screen: the scene in its own colours</div>",
            _swatch(hex_color(instance_colors([7])[0]), "each drawn proposal's samples and decoded shape in the "
                    "proposal's colour (click a shape to inspect it)"),
            _swatch(hex_color(DEAD_COLOR), "red shape: the proposal is terminated at this step"),
        ]
    else:
        return ""
    return '<div class="efem-color-key" style="font-size:0.85em;line-height:1.5">' + "".join(rows) + "</div>"


def instance_table_markdown(
    instances: Instances,
    *,
    threshold: float,
    hidden: set[int] | frozenset[int] = frozenset(),
    metrics: GTMetrics | None = None,
    selected: int | None = None,
) -> str:
    """The instance table: one row per instance, most confident first: id (with its colour), category,
    confidence, number of points, TP/FP with IoU (with ground truth) and whether it is shown.

    Args:
        instances: `efem_viz.em.Instances`.
        threshold: the confidence threshold (rows below it say "below cut").
        hidden: proposal ids hidden by hand (their rows say "hidden").
        metrics: the ground-truth comparison at `threshold` (`efem_viz.eval.comparison.gt_metrics`; its indices
            count the instances kept by the threshold), or None without ground truth.
        selected: the proposal id chosen in the dropdown (its row is marked ◀).

    Returns:
        Markdown ("" for no instances). Category names from the result file are escaped.
    """
    conf = np.asarray(instances.confidence, float).reshape(-1)
    if conf.size == 0:
        return ""
    ids = np.asarray(instances.ids).reshape(-1)
    kept = instances.kept(float(threshold))
    slot = np.cumsum(kept) - 1  # index among the kept instances (what the metrics count)
    tp = set(metrics.tp) if metrics is not None else set()
    cols = result_colors(instances)
    head = "| id | category | conf. | points |" + (" GT (IoU) |" if metrics is not None else "") + " shown |"
    rule = "|---:|---|---:|---:|" + ("---|" if metrics is not None else "") + "---|"
    rows = [head, rule]
    order = np.argsort(-conf, kind="stable")
    for k in order[:MAX_TABLE_ROWS]:
        pid = int(ids[k])
        mark = " ◀" if selected is not None and pid == int(selected) else ""
        shown = "below cut" if not kept[k] else ("hidden" if pid in hidden else "yes")
        row = (f"| {pid} {swatch(tuple(int(c) for c in cols[k]))}{mark} | {cell(instances.category[k])} | "
               f"{conf[k]:.2f} | {len(instances.masks[k]):,} |")
        if metrics is not None:
            if kept[k]:
                j = int(slot[k])
                iou = metrics.ious[j] if j < len(metrics.ious) else float("nan")
                row += f" {'TP' if j in tp else 'FP'} ({iou:.2f}) |"
            else:
                row += " – |"
        rows.append(row + f" {shown} |")
    if order.size > MAX_TABLE_ROWS:
        rows.append(f"\n… {order.size - MAX_TABLE_ROWS} more (least confident) in the dropdown")
    return "\n".join(rows)
