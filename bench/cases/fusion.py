"""Bench case ``fusion``."""

from __future__ import annotations

import numpy as np

from .common import ROOT, emit, timed


def case_fusion(quick: bool) -> None:
    """Fusion, then labels + AP, then pixel + image AP, per query image (5 grid boxes + 12 random
    boxes per image, every method of method §7), all measured in the same run."""
    import dataclasses

    import pandas as pd

    from harness.config.assemble import load_config
    from harness.evaluate.aps import sample_groups
    from harness.evaluate.config import SplitsConfig
    from harness.evaluate.metrics import average_precision
    from harness.evaluate.pixel_aps import pixel_image_rows
    from harness.evaluate.splits import label, paper_splits
    from harness.fusion.config import FusionConfig
    from harness.fusion.samples import fuse_samples
    from harness.fusion.stage import labels_of
    from harness.proposals.builtin import grid5

    rng = np.random.default_rng(0)
    n_img = 50 if quick else 200
    rows, ann = [], []
    for i in range(n_img):
        boxes = [*grid5(1232, 1616).tolist()]
        for _ in range(12):
            x1, y1 = rng.uniform(0, 900), rng.uniform(0, 1200)
            boxes.append([x1, y1, x1 + rng.uniform(50, 330), y1 + rng.uniform(50, 410)])
        for k, b in enumerate(boxes):
            rank = int(rng.integers(1, 101))
            rows.append(
                (
                    "A",
                    "c",
                    i,
                    "B",
                    "c",
                    i,
                    "WI->SU",
                    "grid5" if k < 5 else "yolo",
                    k,
                    *b,
                    rank,
                    100,
                    rank / 100,
                    rng.uniform(0, 2),
                    True,
                )
            )
        ann.append(
            ("A", "c", i, "change", 400.0, 500.0, 700.0, 900.0, "")
            if i % 2
            else ("A", "c", i, "no-change", np.nan, np.nan, np.nan, np.nan, "")
        )
    ranks = pd.DataFrame(
        rows,
        columns=[
            "q_session",
            "q_camera",
            "q_utime",
            "r_session",
            "r_camera",
            "r_utime",
            "season_pair",
            "proposal_method",
            "box_id",
            "x1",
            "y1",
            "x2",
            "y2",
            "rank",
            "L",
            "r",
            "d",
            "exact",
        ],
    )
    frames = pd.DataFrame(
        {"session": "A", "camera": "c", "utime": np.arange(n_img), "width": 1232, "height": 1616}
    )
    annotations = pd.DataFrame(
        ann, columns=["session", "camera", "utime", "status", "x1", "y1", "x2", "y2", "label"]
    )
    fc = FusionConfig(seed=0, max_fused_boxes=4096)
    samples, _ = fuse_samples(ranks, frames, labels_of(annotations), fc)
    allp = samples[samples["proposal_method"] == "all"].reset_index(drop=True)
    methods = tuple(c[4:] for c in samples.columns if c.startswith("loc_"))
    cfg = load_config(ROOT / "datasets" / "fixture.toml")
    cfg = dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, bootstrap=0))
    ids = {g: i for i, g in enumerate(sorted(set(sample_groups(allp))))}

    def fusion() -> None:
        fuse_samples(ranks, frames, labels_of(annotations), fc)

    def labels_ap() -> None:
        for sp in paper_splits(SplitsConfig()):
            lab = label(allp["RoC"].to_numpy(), allp["SoB"].to_numpy(), sp)
            for m in methods:
                sel = (lab >= 0) & allp[f"loc_{m}"].notna().to_numpy()
                average_precision(lab[sel] == 1, allp[f"loc_{m}"].to_numpy()[sel])

    def pixel_image_ap() -> None:
        pixel_image_rows(cfg, allp, frames, annotations, methods, ids)

    note = f"17 boxes per image, {len(methods)} methods"
    emit(
        "fusion (all proposal subsets)",
        [n_img / t for t in timed(fusion, repeat=3)],
        "query images/s",
        notes=note,
    )
    la = timed(labels_ap, repeat=3)
    emit(
        "labels + AP (5 splits, Table I)",
        [1000 * t / n_img for t in la],
        "ms per query image",
        notes=note,
    )
    px = timed(pixel_image_ap, repeat=3)
    emit(
        "pixel AP + image AP (exact regions, Table P)",
        [1000 * t / n_img for t in px],
        "ms per query image",
        ratio_to_labels_ap=round(float(np.median(px) / np.median(la)), 2),
        notes=note + ", without bootstrap",
    )
