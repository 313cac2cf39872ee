"""Scores a robot can threshold: each raw LoC as an exceedance against a null.

docs/decisions.md, *Calibrated alarms*. Raw LoC (``N * sum 1/r'``) has no unit. The calibrated
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
