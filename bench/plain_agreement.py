"""``python -m bench.plain_agreement [--set obchange-rooms]``: Table D's plain difference against
the reference run in ``../shared/realdata/obchange-rooms/reference-difference/``, pair by pair.

For each pair: the registration verdict (the same, or not), the change maps' Pearson correlation
over the pixels either map reads (the harness's map rounded to 8 bits, as the reference's is
stored), and how many of the reference's 10 boxes one of the harness's 10 meets at IoU 0.5 (the
harness's plain difference: :class:`harness.detect.plain.PairDifference` with the default
``[detect]``, every box of Selective Search, NMS at 0.5, the top 10). Prints a line a pair and the
three counts; ``--out FILE`` writes the pairs as CSV. Skips, saying so, where the folder is absent.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import harness  # noqa: F401  (first: it pins the kernels numpy and OpenCV load)
from harness.detect.config import DetectConfig

import cv2  # isort: skip
import numpy as np  # isort: skip
import pandas as pd  # isort: skip

from harness.detect.pair import PairDifference  # isort: skip
from harness.detect.plain import reference_boxes  # isort: skip
from harness.boxes import iou_matrix, nms  # isort: skip
from harness.proposals.config import SelectiveConfig  # isort: skip

REAL = Path(__file__).resolve().parents[2] / "shared" / "realdata"


def _rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def agreement(folder: Path, images: list[str] | None = None) -> pd.DataFrame:
    """A row a pair of ``folder`` (A/, B/, reference-difference/): verdict, correlation, boxes."""
    ref = folder / "reference-difference"
    pairs = pd.read_csv(ref / "pairs.csv")
    dets = pd.read_csv(ref / "detections.csv")
    opt, sel = DetectConfig(), SelectiveConfig()
    rows = []
    for _, p in pairs.iterrows():
        name = str(p["image"])
        if images is not None and name not in images:
            continue
        q, m = _rgb(folder / "B" / name), _rgb(folder / "A" / name)
        pair = PairDifference(q, m, opt)
        mine = np.zeros(q.shape[:2], np.float32) if pair.made is None else pair.made[0]
        theirs = cv2.imread(str(ref / "maps" / f"{Path(name).stem}.png"), cv2.IMREAD_GRAYSCALE)
        ours = np.round(mine * 255.0)
        read = (ours > 0) | (theirs > 0)
        corr = float(np.corrcoef(ours[read], theirs[read])[0, 1]) if read.sum() > 1 else 1.0
        boxes = reference_boxes(q, sel.work_width, sel.mode, sel.seed)
        scores = pair.score(boxes)
        top = boxes[nms(boxes, scores, 0.5)[:10]]
        theirs_top = dets[dets["image"] == name][["x1", "y1", "x2", "y2"]].to_numpy(float)
        met = int((iou_matrix(theirs_top, top).max(1) >= 0.5).sum()) if len(top) else 0
        rows.append(
            {
                "image": name,
                "registered": int(pair.reg.comparable),
                "reference_registered": int(p["registered"]),
                "inliers": pair.reg.inliers,
                "reference_inliers": int(p["inliers"]),
                "map_correlation": round(corr, 4),
                "boxes_met": met,
            }
        )
    return pd.DataFrame(rows)


def summary(t: pd.DataFrame) -> str:
    """The three counts the agreement is judged by."""
    same = int((t["registered"] == t["reference_registered"]).sum())
    both = t[(t["registered"] == 1) & (t["reference_registered"] == 1)]
    return (
        f"same registration verdict: {same} of {len(t)} pairs; change maps correlating >= 0.9: "
        f"{int((both['map_correlation'] >= 0.9).sum())} of the {len(both)} pairs both register "
        f"(every pair: {int((t['map_correlation'] >= 0.9).sum())} of {len(t)}); >= 8 of the "
        f"reference's 10 boxes met at IoU 0.5: {int((t['boxes_met'] >= 8).sum())} of {len(t)} pairs"
    )


def main(argv: list[str] | None = None) -> int:
    """Print each pair's agreement and the counts."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="obchange-rooms")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    folder = REAL / a.set
    if not (folder / "reference-difference" / "pairs.csv").is_file():
        print(f"skipped: {folder}/reference-difference is absent (shared/realdata is read, never "
              "committed)")  # fmt: skip
        return 0
    t = agreement(folder)
    print(t.to_string(index=False))
    print(summary(t))
    if a.out:
        t.to_csv(a.out, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
