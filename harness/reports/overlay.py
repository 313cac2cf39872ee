"""Change-map overlays: the LoC colour scale drawn under a map (the report page and ``detect``)."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd


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


#: A drawn box is left out where more than this share of its area lies inside a higher-scored
#: drawn box of its frame: a person reads one change there, not several nested ones.
INSIDE_SHARE = 0.7


def drawn_boxes(boxes: pd.DataFrame) -> pd.DataFrame:
    """The change boxes of one frame that the page and the overlays draw (a person's view).

    The alarmed boxes (column ``alarmed``) where the frame has any, else all of them; in
    descending ``score``, each kept unless more than :data:`INSIDE_SHARE` of its area lies inside
    a box kept before it. ``detections.json`` keeps every box: this is presentation.
    """
    b = boxes
    if "alarmed" in b.columns and b["alarmed"].astype(bool).any():
        b = b[b["alarmed"].astype(bool)]
    b = b.sort_values("score", ascending=False, kind="stable")
    xy = b[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    kept: list[int] = []
    for i, (x1, y1, x2, y2) in enumerate(xy):
        area = max(x2 - x1, 0.0) * max(y2 - y1, 0.0)
        inside = False
        for j in kept:
            u1, v1, u2, v2 = xy[j]
            iw = max(0.0, min(x2, u2) - max(x1, u1))
            ih = max(0.0, min(y2, v2) - max(y1, v1))
            if area > 0 and iw * ih > INSIDE_SHARE * area:
                inside = True
                break
        if not inside:
            kept.append(i)
    return b.iloc[kept]


def frame_drawn_boxes(dets: pd.DataFrame, k: tuple[str, str, int]) -> np.ndarray:
    """(n, 4) x1, y1, x2, y2 of the change boxes drawn in frame ``k`` (``dets``' ``drawn``).

    What the page's figures and the LoC overlays both draw.
    """
    b = dets[
        (dets["kind"] == "detection")
        & dets["drawn"]
        & (dets["session"] == k[0])
        & (dets["camera"] == k[1])
        & (dets["utime"] == k[2])
    ]
    return b[["x1", "y1", "x2", "y2"]].to_numpy()
