"""Bench case ``crops``."""

from __future__ import annotations

import numpy as np

from .common import DATA, emit, timed


def case_crops(quick: bool) -> None:
    """Crop + resize to 256x256 of 16 boxes from 1,232 x 1,616 JPEG frames (decode included)."""
    import cv2
    import pandas as pd

    from harness.descriptors.crops import iter_crops

    n = 8 if quick else 32
    d = DATA / "crops"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = d / f"{i}.jpg"
        if not p.exists():
            img = cv2.GaussianBlur(rng.integers(0, 256, (1616, 1232, 3), dtype=np.uint8), (0, 0), 3)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        paths.append(str(p))
    rows = []
    for p in paths:
        for _k in range(16):
            x1, y1 = rng.uniform(0, 800), rng.uniform(0, 1100)
            rows.append((p, x1, y1, x1 + rng.uniform(100, 430), y1 + rng.uniform(100, 510)))
    df = pd.DataFrame(rows, columns=["image", "x1", "y1", "x2", "y2"])
    for workers in (0, 2):
        runs = timed(
            lambda w=workers: [
                None for _ in iter_crops(df, df["image"], 256, frames_per_batch=4, num_workers=w)
            ],
            repeat=3,
        )
        emit(
            f"crop+resize[workers={workers}]",
            [len(df) / t for t in runs],
            "subimages/s",
            notes=f"{n} JPEG frames 1232x1616, 16 boxes each",
        )
    _grid5_reduced(paths)
    _edges_reduced(8 if quick else 32)
    _overlap(paths)
    _overlap_bovw(paths)


def _grid5_reduced(paths: list[str]) -> None:
    """grid5's five boxes per NCLT-sized JPEG frame at 256: the full frame against the frame
    decoded at the fraction every box allows (1/2 here), next to the limits measured in the same
    run: libjpeg-turbo's decode of the full frame and of its half."""
    import cv2
    import pandas as pd

    from harness.descriptors.crops import iter_crops
    from harness.proposals.builtin import grid5

    boxes = grid5(1232, 1616)
    df = pd.DataFrame(
        [(p, *b) for p in paths for b in boxes], columns=["image", "x1", "y1", "x2", "y2"]
    )
    n = len(paths)
    for reduced in (False, True):
        runs = timed(
            lambda r=reduced: [None for _ in iter_crops(df, df["image"], 256, reduced=r)],
            repeat=3,
        )
        emit(
            f"grid5 crops[decode={'reduced' if reduced else 'full'}]",
            [1000 * t / n for t in runs],
            "ms/frame",
            notes=f"{n} JPEG frames 1232x1616, grid5 (centre 410x538, four of 821x1077) to 256",
        )
    for flag, name in ((cv2.IMREAD_UNCHANGED, "full"), (cv2.IMREAD_REDUCED_COLOR_2, "1/2")):
        runs = timed(lambda f=flag: [cv2.imread(p, f) for p in paths], repeat=3)
        emit(
            f"jpeg decode[{name}] (limit)",
            [1000 * t / n for t in runs],
            "ms/frame",
            notes="cv2.imread alone (libjpeg-turbo): the decode floor of the row above",
        )


def _edges_reduced(n: int) -> None:
    """The ``edges`` proposals of NCLT-sized JPEG scenes (two tones, noise, eight flat boxes): the
    full frame against the frame decoded at 1/2 (``[proposals] reduced_decode``; edges works on a
    480-px copy either way). The decode limits are the ``jpeg decode`` rows of this case."""
    import cv2
    import pandas as pd

    from harness.proposals.config import ProposalsConfig
    from harness.proposals.proposers import _image_proposals

    d = DATA / "edges"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    rows = []
    for i in range(n):
        p = d / f"{i}.jpg"
        if not p.exists():
            img = np.empty((1616, 1232, 3), np.uint8)
            img[:700], img[700:] = (200, 170, 120), (100, 105, 110)
            img = np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)
            for _ in range(8):
                x, y, (w, h) = (
                    rng.integers(0, 1000),
                    rng.integers(200, 1400),
                    rng.integers(60, 300, 2),
                )
                img[y : y + h, x : x + w] = rng.integers(0, 255, 3)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        rows.append({"session": "s", "camera": "c", "utime": i, "image": str(p), "width": 1232,
                     "height": 1616})  # fmt: skip
    frames = pd.DataFrame(rows)
    for reduced in (False, True):
        cfg = ProposalsConfig(reduced_decode=reduced)
        runs = timed(lambda c=cfg: _image_proposals(frames, c, ["edges"], lambda x: x), repeat=3)
        emit(
            f"edges proposals[decode={'1/2' if reduced else 'full'}]",
            [1000 * t / n for t in runs],
            "ms/frame",
            notes=f"{n} JPEG frames 1232x1616 (decode included), [proposals.edges] work_width 480",
        )


def _overlap(paths: list[str]) -> None:
    """The descriptor stage's loop on grid5 of NCLT-sized JPEG frames (reduced decode, the
    paper's encoder at 256): with a reader thread decoding ahead (``[descriptor] prefetch``) and
    without, next to its two limits measured in the same run, decode alone and encode alone.
    Overlapped, the loop should cost about the larger of the two, not their sum."""
    import statistics

    import pandas as pd

    from harness.descriptors import AutoencoderDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder
    from harness.descriptors.config import DescriptorConfig
    from harness.descriptors.crops import iter_crops
    from harness.proposals.builtin import grid5

    boxes = grid5(1232, 1616)
    df = pd.DataFrame(
        [(p, *b) for p in paths for b in boxes], columns=["image", "x1", "y1", "x2", "y2"]
    )
    n = len(paths)
    d = AutoencoderDescriptor(DescriptorConfig(input_size=256, device="cpu"))
    d.model = ConvAutoencoder().eval()
    crops = [c for _, c in iter_crops(df, df["image"], 256, reduced=True)]
    d.encode(crops[0])  # warm

    def loop(depth: int) -> None:
        for _, c in iter_crops(df, df["image"], 256, reduced=True, prefetch=depth):
            d.encode(c)

    rounds: dict[str, list[float]] = {"decode": [], "encode": [], "p0": [], "p2": []}
    for _ in range(3):  # interleaved: this machine's rate drifts within a minute
        rounds["decode"] += timed(
            lambda: [None for _ in iter_crops(df, df["image"], 256, reduced=True)], repeat=1
        )
        rounds["encode"] += timed(lambda: [d.encode(c) for c in crops], repeat=1)
        rounds["p0"] += timed(lambda: loop(0), repeat=1)
        rounds["p2"] += timed(lambda: loop(2), repeat=1)
    med = {k: statistics.median(v) for k, v in rounds.items()}
    limit = max(med["decode"], med["encode"])
    for key, name in (("decode", "decode+crop alone (limit)"), ("encode", "encode alone (limit)")):
        emit(
            f"descriptor loop: {name}",
            [1000 * t / n for t in rounds[key]],
            "ms/frame",
            notes=f"{n} JPEG frames 1232x1616, grid5 at 256, reduced decode",
        )
    for key, depth in (("p0", 0), ("p2", 2)):
        emit(
            f"descriptor loop[prefetch={depth}]",
            [1000 * t / n for t in rounds[key]],
            "ms/frame",
            vs_limit=round(med[key] / limit, 2),
            notes=f"{med[key] / limit:.2f}x max(decode, encode) and "
            f"{med[key] / (med['decode'] + med['encode']):.2f}x their sum, same rounds",
        )


def _overlap_bovw(paths: list[str]) -> None:
    """The same for BoVW's feature loop (dense RootSIFT at 128, one core): with and without the
    reader thread, in interleaved rounds."""
    import statistics

    import pandas as pd

    from harness.proposals.builtin import grid5
    from harness.retrieval.bovw import iter_features
    from harness.retrieval.config import BovwConfig

    rows = pd.DataFrame(
        [
            ("s", "c", i, "grid5", k, *b)
            for i in range(len(paths))
            for k, b in enumerate(grid5(1232, 1616))
        ],
        columns=["session", "camera", "utime", "proposal_method", "box_id", "x1", "y1", "x2", "y2"],
    )
    frames = pd.DataFrame(
        [("s", "c", i, p) for i, p in enumerate(paths)],
        columns=["session", "camera", "utime", "image"],
    )
    runs: dict[int, list[float]] = {0: [], 2: []}
    for _ in range(3):
        for depth in runs:
            bc = BovwConfig(prefetch=depth)
            runs[depth] += timed(
                lambda bc=bc: [None for _ in iter_features(bc, rows, frames, "bench")], repeat=1
            )
    base = statistics.median(runs[0])
    for depth, r in runs.items():
        emit(
            f"bovw feature loop[prefetch={depth}]",
            [1000 * t / len(paths) for t in r],
            "ms/frame",
            notes=f"{len(paths)} JPEG frames 1232x1616, grid5, dense RootSIFT at 128; "
            f"{base / statistics.median(r):.2f}x the loop without the thread, same rounds",
        )
