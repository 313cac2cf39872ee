"""The detect page's notes on the frames its most-changed list leaves out (method §13.2, 13.5).

Uncertain pairs (another place matches almost as well) and pairs that could not be registered
(not comparable): counted and named.
"""

from __future__ import annotations

import pandas as pd

from harness.reports.html import esc


def not_comparable_html(fr: pd.DataFrame) -> str:
    """The pairs that could not be registered, counted and named (docs/method.md, §13.5)."""
    if "comparable" not in fr.columns or fr["comparable"].astype(bool).all():
        return ""
    bad = fr[~fr["comparable"].astype(bool)]
    label = [
        f"{n or f'{s} {c} {u}'} ({why})"
        for s, c, u, n, why in zip(
            bad["session"], bad["camera"], bad["utime"], bad.get("name", [""] * len(bad)),
            bad["not_comparable_why"], strict=True,
        )
    ]  # fmt: skip
    shown = "; ".join(label[:20]) + (f" and {len(label) - 20} more" if len(label) > 20 else "")
    fallback = (
        (bad["compared_by"].isin(["ecc", "identity", "colour"])).any()
        if "compared_by" in bad
        else False
    )
    what = (
        "compared without a registration (by the colours' novelty, or a fallback warp): "
        "their boxes are marked and measured apart in Table D"
        if fallback
        else "no change box and no score"
    )
    return (
        f'<p class="note uncertain" data-not-comparable="{len(bad)}">Not comparable: '
        f"{len(bad)} of {len(fr)} query frames could not be registered with their map frame, so "
        f"they raise no alarm and are left out of this list ({what}): {esc(shown)}.</p>"
    )


def uncertain_html(fr: pd.DataFrame) -> str:
    """How many uncertain pairs the most-changed list leaves out, naming them (method §13.2)."""
    if "uncertain_pair" not in fr.columns or not fr["uncertain_pair"].any():
        return ""
    bad = fr[fr["uncertain_pair"]]
    label = [
        str(n) if n else f"{s} {c} {u}"
        for s, c, u, n in zip(
            bad["session"],
            bad["camera"],
            bad["utime"],
            bad.get("name", [""] * len(bad)),
            strict=True,
        )
    ]
    shown = ", ".join(label[:20]) + (f" and {len(label) - 20} more" if len(label) > 20 else "")
    return (
        f'<p class="note uncertain" data-uncertain="{len(bad)}">Uncertain pairs: {len(bad)} of '
        f"{len(fr)} query frames were paired with a map frame that another place matches almost "
        "as well (pair_confidence under [pairs] min_pair_confidence), so their change scores may "
        f"compare different places; they are left out of this list: {esc(shown)}.</p>"
    )
