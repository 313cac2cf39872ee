"""``python -m bench.opencv_calls [--out FILE]``: every cv2 call the harness makes, measured.

Each call runs on fixed inputs (a rendered fixture-like frame at 240 x 320 and an NCLT-sized
1,232 x 1,616 one), and its output is digested. Run it under two OpenCV releases and compare the
two JSON files with ``--compare A B``: which calls give other bytes, and the median time of each
(the choice between OpenCV 4 and 5 is made on this, not on what pip happens to pick).
The list of calls is checked against the harness's source by ``tests/test_lock.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A textured RGB frame: smooth gradients, rectangles, circles and noise (seeded)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([x / w * 200, y / h * 200, (x + y) / (w + h) * 255], -1)
    for _ in range(12):
        x0, y0 = int(rng.integers(0, w - 20)), int(rng.integers(0, h - 20))
        cv2.rectangle(img, (x0, y0), (x0 + int(rng.integers(8, w // 4)), y0 + 30),
                      tuple(float(v) for v in rng.integers(0, 255, 3)), -1)  # fmt: skip
        cv2.circle(img, (x0, y0), int(rng.integers(4, 30)), (255.0, 255.0, 255.0), 2)
    img += rng.normal(0, 6, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def _digest(v: Any) -> str:
    h = hashlib.sha256()
    for a in v if isinstance(v, tuple | list) else (v,):
        if isinstance(a, np.ndarray):
            h.update(str((a.dtype, a.shape)).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        else:
            h.update(repr(a).encode())
    return h.hexdigest()[:16]


def _sift(gray: np.ndarray) -> tuple:
    kp, desc = cv2.SIFT_create(nfeatures=500).detectAndCompute(gray, None)
    return np.array([k.pt + (k.size, k.angle) for k in kp], np.float64), desc


def _dense_sift(gray: np.ndarray) -> tuple:
    """BoVW's dense SIFT: a grid of cv2.KeyPoint every 8 px, diameter 16, described in place."""
    crop = cv2.resize(gray, (64, 64), interpolation=cv2.INTER_AREA)
    grid = [
        cv2.KeyPoint(float(x), float(y), 16.0) for y in range(8, 57, 8) for x in range(8, 57, 8)
    ]
    kp, desc = cv2.SIFT_create().compute(crop, grid)
    return np.array([k.pt for k in kp], np.float64), desc


def _orb(gray: np.ndarray) -> tuple:
    kp, desc = cv2.ORB_create(nfeatures=500).detectAndCompute(gray, None)
    return np.array([k.pt + (k.size, k.angle) for k in kp], np.float64), desc


def _keypoints(gray: np.ndarray) -> tuple:
    """Keypoint localization's calls: SIFT and AKAZE keypoints, ratio-test matches, a MAGSAC
    fundamental matrix; the aligned difference's erosion and dilation; Selective Search on one
    thread (its ranking's generator seeded as the harness seeds it)."""
    import ctypes

    moved = np.roll(gray, (3, 5), axis=(0, 1))
    sift = cv2.SIFT_create(nfeatures=1500)
    kq, dq = sift.detectAndCompute(moved, None)
    km, dm = sift.detectAndCompute(gray, None)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dq, dm, k=2)
    good = [a for a, *b in knn if b and a.distance < 0.8 * b[0].distance]
    p1 = np.array([kq[g.queryIdx].pt for g in good], np.float32)
    p2 = np.array([km[g.trainIdx].pt for g in good], np.float32)
    F, mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, 1.5, 0.999, 2000)
    ak = cv2.AKAZE_create().detectAndCompute(gray, None)[1]
    k = np.ones((7, 7), np.uint8)
    f32 = gray.astype(np.float32)
    env = cv2.erode(f32, k, borderType=cv2.BORDER_REPLICATE), cv2.dilate(f32, k)
    ss = cv2.ximgproc.segmentation.createSelectiveSearchSegmentation()
    small = cv2.resize(gray, (256, round(256 * gray.shape[0] / gray.shape[1])))
    ss.setBaseImage(cv2.cvtColor(small, cv2.COLOR_GRAY2BGR))
    ss.switchToSelectiveSearchFast()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    ctypes.CDLL(None).srand(0)
    rects = ss.process()
    cv2.setNumThreads(threads)
    return F, mask, ak, env, rects


def _local(gray: np.ndarray) -> tuple:
    """The local localizer's calls (method §13.3): ORB matches, a RANSAC homography, the warp, an
    ECC fit, the Sobel gradients, a pyramid level, template matching and its best score."""
    h, w = gray.shape
    moved = np.roll(gray, (3, 5), axis=(0, 1))
    orb = cv2.ORB_create(nfeatures=500)
    kq, dq = orb.detectAndCompute(moved, None)
    km, dm = orb.detectAndCompute(gray, None)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(dq, dm, k=2)
    good = [a for a, *b in knn if b and a.distance < 0.75 * b[0].distance]
    src = np.array([kq[g.queryIdx].pt for g in good], np.float32).reshape(-1, 1, 2)
    dst = np.array([km[g.trainIdx].pt for g in good], np.float32).reshape(-1, 1, 2)
    H, _ = cv2.findHomography(src, dst, cv2.RANSAC, 3.0, maxIters=2000, confidence=0.995)
    corners = np.array([[[0.0, 0.0]], [[w, 0.0]], [[w, h]], [[0.0, h]]])
    moved_corners = cv2.perspectiveTransform(corners, H)
    f32 = gray.astype(np.float32)
    gx, gy = cv2.Sobel(f32, cv2.CV_32F, 1, 0), cv2.Sobel(f32, cv2.CV_32F, 0, 1)
    g = np.sqrt(gx * gx + gy * gy)  # the harness's magnitude (not cv2.magnitude: see align.py)
    warped = cv2.warpPerspective(g, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    small = cv2.pyrDown(cv2.pyrDown(f32))
    try:
        cc, warp = cv2.findTransformECC(
            small, np.roll(small, 1, axis=1), np.eye(2, 3, dtype=np.float32),
            cv2.MOTION_AFFINE, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
            None, 5,
        )  # fmt: skip
    except cv2.error:
        cc, warp = float("nan"), None
    ncc = cv2.matchTemplate(g[40:200, 40:200], g[60:120, 60:120], cv2.TM_CCOEFF_NORMED)
    return H, moved_corners, warped, cc, warp, ncc, cv2.minMaxLoc(ncc)


def _mser(gray: np.ndarray) -> tuple:
    regions, boxes = cv2.MSER_create().detectRegions(gray)
    return np.asarray(boxes), len(regions)


def _onnx_net() -> Path:
    """A small convolutional network written to ONNX by torch (once per process)."""
    import tempfile

    import torch

    path = Path(tempfile.mkdtemp()) / "net.onnx"
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Conv2d(3, 8, 3, padding=1), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(4)
    ).eval()
    torch.onnx.export(net, (torch.zeros(1, 3, 64, 64),), str(path), dynamo=False)
    return path


def _dnn(rgb: np.ndarray, net: Path) -> Any:
    """readNetFromONNX and a forward pass; NMSBoxes and NMSBoxesBatched on seeded boxes."""
    n = cv2.dnn.readNetFromONNX(str(net))
    x = cv2.resize(rgb, (64, 64), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    n.setInput(np.ascontiguousarray(x.transpose(2, 0, 1)[None]))
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 200, (300, 2))
    boxes = [[float(a), float(b), float(c), float(d)] for (a, b), (c, d)
             in zip(xy, rng.uniform(5, 60, (300, 2)), strict=True)]  # fmt: skip
    scores = [float(v) for v in rng.uniform(0, 1, 300)]
    classes = [int(v) for v in rng.integers(0, 3, 300)]
    keep = cv2.dnn.NMSBoxes(boxes, scores, 0.1, 0.5)
    keep_b = cv2.dnn.NMSBoxesBatched(boxes, scores, classes, 0.1, 0.5)
    return n.forward(), np.asarray(keep).ravel(), np.asarray(keep_b).ravel()


def _png_jpeg(bgr: np.ndarray) -> tuple:
    ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
    ok2, png = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    dec = cv2.imdecode(jpg, cv2.IMREAD_COLOR)
    half = cv2.imdecode(jpg, cv2.IMREAD_REDUCED_COLOR_2)
    quarter = cv2.imdecode(jpg, cv2.IMREAD_REDUCED_COLOR_4)
    eighth = cv2.imdecode(jpg, cv2.IMREAD_REDUCED_COLOR_8)
    ok3, tif = cv2.imencode(".tiff", bgr, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    back = cv2.imdecode(png, cv2.IMREAD_UNCHANGED), cv2.imdecode(tif, cv2.IMREAD_UNCHANGED)
    return jpg, png, dec, half, quarter, eighth, *back, ok, ok2, ok3


def _bayer(rgb: np.ndarray) -> tuple:
    raw = np.ascontiguousarray(rgb[:, :, 1])
    return tuple(
        cv2.cvtColor(raw, c)
        for c in (
            cv2.COLOR_BayerRG2BGR,
            cv2.COLOR_BayerGR2BGR,
            cv2.COLOR_BayerGB2BGR,
            cv2.COLOR_BayerBG2BGR,
        )
    )


def _contours(gray: np.ndarray) -> tuple:
    edges = cv2.Canny(gray, 50, 150)
    closed = cv2.morphologyEx(edges, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    dil = cv2.dilate(closed, np.ones((3, 3), np.uint8))
    cs, _ = cv2.findContours(dil, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    rects = np.array([cv2.boundingRect(c) for c in cs])
    n, lab, stats, cent = cv2.connectedComponentsWithStats(dil)
    return edges, closed, rects, n, lab, stats, cent


def _draw(rgb: np.ndarray) -> np.ndarray:
    img = rgb.copy()
    cv2.rectangle(img, (5, 5), (60, 40), (255, 0, 0), 2)
    cv2.ellipse(img, (80, 80), (30, 15), 20, 0, 360, (0, 255, 0), 1, cv2.LINE_AA)
    (_tw, _th), _base = cv2.getTextSize("change 0.93", cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    cv2.putText(img, "change 0.93", (10, 100), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)  # fmt: skip
    return img


def calls(rgb: np.ndarray, net: Path) -> dict[str, Callable[[], Any]]:
    """Every cv2 call (or group of calls on one result) the harness makes, on ``rgb``."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    f32 = gray.astype(np.float32)
    h, w = gray.shape
    return {
        "cvtColor(RGB2GRAY, RGB2BGR, RGB2HSV, RGB2Lab, BGR2HSV, GRAY2RGB, BGR2RGB)": lambda: (
            cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY),
            cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
            cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV),
            cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab),
            cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV),
            cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB),
            cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
        ),
        "cvtColor(RGBA2BGRA, BGRA2RGB)": lambda: (
            cv2.cvtColor(np.dstack([rgb, gray]), cv2.COLOR_RGBA2BGRA),
            cv2.cvtColor(np.dstack([bgr, gray]), cv2.COLOR_BGRA2RGB),
        ),
        "cvtColor(Bayer*2BGR)": lambda: _bayer(rgb),
        "resize(INTER_AREA)": lambda: cv2.resize(
            rgb, (w // 3, h // 3), interpolation=cv2.INTER_AREA
        ),
        "resize(INTER_AREA, float32 256x256)": lambda: cv2.resize(
            f32, (256, 256), interpolation=cv2.INTER_AREA
        ),
        "resize(INTER_LINEAR)": lambda: cv2.resize(
            rgb, (w * 2 // 3, h * 2 // 3), interpolation=cv2.INTER_LINEAR
        ),
        "resize(INTER_NEAREST)": lambda: cv2.resize(
            rgb, (w // 2, h // 2), interpolation=cv2.INTER_NEAREST
        ),
        "rotate(90 cw, 90 ccw, 180)": lambda: (
            cv2.rotate(rgb, cv2.ROTATE_90_CLOCKWISE),
            cv2.rotate(rgb, cv2.ROTATE_90_COUNTERCLOCKWISE),
            cv2.rotate(rgb, cv2.ROTATE_180),
        ),
        "GaussianBlur": lambda: (
            cv2.GaussianBlur(rgb, (5, 5), 0),
            cv2.GaussianBlur(f32, (0, 0), 2.0),
        ),
        "getRotationMatrix2D, warpAffine (INTER_LINEAR, BORDER_REFLECT: the null's copies)": (
            lambda: cv2.warpAffine(
                rgb,
                cv2.getRotationMatrix2D((w / 2.0, h / 2.0), 1.5, 0.98),
                (w, h),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REFLECT,
            )
        ),
        "remap (INTER_LINEAR, BORDER_REFLECT: the null copies' smooth displacement)": (
            lambda: cv2.remap(
                rgb,
                *np.meshgrid(
                    np.arange(w, dtype=np.float32) + 0.37, np.arange(h, dtype=np.float32) - 0.21
                ),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REFLECT,
            )
        ),
        "Sobel(CV_32F)": lambda: (
            cv2.Sobel(f32, cv2.CV_32F, 1, 0, ksize=3),
            cv2.Sobel(f32, cv2.CV_32F, 0, 1, ksize=3),
        ),
        "integral": lambda: cv2.integral(gray),
        "copyMakeBorder(REPLICATE), subtract, multiply, add, min (float32 planes)": lambda: cv2.min(
            cv2.add(
                cv2.multiply(
                    d := cv2.subtract(
                        f32, cv2.copyMakeBorder(f32, 2, 2, 2, 2, cv2.BORDER_REPLICATE)[:-4, 4:]
                    ),
                    d,
                ),
                f32,
            ),
            f32,
        ),
        "meanStdDev": lambda: cv2.meanStdDev(rgb),
        # the per-crop normalisation's lookup: a float32 table per channel
        "LUT (float32 table, 3 channels)": lambda: cv2.LUT(
            rgb, np.linspace(0, 1, 768, dtype=np.float32).reshape(1, 256, 3)
        ),
        "calcHist": lambda: cv2.calcHist(
            [cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)], [0, 1], None, [8, 8], [0, 180, 0, 256]
        ),
        "applyColorMap(INFERNO)": lambda: cv2.applyColorMap(gray, cv2.COLORMAP_INFERNO),
        "Canny, morphologyEx, dilate, findContours, boundingRect, connectedComponentsWithStats": (
            lambda: _contours(gray)
        ),
        "SIFT_create().detectAndCompute": lambda: _sift(gray),
        "KeyPoint grid, SIFT_create().compute (dense SIFT)": lambda: _dense_sift(gray),
        "ORB_create().detectAndCompute": lambda: _orb(gray),
        "MSER_create().detectRegions": lambda: _mser(gray),
        "local: ORB + BFMatcher, findHomography, perspectiveTransform, warpPerspective, "
        "findTransformECC, pyrDown, matchTemplate, minMaxLoc": lambda: _local(gray),
        "keypoints: SIFT + BFMatcher, findFundamentalMat (USAC_MAGSAC), AKAZE, erode/dilate, "
        "ximgproc Selective Search": lambda: _keypoints(gray),
        "imencode/imdecode (JPEG q90, PNG, TIFF, IMREAD_REDUCED_COLOR_2/4/8)": lambda: _png_jpeg(
            bgr
        ),
        "rectangle, ellipse, getTextSize, putText (LINE_AA)": lambda: _draw(rgb),
        "dnn.readNetFromONNX + forward, dnn.NMSBoxes, dnn.NMSBoxesBatched": lambda: _dnn(rgb, net),
    }


#: The frame sizes measured: the fixture's scale and an NCLT frame.
SIZES = ((240, 320), (1232, 1616))


def measure(reps: int = 5, sizes: tuple[tuple[int, int], ...] = SIZES) -> dict[str, Any]:
    """Digest and median seconds of every call on each frame size."""
    out: dict[str, Any] = {"opencv": cv2.__version__, "calls": {}}
    net = _onnx_net()
    for size in sizes:
        rgb = _image(*size)
        for name, fn in calls(rgb, net).items():
            times, dig = [], ""
            for _ in range(reps):
                t0 = time.perf_counter()
                dig = _digest(fn())
                times.append(time.perf_counter() - t0)
            out["calls"][f"{size[0]}x{size[1]} {name}"] = {
                "digest": dig,
                "median_ms": round(statistics.median(times) * 1e3, 3),
            }
    return out


def compare(a: dict[str, Any], b: dict[str, Any]) -> str:
    """A markdown table: each call's bytes equal or not, and both medians with their ratio."""
    lines = [
        f"| call | same bytes | {a['opencv']} ms | {b['opencv']} ms | ratio |",
        "|---|---|---:|---:|---:|",
    ]
    for k, x in a["calls"].items():
        y = b["calls"][k]
        ratio = y["median_ms"] / x["median_ms"] if x["median_ms"] else float("nan")
        same = "yes" if x["digest"] == y["digest"] else "**no**"
        lines.append(
            f"| {k} | {same} | {x['median_ms']:.2f} | {y['median_ms']:.2f} | {ratio:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write the measurement here (JSON)")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    ap.add_argument("--quick", action="store_true", help="the small frame only, once (a smoke run)")
    args = ap.parse_args(argv)
    if args.compare:
        a, b = (json.loads(p.read_text()) for p in args.compare)
        print(compare(a, b))
        return 0
    res = json.dumps(measure(1, SIZES[:1]) if args.quick else measure(), indent=1)
    if args.out:
        args.out.write_text(res + "\n")
    else:
        print(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
