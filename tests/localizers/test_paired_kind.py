"""A new paired-frame localizer kind is one file plus its registration (docs/architecture.md,
*Where to add*): ``examples/plugins/patch_ncc.py`` ranks each box by how unlike the same box of
its paired map frame it looks, and ``harness detect`` ranks with it, scores its no-change null
with it and names it, as a user types the command, with nothing else added to the harness.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.localizers.kinds import LOCALIZER_KINDS, paired_kinds

from ..conftest import TEST_NULL_PAIRS, blob_wall

ROOT = Path(__file__).resolve().parents[2]
PLUGIN = ROOT / "examples" / "plugins" / "patch_ncc.py"


def _folders(d: Path, n: int = 9) -> list[tuple[int, int, int, int]]:
    """A camera sliding along a wall of blobs (``A``), the same frames with a magenta square
    pasted into every third (``B``), and the annotations; returns the pasted boxes."""
    w, h = 160, 120
    wall = blob_wall(5, w + 6 * n, h)
    (d / "A").mkdir(parents=True)
    (d / "B").mkdir()
    rows, boxes = ["image,status,x1,y1,x2,y2,label"], []
    for i in range(n):
        im = np.ascontiguousarray(wall[:, 6 * i : 6 * i + w])
        q = im.copy()
        if i % 3 == 0:
            x, y = 40 + 5 * i, 30 + 3 * i
            q[y : y + 36, x : x + 36] = (230, 40, 200)
            rows.append(f"f{i:02d}.png,change,{x},{y},{x + 36},{y + 36},box")
            boxes.append((x, y, x + 36, y + 36))
        else:
            rows.append(f"f{i:02d}.png,no-change,,,,,")
        cv2.imwrite(str(d / "A" / f"f{i:02d}.png"), im[..., ::-1])
        cv2.imwrite(str(d / "B" / f"f{i:02d}.png"), q[..., ::-1])
    (d / "ann.csv").write_text("\n".join(rows) + "\n")
    return boxes


def test_a_paired_frame_kind_is_one_file_and_detect_ranks_and_calibrates_with_it(
    tmp_path: Path,
) -> None:
    pasted = _folders(tmp_path)
    out = tmp_path / "out"
    small = tmp_path / "null.toml"  # a smaller null: its own figures are tests/detect's
    small.write_text(f"[detect.null]\npairs = {TEST_NULL_PAIRS}\n")
    cmd = ["--plugin", str(PLUGIN), "detect", "--map-images", str(tmp_path / "A"),
           "--query-images", str(tmp_path / "B"), "--annotations", str(tmp_path / "ann.csv"),
           "--config", str(small), "--localizer", "patch-ncc", "--out", str(out)]  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "harness.cli", *cmd], cwd=ROOT,
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    rec = json.loads((out / "detect.json").read_text())
    assert rec["localizers"] == ["patch-ncc"] and rec["options"]["localizer"] == "patch-ncc"
    assert rec["options"]["patch-ncc"] == {"frames_per_unit": 64, "min_side": 4}  # its defaults
    cal = rec["calibration"]  # the null scored by the same kind, not calibrated within the run
    assert (cal["method"], cal["construction"], cal["frames_scored"]) == (
        "null",
        "perturbed",
        TEST_NULL_PAIRS,
    )
    # each pasted square: the top box of its frame lies on it
    fr = pd.read_csv(out / "frames.csv").set_index("name")
    for i, (x1, y1, x2, y2) in zip(range(0, 9, 3), pasted, strict=True):
        top = fr.loc[f"f{i:02d}.png", ["top_x1", "top_y1", "top_x2", "top_y2"]].to_numpy(float)
        ix = max(0.0, min(x2, top[2]) - max(x1, top[0])) * max(
            0.0, min(y2, top[3]) - max(y1, top[1])
        )
        union = (x2 - x1) * (y2 - y1) + (top[2] - top[0]) * (top[3] - top[1]) - ix
        assert ix / union > 0.5, (i, top)
    t = pd.read_csv(out / "tableD.csv").set_index("row")
    assert t.loc["detector", "ap50_voc_all_point"] > t.loc["detector", "chance_high"]
    # the plugin's registration is all it took: the harness's own kinds are untouched
    assert "patch-ncc" not in LOCALIZER_KINDS and paired_kinds() == ("local", "keypoints")
    bad = subprocess.run([sys.executable, "-m", "harness.cli", *cmd[2:-4], "--localizer",
                          "patch-ncc", "--out", str(tmp_path / "no")], cwd=ROOT,
                         capture_output=True, text=True, check=False)  # fmt: skip
    assert bad.returncode == 1 and bad.stderr.count("ERROR:") == 1, bad.stderr
    assert "patch-ncc" in bad.stderr and "keypoints or config" in bad.stderr, bad.stderr
