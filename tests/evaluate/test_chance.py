"""method §9's floor, chance band, ceiling and verdict (:mod:`harness.evaluate.chance`)."""

from __future__ import annotations

import contextlib
import dataclasses
import io

import numpy as np
import pandas as pd
import pytest

from harness.evaluate import chance
from harness.evaluate.metrics import average_precision, stratified_ap, weighted_average_precision

from ..conftest import ROOT


def test_aps_of_rows_is_the_weighted_ap_of_every_row_with_ties_and_weights() -> None:
    rng = np.random.default_rng(0)
    for trial in range(40):
        n = int(rng.integers(1, 60))
        y = rng.random(n) < rng.random()
        s = np.round(rng.random((6, n)) * rng.integers(1, 6))  # many ties
        w = rng.random(n) * 3 if trial % 2 else np.ones(n)
        want = [weighted_average_precision(y, row, w) for row in s]
        np.testing.assert_allclose(chance.aps_of_rows(y, s, w), want, atol=1e-12, rtol=0)


def test_order_aps_is_average_precision_of_the_same_permutations() -> None:
    for n, p in [(1, 1), (5, 1), (5, 5), (37, 4), (200, 3), (100, 50)]:
        got = chance.order_aps(n, p, 50, 7)
        rows = np.random.default_rng(7).permuted(np.broadcast_to(np.arange(n) < p, (50, n)), axis=1)
        want = [average_precision(r, -np.arange(n)) for r in rows]
        np.testing.assert_allclose(got, want, atol=1e-12, rtol=0)


def test_the_issue_s_table_of_random_order_aps() -> None:
    """The bias the issue measured with a plain loop (400 orders each): the floor is not the
    positive rate, and this module finds the same means within their Monte Carlo error."""
    for n, p, issue_mean in [(100, 5, 0.100), (400, 30, 0.099), (1000, 70, 0.084)]:
        y = np.arange(n) < p
        floor, lo, hi = chance.plain_chance(y, 400, 0)
        assert floor == pytest.approx(issue_mean, abs=0.012)
        assert floor > p / n + 0.005 and lo < floor < hi


def test_the_stratified_floor_equals_a_plain_loop_over_random_orders() -> None:
    """One small split: the floor by a plain loop of stratified_ap over 400 random score vectors
    against the vectorised draws (independent streams: within 4 combined standard errors)."""
    rng = np.random.default_rng(3)
    n = 300
    sob = rng.random(n) * 0.5
    y = rng.random(n) < 0.04 + 0.3 * sob  # few positives, more in the larger strata
    edges = np.array([0, 0.02, 0.05, 0.1, 0.2, 0.4, 1.0])
    loop = np.array([stratified_ap(y, rng.random(n), sob, edges)[0] for _ in range(400)])
    floor, lo, hi = chance.stratified_chance(y, sob, edges, 400, 11)
    assert lo < floor < hi
    se = loop.std() / np.sqrt(400)
    assert abs(floor - loop.mean()) < 4 * np.sqrt(2) * se, (floor, loop.mean(), se)
    assert abs(hi - np.percentile(loop, 95)) < 0.03
    assert floor > stratified_ap(y, rng.random(n), sob, edges)[1] - 0.05  # not the positive rate


def test_verdict_rule() -> None:
    v = chance.verdict
    assert v(0.5, 0.1, 0.2, 0.05, 0.4) == "above"
    assert v(0.5, 0.1, 0.2, -0.01, 0.4) == "chance"  # above the band, but not clear of random
    assert v(0.19, 0.1, 0.2, 0.05, 0.4) == "chance"  # clear of random, but inside the band
    assert v(0.05, 0.1, 0.2, -0.3, -0.01) == "below"
    assert v(0.05, 0.1, 0.2, -0.3, 0.01) == "chance"
    assert v(0.5, 0.1, 0.2, float("nan"), float("nan")) == "untested"
    assert v(float("nan"), 0.1, 0.2, 0.1, 0.2) == "undefined"
    assert v(0.1, 0.1, 0.2, 0.0, 0.0) == "chance"  # the random row against itself


def _samples(seed: int, n_images: int = 40, per: int = 30) -> pd.DataFrame:
    """A split's samples: per query image ``per`` boxes, few positives; ``loc_rank_fusion``
    informative, ``loc_random`` and ``loc_other_random`` uniform noise."""
    rng = np.random.default_rng(seed)
    n = n_images * per
    img = np.repeat(np.arange(n_images), per)
    roc = np.where(rng.random(n) < 0.08, 1.0, 0.0)
    return pd.DataFrame(
        {
            "q_session": "q",
            "q_camera": "c",
            "q_utime": img,
            "r_session": "r",
            "RoC": roc,
            "SoB": rng.random(n) * 0.3,
            "loc_rank_fusion": roc + rng.normal(0, 0.6, n),
            "loc_random": rng.random(n),
            "loc_other_random": rng.random(n),
        }
    )


def _cfg() -> object:
    from harness.config.assemble import load_config

    cfg = load_config(ROOT / "datasets" / "fixture.toml")
    return dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, bootstrap=300))


def test_random_is_never_above_chance_and_other_noise_rarely_is() -> None:
    """Over 60 seeds of a small split (Table I and S): the ``random`` row is never above chance
    (its paired difference from itself is 0 by construction); an independent random score is
    above chance in at most 6 of 60 seeds (the band alone lets 5% through, i.e. 3 expected;
    P(X >= 7 | Binomial(60, 0.05)) < 0.04, and the paired condition only lowers the rate); the
    informative method is above chance in at least 55."""
    from harness.evaluate.aps import pooled_rows, sample_groups
    from harness.evaluate.splits import paper_splits

    cfg = _cfg()
    split = paper_splits()[-1]
    noise_above = informative_above = 0
    for seed in range(60):
        df = _samples(seed)
        ids = {g: i for i, g in enumerate(sorted(set(sample_groups(df))))}
        cfg_s = dataclasses.replace(cfg, seed=seed)
        for table in ("I", "S"):
            rows = {
                r["fusion"]: r
                for r in pooled_rows(
                    cfg_s, df, ("rank_fusion", "other_random", "random"), split, table, ids
                )
            }
            assert rows["random"]["verdict"] == "chance"
            for r in rows.values():  # every verdict is the rule applied to the row's columns
                assert r["verdict"] == chance.verdict(
                    r["ap"], r["chance_low"], r["chance_high"],
                    r["vs_random_diff_ci_low"], r["vs_random_diff_ci_high"],
                )  # fmt: skip
            if table == "S":
                noise_above += rows["other_random"]["verdict"] == "above"
                informative_above += rows["rank_fusion"]["verdict"] == "above"
    assert noise_above <= 6, noise_above
    assert informative_above >= 55, informative_above


def test_match50_is_cocoeval_s_matching() -> None:
    """Table D's fast matcher gives pycocotools' VOC all-point AP50 exactly on random boxes."""
    from harness.boxes import iou_matrix
    from harness.evaluate.box_ap import coco_eval, match50, weighted_voc

    rng = np.random.default_rng(5)
    for _ in range(15):
        gt_imgs, anns, dets, sc, tp = [], [], [], [], []
        n_gt = 0
        for i in range(1, 8):
            gt_imgs.append({"id": i, "width": 100, "height": 100})
            g = rng.uniform(0, 60, (int(rng.integers(0, 4)), 2))
            g = np.hstack([g, g + rng.uniform(10, 40, g.shape)])
            for b in g:
                anns.append({"id": len(anns) + 1, "image_id": i, "category_id": 1,
                             "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]],
                             "area": (b[2] - b[0]) * (b[3] - b[1]), "iscrowd": 0})  # fmt: skip
            n_gt += len(g)
            # detections near the ground truth and elsewhere
            d = np.vstack([g + rng.normal(0, 4, g.shape), rng.uniform(0, 60, (3, 2)).repeat(2, 1)])
            d[:, 2:] = np.maximum(d[:, 2:], d[:, :2] + 5)
            s = rng.random(len(d))
            for b, x in zip(d, s, strict=True):
                dets.append({"image_id": i, "category_id": 1, "score": float(x),
                             "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]]})  # fmt: skip
            order = np.argsort(-s, kind="stable")
            t = np.zeros(len(d), bool)
            t[order] = match50(iou_matrix(d, g), order)
            sc.append(s)
            tp.append(t)
        if not n_gt:
            continue
        gt = {"images": gt_imgs, "annotations": anns, "categories": [{"id": 1, "name": "c"}]}
        with contextlib.redirect_stdout(io.StringIO()):
            voc = coco_eval(gt, dets)[0]
        s_all, t_all = np.concatenate(sc), np.concatenate(tp)
        assert weighted_voc(s_all, t_all, np.ones(len(s_all)), n_gt) == pytest.approx(
            voc, abs=1e-12
        )
