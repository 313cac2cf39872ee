"""Change-map overlays: the LoC colour scale drawn under a map (the report page and ``detect``)."""

from __future__ import annotations

import cv2
import numpy as np


def colour_bar(width: int, lo: float, hi: float, height: int = 30) -> np.ndarray:
    """The LoC map's colour scale: the inferno ramp from ``lo`` (left) to ``hi``, labelled.

    The map is normalised per image, so the bar states that image's range of the method's LoC.
    """
    ramp = np.linspace(0, 255, max(width, 2)).astype(np.uint8)[None, :].repeat(12, 0)
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_INFERNO)[..., ::-1]
    out = np.full((height, width, 3), 255, np.uint8)
    out[2:14] = bar[:, :width]
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    left = f"LoC {lo:.3g}" if lo == lo else "no LoC"
    right = f"{hi:.3g} (more changed)" if hi == hi else ""
    cv2.putText(out, left, (1, height - 4), font, scale, (40, 40, 40), 1, cv2.LINE_AA)
    (tw, _), _ = cv2.getTextSize(right, font, scale, 1)
    cv2.putText(out, right, (max(1, width - tw - 1), height - 4), font, scale, (40, 40, 40), 1)
    return out
