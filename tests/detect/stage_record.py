"""``harness detect``'s keypoint stages against ``tests/regression/detect_stages.json``.

The default detector rests on SIFT, whose last bits differ between CPUs of this project's kind
(OpenCV's own kernels, which the AVX2 cap does not reach everywhere): an inlier count that moves by
one can cross the registration's threshold of 15, and a keypoint's match can pass or fail the ratio
test. So the record holds each stage's values, frame by frame, and the rule of docs/decisions.md
(*One answer on every CPU*, the detect stages) says how far each may move on another CPU:

- **registration**: the same frames comparable (a frame whose inlier count lies within 3 of
  ``min_inliers`` on either side may flip), inliers within 3 or 10%, shifts within 0.5 px,
  rotation within 0.1 degree, scale within 0.5%;
- **keypoint localization**: the same boxes a frame, each frame's mean LoC within 0.02 or 3%;
- **plain difference**: each frame's mean box difference within 2% (or 0.01);
- **change boxes**: the same count a frame, each frame's top score within 0.02 (or 3%);
- **Table D**: each row's AP50 within 0.01 (0.05 where a registration flipped; a flipped
  frame's later rows are not compared: another method compared it).

On the CPU that recorded it (same model and flags) every stage must match byte for byte (its
digest); elsewhere, within the rule. A failure names the first stage, in pipeline order, that
leaves its tolerance, this CPU and the recording one. Regenerate after an intended change with
``python -m tests.detect.stage_record RUN > tests/regression/detect_stages.json`` on the README's
second detect command's run (``tests/detect/test_detect.py``'s ``detected`` fixture).
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..stage_digests import cpu_record

RECORD = Path(__file__).resolve().parents[1] / "regression" / "detect_stages.json"
STAGES = ("registration", "keypoint localization", "plain difference", "change boxes", "Table D")
KEY = ["session", "camera", "utime"]
MIN_INLIERS = 15  # [detect.difference] min_inliers, the default the record's run uses


def _chunks(out: Path, name: str) -> pd.DataFrame:
    """``name`` of every detect and null chunk the run used (``detect.json``'s cache entries)."""
    used = json.loads((out / "detect.json").read_text())["cache_entries"]
    parts = [pd.read_parquet(out / "cache" / st / k / name) for st in ("detect", "detect-null")
             for k in used.get(st, [])]  # fmt: skip
    return pd.concat(parts, ignore_index=True)


def _per_frame(df: pd.DataFrame, col: str) -> pd.DataFrame:
    key = ["q_session", "q_camera", "q_utime"]
    g = df.groupby(key, sort=True)[col]
    t = pd.DataFrame({"n": g.size(), "mean": g.mean()}).reset_index()
    return t.rename(columns=dict(zip(key, KEY, strict=True)))


def stage_values(out: Path) -> dict[str, pd.DataFrame]:
    """Each stage's values, one row a frame (Table D: one row a table row), in a fixed order."""
    fr = _chunks(out, "frames.parquet")
    reg = fr[[*KEY, "comparable", "inliers", "reg_dx", "reg_dy", "reg_rotation_deg", "reg_scale"]]
    cand = _chunks(out, "candidates.parquet")
    dets = json.loads((out / "detections.json").read_text())
    images = {i["id"]: i for i in json.loads((out / "images.json").read_text())["images"]}
    d = pd.DataFrame([{**{k: images[x["image_id"]][k] for k in KEY}, "score": x["score"]}
                      for x in dets])  # fmt: skip
    boxes = d.groupby(KEY, sort=True)["score"].agg(["size", "max"]).reset_index()
    table = pd.read_csv(out / "tableD.csv")[["row", "ap50_voc_all_point"]]
    return {
        "registration": reg.sort_values(KEY).reset_index(drop=True),
        "keypoint localization": _per_frame(cand, "loc"),
        "plain difference": _per_frame(cand, "difference"),
        "change boxes": boxes.rename(columns={"size": "n", "max": "top"}),
        "Table D": table.rename(columns={"ap50_voc_all_point": "ap50"}),
    }


def _digest(df: pd.DataFrame) -> str:
    return hashlib.sha256(df.to_csv(index=False, float_format="%r").encode()).hexdigest()[:16]


def record(out: Path) -> dict[str, Any]:
    """What the JSON record holds: the CPU, and each stage's digest and values."""
    vals = stage_values(out)
    return {
        "cpu": cpu_record(),
        "stages": {s: {"digest": _digest(v), "values": _values(v)} for s, v in vals.items()},
    }


def _values(v: pd.DataFrame) -> Any:
    return json.loads(v.to_json(orient="split", index=False, double_precision=10))


def _close(a: pd.Series, b: pd.Series, abs_tol: float, rel: float) -> np.ndarray:
    x, y = a.to_numpy(np.float64), b.to_numpy(np.float64)
    both_nan = np.isnan(x) & np.isnan(y)
    return both_nan | (np.abs(x - y) <= np.maximum(abs_tol, rel * np.abs(y)))


def outside(
    stage: str, got: pd.DataFrame, want: pd.DataFrame, flipped: frozenset = frozenset()
) -> list[str]:
    """What of ``got`` leaves the stage's tolerance around ``want`` (empty: within it).

    ``flipped``: the frames whose registration went the other way near its threshold (allowed):
    what follows from it there is another comparison, so their later rows are not compared, and
    Table D may move by 0.05 then.
    """
    if len(got) != len(want) or list(got.columns) != list(want.columns):
        return [f"{len(got)} rows {list(got.columns)} against {len(want)} {list(want.columns)}"]
    id_cols = KEY if stage != "Table D" else ["row"]
    if not got[id_cols].astype(str).equals(want[id_cols].astype(str)):
        return ["other frames or rows"]
    checks: dict[str, list[tuple[str, float, float]]] = {
        "registration": [("inliers", 3, 0.10), ("reg_dx", 0.5, 0), ("reg_dy", 0.5, 0),
                         ("reg_rotation_deg", 0.1, 0), ("reg_scale", 0, 0.005)],
        "keypoint localization": [("n", 0, 0), ("mean", 0.02, 0.03)],
        "plain difference": [("n", 0, 0), ("mean", 0.01, 0.02)],
        "change boxes": [("n", 0, 0), ("top", 0.02, 0.03)],
        "Table D": [("ap50", 0.05 if flipped else 0.01, 0)],
    }  # fmt: skip
    bad = []
    skip = (
        np.array([tuple(k) in flipped for k in want[KEY].to_numpy().tolist()], bool)
        if stage not in ("registration", "Table D")
        else np.zeros(len(want), bool)
    )
    near = (np.abs(want["inliers"] - MIN_INLIERS) <= 3) if stage == "registration" else None
    if near is not None:
        flips = (got["comparable"].astype(bool) != want["comparable"].astype(bool)) & ~near
        bad += [f"comparable at {tuple(r)}" for r in want.loc[flips, KEY].to_numpy().tolist()]
    for col, a, r in checks[stage]:
        ok = _close(got[col], want[col], a, r) | skip
        if near is not None:
            ok |= near.to_numpy()
        bad += [f"{col} {g!r} against {w!r} at row {i}" for i, (g, w) in
                enumerate(zip(got[col], want[col], strict=True)) if not ok[i]]  # fmt: skip
    return bad


def first_stage_outside(out: Path, rec: dict[str, Any]) -> str | None:
    """None where every stage holds (byte for byte on the recording CPU, else within the rule);
    else a message naming the first stage that does not, what moved, and both CPUs."""
    here, same_cpu = cpu_record(), cpu_record() == rec["cpu"]
    flipped: frozenset = frozenset()
    for stage, v in stage_values(out).items():
        r = rec["stages"][stage]
        want = pd.DataFrame(r["values"]["data"], columns=r["values"]["columns"])
        if same_cpu and _digest(v) == r["digest"]:
            continue
        v = v.reset_index(drop=True)
        if stage == "registration":
            moved = v["comparable"].astype(bool) != want["comparable"].astype(bool)
            flipped = frozenset(tuple(k) for k in want.loc[moved, KEY].to_numpy().tolist())
        bad = outside(stage, v, want, flipped) if not same_cpu else ["its digest"]
        if bad:
            return (
                f"the first detect stage that differs from the record is {stage!r} ("
                f"{'; '.join(bad[:4])}{' ...' if len(bad) > 4 else ''}). "
                f"This CPU: {here['model']}, "
                f"{' '.join(here['flags'])}. Recorded on: {rec['cpu']['model']}, "
                f"{' '.join(rec['cpu']['flags'])}. docs/decisions.md, One answer on every CPU, "
                "says how far each detect stage may move across CPUs."
            )
    return None


if __name__ == "__main__":  # python -m tests.detect.stage_record RUN > detect_stages.json
    json.dump(record(Path(sys.argv[1])), sys.stdout, indent=1, sort_keys=True)
    print()
