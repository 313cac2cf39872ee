"""Table D's pixel part: ``tableD_pixel.md`` and the page's ``tableDP`` (method §9 and 13.2).

Rendered from the table :func:`harness.evaluate.table_d_pixel.pixel_table` computes.
"""

from __future__ import annotations

import pandas as pd

from harness.evaluate.chance import MARK_LEGEND, VERDICT_WORDS, few_text, few_warning
from harness.reports.html import esc


def pixel_markdown(t: pd.DataFrame) -> str:
    """The pixel table as markdown, with its floor, band, ceiling and what it measures."""
    d = t.iloc[0]
    cells = [
        f"| {r.row} | {r.pixel_ap:.3f} [{r.ci_low:.3f}, {r.ci_high:.3f}] | "
        + (
            few_text(int(r.positive_images))
            if r.verdict == "few"
            else VERDICT_WORDS[str(r.verdict)]
        )
        + " |"
        for r in t.itertuples()
    ]
    lines = [
        "# Table D, pixels: the LoC maps against the change masks",
        "",
        f"Pixel AP (method §9: 101-point, the pixels of the {int(d['masked_frames'])} masked query "
        "images pooled; each pixel takes the LoC of the smallest box holding it, a pixel no box "
        "covers the lowest LoC; positive where its mask is non-zero) with its 95% bootstrap "
        "interval over masked images.",
        "",
        "| | pixel AP [95% CI] | verdict |",
        "|---|---:|---|",
        *cells,
        "",
        "| pixel AP of these boxes | value |",
        "|---|---:|",
        f"| positive rate (change pixels among all pixels) | {d['positive_rate']:.4f} |",
        f"| floor (mean pixel AP of random box scores, same maps) | {d['floor']:.3f} |",
        f"| chance band (5th-95th percentile of those draws) | {d['chance_low']:.3f}-"
        f"{d['chance_high']:.3f} |",
        f"| ceiling (boxes scored by their share of change pixels, same maps) | "
        f"{d['ceiling']:.3f} |",
        "",
        f"Verdict (method §9): {MARK_LEGEND}",
    ]
    if d["verdict"] == "few":
        few = int((t["verdict"] == "few").sum())
        lines += ["", few_warning(few, int(d["positive_images_needed"]))]
    elif d["verdict"] == "baseline":
        lines += [
            "",
            f"WARNING: the detector's pixel AP is above chance but not clear of the best no-pixel "
            f"baseline ({d['best_no_pixel']}; paired difference [{d['vs_no_pixel_ci_low']:+.3f}, "
            f"{d['vs_no_pixel_ci_high']:+.3f}]): no verdict above it (method §13.3).",
        ]
    return "\n".join(lines) + "\n"


def pixel_html(t: pd.DataFrame | None) -> str:
    """The pixel table for the page, verdicts as ``data-verdict`` cells."""
    if t is None:
        return ""
    d = t.iloc[0]
    rows = "".join(
        f"<tr><td>{esc(r.row)}</td><td data-verdict='{esc(r.verdict)}'>{r.pixel_ap:.3f} "
        f"[{r.ci_low:.3f}, {r.ci_high:.3f}]</td><td>"
        + esc(
            few_text(int(r.positive_images))
            if r.verdict == "few"
            else VERDICT_WORDS[str(r.verdict)]
        )
        + "</td></tr>"
        for r in t.itertuples()
    )
    return (
        '<h2 id="tableDP">Table D, pixels: the LoC maps against the change masks</h2>'
        f"<p class='note'>Pixel AP (method §9) of the {int(d['masked_frames'])} masked query "
        "images' pixels pooled, each pixel the LoC of the smallest box holding it, positive where "
        "its mask is non-zero; 95% bootstrap interval over masked images.</p>"
        "<table data-table='DP'><tr><th></th><th>pixel AP</th><th>verdict</th></tr>"
        f"{rows}</table><p class='note' data-chance='DP'>Positive rate "
        f"{d['positive_rate']:.4f}; floor {d['floor']:.3f} (random box scores, same maps), "
        f"chance band {d['chance_low']:.3f}-{d['chance_high']:.3f}, ceiling {d['ceiling']:.3f} "
        "(boxes scored by their share of change pixels).</p>"
    )
