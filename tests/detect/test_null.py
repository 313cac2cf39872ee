"""The no-change null that calibrates ``harness detect``'s alarms (docs/decisions.md, *Calibrated
alarms*): its perturbed copies, its pairs, and what it flags where nothing changed.

The copies are checked against OpenCV's own operations by hand, the pairs' construction on a
small frame table, and the whole command as a user types it on a folder given as both map and
query (nothing can have changed: no frame and no box may be flagged at 0.01), on written images
and (``tests/detect/test_detect_real.py``) on the real revisits of ``obchange-dev``.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.cli import main
from harness.detect.config import NullConfig
from harness.detect.null import construction_for, draw, null_choice, null_pairs
from harness.imagestore import ImageRef, read_image
from harness.perturb import Perturbation, apply, fragment, parse
from harness.runtime.stage import Table


def _wall(n: int, w: int = 160, h: int = 120) -> list[np.ndarray]:
    """``n`` frames of a camera sliding along a wall of coloured blobs (RGB)."""
    rng = np.random.default_rng(5)
    wall = np.full((h, w + 6 * n, 3), 120, np.uint8)
    for _ in range(wall.shape[1] * h // 300):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        cv2.circle(wall, (int(rng.integers(0, wall.shape[1])), int(rng.integers(0, h))),
                   int(rng.integers(2, 12)), c, -1)  # fmt: skip
    return [np.ascontiguousarray(wall[:, 6 * i : 6 * i + w]) for i in range(n)]


def test_a_copy_is_named_by_its_drawn_values_and_made_as_it_is_read(tmp_path: Path) -> None:
    img = _wall(1)[0]
    cv2.imwrite(str(tmp_path / "a.png"), img[..., ::-1])
    p = Perturbation(1.08, -5.0, 0.01, -0.02, 1.5, 0.98, 0.004, 80)
    uri = str(tmp_path / "a.png") + fragment(p)
    ref = ImageRef.parse(uri)
    assert (ref.path, ref.perturbed) == (str(tmp_path / "a.png"), p)
    assert parse(fragment(p).split("=", 1)[1]) == p
    got = read_image(uri)
    # by hand: gain and offset, the affine warp about the centre plus the shift, the blur, JPEG
    h, w = img.shape[:2]
    x = np.clip(img.astype(np.float32) * 1.08 - 5.0, 0, 255).astype(np.uint8)
    m = cv2.getRotationMatrix2D((w / 2, h / 2), 1.5, 0.98)
    m[:, 2] += (0.01 * w, -0.02 * h)
    x = cv2.warpAffine(x, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    x = cv2.GaussianBlur(x, (0, 0), 0.004 * w)
    ok, buf = cv2.imencode(".jpg", x[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    np.testing.assert_array_equal(got, cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    assert np.array_equal(apply(img, Perturbation()), img)  # the identity draw changes nothing
    assert not np.array_equal(got, img)


def test_a_uri_that_names_no_copy_is_one_error_naming_it(tmp_path: Path) -> None:
    from harness.errors import IngestError

    cv2.imwrite(str(tmp_path / "a.png"), _wall(1)[0])
    for bad in ("#perturb=z1", "#perturb=gx", "#perturb="):
        with pytest.raises(IngestError, match=re.escape(str(tmp_path / "a.png") + bad)):
            read_image(str(tmp_path / "a.png") + bad)


def test_every_draw_is_within_the_stated_limits_and_the_same_each_time() -> None:
    nc = NullConfig()
    draws = [draw(nc, i) for i in range(300)]
    assert draws == [draw(nc, i) for i in range(300)]  # by (seed, i): the same on every run
    assert len(set(draws)) == 300
    for d in draws:
        assert abs(d.gain - 1) <= nc.gain and abs(d.offset) <= nc.offset
        assert max(abs(d.dx), abs(d.dy)) <= nc.shift and abs(d.rotation_deg) <= nc.rotation_deg
        assert abs(d.scale - 1) <= nc.scale and 0 <= d.blur <= nc.blur
        assert nc.jpeg_quality <= d.jpeg <= 95
    assert draw(NullConfig(seed=1), 0) != draws[0]


def _tables(n: int) -> tuple[Table, Table]:
    fr = pd.DataFrame({
        "session": ["map"] * n + ["new"] * 2, "camera": "cam",
        "utime": [*range(1000, 1000 + 10 * n, 10), 5, 6],
        "image": [f"/m/{i}.png" for i in range(n)] + ["/q/0.png", "/q/1.png"],
        "width": 160, "height": 120,
    })  # fmt: skip
    props = pd.DataFrame({
        "session": "map", "camera": "cam",
        "utime": np.repeat(fr["utime"].to_numpy()[:n], 2),
        "x1": 1.0, "y1": 2.0, "x2": 30.0, "y2": 40.0, "proposal_method": "segments",
    })  # fmt: skip
    return Table(fr, "frames-key"), Table(props, "props-key")


def _null(frames: Table, props: Table, nc: NullConfig, by: str) -> Any:
    return null_pairs(frames, null_choice(frames, "map", nc, by), props, nc)


def test_the_null_pairs_by_construction() -> None:
    frames, props = _tables(5)
    nb = _null(frames, props, NullConfig(), "pose")
    assert nb.construction == "neighbours" and nb.copies == 0
    p = nb.pairs.df
    # each frame against the next and back: (0, 1), (1, 0), (1, 2), (2, 1), ...
    want = [(a, b) for i in range(4) for a, b in ((i, i + 1), (i + 1, i))]
    got = zip((p["q_utime"] - 1000) // 10, (p["r_utime"] - 1000) // 10, strict=True)
    assert list(got) == want
    assert (p["r_camera"] == "cam").all() and p["q_camera"].is_unique  # each pair its own query
    assert (nb.pairs.df["q_session"] == "map").all() and (p["season_pair"] == "null").all()
    # each null query holds its frame's proposals, under its own name
    pr = nb.proposals.df
    assert len(pr) == 2 * len(p) and set(pr["camera"]) == set(p["q_camera"])
    # the null's own queries are frames with the originals' images
    fq = nb.frames.df.set_index(["camera", "utime"])["image"]
    keys = zip(p["q_camera"], p["q_utime"], strict=True)
    assert all(fq[(c, u)] == f"/m/{(u - 1000) // 10}.png" for c, u in keys)
    pt = _null(frames, props, NullConfig(pairs=12), "name")
    assert pt.construction == "perturbed" and pt.copies == 3 and len(pt.pairs.df) == 12
    refs = pt.frames.df.set_index(["camera", "utime"])["image"]
    imgs = [refs[(c, u)] for c, u in zip(pt.pairs.df["r_camera"], pt.pairs.df["r_utime"],
                                          strict=True)]  # fmt: skip
    refs_ = [ImageRef.parse(i) for i in imgs]
    assert all(r.perturbed == draw(NullConfig(pairs=12), j) for j, r in enumerate(refs_))
    assert [r.path for r in refs_] == [f"/m/{j % 5}.png" for j in range(12)]
    assert pt.pairs.key != _null(frames, props, NullConfig(pairs=12, seed=1), "name").pairs.key
    # the map is a sequence where the pairs follow its order or poses; by name or retrieval not
    assert [construction_for(NullConfig(), by) for by in ("pose", "order", "sequence", "name",
            "retrieval")] == ["neighbours"] * 3 + ["perturbed"] * 2  # fmt: skip
    assert construction_for(NullConfig(construction="perturbed"), "pose") == "perturbed"


def test_the_null_is_chosen_before_proposals_and_proposes_only_its_queries() -> None:
    """The null's map frames are chosen from the frames alone; only they are proposed, and a pair
    whose query frame has no proposal is left out and counted."""
    frames, props = _tables(40)
    nc = NullConfig(pairs=10)
    choice = null_choice(frames, "map", nc, "pose")
    asked = choice.query_frames(frames.df)
    # ten pairs of consecutive frames, spread over the map: at most ten map frames proposed
    assert len(choice.queries) == 10 and 0 < len(asked) <= 10 and (asked["session"] == "map").all()
    assert list(asked.index) == sorted(asked.index)  # the frame table's order
    full = _null(frames, props, nc, "pose")
    assert full.no_proposals == 0 and len(full.pairs.df) == 10
    # the first query frame has no proposal: its pair (only) is left out
    first = int(choice.queries["utime"].iloc[0])
    some = Table(props.df[props.df["utime"] != first], "props-without-one")
    cut = null_pairs(frames, choice, some, nc)
    lost = int((choice.queries["utime"] == first).sum())
    assert cut.no_proposals == lost and len(cut.pairs.df) == 10 - lost
    assert first not in set(cut.pairs.df["q_utime"])


def _detect(argv: list[str]) -> tuple[str, dict]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    out = Path(argv[argv.index("--out") + 1])
    return buf.getvalue(), json.loads((out / "detect.json").read_text())


def _says_nothing(printed: str, rec: dict, n: int) -> None:
    said = [x for x in printed.splitlines() if x.startswith("alarms: ")]
    assert re.fullmatch(rf"alarms: 0 of {n} frames and 0 of \d+ change boxes exceed the "
                        r"false-alarm rate 0\.01 \(null: 100 no-change pairs from the map, "
                        r"perturbed; alarms\.csv\)", said[0]), said  # fmt: skip
    assert "no change detected at that rate" in printed
    assert rec["alarm"]["frames"] == rec["alarm"]["boxes"] == 0 and rec["alarm"]["of_boxes"] > 0


def test_the_same_folder_as_map_and_query_flags_no_frame_and_no_box(tmp_path: Path) -> None:
    """Nothing can have changed; the null (perturbed copies: a folder paired by name is no
    sequence) says so. Calibrated within the run, the same frames' boxes still rank among their
    own candidates: that calibration can never say that nothing changed."""
    d = tmp_path / "x"
    d.mkdir()
    for i, im in enumerate(_wall(12)):
        cv2.imwrite(str(d / f"f{i:02d}.png"), im[..., ::-1])
    printed, rec = _detect(["detect", "--map-images", str(d), "--query-images", str(d),
                            "--out", str(tmp_path / "out")])  # fmt: skip
    cal = rec["calibration"]
    assert cal["method"] == "null" and cal["construction"] == "perturbed"
    assert (cal["pairs"], cal["copies_per_map_frame"], cal["frames_scored"]) == (100, 9, 100)
    assert cal["limits"] == {k: v for k, v in NullConfig().__dict__.items()
                             if k not in ("construction", "pairs")}  # fmt: skip
    _says_nothing(printed, rec, 12)
    page = (tmp_path / "out" / "detect.html").read_text()
    assert "data-alarms='0' data-calibration='null'" in page and "perturbed copy" in page
    assert len(rec["cache_entries"]["detect-null"]) >= 1
    assert cal["chunks"] == {"scored_now": len(rec["cache_entries"]["detect-null"]), "reused": 0}
    # the same command again: the null is paid once, and detect.json says it was reused
    _, again = _detect(["detect", "--map-images", str(d), "--query-images", str(d),
                        "--out", str(tmp_path / "out")])  # fmt: skip
    n = cal["chunks"]["scored_now"]
    assert again["calibration"]["chunks"] == {"scored_now": 0, "reused": n}
    assert {k: v for k, v in again["calibration"].items() if k != "chunks"} == {
        k: v for k, v in cal.items() if k != "chunks"
    }
    # by name, within the run: the old calibration, still there
    within = ["--calibration", "within-run", "--out", str(tmp_path / "w")]
    printed_w, rec_w = _detect(["detect", "--map-images", str(d), "--query-images", str(d),
                                *within])  # fmt: skip
    assert rec_w["calibration"] == {"method": "within-run"}
    assert "calibrated within the run" in printed_w and "detect-null" not in rec_w["cache_entries"]
