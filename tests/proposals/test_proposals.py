"""Proposals.

grid5 by hand, the unsupervised proposers, YOLO plumbing with a local random model, user tables.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from harness.boxes import nms
from harness.errors import AnnotationError, ConfigError
from harness.proposals.builtin import edge_boxes, grid5
from harness.proposals.config import EdgesConfig, ProposalsConfig, YoloConfig
from harness.proposals.file import load_file_proposals
from harness.proposals.proposers import compute_proposals
from harness.proposals.yolo import YoloProposer


def test_grid5_by_hand() -> None:
    g = grid5(90, 60)
    assert g.shape == (5, 4)
    assert g.tolist() == [
        [30, 20, 60, 40],
        [0, 0, 60, 40],
        [30, 0, 90, 40],
        [0, 20, 60, 60],
        [30, 20, 90, 60],
    ]


def test_nms_keeps_the_best_of_overlapping_boxes() -> None:
    b = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30]], float)
    keep = nms(b, np.array([0.5, 0.9, 0.1]), 0.5)
    assert keep.tolist() == [1, 2]


def test_edge_boxes_find_a_textured_object_and_are_deterministic() -> None:
    img = np.full((120, 160, 3), 120, np.uint8)
    yy, xx = np.mgrid[0:40, 0:30]
    img[40:80, 60:90] = np.where(((xx // 5 + yy // 5) % 2)[..., None] == 1, 230, 20).astype(
        np.uint8
    )
    b1, s1 = edge_boxes(img, EdgesConfig())
    b2, s2 = edge_boxes(img, EdgesConfig())
    assert np.array_equal(b1, b2) and np.array_equal(s1, s2)
    iou = [
        (min(b[2], 90) - max(b[0], 60))
        * (min(b[3], 80) - max(b[1], 40))
        / (
            (b[2] - b[0]) * (b[3] - b[1])
            + 1200
            - (min(b[2], 90) - max(b[0], 60)) * (min(b[3], 80) - max(b[1], 40))
        )
        for b in b1
        if b[2] > 60 and b[0] < 90 and b[3] > 40 and b[1] < 80
    ]
    assert max(iou) > 0.8


class TinyYolo(torch.nn.Module):
    """A YOLOv8-layout head with random weights: (B, 4 + nc, N) in input pixels."""

    def __init__(self, nc: int = 3, n: int = 16) -> None:
        super().__init__()
        self.n, self.nc = n, nc
        self.conv = torch.nn.Conv2d(3, 4 + nc, 3, stride=8, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(x)  # (B, 4 + nc, S/8, S/8)
        y = torch.nn.functional.adaptive_avg_pool2d(y, (4, 4)).flatten(2)  # (B, 4 + nc, 16)
        s = x.shape[-1]
        xy = torch.sigmoid(y[:, :2]) * s
        wh = torch.sigmoid(y[:, 2:4]) * s / 2 + 4
        return torch.cat([xy, wh, torch.sigmoid(y[:, 4:])], 1)


@pytest.fixture()
def tiny_weights(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    path = tmp_path / "tiny.torchscript"
    torch.jit.script(TinyYolo()).save(str(path))
    return path


def test_yolo_plumbing_with_a_local_random_model(tiny_weights: Path) -> None:
    prop = YoloProposer(YoloConfig(weights=str(tiny_weights), imgsz=64, batch=2, conf=0.05))
    imgs = [
        np.random.default_rng(i).integers(0, 256, (60, 40, 3), dtype=np.uint8) for i in range(3)
    ]
    out = prop(imgs)
    assert len(out) == 3
    for boxes, scores, classes in out:
        assert len(boxes) > 0 and boxes.shape[1] == 4
        assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= 40).all() and (boxes[:, 3] <= 60).all()
        assert (scores >= 0.05).all() and classes.dtype == np.int64
    again = prop(imgs)
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(out, again, strict=True))


def test_yolo_without_weights_says_how_to_get_them(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nothing is downloaded at run time"):
        YoloProposer(YoloConfig(weights=str(tmp_path / "missing.torchscript")))
    with pytest.raises(ConfigError, match="weights is not set"):
        YoloProposer(YoloConfig())


def test_file_proposals_validated(tmp_path: Path) -> None:
    frames = pd.DataFrame(
        {
            "session": ["A"],
            "camera": ["c"],
            "utime": [1],
            "width": [50],
            "height": [40],
            "image": [""],
        }
    )
    p = tmp_path / "p.csv"
    pd.DataFrame(
        {
            "session": ["A", "A"],
            "camera": ["c", "c"],
            "utime": [1, 1],
            "x1": [0, 5],
            "y1": [0, 5],
            "x2": [10, 60],
            "y2": [10, 20],
        }
    ).to_csv(p, index=False)
    with pytest.raises(AnnotationError, match=r"row 2: box outside the image"):
        load_file_proposals(p, frames)
    pd.DataFrame(
        {
            "session": ["A"],
            "camera": ["c"],
            "utime": [1],
            "x1": [0],
            "y1": [0],
            "x2": [10],
            "y2": [10],
        }
    ).to_csv(p, index=False)
    df = compute_proposals(frames, ProposalsConfig(methods=("grid5", "file"), file=str(p)))
    assert df.groupby("proposal_method").size().to_dict() == {"file": 1, "grid5": 5}


def test_reduced_decode_picks_the_smallest_scale_that_holds_the_work_width() -> None:
    from harness.proposals.proposers import decode_scale

    cfg = ProposalsConfig()  # edges 480 px, mser 320 px wide copies
    assert decode_scale(1232, cfg, ["edges"], False) == 2  # NCLT upright: 616 >= 480 > 308
    assert decode_scale(2600, cfg, ["edges"], False) == 4
    assert decode_scale(2600, cfg, ["mser"], False) == 8  # 325 >= 320
    assert decode_scale(2600, cfg, ["edges", "mser"], False) == 4  # the widest copy decides
    assert decode_scale(120, cfg, ["edges"], False) == 1  # the fixture: whole frames
    assert decode_scale(2600, cfg, ["edges"], True) == 1  # YOLO sizes its own input
    assert decode_scale(2600, cfg, ["edges", "segments"], False) == 1
    assert decode_scale(2600, cfg, ["edges", "a_users_method"], False) == 1
    off = ProposalsConfig(reduced_decode=False)
    assert decode_scale(2600, off, ["edges"], False) == 1


def test_edges_on_a_reduced_decode_find_the_boxes_of_the_full_frame(tmp_path: Path) -> None:
    """NCLT-sized JPEGs: decoded at 1/2, the edge proposals are those of the full frame (in the
    frame's own pixels): at least 90% of them within IoU 0.9 of one, the same count within 10%."""
    import cv2

    from harness.boxes import iou_matrix
    from harness.proposals.proposers import _image_proposals

    rng = np.random.default_rng(0)
    rows = []
    for n in range(3):
        img = np.empty((1616, 1232, 3), np.uint8)
        img[:700], img[700:] = (200, 170, 120), (100, 105, 110)
        img = np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)
        for _ in range(8):
            x, y, (w, h) = rng.integers(0, 1000), rng.integers(200, 1400), rng.integers(60, 300, 2)
            img[y : y + h, x : x + w] = rng.integers(0, 255, 3)
        cv2.imwrite(str(tmp_path / f"{n}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        rows.append(
            {"session": "s", "camera": "c", "utime": n, "image": str(tmp_path / f"{n}.jpg"),
             "width": 1232, "height": 1616}
        )  # fmt: skip
    frames = pd.DataFrame(rows)
    got = {
        rd: pd.concat(
            _image_proposals(frames, ProposalsConfig(reduced_decode=rd), ["edges"], lambda x: x)
        )
        for rd in (False, True)
    }
    full, reduced = got[False], got[True]
    assert abs(len(reduced) - len(full)) <= 0.1 * len(full) and len(full) >= 20
    best = np.concatenate(
        [
            iou_matrix(
                full[full["utime"] == u][["x1", "y1", "x2", "y2"]].to_numpy(),
                reduced[reduced["utime"] == u][["x1", "y1", "x2", "y2"]].to_numpy(),
            ).max(axis=1)
            for u in range(3)
        ]
    )
    assert (best >= 0.9).mean() >= 0.9, np.sort(best)
    assert (reduced[["x2", "y2"]].to_numpy() <= [1232, 1616]).all()


def test_proposals_are_the_same_rows_and_key_with_threads(tmp_path: Path) -> None:
    """``[proposals] threads`` runs edges and mser on several frames at once (19 frames: more than
    one round of the pool, and a short one): the same rows as one frame at a time, in the same
    cache entry. With selective listed, six frames or more go side by side too, Selective Search in
    a worker process per thread (each frame seeded before it): the same rows as in this process;
    fewer go one at a time (the workers would cost more to start than they save)."""
    import dataclasses

    import cv2

    from harness.proposals import keys
    from harness.proposals.proposers import compute_proposals

    rng = np.random.default_rng(4)
    rows = []
    for n in range(19):
        img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), (0, 0), 3)
        for _ in range(4):
            x, y = rng.integers(0, 250), rng.integers(0, 180)
            img[y : y + 50, x : x + 60] = rng.integers(0, 255, 3)
        cv2.imwrite(str(tmp_path / f"{n}.jpg"), img)
        rows.append(("s", "c", n, str(tmp_path / f"{n}.jpg"), 320, 240))
    frames = pd.DataFrame(rows, columns=["session", "camera", "utime", "image", "width", "height"])
    base = ProposalsConfig(methods=("grid5", "edges", "mser"))
    one = compute_proposals(frames, dataclasses.replace(base, threads=1))
    assert set(one["proposal_method"]) == {"grid5", "edges", "mser"} and len(one) > 19 * 5
    for threads in (3, 0):
        many = dataclasses.replace(base, threads=threads)
        pd.testing.assert_frame_equal(compute_proposals(frames, many), one)
        assert keys.proposals(many, "k", []) == keys.proposals(base, "k", [])
    ss = ProposalsConfig(methods=("edges", "selective"), threads=3)
    for n in (3, 6):  # one at a time; in three worker processes
        alone = compute_proposals(frames.iloc[:n], dataclasses.replace(ss, threads=1))
        assert (alone["proposal_method"] == "selective").sum() > 5 * n
        pd.testing.assert_frame_equal(compute_proposals(frames.iloc[:n], ss), alone)
