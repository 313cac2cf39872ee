"""The plain difference by the reference recipe (``harness.detect.plain``, docs/method.md §13.5).

On the synthetic shifted pair of tests/localizers/test_keypoints.py (truth known: a shift of
(7, 4) px and a new object), the recipe registers by the shift, its change map is the object, its
ring contrast ranks the object's box first and the registered pair's tier lifts every score; two
unrelated scenes are not registered and are read by their colours. On real revisits, the recipe
agrees pair by pair with the reference run in ``../shared/realdata/obchange-rooms/
reference-difference/`` (skipped, saying so, where it is absent).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.detect.config import DetectConfig
from harness.detect.pair import PairDifference
from harness.detect.plain import (
    REGISTERED_TIER,
    colour_map,
    register_reference,
    registered_map,
    ring_contrast,
)

from ..conftest import ROOT
from ..localizers.test_keypoints import OBJECT, _background_boxes, _pair, _texture

cv2 = pytest.importorskip("cv2")

ROOMS = ROOT.parent / "shared" / "realdata" / "obchange-rooms"
DEV = ROOT.parent / "shared" / "realdata" / "obchange-dev"


def _rgb(g: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(g, cv2.COLOR_GRAY2RGB)


def test_a_shifted_pair_registers_and_its_map_and_ring_find_the_new_object() -> None:
    q, m = (_rgb(x) for x in _pair())
    reg = register_reference(q, m, 15)
    assert reg.comparable and reg.inliers >= 30 and reg.footprint > 0.95
    moved = cv2.perspectiveTransform(np.array([[[100.0, 100.0]]]), reg.H).ravel()
    np.testing.assert_allclose(moved, [93.0, 96.0], atol=0.5)  # map (x, y) is query (x-7, y-4)
    d = registered_map(q, m, reg.H)
    assert d.shape == q.shape[:2] and d.dtype == np.float32
    assert d.min() >= 0.0 and d.max() <= 1.0
    assert (d[:, -5:] == 0).all() and (d[-3:, :] == 0).all()  # the map does not reach them
    x1, y1, x2, y2 = OBJECT
    assert np.median(d[y1:y2, x1:x2]) > 4 * max(np.median(d[20:200, 20:200]), 0.01)
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    c = ring_contrast(d, boxes)
    assert c[0] > 0.1 and c[0] > 3 * max(c[1:].max(), 0.01), c
    pair = PairDifference(q, m, DetectConfig())
    assert pair.tier == REGISTERED_TIER
    np.testing.assert_array_equal(pair.score(boxes), pair.contrast(boxes) + REGISTERED_TIER)


def test_the_ring_contrast_is_the_mean_inside_less_the_rings() -> None:
    """A box over a bright square on a dark frame: inside 1, ring 0 (the ring at least 4 px)."""
    d = np.zeros((480, 640), np.float32)
    d[100:150, 200:260] = 1.0
    got = ring_contrast(d, np.array([[200.0, 100.0, 260.0, 150.0], [0, 0, 40, 40]]))
    np.testing.assert_allclose(got, [1.0, 0.0])
    # a box half on the square: the mean inside less the ring's, by hand
    box = np.array([[230.0, 100.0, 290.0, 150.0]])  # 30 of its 60 columns bright
    ring_x1, ring_x2 = 230 - 15, 290 + 15  # a quarter of 60 each side; 12.5 rounds to 12 rows
    inside, grown = d[100:150, 230:290], d[100 - 12 : 150 + 12, ring_x1:ring_x2]
    ring = (grown.sum() - inside.sum()) / (grown.size - inside.size)
    np.testing.assert_allclose(ring_contrast(d, box), [inside.mean() - ring], rtol=1e-6)


def test_unrelated_scenes_are_not_registered_and_read_by_their_colours() -> None:
    rng = np.random.default_rng(3)
    q = _rgb(_texture(rng, 240, 320))
    m = _rgb(_texture(np.random.default_rng(99), 240, 320))  # grey, as the query's scene
    q[60:120, 100:180] = (60, 120, 200)  # a blue object (Lab b -47), new to the map's colours
    reg = register_reference(q, m, 15)
    assert not reg.comparable and reg.why
    pair = PairDifference(q, m, DetectConfig())
    assert pair.tier == 0.0 and pair.used.method == "colour" and pair.made is not None
    novel = colour_map(q, m)
    assert novel[70:110, 110:170].mean() > 0.5 > novel[150:230, 200:300].mean()
    dropped = PairDifference(q, m, DetectConfig(not_comparable="drop"))
    assert dropped.made is None and np.isnan(dropped.contrast(np.array([[0, 0, 9, 9.0]]))).all()


@pytest.mark.skipif(
    not (ROOMS / "reference-difference" / "pairs.csv").is_file() or not DEV.is_dir(),
    reason=f"no reference run here: {ROOMS}/reference-difference is absent (shared/realdata is "
    "read, never committed)",
)
def test_the_plain_difference_agrees_with_the_reference_pair_by_pair() -> None:
    """obchange-dev's ten pairs (all 51: ``python -m bench.plain_agreement``): the same verdict,
    maps that correlate >= 0.9, and >= 8 of the reference's 10 boxes met at IoU 0.5."""
    from bench.plain_agreement import agreement

    names = sorted(p.name for p in (DEV / "B").iterdir())
    t = agreement(ROOMS, names)
    assert len(t) == 10
    # SIFT's last bits differ across CPUs of this kind (docs/decisions.md, *One answer on every
    # CPU*): these ten pairs lie 11 or more inliers from the threshold of 15 (26-217 registered,
    # 0-6 not) and correlate 0.948 or more, so the verdicts and maps hold on each; a box near
    # another's score may swap, so one pair in ten may fall under 8 boxes on another CPU
    assert (t["registered"] == t["reference_registered"]).all(), t
    assert (t["map_correlation"] >= 0.9).all(), t
    assert (t["boxes_met"] >= 8).sum() >= 8, t


def test_the_bench_says_why_it_skips(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from bench import plain_agreement

    assert plain_agreement.main(["--set", "no-such-set"]) == 0
    assert "skipped:" in capsys.readouterr().out
