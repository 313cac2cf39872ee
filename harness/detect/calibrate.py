"""Scores a robot can threshold: each raw LoC as an exceedance against a null.

docs/method.md, *Calibrated alarms*. Raw LoC (``N * sum 1/r'``) has no unit. The calibrated
score of a frame is the share of the null's frames that score at least as high; of a change box,
the share of the null's change boxes. By default the null is made of pairs that hold no change
by construction, scored by the same detector (:mod:`harness.detect.null`); within the run
(``[detect] calibration = "within-run"``) it is the run's own frames and candidate boxes, which
can never say that nothing changed. Both are estimated as ``(1 + #{null >= s}) / (1 + n)``,
which never reaches 0 and is a valid (conservative) p-value where the score is drawn like the
null's. Thresholding it at a rate ``a`` (``harness detect --alarm a``) flags about a share ``a``
of unchanged content: the nominal false-alarm rate, measured on frames annotated ``no-change``
in Table D.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd


def exceedance(null: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``(1 + #{null >= v}) / (1 + n)`` for each ``v`` of ``values`` (NaN stays NaN).

    ``null``'s non-finite values are left out; with an empty null every value gets 1.
    """
    ref = np.sort(np.asarray(null, np.float64)[np.isfinite(np.asarray(null, np.float64))])
    v = np.asarray(values, np.float64)
    ge = len(ref) - np.searchsorted(ref, v, side="left")
    out = (1.0 + ge) / (1.0 + len(ref))
    return np.where(np.isfinite(v), out, np.nan)


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


@dataclass(frozen=True)
class Alarms:
    """What the nominal false-alarm rate flags: the one count the files, console and page read.

    ``frames``: the flagged frame rows; ``boxes``: the flagged change-box rows; ``of_frames``,
    ``of_boxes``: how many there were to flag.
    """

    rate: float
    frames: pd.DataFrame
    boxes: pd.DataFrame
    of_frames: int
    of_boxes: int

    def record(self) -> dict[str, Any]:
        """``detect.json``'s ``alarm``: the rate, the frames and boxes flagged, of how many."""
        return {
            "rate": self.rate,
            "frames": len(self.frames),
            "boxes": len(self.boxes),
            "of_frames": self.of_frames,
            "of_boxes": self.of_boxes,
        }


def alarms_of(fr: pd.DataFrame, det: pd.DataFrame, rate: float) -> Alarms:
    """The frames and change boxes flagged at the nominal false-alarm rate ``rate``.

    A frame is flagged where its calibrated score is at most ``rate`` and its pair is comparable;
    a box only where its own calibrated score is at most ``rate`` and its frame is flagged (the
    frame is tested first: the boxes of a frame whose score the no-change null reaches are not
    flagged). ``fr``: the frame rows; ``det``: the change boxes (``exceedance``, ``comparable``).
    """
    key = ["session", "camera", "utime"]
    frames = fr[(fr["exceedance"] <= rate) & fr["comparable"].astype(bool)]
    in_flagged = pd.MultiIndex.from_frame(det[key]).isin(pd.MultiIndex.from_frame(frames[key]))
    boxes = det[(det["exceedance"] <= rate) & det["comparable"].astype(bool) & in_flagged]
    return Alarms(rate, frames, boxes, len(fr), len(det))
