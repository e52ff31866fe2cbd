"""The report's answer, at the top of the page: the asset relit under each evaluation light beside the truth, the
headline figures (relighting and maps: the method's, the no-prior baseline's and the 2D predictions'), and one line
per ablation saying whether this object agrees with the paper, which has Full ahead of each of them."""

from __future__ import annotations

import html

from matspray.eval.page.markup import markdown_to_html
from matspray.eval.tables import (
    MISSING,
    _bold_best,
    _comparable,
    format_metallic_psnr,
    format_metric,
    markdown_table,
)
from matspray.presets import BASELINE, LABELS, PAPER_ABLATION, PAPER_BASELINE, PAPER_SOFTMAX

# (column, table1 row, metric): relighting in full, and each map by its PSNR
HEADLINE_COLUMNS = (
    ("Relighting PSNR ↑", "relighting", "psnr"),
    ("SSIM ↑", "relighting", "ssim"),
    ("LPIPS ↓", "relighting", "lpips"),
    ("Base colour PSNR ↑", "basecolor", "psnr"),
    ("Roughness PSNR ↑", "roughness", "psnr"),
    ("Metallic PSNR ↑", "metallic", "psnr"),
)
# what Full is compared with, and the paper's relighting PSNR of both (its Table 2, softmax ablation and Table 1)
COMPARISONS = (
    ("no-softmax", PAPER_SOFTMAX),
    ("proj-average", PAPER_ABLATION),
    ("supervised", PAPER_ABLATION),
    (BASELINE, PAPER_BASELINE),
)


DISAGREEMENT_NOTE = (
    " One object can go against the mean of many: on the demo object Without Softmax relights above Full, measured "
    'and explained in MatSpray\'s docs/dev/relighting-gap.md ("The demo object").'
)


def headline_table(table1: dict) -> str:
    """Markdown: one row per method of Table 1 (Ours, the no-prior baseline, the 2D predictions, as the run has
    them), the columns of HEADLINE_COLUMNS, the best of each column bold."""
    names = list(table1)
    columns = []
    for _, row, metric in HEADLINE_COLUMNS:
        entries = [table1[name].get(row) for name in names]
        if row == "metallic" and metric == "psnr":
            cells = [format_metallic_psnr(entry) for entry in entries]
        else:
            cells = [format_metric(entry, metric) for entry in entries]
        columns.append(_bold_best(cells, [_comparable(e, metric) for e in entries], metric != "lpips"))
    rows = [[name] + [column[i] for column in columns] for i, name in enumerate(names)]
    return markdown_table([""] + [title for title, _, _ in HEADLINE_COLUMNS], rows)


def ablation_verdicts(variants: dict) -> list[tuple[str, bool | None]]:
    """One line per variant compared with Full (relighting PSNR in dB, this run's and the paper's), and whether it
    agrees with the paper, which has Full ahead of each (None: a tie, equal at the precision shown, 0.1 dB)."""
    if "full" not in variants:
        return []
    full = variants["full"]["summary"]["relighting"]["psnr"]
    lines = []
    for other, paper in COMPARISONS:
        if other not in variants:
            continue
        theirs = variants[other]["summary"]["relighting"]["psnr"]
        label, gap = LABELS.get(other, other), full - theirs
        cited = f"paper: {paper['full']:.1f} vs {paper[other]:.1f}"
        if round(gap, 1) == 0:
            lines.append((f"Full vs {label}: a tie here ({full:.1f} vs {theirs:.1f} dB; {cited}, Full ahead).", None))
        elif gap > 0:
            text = f"Full vs {label}: agrees with the paper. Full ahead by {gap:.1f} dB "
            text += f"({full:.1f} vs {theirs:.1f}; {cited})."
            lines.append((text, True))
        else:
            text = (
                f"Full vs {label}: does NOT agree with the paper. {label} beats Full by {-gap:.1f} dB here "
                f"({theirs:.1f} vs {full:.1f}); in the paper Full is ahead ({cited})."
            )
            lines.append((text, False))
    return lines


def verdicts_html(variants: dict) -> str:
    """The ablation lines as a list, each marked as agreeing or not; empty without Full."""
    lines = ablation_verdicts(variants)
    if not lines:
        return ""
    css = {True: "agrees", False: "disagrees", None: "tie"}
    items = "".join(f'<li class="{css[agrees]}">{html.escape(text)}</li>' for text, agrees in lines)
    return (
        '<h2>Ablations against the paper</h2><ul class="verdicts" id="verdicts">'
        + items
        + "</ul><p class='note'>Relighting PSNR over the test views and held-out lights of "
        "this one object; the paper's are means over its objects (17, or a subset for Supervised and Proj. "
        "Average)." + (DISAGREEMENT_NOTE if any(agrees is False for _, agrees in lines) else "") + "</p>"
    )


def relit_grid(view_name: str, env_names: list[str], figures, size: int) -> str:
    """The truth above the Full asset, one column per light, from the PNGs the test view's rows wrote."""
    columns = f"1.2em repeat({len(env_names)}, {size + 8}px)"
    cells = ['<span class="rowlabel">ground truth</span>']
    cells += [figures.figure(f"{view_name}_{env}_gt", f"ground truth, {env}") for env in env_names]
    cells.append('<span class="rowlabel">Full (ours)</span>')
    cells += [figures.figure(f"{view_name}_{env}_full", f"{LABELS['full']}, {env}") for env in env_names]
    style = f"grid-template-columns: {columns}; --picture: {size}px"
    return f'<div class="relit-grid" id="summary-relit" style="{style}">' + "".join(cells) + "</div>"


def summary_section(metrics: dict, view_name: str | None, figures, simulated: bool) -> str:
    """The top of the report: relit pictures (left; when the run has Full and relit truth) and the headline with the
    ablations (right)."""
    env_names = metrics.get("relight_envs", [])
    size = max(120, min(200, 540 // max(len(env_names), 1)))
    left = ""
    if view_name is not None and env_names and "full" in metrics.get("variants", {}):
        left = (
            f"<div><h2>Relit, test view {html.escape(view_name)}</h2>"
            + relit_grid(view_name, env_names, figures, size)
            + "<p class='note'>Held-out lights, never seen in training. Click a picture to "
            "enlarge it.</p></div>"
        )
    table1 = metrics.get("table1", {})
    views = len(next(iter(metrics.get("variants", {}).values()), {}).get("per_view", []))
    caption = f"Mean over {views} test views under {len(env_names)} held-out lights, on the object (its true mask)." + (
        " The 2D predictions are simulated from the ground truth." if simulated else ""
    )
    right = (
        '<div><h2>Headline</h2><div id="headline">'
        + (markdown_to_html(headline_table(table1)) if table1 else f"<p>{MISSING} no figures</p>")
        + f"</div><p class='note'>{html.escape(caption)}</p>"
        + verdicts_html(metrics.get("variants", {}))
        + "</div>"
    )
    return f'<section class="summary">{left}{right}</section>'
