"""The ``local`` localizer (method §13.3): a rank computed by hand; the pasted box ranks worst."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from harness.errors import ConfigError
from harness.localizers.align import align_pair, feature_image
from harness.localizers.config import LocalConfig, check_local
from harness.localizers.local import box_rank, pair_ranks

from .test_localizers import _config

W, H = 96, 72
SHIFT = (2, 1)  # the query is the map moved 2 px right and 1 px down: within the tolerance
OBJECT = (56, 20, 76, 44)  # pasted into the query only


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (H // 6, W // 6)).astype(np.uint8)
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    m = _texture(0)
    q = np.roll(m, SHIFT[::-1], axis=(0, 1)).copy()
    x1, y1, x2, y2 = OBJECT
    yy, xx = np.mgrid[y1:y2, x1:x2]
    q[y1:y2, x1:x2] = np.where((xx // 4 + yy // 4) % 2 == 0, 250, 10).astype(np.uint8)
    return q, m


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def _rank_by_hand(
    src: np.ndarray, dst: np.ndarray, box: tuple[int, int, int, int], g: int, t: int
) -> tuple[int, int]:
    """method §13.3 step 2 with numpy alone: every window position's NCC, the best within t."""
    x1, y1, x2, y2 = box
    tpl = src[y1:y2, x1:x2].astype(np.float64)
    th, tw = tpl.shape
    scores = {}
    for y in range(max(0, y1 - g), min(dst.shape[0], y2 + g) - th + 1):
        for x in range(max(0, x1 - g), min(dst.shape[1], x2 + g) - tw + 1):
            scores[(x, y)] = _ncc(tpl, dst[y : y + th, x : x + tw].astype(np.float64))
    best = max(v for (x, y), v in scores.items() if abs(x - x1) <= t and abs(y - y1) <= t)
    return sum(v > best + 1e-4 for v in scores.values()) + 1, len(scores)


def test_one_subimage_rank_by_hand_and_the_pasted_object_ranks_worst() -> None:
    q, m = _pair()
    lc = LocalConfig(both_directions=False)
    fq, fm = feature_image(q, lc.image), feature_image(m, lc.image)
    valid = np.ones(q.shape, bool)
    box = (20, 14, 44, 38)  # background: present in both frames, moved by SHIFT
    t = max(lc.min_tolerance_px, round(lc.tolerance * math.hypot(W, H)))
    g = max(lc.min_grow_px, round(lc.grow * 24), lc.window_over_tolerance * t)
    assert (t, g) == (2, 6)
    rank, L, _ = box_rank(fq, fm, valid, box, lc)
    assert (rank, L) == _rank_by_hand(fq, fm, box, g, t)
    assert rank == 1 and L == 13 * 13  # the texture is found where it should be

    both = LocalConfig()
    boxes = [(8, 8, 28, 32), (30, 40, 50, 64), box, OBJECT]
    r = [
        (lambda x: x[0] / x[1])(box_rank(fq, fm, valid, b, both))  # type: ignore[index]
        for b in boxes
    ]
    assert int(np.argmax(r)) == 3, r  # the pasted object localizes worst
    assert r[3] > 5 * max(r[:3])


def test_pair_ranks_aligns_and_ranks_files(tmp_path) -> None:
    q, m = _pair()
    cv2.imwrite(str(tmp_path / "q.png"), q)
    cv2.imwrite(str(tmp_path / "m.png"), m)
    boxes = np.array([[8, 8, 28, 32], OBJECT, [0, 0, 1, 1]], np.float64)
    al, got = pair_ranks(str(tmp_path / "q.png"), str(tmp_path / "m.png"), (W, H), boxes,
                         LocalConfig(align=("identity",)))  # fmt: skip
    assert al.method == "identity"
    assert got[1, 0] / got[1, 1] > got[0, 0] / got[0, 1]
    assert np.isnan(got[2]).all()  # under 2 px: no rank (the caller counts it)


def test_a_homography_is_found_for_a_warped_copy_and_refused_for_noise() -> None:
    m = _texture(3)
    big = cv2.resize(m, (W * 3, H * 3), interpolation=cv2.INTER_CUBIC)
    Hq = np.array([[1.0, 0.02, 4.0], [-0.01, 1.0, 3.0], [0.0, 0.0, 1.0]])
    q = cv2.warpPerspective(big, Hq, big.shape[::-1])
    for keypoints in ("orb", "sift"):
        lc = LocalConfig(align=("homography", "identity"), keypoints=keypoints, min_inliers=8)
        al = align_pair(q, big, lc)
        assert al.method == "homography" and al.inliers >= 8, keypoints
        # H maps query pixels to map pixels: the inverse of the warp that made the query
        pts = np.array([[[10.0, 10.0]], [[250.0, 30.0]], [[140.0, 190.0]]])
        want = cv2.perspectiveTransform(pts, np.linalg.inv(Hq))
        assert al.H is not None, keypoints
        err = np.abs(cv2.perspectiveTransform(pts, al.H) - want).max()
        assert err < {"orb": 5.0, "sift": 1.5}[keypoints], (keypoints, err)  # ORB: coarser
    noise = np.random.default_rng(1).integers(0, 256, big.shape).astype(np.uint8)
    refused = align_pair(noise, big, LocalConfig(align=("homography",), identity_min_ncc=0.5))
    assert refused.method == "none" and refused.H is None


def test_bad_options_are_one_config_error() -> None:
    with pytest.raises(ConfigError, match="align"):
        check_local(LocalConfig(align=("sift",)), "[detect.local]")
    with pytest.raises(ConfigError, match="tolerance"):
        check_local(LocalConfig(tolerance=2.0), "[detect.local]")


def test_the_config_reads_detect_local_and_a_local_localizer(tmp_path) -> None:
    from harness.config.assemble import load_config

    cfg = load_config(
        _config(
            tmp_path,
            '[detect]\nlocalizer = "local"\n\n[detect.local]\ntolerance = 0.02\n'
            'align = ["identity"]\n',
        )
    )
    assert cfg.detect.localizer == "local"
    assert cfg.detect.local == LocalConfig(tolerance=0.02, align=("identity",))
    (loc,) = load_config(
        _config(tmp_path, '[[localizers]]\nname = "mine"\nlocal = { grow = 0.5 }\n')
    ).localizer_set()
    assert (loc.kind, loc.options) == ("local", LocalConfig(grow=0.5))
    for bad, word in (
        ('[detect]\nlocalizer = "global"\n', "[detect] localizer"),
        ("[detect.local]\nwork_side = 8\n", "work_side"),
        ('[[localizers]]\nname = "m"\nlocal = { align = ["sift"] }\n', "align"),
    ):
        with pytest.raises(ConfigError, match=re.escape(word)):
            load_config(_config(tmp_path, bad))


def test_the_no_pixel_baselines_of_table_d_by_hand() -> None:
    """Table D's rows that read no pixel (method §13.3): a box's area, and how many of the frame's
    candidates overlap it (itself included); the detector is above only when clear of the best."""
    from harness.boxes import greedy_nms
    from harness.evaluate.chance import ChanceSettings
    from harness.evaluate.table_d import no_pixel_scores
    from harness.evaluate.table_d_chance import table_d_chance

    boxes = np.array([[0, 0, 10, 10], [5, 5, 25, 15], [40, 40, 44, 60]], np.float64)
    s = no_pixel_scores(boxes)
    assert s["size_prior"].tolist() == [100.0, 200.0, 80.0]
    assert s["cover_count"].tolist() == [2.0, 2.0, 1.0]
    # a detector that ranks exactly like box area cannot be above box area
    cands = {i: boxes + 3 * i for i in range(8)}
    gts = {i: boxes[1:2] + 3 * i for i in range(8)}

    def nms(b: np.ndarray, sc: np.ndarray) -> np.ndarray:
        return greedy_nms(b, sc, 0.5, 10)

    area = {i: (cands[i], no_pixel_scores(cands[i])["size_prior"]) for i in cands}
    rnd = np.random.default_rng(0)
    dets = {
        "detector": area,
        "random": {i: (cands[i], rnd.random(3)) for i in cands},
        "size_prior": area,
        "cover_count": {i: (cands[i], no_pixel_scores(cands[i])["cover_count"]) for i in cands},
    }
    out = table_d_chance(cands, gts, dets, nms, ChanceSettings(50, 50, 0.95, 0))
    assert out["detector"]["best_no_pixel"] == "size_prior"
    assert out["detector"]["vs_no_pixel_ci_low"] == out["detector"]["vs_no_pixel_ci_high"] == 0
    assert out["detector"]["verdict"] in ("baseline", "chance", "few")
    assert out["detector"]["verdict"] != "above"


def test_large_frames_align_on_a_pyramid_level_and_decode_gray(tmp_path) -> None:
    """``align_side``: a 640 x 480 pair aligns at 320 x 240 and the warp is scaled back to the
    work pixels; a JPEG's reduced gray decode is what ``read_gray`` returns, turned upright."""
    from harness.localizers.local import read_gray

    rng = np.random.default_rng(4)
    m = cv2.resize(rng.integers(0, 256, (48, 64)).astype(np.uint8), (640, 480), cv2.INTER_CUBIC)
    Hq = np.array([[1.0, 0.0, 12.0], [0.0, 1.0, 8.0], [0.0, 0.0, 1.0]])
    q = cv2.warpPerspective(m, Hq, (640, 480))
    lc = LocalConfig(align=("homography",), keypoints="sift", align_side=320)
    al = align_pair(q, m, lc)
    assert al.method == "homography" and al.H is not None
    pts = np.array([[[100.0, 100.0]], [[500.0, 300.0]]])
    err = np.abs(
        cv2.perspectiveTransform(pts, al.H) - cv2.perspectiveTransform(pts, np.linalg.inv(Hq))
    )
    assert err.max() < 2.0, err
    path = tmp_path / "f.jpg"
    cv2.imwrite(str(path), cv2.cvtColor(m, cv2.COLOR_GRAY2BGR))
    want = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_2)
    assert np.array_equal(read_gray(str(path), 2), want)
    assert np.array_equal(read_gray(f"{path}#rot=cw", 2), cv2.rotate(want, cv2.ROTATE_90_CLOCKWISE))
    assert read_gray(str(tmp_path / "f.png"), 2) is None


def test_the_page_says_which_pairs_could_not_be_aligned() -> None:
    """method §13.3: a pair no link of the chain accepts is named on the page, never scored."""
    import pandas as pd

    from harness.reports.detect_page import alignment_html

    al = pd.DataFrame(
        {
            "q_session": ["q", "q", "q"],
            "q_camera": ["Cam5"] * 3,
            "q_utime": [1, 2, 3],
            "align": ["homography", "none", "identity"],
            "inliers": [40, 0, 0],
        }
    )
    html = alignment_html(al)
    assert "homography 1, identity 1" in html
    assert "could not align 1 of 3 pairs" in html and "q Cam5 2" in html
    assert "could not align" not in alignment_html(al[al["align"] != "none"])
    assert alignment_html(None) == ""


def test_the_gradient_image_is_the_same_bits_wherever_its_buffers_lie() -> None:
    """The gradient magnitude is IEEE's (products, sum, square root in float32), not
    ``cv2.magnitude``'s: OpenCV's result depends on where its output buffer starts (measured:
    4 different results for 16 placements of the same inputs), so the same frames gave other
    ranks from run to run."""
    gray = _texture(3)
    b = cv2.GaussianBlur(gray.astype(np.float32), (3, 3), 0)
    gx, gy = cv2.Sobel(b, cv2.CV_32F, 1, 0), cv2.Sobel(b, cv2.CV_32F, 0, 1)
    want = np.sqrt(gx * gx + gy * gy)
    for offset in range(0, 64, 4):  # the input placed at every 4-byte offset of a cache line
        buf = np.zeros(gray.size + 128, np.uint8)
        start = (-buf.ctypes.data) % 64 + offset
        placed = buf[start : start + gray.size].reshape(gray.shape)
        placed[...] = gray
        got = feature_image(placed, "gradient")
        assert got.dtype == np.float32 and got.tobytes() == want.tobytes(), offset
