"""The alarms in words, as the console and the page print them (docs/method.md).

A calibrated score (an exceedance against the no-change null, :mod:`harness.detect.calibrate`)
as a person reads it, and the lines that say what the false-alarm rate flagged.
"""

from __future__ import annotations

import math
from typing import Any


def in_words(p: float, what: str) -> str:
    """``1 in 1,000 {what} scores this high`` (the exceedance as a person reads it).

    From a share of one in five up, where "1 in n" reads oddly ("1 in 1 frames"), the share
    itself: ``60% of {what} score this high``.
    """
    if p != p:
        return f"no calibrated score ({what})"
    if p > 0.2:
        return f"{100 * p:.0f}% of {what} score this high"
    n = max(1, round(1.0 / p))
    return f"1 in {n:,} {what} scores this high"


def alarm_words(al: dict[str, Any], cal: dict[str, Any]) -> str:
    """The console's and the page's lines on the alarms.

    ``al``: ``detect.json``'s ``alarm``; ``cal``: its ``calibration``.
    """
    n, rate = al.get("of_frames", 0), al["rate"]
    if cal.get("method") == "null":
        null_n = int(cal.get("frames_scored", cal.get("pairs", 0)))
        against = f"null: {null_n} no-change pairs from the map, {cal.get('construction')}"
        least = 1 / (null_n + 1)
        small = (
            f" (the null's {null_n} pairs flag nothing below 1/{null_n + 1} = {least:.3g}: set "
            f"[detect.null] pairs to {math.ceil(1 / rate - 1)} or more, or pass --alarm "
            f"{least:.2g})"
        )
    else:
        against = "calibrated within the run: its own frames and candidate boxes"
        least = 2 / (n + 1) if n else 1.0  # the top frame is in its own null
        small = (
            f" (with {n} frames the least calibrated score is 2/{n + 1} = {least:.3g}, above "
            f"{rate:g}: pass --alarm {least:.2g} or more to flag any)"
        )
    lines = [
        f"alarms: {al['frames']} of {n} frames and {al['boxes']} of {al.get('of_boxes', 0)} change "
        f"boxes exceed the false-alarm rate {rate:g} ({against}; alarms.csv)"
    ]
    if not al["frames"]:
        lines.append("no change detected at that rate" + (small if least > rate else ""))
    return "\n".join(lines)
