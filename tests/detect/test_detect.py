"""``harness detect`` (method §13): the change detector on a new session, as a user runs it.

The README's two commands run as typed (with ``--data-root`` pointing at the session's fixture):
``datasets/fixture-detect.toml`` (no annotation file) writes every output; ``datasets/fixture.toml``
(annotations named) also writes Table D, whose APs pycocotools gives again from
``detections.json`` and a ground truth built here from the annotation CSV.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from harness.boxes import greedy_nms
from harness.cli import main
from harness.cli.parser import build_parser
from harness.cli.runs import detect_overrides
from harness.config.assemble import load_config, with_overrides
from harness.evaluate import chance
from harness.evaluate.box_ap import _voc_all_point

from ..conftest import TEST_NULL_PAIRS, shared_stages, small_null_config
from ..readme_text import manual_text
from .stage_record import RECORD, first_stage_outside

ROOT = Path(__file__).resolve().parents[2]
MAP, QUERY = "2012-01-22", "2012-03-31"


def _run(argv: list[str]) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return buf.getvalue()


@pytest.fixture(scope="module")
def detected(local_run: tuple, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """(run without annotations, run with them, what the second printed)."""
    p, _, run = local_run
    base = tmp_path_factory.mktemp("detect")
    a, b = base / "noann", base / "ann"
    shutil.copytree(run / "cache" / "ingest", a / "cache" / "ingest")  # logs read once
    shutil.copy(run / ".dbl-harness.json", a / ".dbl-harness.json")
    world = ["--data-root", str(p.cfg.data_root)]
    cmd = ["detect", "--map", MAP, "--query", QUERY]
    with shared_stages(tmp_path_factory, "detect-run", a):  # the Ray test's local run shares it
        _run([*cmd[:1], "--config", "datasets/fixture-detect.toml", *cmd[1:], "--out", str(a),
              *world])  # fmt: skip
    shutil.copytree(a / "cache", b / "cache")  # the same pairs, proposals, model and ranks
    shutil.copy(a / ".dbl-harness.json", b / ".dbl-harness.json")
    printed = _run(  # the README's second command: two new sessions, Table D
        [*cmd[:1], "--config", "datasets/fixture.toml", *cmd[1:], "--query", "2012-08-04",
         "--out", str(b), *world]
    )  # fmt: skip
    return a, b, printed


def test_the_detect_stages_are_the_recorded_ones(detected: tuple) -> None:
    """The README's second command's keypoint stages (registration, keypoint localization, the
    plain difference, the change boxes, Table D) against ``tests/regression/detect_stages.json``:
    byte for byte on the recording CPU, within docs/decisions.md's rule on another; where one is
    not, the failure names the first stage that is not and both CPUs (tests/detect/stage_record)."""
    _, b, _ = detected
    rec = json.loads(RECORD.read_text())
    msg = first_stage_outside(b, rec)
    assert msg is None, msg
    other = {**rec, "cpu": {"model": "another CPU", "flags": []}}  # the rule, as elsewhere
    assert first_stage_outside(b, other) is None
    stages = other["stages"]
    values = stages["plain difference"]["values"]
    moved = {**values, "data": [[*r[:-1], r[-1] * 1.5 + 0.1] if i == 3 else r
                                for i, r in enumerate(values["data"])]}  # fmt: skip
    msg = first_stage_outside(b, {**other, "stages": {**stages, "plain difference": {
        **stages["plain difference"], "values": moved}}})  # fmt: skip
    assert msg is not None and msg.startswith(
        "the first detect stage that differs from the record is 'plain difference' (mean "
    ), msg
    assert "This CPU: " in msg and "Recorded on: another CPU" in msg


def test_detect_without_annotations_writes_every_output(detected: tuple) -> None:
    out, _, _ = detected
    for name in ("detections.json", "images.json", "frames.parquet", "frames.csv",
                 "trajectory.png", "detect.html", "detect.json"):  # fmt: skip
        assert (out / name).is_file(), name
    assert not (out / "tableD.md").exists()
    images = json.loads((out / "images.json").read_text())
    dets = json.loads((out / "detections.json").read_text())
    fr = pd.read_parquet(out / "frames.parquet")
    assert len(images["images"]) == len(fr) == 64  # every query frame ([pairs] stride_m = 0)
    assert set(fr["session"]) == {QUERY} and set(fr["r_session"]) == {MAP}
    assert images["categories"] == [{"id": 1, "name": "change", "supercategory": "change"}]
    size = {i["id"]: (i["width"], i["height"]) for i in images["images"]}
    per = pd.Series([d["image_id"] for d in dets]).value_counts()
    assert per.max() <= 10 and len(dets) > len(fr)  # at most max_boxes per frame
    for d in dets:
        x, y, w, h = d["bbox"]
        assert d["category_id"] == 1 and w > 0 and h > 0
        assert x >= 0 and y >= 0 and x + w <= size[d["image_id"]][0] + 1e-9
    # the frame's score is its largest fused LoC (method §13); its best detection is its best-scored
    # candidate, every candidate at least [detect] min_box_side (2 px) a side
    best = pd.DataFrame(dets).groupby("image_id")["score"].max()
    f = fr.set_index("image_id").loc[best.index]
    chunks = list((out / "cache" / "detect").glob("*/"))
    samples = pd.concat([pd.read_parquet(c / "samples.parquet") for c in chunks])
    cands = pd.concat([pd.read_parquet(c / "candidates.parquet") for c in chunks])
    np.testing.assert_allclose(f["score"], samples.groupby("q_utime")["loc"].max()[f["utime"]])
    np.testing.assert_allclose(best, cands.groupby("q_utime")["loc"].max()[f["utime"]])
    assert (np.minimum(cands["x2"] - cands["x1"], cands["y2"] - cands["y1"]) >= 2).all()
    assert json.loads((out / "detect.json").read_text())["thin_boxes_dropped"] >= 0
    # the most changed places: frames whose pairs were registered (a pair that was not is never
    # among them; most of the fixture's 120 x 160 views cannot be registered, and say why)
    rec = json.loads((out / "detect.json").read_text())
    comparable = int(fr["comparable"].sum())
    assert rec["not_comparable"]["frames"] == 64 - comparable > 0
    assert fr.loc[~fr["comparable"], "not_comparable_why"].str.startswith("too few").all()
    assert set(fr.loc[~fr["comparable"], "compared_by"]) <= {"colour"}
    maps = sorted((out / "locmaps").glob("*.npy"))
    assert len(maps) == min(10, comparable) and np.load(maps[0]).dtype == np.float16
    assert len(list((out / "locmaps").glob("*.png"))) == len(maps)
    shown = {int(p.stem.rsplit("_", 1)[1]) for p in maps}
    assert shown <= set(fr.loc[fr["comparable"], "utime"])
    assert rec["query_frames"] == 64 and rec["table_d"] is None and rec["ms_per_query_frame"] > 0


def test_a_rerun_does_no_work_and_writes_the_same_detections(
    detected: tuple, local_run: tuple
) -> None:
    out, _, _ = detected
    before = (out / "detections.json").read_bytes()
    _run(["detect", "--config", "datasets/fixture-detect.toml", "--map", MAP, "--query", QUERY,
          "--out", str(out), "--data-root", str(local_run[0].cfg.data_root)])  # fmt: skip
    rec = json.loads((out / "detect.json").read_text())
    assert rec["stage_units_run"] and not any(rec["stage_units_run"].values()), rec
    assert (out / "detections.json").read_bytes() == before


def test_with_annotations_table_d_is_what_pycocotools_gives_from_the_files(
    detected: tuple,
) -> None:
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    _, out, printed = detected
    assert "# Table D" in printed
    t = pd.read_csv(out / "tableD.csv")
    assert t["row"].tolist()[:6] == [
        "detector",
        "random scores, same boxes (one draw)",
        "box area alone (no pixel)",  # method §13.3: the baselines that read no pixel
        "cover count alone (no pixel)",
        # and the two that read pixels but no localizer: the plain difference of the registered
        # pair on boxes of its own, and on the detector's candidates
        "plain difference, registered, its own boxes (pixels, no localizer; reference recipe)",
        "plain difference on the detector's boxes (pixels, no localizer)",
    ]
    # the fixture's views that cannot be registered carry fallback boxes: measured apart (the
    # registered ones only where they hold a change box)
    assert t["row"].tolist()[6:] in (
        ["detector, frames that could not be registered (fallback boxes) only"],
        ["detector, registered frames only",
         "detector, frames that could not be registered (fallback boxes) only"],
    )  # fmt: skip
    images = {
        (i["session"], i["camera"], i["utime"]): i
        for i in json.loads((out / "images.json").read_text())["images"]
    }
    ann = pd.read_csv(ROOT / "annotations" / "fixture.csv")
    ann = ann[ann["session"].isin([QUERY, "2012-08-04"])]
    gt_images = [
        {"id": images[k]["id"], "width": images[k]["width"], "height": images[k]["height"]}
        for k in {(s, c, int(u)) for s, c, u in ann[["session", "camera", "utime"]].to_numpy()}
        if k in images
    ]
    gt_anns = [
        {"id": i + 1, "image_id": images[(r.session, r.camera, int(r.utime))]["id"],
         "category_id": 1, "bbox": [r.x1, r.y1, r.x2 - r.x1, r.y2 - r.y1],
         "area": (r.x2 - r.x1) * (r.y2 - r.y1), "iscrowd": 0}
        for i, r in enumerate(ann[ann["status"] == "change"].itertuples())
    ]  # fmt: skip
    keep = {i["id"] for i in gt_images}
    dets = [d for d in json.loads((out / "detections.json").read_text()) if d["image_id"] in keep]
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {"images": gt_images, "annotations": gt_anns,
                      "categories": [{"id": 1, "name": "change"}]}  # fmt: skip
        gt.createIndex()
        ev = COCOeval(gt, gt.loadRes(dets), "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    det = t.iloc[0]
    assert det["annotated_frames"] == len(gt_images) and det["change_boxes"] == len(gt_anns)
    assert det["coco_ap_50_95"] == pytest.approx(ev.stats[0], abs=5e-5)
    assert det["coco_ap_50"] == pytest.approx(ev.stats[1], abs=5e-5)
    assert ev.stats[1] > 0  # some box matches: the comparison is not of two zeros
    # the fast matcher behind the floor's draws and the intervals gives COCOeval's AP50
    assert t["matcher_ap50"].to_numpy() == pytest.approx(t["ap50_voc_all_point"], abs=5e-5)
    # method §9: the floor and band of random scores on the same candidates, the ceiling of oracle
    # scores, and the verdict by the one rule
    assert 0 < det["chance_low"] <= det["floor"] <= det["chance_high"] < det["ceiling"] <= 1
    # no order of these candidates recalls more change boxes than the candidates meet at all
    assert det["ceiling"] <= det["candidate_recall"] + 5e-5
    assert det["ci_low"] <= det["ap50_voc_all_point"] <= det["ci_high"]
    assert det["verdict"] == chance.versus_no_pixel(chance.verdict(
        det["ap50_voc_all_point"], det["chance_low"], det["chance_high"],
        det["vs_random_ci_low"], det["vs_random_ci_high"],
    ), det["vs_no_pixel_ci_low"])  # fmt: skip
    assert t.iloc[1]["verdict"] == "chance"  # the random row is never above chance
    md = (out / "tableD.md").read_text()
    assert "VOC all-point" in md and "ceiling" in md and "chance band" in md
    assert ("WARNING" in md) == (det["verdict"] != "above")
    assert ("NOTE: only" in md) == (det["candidate_recall"] < 0.5)


def test_the_detect_page_renders_in_a_real_browser(detected: tuple) -> None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("no Chromium here: install Debian's chromium package")
    _, out, _ = detected
    page = (out / "detect.html").read_text()
    assert page.index('id="trajectory"') < page.index('data-table="D"') < page.index('id="places"')
    # the most changed places: the registered frames with a score, ten at most
    fr = pd.read_parquet(out / "frames.parquet")
    places = min(10, int((fr["comparable"].astype(bool) & fr["score"].notna()).sum()))
    assert len(re.findall(r'data-place="\d+"', page)) == places > 0
    assert "http://" not in page and "https://" not in page
    dom = subprocess.run(
        [chromium, "--headless=new", "--no-sandbox", "--disable-gpu",
         "--virtual-time-budget=15000", "--dump-dom", (out / "detect.html").resolve().as_uri()],
        capture_output=True, text=True, timeout=120, check=True,
    ).stdout  # fmt: skip
    attrs = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', re.search(r"<body([^>]*)>", dom)[1]))
    # the trajectory, query | map | LoC map for each of the places and the six annotated change
    # frames, every one loaded
    assert int(attrs["images-total"]) == 1 + 3 * places + 6
    assert attrs["images-loaded"] == attrs["images-total"], attrs
    assert attrs["tables"] == "1"


def test_nms_keeps_the_highest_loc_and_drops_its_overlaps() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30], [0, 0, 9, 10]], float)
    loc = np.array([0.5, 0.9, 0.1, np.nan])
    # box 1 (0.9) first; box 0 overlaps it at IoU 81/100 > 0.5: dropped; box 2 kept; NaN never
    assert greedy_nms(boxes, loc, 0.5, 10).tolist() == [1, 2]
    assert greedy_nms(boxes, loc, 0.9, 10).tolist() == [1, 0, 2]
    assert greedy_nms(boxes, loc, 0.9, 2).tolist() == [1, 0]


def test_table_d_evaluator_on_boxes_whose_ap_is_known_by_hand() -> None:
    from harness.evaluate.box_ap import coco_eval

    gt = {
        "images": [{"id": 1, "width": 100, "height": 100}, {"id": 2, "width": 100, "height": 100},
                   {"id": 3, "width": 100, "height": 100}],  # image 3: annotated no-change
        "annotations": [
            {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "area": 400,
             "iscrowd": 0},
            {"id": 2, "image_id": 2, "category_id": 1, "bbox": [50, 50, 30, 30], "area": 900,
             "iscrowd": 0},
        ],
        "categories": [{"id": 1, "name": "change"}],
    }  # fmt: skip
    dets = [
        {"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9},  # TP
        {"image_id": 3, "category_id": 1, "bbox": [0, 0, 10, 10], "score": 0.8},  # FP
        {"image_id": 2, "category_id": 1, "bbox": [52, 50, 30, 30], "score": 0.7},  # TP, IoU .87
    ]
    voc, coco, coco50 = coco_eval(gt, dets)
    # precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1: all-point area 1/2 * 1 + 1/2 * 2/3
    assert voc == pytest.approx(0.5 + 0.5 * 2 / 3)
    # COCO's 101-point AP@.5: p(R) = 1 for R <= .5 (51 points), 2/3 above (50 points)
    assert coco50 == pytest.approx((51 + 50 * 2 / 3) / 101, abs=1e-6)
    assert 0 < coco < coco50


def test_voc_all_point_ap_by_hand() -> None:
    # 3 ground-truth boxes; detections by score: TP, FP, TP -> precision 1, 1/2, 2/3 at recall
    # 1/3, 1/3, 2/3; the envelope: 1 up to recall 1/3, 2/3 up to 2/3, 0 after
    ap = _voc_all_point(np.array([1, 0, 1]), np.array([0.9, 0.8, 0.7]), 3)
    assert ap == pytest.approx(1 / 3 * 1 + 1 / 3 * 2 / 3)


def test_the_detect_flags_are_honoured_as_typed(
    detected: tuple, local_run: tuple, tmp_path: Path
) -> None:
    """``--fusion``, ``--nms-iou``, ``--max-boxes`` and ``--top`` as the README shows them (with
    a 20-pair null: nothing here reads the null's figures)."""
    a, _, _ = detected
    out = tmp_path / "flags"
    shutil.copytree(a / "cache", out / "cache")  # the map, model and ranks are reused
    shutil.copy(a / ".dbl-harness.json", out / ".dbl-harness.json")
    flags = ["--fusion", "rank_fusion_le2", "--nms-iou", "0.2", "--max-boxes", "3", "--top", "4"]
    cfg = small_null_config(ROOT / "datasets" / "fixture-detect.toml", tmp_path)
    _run(["detect", "--config", str(cfg), "--map", MAP, "--query", QUERY,
          "--out", str(out), "--data-root", str(local_run[0].cfg.data_root), *flags])  # fmt: skip
    rec = json.loads((out / "detect.json").read_text())
    assert {k: rec["options"][k] for k in ("fusion", "nms_iou", "max_boxes", "top")} == {
        "fusion": "rank_fusion_le2", "nms_iou": 0.2, "max_boxes": 3, "top": 4,
    }  # fmt: skip
    skip = ("segments", "keypoints", "difference", "selective")
    assert {k: v for k, v in rec["options"].items() if k not in skip} == {
        "fusion": "rank_fusion_le2", "nms_iou": 0.2, "max_boxes": 3, "top": 4,
        "chunk_frames": 64, "seed": 0, "boxes": "subimages", "box_score": "max",
        "locmap_level": 0.5, "min_box_side": 2.0, "localizer": "keypoints",
        "box_prior": "difference_product", "localization_weight": 4.0, "proposals": "selective",
        "not_comparable": "fallback",
    }  # fmt: skip
    assert rec["options"]["difference"]["box_score"] == "ratio"
    dets = pd.DataFrame(json.loads((out / "detections.json").read_text()))
    assert dets.groupby("image_id").size().max() == 3  # --max-boxes
    for _, g in dets.groupby("image_id"):  # --nms-iou: no kept pair overlaps more than 0.2
        b = np.array(g["bbox"].tolist(), np.float64)
        x1, y1, x2, y2 = b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]
        iw = np.clip(np.minimum(x2[:, None], x2) - np.maximum(x1[:, None], x1), 0, None)
        ih = np.clip(np.minimum(y2[:, None], y2) - np.maximum(y1[:, None], y1), 0, None)
        inter = iw * ih
        iou = inter / ((b[:, 2] * b[:, 3])[:, None] + b[:, 2] * b[:, 3] - inter)
        np.fill_diagonal(iou, 0)
        assert iou.max() <= 0.2 + 1e-9
    fr = pd.read_parquet(out / "frames.parquet")
    assert len(list((out / "locmaps").glob("*.npy"))) == min(4, int(fr["comparable"].sum()))
    # --fusion: the frame scores (the largest fused LoC) are another rule's than the default run's
    before = pd.read_parquet(a / "frames.parquet").sort_values("image_id")["score"].to_numpy()
    after = pd.read_parquet(out / "frames.parquet").sort_values("image_id")["score"].to_numpy()
    assert not np.allclose(before, after)


def test_the_readme_quotes_table_d_as_the_command_prints_it(
    detected: tuple, local_run: tuple
) -> None:
    """The README's Table D rows and figures are this run's (issue 34 item 7)."""
    from ..readme_text import table_rows_after
    from ..stage_digests import skip_unless_recorded_model

    _, out, _ = detected
    md = (out / "tableD.md").read_text()
    assert "# Table D" in md
    skip_unless_recorded_model(local_run[2])
    for row in table_rows_after("as the second command prints it:", tables=2):
        assert row in md, row
    t = pd.read_csv(out / "tableD.csv").set_index("row")
    det = t.loc["detector"]
    met = round(float(det["candidate_recall"]) * int(det["change_boxes"]))
    text = manual_text()
    flat = " ".join(text.split())
    assert f"meet {met} of the {int(det['change_boxes'])} change boxes at IoU 0.5" in flat
    assert f"could reach AP50 {float(det['ceiling']):.2f}" in flat
    assert (
        f"is [{det['vs_no_pixel_ci_low']:+.3f}, {det['vs_no_pixel_ci_high']:+.3f}] over annotated"
        in flat
    )


def test_detect_resumes_after_a_kill_at_the_next_chunk(
    detected: tuple, local_run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed in its third chunk of 16 query frames, a rerun builds only the chunks not finished
    and writes the boxes the uninterrupted run wrote (one chunk of 64), byte for byte."""
    from harness.apps import detect
    from harness.config.assemble import load_config

    a, _, _ = detected
    p, _, _ = local_run
    o = tmp_path / "o"
    shutil.copytree(a / "cache", o / "cache", ignore=shutil.ignore_patterns("detect"))
    shutil.copy(a / ".dbl-harness.json", o / ".dbl-harness.json")
    toml = tmp_path / "fixture-detect-16.toml"  # chunks of 16 query frames, as a user sets them
    text = (ROOT / "datasets" / "fixture-detect.toml").read_text()
    text = text.replace('"datasets/', f'"{ROOT}/datasets/')
    toml.write_text(f"{text}\n[detect]\nchunk_frames = 16\n")
    cfg = load_config(toml, data_root=str(p.cfg.data_root))
    real, calls = detect.detect_chunk, {"n": 0}

    def dying(*args: object, **kw: object) -> dict[str, int]:
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # as a kill in the middle of the third chunk
        return real(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(detect, "detect_chunk", dying)
    with pytest.raises(KeyboardInterrupt):
        detect.run_detect(cfg, MAP, [QUERY], o)
    assert not (o / "detections.json").exists()
    monkeypatch.setattr(detect, "detect_chunk", real)
    rec = detect.run_detect(cfg, MAP, [QUERY], o).record
    assert rec["stage_units_run"]["detect"] == 4 - 2  # the two chunks finished before the kill
    assert (o / "detections.json").read_bytes() == (a / "detections.json").read_bytes()
    assert (o / "frames.csv").read_bytes() == (a / "frames.csv").read_bytes()


def test_rerun_recording_reads_back_with_the_sdk(
    detected: tuple, local_run: tuple, tmp_path: Path
) -> None:
    """``harness detect ... --fusion rrf --rerun OUT.rrd`` as the README shows it (issue 38): the
    recording, read back with the Rerun SDK, holds the map trajectory, every query frame on the
    ``utime`` timeline with its image, its change boxes (those of ``detections.json``), its LoC map
    and its score; a file that is not a recording of ours is never replaced."""
    rerun_chunk = pytest.importorskip("rerun.chunk")
    a, _, _ = detected
    out = tmp_path / "rr"
    shutil.copytree(a / "cache", out / "cache")
    shutil.copy(a / ".dbl-harness.json", out / ".dbl-harness.json")
    rrd = tmp_path / "detect.rrd"
    readme = manual_text()
    typed = re.search(r"^harness detect .* --rerun \S+$", readme, re.M)
    assert typed is not None, "the README's --rerun command"
    argv = typed.group(0).split()[1:]
    argv[argv.index("--out") + 1] = str(out)
    argv[argv.index("--rerun") + 1] = str(rrd)
    assert argv[argv.index("--fusion") + 1] == "rrf"
    argv += ["--data-root", str(local_run[0].cfg.data_root)]
    assert f"rerun {typed.group(0).split()[-1]}" in " ".join(readme.split())  # how to open it
    printed = _run(argv)
    assert f"rerun recording: {rrd}" in printed
    rec = json.loads((out / "detect.json").read_text())
    assert rec["options"]["fusion"] == "rrf"
    frames = pd.read_parquet(out / "frames.parquet")
    dets = pd.DataFrame(json.loads((out / "detections.json").read_text()))
    reader = rerun_chunk.RrdReader(rrd)
    assert [s.application_id for s in reader.recordings()] == ["dbl-harness detect"]
    rows: dict[str, int] = {}
    boxes = 0
    utimes: set[int] = set()
    for ch in reader.stream():
        path = str(ch.entity_path)
        rows[path] = rows.get(path, 0) + ch.num_rows
        batch = ch.to_record_batch()
        names = batch.schema.names
        if path.endswith("/image/changes"):
            col = next(n for n in names if n.endswith("half_sizes"))
            boxes += sum(len(v) for v in batch.column(col).to_pylist() if v)
        if path.endswith("/image") and "utime" in names:
            utimes.update(int(u) for u in batch.column("utime").to_pylist())
    n = len(frames)
    cam = f"/camera/{frames['camera'].iloc[0]}"
    assert rows["/world/map"] == 1
    assert rows[f"/world/query/{QUERY}/trajectory"] == 1
    assert rows[f"/world/query/{QUERY}/frame"] == n
    assert rows[f"{cam}/image"] == rows[f"{cam}/loc"] == rows["/detect/score"] == n
    assert utimes == set(frames["utime"].astype(int))
    assert boxes == len(dets)
    # ours is replaced by the same command; a file of the user's is not
    assert "rerun recording" in _run(argv)
    mine = tmp_path / "notes.rrd"
    mine.write_text("the user's own file")
    theirs = list(argv)
    theirs[theirs.index("--rerun") + 1] = str(mine)
    assert main(theirs) == 1
    assert mine.read_text() == "the user's own file"


def test_box_generators_on_a_loc_map_known_by_hand() -> None:
    """method §13.1's generators on a 20 x 10 frame whose left half has LoC 1 and right half 5."""
    from harness.detect.boxes import candidate_boxes

    fused = np.array([[0, 0, 10, 10], [10, 0, 20, 10]], np.float64)
    loc = np.array([1.0, 5.0])
    b, s = candidate_boxes("fused", fused, loc, fused, 20, 10)
    assert b.tolist() == fused.tolist() and s.tolist() == [1.0, 5.0]
    # locmap at half the range (3): the right half alone, scored by its LoC
    b, s = candidate_boxes("locmap", fused, loc, fused, 20, 10, "max", 0.5)
    assert b.tolist() == [[10, 0, 20, 10]] and s.tolist() == [5.0]
    # proposals: the originals (duplicates merged) scored by the LoC inside, max or mean
    orig = np.array([[0, 0, 20, 10], [0, 0, 10, 10], [0, 0, 10, 10], [5, 0, 15, 10]], np.float64)
    b, s = candidate_boxes("proposals", fused, loc, orig, 20, 10, "max")
    assert b.tolist() == [[0, 0, 10, 10], [0, 0, 20, 10], [5, 0, 15, 10]]
    assert s.tolist() == [1.0, 5.0, 5.0]
    _, s = candidate_boxes("proposals", fused, loc, orig, 20, 10, "mean")
    assert s.tolist() == [1.0, 3.0, 3.0]
    # two separate changed blobs are two boxes (8-connected regions)
    fused3 = np.array([[0, 0, 4, 10], [4, 0, 16, 10], [16, 0, 20, 10]], np.float64)
    b, s = candidate_boxes("locmap", fused3, np.array([9.0, 0.0, 7.0]), fused3, 20, 10)
    assert b.tolist() == [[0, 0, 4, 10], [16, 0, 20, 10]] and s.tolist() == [9.0, 7.0]


#: The preset that runs the paper's own detector (method §13: each proposal ranked against the
#: whole map by the config's localizer, the fused qBBs as boxes, their LoC alone), as docs/detect.md
#: types it: ``--preset paper``, the flags ``--localizer config --boxes fused --box-prior none``.
PAPER = ("--preset", "paper")


def _options(args: Any, cfg: Any) -> Any:
    """The ``[detect]`` a command line assembles over ``cfg``."""
    return with_overrides(cfg, detect_overrides(args), "test", "harness detect").detect


def test_a_preset_is_its_flags_and_a_typed_flag_wins() -> None:
    """``--preset paper`` sets the paper's three values; a flag typed beside it wins; every preset
    is listed by ``harness detect --help`` with what it is."""
    cfg = load_config(Path("datasets/fixture.toml"))
    parse = build_parser().parse_args
    base = ["detect", "--config", "datasets/fixture.toml", "--map", MAP, "--query", QUERY,
            "--out", "x"]  # fmt: skip
    flags = parse([*base, "--localizer", "config", "--boxes", "fused", "--box-prior", "none"])
    assert _options(parse([*base, *PAPER]), cfg) == _options(flags, cfg)
    typed = _options(parse([*base, *PAPER, "--box-prior", "area"]), cfg)
    assert (typed.localizer, typed.boxes, typed.box_prior) == ("config", "fused", "area")
    assert _options(parse([*base, "--preset", "default"]), cfg) == cfg.detect
    helped = subprocess.run([sys.executable, "-m", "harness.cli", "detect", "--help"],
                            capture_output=True, text=True, check=True).stdout  # fmt: skip
    words = " ".join(helped.split())
    for name in ("default", "paper", "local"):
        assert f"{name}: " in words, name


@pytest.fixture(scope="module")
def paper_detected(
    detected: tuple, local_run: tuple, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """The README's second command with :data:`PAPER`: the model the paper's tests share."""
    _, b, _ = detected
    out = tmp_path_factory.mktemp("paper") / "run"
    shutil.copytree(b / "cache", out / "cache")
    shutil.copy(b / ".dbl-harness.json", out / ".dbl-harness.json")
    _run(["detect", "--config", "datasets/fixture.toml", "--map", MAP, "--query", QUERY,
          "--query", "2012-08-04", "--out", str(out), "--data-root",
          str(local_run[0].cfg.data_root), *PAPER])  # fmt: skip
    return out


def _scored_again(paper_detected: Path, local_run: tuple, out: Path, *flags: str) -> Path:
    """The README's second command again with the paper's detector and ``flags``, into ``out``,
    reusing that run's cache (map, model, ranks); returns ``out``."""
    shutil.copytree(paper_detected / "cache", out / "cache")
    shutil.copy(paper_detected / ".dbl-harness.json", out / ".dbl-harness.json")
    _run(["detect", "--config", "datasets/fixture.toml", "--map", MAP, "--query", QUERY,
          "--query", "2012-08-04", "--out", str(out), "--data-root",
          str(local_run[0].cfg.data_root), *PAPER, *flags])  # fmt: skip
    return out


def test_boxes_proposals_as_typed_scores_the_original_proposals(
    paper_detected: Path, local_run: tuple, tmp_path: Path
) -> None:
    """``--boxes proposals`` (method §13.1): every change box is an original proposal of its frame,
    Table D names the generator and its candidates are those proposals."""
    opt = json.loads((paper_detected / "detect.json").read_text())["options"]  # PAPER passed on
    assert "localizer" not in opt and (opt["boxes"], opt["box_prior"]) == ("fused", "none")
    paper = pd.read_csv(paper_detected / "tableD.csv").iloc[0]  # the paper's detector, quoted
    assert paper.verdict == "chance"
    readme_ = " ".join(manual_text().split())
    assert (
        f"--box-prior none`) on the same frames: AP50 {paper.ap50_voc_all_point:.3f}, cannot be "
        "told from chance" in readme_
    )
    out = _scored_again(paper_detected, local_run, tmp_path / "props", "--boxes", "proposals",
                        "--alarm", "0.2")  # fmt: skip
    rec = json.loads((out / "detect.json").read_text())
    assert rec["options"]["boxes"] == "proposals"
    assert rec["alarm"]["rate"] == 0.2  # --alarm: the README's "still 0 at 0.2"
    assert (pd.read_csv(out / "alarms.csv")["exceedance"] <= 0.2).all()
    t = pd.read_csv(out / "tableD.csv")
    assert (t["boxes"] == "proposals").all()
    readme = " ".join(manual_text().split())
    d = t.iloc[0]
    assert (
        f"`proposals` reaches AP50 {d.ap50_voc_all_point:.3f} against a floor of {d.floor:.3f} and "
        f"a chance band up to {d.chance_high:.3f} (ceiling {d.ceiling:.3f})"
    ) in readme
    assert d.verdict == "chance"
    assert d.alarm_nominal == 0.2 and d.alarm_measured == 0.0
    assert "(boxes: proposals)" in (out / "tableD.md").read_text()
    images = {i["id"]: i for i in json.loads((out / "images.json").read_text())["images"]}
    ranks = pd.concat(pd.read_parquet(f) for f in (out / "cache" / "ranks").glob("*/ranks.parquet"))
    boxes = {
        (s, c, int(u)): set(map(tuple, g[["x1", "y1", "x2", "y2"]].to_numpy().tolist()))
        for (s, c, u), g in ranks.groupby(["q_session", "q_camera", "q_utime"])
    }
    dets = json.loads((out / "detections.json").read_text())
    assert dets
    for d in dets:
        i = images[d["image_id"]]
        x, y, w, h = d["bbox"]
        assert (x, y, x + w, y + h) in boxes[(i["session"], i["camera"], i["utime"])]


def test_boxes_segments_with_contrast_as_typed(
    paper_detected: Path, local_run: tuple, tmp_path: Path
) -> None:
    """``--boxes segments --box-score contrast`` (method §13.1): every change box is a colour region
    of its frame, the candidates meet most change boxes, and the README quotes Table D as run."""
    from harness.imagestore import read_image
    from harness.proposals.builtin import segment_boxes
    from harness.proposals.config import SegmentsConfig

    # the README's command as typed (its --out here, the fixture's --data-root added)
    lines = manual_text().splitlines()
    typed = next(x for x in lines if x.startswith("harness detect") and "detect-segments" in x)
    argv = typed.split()[1:]
    out = tmp_path / "segments"
    argv[argv.index("--out") + 1] = str(out)
    shutil.copytree(paper_detected / "cache", out / "cache")  # the paper run's model and ranks
    shutil.copy(paper_detected / ".dbl-harness.json", out / ".dbl-harness.json")
    _run([*argv, "--data-root", str(local_run[0].cfg.data_root)])
    rec = json.loads((out / "detect.json").read_text())
    # the paper's detector: no local options in its record, its score unfused with area
    assert "localizer" not in rec["options"] and rec["options"]["box_prior"] == "none"
    assert (rec["options"]["boxes"], rec["options"]["box_score"]) == ("segments", "contrast")
    t = pd.read_csv(out / "tableD.csv")
    assert (t["boxes"] == "segments").all()
    d = t.iloc[0]
    assert d.candidate_recall > 0.7  # the regions meet the objects: proposals' recall is 0.30
    page = (out / "detect.html").read_text()  # the command's last output, the page
    assert "boxes: segments" in page and f"{d.ceiling:.3f}" in page
    from ..stage_digests import skip_unless_recorded_model

    skip_unless_recorded_model(local_run[2])
    readme = " ".join(manual_text().split())
    assert (
        f"`segments` with `--box-score contrast` reaches AP50 {d.ap50_voc_all_point:.3f} against "
        f"a floor of {d.floor:.3f} and a chance band up to {d.chance_high:.3f} (ceiling "
        f"{d.ceiling:.3f}, candidates' recall {d.candidate_recall:.3f})"
    ) in readme
    images = {i["id"]: i for i in json.loads((out / "images.json").read_text())["images"]}
    dets = json.loads((out / "detections.json").read_text())
    assert dets
    regions: dict[int, set] = {}
    for det in dets[:20]:
        i = images[det["image_id"]]
        if det["image_id"] not in regions:
            found = segment_boxes(read_image(i["file_name"]), SegmentsConfig())[0]
            regions[det["image_id"]] = set(map(tuple, found.tolist()))
        x, y, w, h = det["bbox"]
        assert (x, y, x + w, y + h) in regions[det["image_id"]]


def test_segment_boxes_frame_coloured_objects_on_a_textured_scene() -> None:
    """A flat object and a checkered one on a noisy two-tone scene: each gets a box that fits it,
    the checkered one whole (its cells merged by the closings); the same image, the same boxes."""
    from harness.boxes import iou_matrix
    from harness.proposals.builtin import segment_boxes
    from harness.proposals.config import SegmentsConfig

    rng = np.random.default_rng(0)
    img = np.empty((160, 120, 3), np.uint8)
    img[:80], img[80:] = (120, 160, 220), (110, 110, 105)  # sky over road
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    img[90:130, 10:30] = (230, 40, 40)  # a red bin
    yy, xx = np.mgrid[30:100, 60:100]
    img[30:100, 60:100] = np.where((((yy // 4) + (xx // 4)) % 2 == 0)[..., None], (20, 160, 120),
                                   (40, 200, 90))  # fmt: skip
    boxes, scores = segment_boxes(img, SegmentsConfig())
    best = iou_matrix(boxes, np.array([[10, 90, 30, 130], [60, 30, 100, 100]], float)).max(axis=0)
    assert (best > 0.9).all(), best
    assert len(scores) == len(boxes) and (np.diff(scores) <= 0).all()  # largest first
    again, _ = segment_boxes(img.copy(), SegmentsConfig())
    assert np.array_equal(boxes, again)


def test_contrast_prefers_the_box_that_frames_the_hot_region() -> None:
    """``contrast``: the mean inside less the ring's mean. On a map hot in one 10 x 10 square, the
    box on the square beats one twice as large around it and one half on it; ``max`` ties them."""
    from harness.detect.boxes import inside_score as _inside

    m = np.ones((60, 60))
    m[20:30, 20:30] = 9.0
    on, around, half = (np.array(b, float) for b in ([20, 20, 30, 30], [15, 15, 35, 35],
                                                     [25, 20, 35, 30]))  # fmt: skip
    c = {k: _inside(m, b, "contrast") for k, b in (("on", on), ("around", around), ("half", half))}
    assert c["on"] == 8.0 and c["on"] > c["around"] > 0 and c["on"] > c["half"]
    assert _inside(m, on, "max") == _inside(m, around, "max") == 9.0
    edge = np.full((60, 60), np.nan)
    edge[0:10, 0:10] = 4.0  # no mapped pixel around it: the ring counts 0
    assert _inside(edge, np.array([0, 0, 10, 10], float), "contrast") == 4.0


def test_exceedance_and_its_words_by_hand() -> None:
    from harness.detect.calibrate import exceedance
    from harness.reports.alarm_words import in_words

    got = exceedance(np.array([1.0, 2.0, 3.0, 4.0, np.nan]), np.array([4.0, 2.5, 0.0, np.nan]))
    assert got[:3].tolist() == [2 / 5, 3 / 5, 5 / 5] and np.isnan(got[3])
    assert exceedance(np.zeros(0), np.array([1.0])).tolist() == [1.0]
    assert in_words(0.001, "candidate boxes") == "1 in 1,000 candidate boxes scores this high"
    assert in_words(0.2, "frames") == "1 in 5 frames scores this high"
    assert in_words(1.0, "frames") == "100% of frames score this high"  # not "1 in 1 frames"
    from harness.evaluate.box_ap import clopper_pearson

    lo, hi = clopper_pearson(3, 10)  # the textbook interval of 3 in 10
    assert (round(lo, 4), round(hi, 4)) == (0.0667, 0.6525)
    assert clopper_pearson(0, 4)[1] == pytest.approx(1 - 0.025**0.25)


def test_clopper_pearson_is_scipy_stats_beta_bit_for_bit() -> None:
    """The interval's quantiles come from ``scipy.special.betaincinv`` (no ``scipy.stats``
    import in a run): the values ``scipy.stats.beta.ppf`` gives, bit for bit, on every count up
    to 200 and a spread of larger ones, at two levels."""
    from scipy.stats import beta

    from harness.evaluate.box_ap import clopper_pearson

    for n in [*range(1, 201), 500, 1000, 5000]:
        for k in range(0, n + 1, max(1, n // 40)):
            for ci in (0.95, 0.9):
                a = (1.0 - ci) / 2.0
                lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
                hi = 1.0 if k == n else float(beta.ppf(1.0 - a, k + 1, n - k))
                assert clopper_pearson(k, n, ci) == (lo, hi), (k, n, ci)


def test_calibrated_scores_and_alarms_of_the_scored_run(detected: tuple) -> None:
    """The README's second command: every frame's and box's exceedance recomputes from the
    no-change null's frames and boxes (the map's neighbours, docs/decisions.md, *Calibrated
    alarms*), ``alarms.csv`` holds exactly what the default nominal rate flags, Table D measures
    the rate on the no-change frames and the changed ones, and the README's and the page's words
    are this run's."""
    from harness.reports.alarm_words import in_words

    _, out, printed = detected
    rec = json.loads((out / "detect.json").read_text())
    assert rec["calibration"]["method"] == "null", rec["calibration"]
    assert rec["calibration"]["construction"] == "neighbours"  # the map is a session: a sequence
    chunks = [out / "cache" / "detect-null" / k for k in rec["cache_entries"]["detect-null"]]
    s = pd.concat(pd.read_parquet(c / "frames.parquet") for c in chunks)["score"].to_numpy()
    assert len(s) == rec["calibration"]["pairs"] == 100
    fr = pd.read_csv(out / "frames.csv")
    want = np.array([(1 + (s >= v).sum()) / (1 + len(s)) for v in fr["score"]])
    np.testing.assert_allclose(fr["exceedance"], want, rtol=1e-5)
    boxes = pd.concat(pd.read_parquet(c / "boxes.parquet") for c in chunks)
    null = boxes.loc[boxes["kind"] == "detection", "score"].to_numpy()
    assert len(null) == rec["calibration"]["boxes"]
    dets = json.loads((out / "detections.json").read_text())
    for d in dets[:50]:
        assert d["exceedance"] == pytest.approx((1 + (null >= d["score"]).sum()) / (1 + len(null)))
    alarms = pd.read_csv(out / "alarms.csv")
    rate = rec["alarm"]["rate"]
    assert rate == 0.01
    assert (alarms["exceedance"] <= rate).all()
    # a pair that could not be registered raises no alarm (docs/method.md, §13.5), and a box
    # raises one only where its frame does
    ok = fr["comparable"].astype(bool)
    frames_on = set(fr.loc[(fr["exceedance"] <= rate) & ok, "image_id"])
    assert (alarms["kind"] == "frame").sum() == len(frames_on)
    assert (alarms["kind"] == "box").sum() == sum(
        d["exceedance"] <= rate and d["comparable"] and d["image_id"] in frames_on for d in dets
    )
    t = pd.read_csv(out / "tableD.csv").iloc[0]
    ann = pd.read_csv(ROOT / "annotations" / "fixture.csv")
    quiet = ann[ann["status"] == "no-change"].merge(fr, on=["session", "camera", "utime"])
    assert int(t["no_change_frames"]) == len(quiet) > 0
    flagged = (quiet["exceedance"] <= rate) & quiet["comparable"].astype(bool)
    assert t["alarm_measured"] == pytest.approx(flagged.mean())
    # the exact interval of 0 in n: [0, 1 - 0.025 ** (1 / n)]
    if t["alarm_measured"] == 0:
        assert t["alarm_ci_low"] == 0 and t["alarm_ci_high"] == pytest.approx(
            1 - 0.025 ** (1 / len(quiet)),
            abs=5e-5,  # tableD.csv keeps four decimals
        )
    top = fr[fr["comparable"].astype(bool)].sort_values("score", ascending=False).iloc[0]
    words = in_words(float(top["exceedance"]), "no-change null frames")
    assert f": {words} (change score " in printed  # the calibrated score leads, in words
    readme = " ".join(manual_text().split())
    assert f'("{words}")' in readme
    assert words in (out / "detect.html").read_text()
    assert (
        f"on the fixture, {int((quiet['exceedance'] <= rate).sum())} of {len(quiet)} at {rate:g}"
    ) in readme


def test_the_page_shows_annotated_changes_in_red_beside_the_detections(detected: tuple) -> None:
    """Issue 36's page: with annotations, the annotated change frames (most changed first) show
    their annotated boxes in red beside the detections in yellow; without, no such section."""
    from harness.reports.detect_page import ANNOTATED_SHOWN

    a, out, _ = detected
    page = (out / "detect.html").read_text()
    fr = pd.read_csv(out / "frames.csv")
    ann = pd.read_csv(ROOT / "annotations" / "fixture.csv")
    changed = ann[ann["status"] == "change"][["session", "camera", "utime"]].drop_duplicates()
    n = len(fr.merge(changed, on=["session", "camera", "utime"]))
    assert f'data-annotated="{min(n, ANNOTATED_SHOWN)}"' in page
    assert f"of the {n} annotated change frames" in page
    assert "annotated changes in red" in page
    assert 'id="annotated"' not in (a / "detect.html").read_text()


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--alarm", "0"], "--alarm = 0.0 is out of range; allowed: (0, 1): a false-alarm rate"),
        (["--alarm", "1.5"], "--alarm = 1.5"),
        (
            ["--boxes", "pixels"],
            "--boxes = 'pixels' is out of range; allowed: one of fused, locmap, proposals, "
            "segments, subimages",
        ),
        (["--box-score", "median"], "--box-score = 'median' is out of range; allowed: one of max"),
        (["--fusion", "score_max"], "--fusion = 'score_max' is out of range; allowed: rank_fusion"),
        (["--top", "-1"], "--top = -1 is out of range; allowed: >= 0 places"),
        (["--rerun", "/nonexistent-folder/x.rrd"], "does not exist"),
    ],
)
def test_bad_detect_flags_are_one_error_line_before_any_work(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture, flags: list, says: str
) -> None:
    out = tmp_path / "o"
    argv = ["detect", "--config", "datasets/fixture-detect.toml", "--map", MAP, "--query", QUERY,
            "--out", str(out), "--data-root", str(local_run[0].cfg.data_root), *flags]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("ERROR:")]
    assert len(lines) == 1 and says in lines[0], err
    assert not out.exists()


def test_detect_reads_the_detect_table_where_no_flag_is_typed(tmp_path: Path) -> None:
    """``[detect]`` is passed through: a flag as typed wins, the table fills what is not typed."""
    from harness.cli.parser import build_parser
    from harness.config.assemble import load_config

    text = (ROOT / "datasets" / "fixture.toml").read_text()
    (tmp_path / "c.toml").write_text(
        text + '\n[detect]\nboxes = "locmap"\nbox_score = "mean"\nlocmap_level = 0.3\n'
    )
    cfg = load_config(tmp_path / "c.toml")
    base = ["detect", "--config", "c.toml", "--map", MAP, "--query", QUERY, "--out", "o"]
    opt = _options(build_parser().parse_args(base), cfg)
    assert (opt.boxes, opt.box_score, opt.locmap_level) == ("locmap", "mean", 0.3)
    opt = _options(build_parser().parse_args([*base, "--boxes", "proposals"]), cfg)
    assert opt.boxes == "proposals"
    # the flags' keys too (issue 51: one options record): the table's value, or the flag typed
    (tmp_path / "c.toml").write_text(
        text + '\n[detect]\nfusion = "rrf"\nnms_iou = 0.3\nmax_boxes = 4\ntop = 2\n'
    )
    cfg = load_config(tmp_path / "c.toml")
    opt = _options(build_parser().parse_args(base), cfg)
    assert (opt.fusion, opt.nms_iou, opt.max_boxes, opt.top) == ("rrf", 0.3, 4, 2)
    typed = [*base, "--fusion", "borda", "--nms-iou", "0.6", "--max-boxes", "7", "--top", "0"]
    opt = _options(build_parser().parse_args(typed), cfg)
    assert (opt.fusion, opt.nms_iou, opt.max_boxes, opt.top) == ("borda", 0.6, 7, 0)


@pytest.mark.parametrize(
    ("key", "says"),
    [
        ('fusion = "score_max"', "[detect] fusion = 'score_max' is out of range"),
        ("nms_iou = 0", "[detect] nms_iou = 0.0 is out of range; allowed: (0, 1]"),
        ("max_boxes = 0", "[detect] max_boxes = 0"),
        ("top = -1", "[detect] top = -1"),
        ("chunk_frames = 0", "[detect] chunk_frames = 0"),
    ],
)
def test_a_bad_detect_key_is_one_error_at_load(tmp_path: Path, key: str, says: str) -> None:
    from harness.config.assemble import load_config
    from harness.errors import ConfigError

    text = (ROOT / "datasets" / "fixture.toml").read_text()
    (tmp_path / "c.toml").write_text(text + f"\n[detect]\n{key}\n")
    with pytest.raises(ConfigError, match=re.escape(says)):
        load_config(tmp_path / "c.toml")


def test_a_registered_fusion_method_is_usable_by_detect(
    paper_detected: Path, local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One catalogue for the paper's rules and a user's (issue 35): a method registered with
    ``fusion.register_fusion_rule`` is a ``--method`` of ``harness detect``; one registered with
    ``detect=False`` is refused in one ERROR line before any work."""
    from harness import methods
    from harness.fusion import fuse as fusion

    def best_rank(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
        return np.where(cover, (L / (L + 1.0 - r * L))[None, :], 0.0).max(1)

    saved = dict(methods.FUSION_RULES), dict(methods.METHOD_LABELS)
    try:
        fusion.register_fusion_rule("best_rank", best_rank, "best single rank")
        fusion.register_fusion_rule("no_detect", best_rank, "not for detect", detect=False)
        a = paper_detected  # the paper's detector: the fused qBBs scored by the fusion rule
        out = tmp_path / "registered"
        shutil.copytree(a / "cache", out / "cache")  # the map, model and ranks are reused
        shutil.copy(a / ".dbl-harness.json", out / ".dbl-harness.json")
        world = str(local_run[0].cfg.data_root)
        argv = ["detect", "--config", "datasets/fixture-detect.toml", "--map", MAP, "--query",
                QUERY, "--out", str(out), "--data-root", world, *PAPER]  # fmt: skip
        _run([*argv, "--method", "best_rank"])  # the flag's old name still works
        assert json.loads((out / "detect.json").read_text())["options"]["fusion"] == "best_rank"
        dets = pd.DataFrame(json.loads((out / "detections.json").read_text()))
        before = pd.DataFrame(json.loads((a / "detections.json").read_text()))
        assert (dets["score"] >= 1.0).all()  # 1 / r' >= 1 for every box
        assert dets["score"].max() < before["score"].max()  # one list's 1/r', not N * sum(1/r')
        capsys.readouterr()
        assert main([*argv, "--fusion", "no_detect"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ERROR:") and "no_detect" in err[0]
        assert "best_rank" in err[0]  # the registered one is offered
    finally:
        for d, before_ in zip((methods.FUSION_RULES, methods.METHOD_LABELS), saved, strict=True):
            d.clear()
            d.update(before_)


def test_detect_by_retrieval_says_how_often_it_agrees_with_the_pose_pairs(
    detected: tuple, paper_detected: Path, local_run: tuple, tmp_path: Path
) -> None:
    """``[pairs] by = "retrieval"`` where poses exist (method §13.2): ``detect.json``'s agreement is
    the share recomputed from its retrieval pairs and the pose pairs of the pose run."""
    a, _, _ = detected
    out = tmp_path / "retrieval"
    # the map's proposals and the model that pairs by retrieval are reused
    shutil.copytree(paper_detected / "cache", out / "cache")
    shutil.copy(a / ".dbl-harness.json", out / ".dbl-harness.json")
    text = (ROOT / "datasets" / "fixture-detect.toml").read_text()
    cfg = tmp_path / "by-retrieval.toml"
    text = text.replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    text = text.replace('queries = "annotated"', 'queries = "annotated"\nby = "retrieval"')
    cfg.write_text(f"{text}\n[detect.null]\npairs = {TEST_NULL_PAIRS}\n")  # its null is not read
    printed = _run(["detect", "--config", str(cfg), "--map", MAP, "--query", QUERY, "--out",
                    str(out), "--data-root", str(local_run[0].cfg.data_root)])  # fmt: skip
    agree = json.loads((out / "detect.json").read_text())["pairing"]["agreement_with_pose_pairs"]
    (entry,) = (out / "cache" / "pairs_retrieval").iterdir()
    rp = pd.read_parquet(entry / "pairs.parquet")
    pose = pd.read_parquet(a / "frames.parquet")  # the pose run: each query frame's map frame
    frames = pd.concat(
        [pd.read_parquet(f) for f in (a / "cache" / "frames").glob("*/frames.parquet")]
    ).drop_duplicates(["session", "camera", "utime"])
    xy = frames.set_index(["session", "camera", "utime"])[["x", "y"]]
    pose = pose.rename(columns={"session": "q_session", "camera": "q_camera", "utime": "q_utime"})
    keys = ["q_session", "q_camera", "q_utime", "r_session"]
    m = rp.merge(pose[[*keys, "r_camera", "r_utime"]], on=keys, suffixes=("", "_p"))
    ra = xy.loc[list(zip(m.r_session, m.r_camera, m.r_utime, strict=True))].to_numpy()
    rb = xy.loc[list(zip(m.r_session, m.r_camera_p, m.r_utime_p, strict=True))].to_numpy()
    dist = np.linalg.norm(ra - rb, axis=1)
    assert agree["compared"] == len(m) > 0
    assert agree["agree"] == int((dist <= 10.0).sum())
    assert f"{agree['agree']} of {agree['compared']}" in printed
    assert f"(a random map frame: {100 * agree['chance_share']:.0f}%)" in printed
    from ..stage_digests import skip_unless_recorded_model

    skip_unless_recorded_model(local_run[2])
    readme = " ".join(manual_text().split())
    share = round(100 * agree["share"])
    ci = f"{100 * agree['share_ci_low']:.0f}-{100 * agree['share_ci_high']:.0f}%"
    assert (
        f"pairs {agree['agree']} of its {agree['compared']} query frames ({share}%, 95% interval "
        f"{ci}; a random map frame: {100 * agree['chance_share']:.0f}%)" in readme
    ), agree
    assert f"(a random map frame: {100 * agree['chance_share']:.0f}%)" in printed


def test_the_default_detector_registers_localizes_and_differences(
    detected: tuple, paper_detected: Path, local_run: tuple, tmp_path: Path
) -> None:
    """The README's second command, no flag: keypoint localization of Selective Search's boxes
    times the registered pair's plain difference (``--localizer keypoints --proposals selective
    --boxes subimages --box-prior difference_product``, docs/decisions.md's rule chose them); each
    pair's geometry written; Table D with its baseline rows and, where views could not be
    registered, the detector measured apart on them; the verdict the rule's."""
    _, b, _ = detected
    rec = json.loads((b / "detect.json").read_text())
    opt = rec["options"]
    assert (opt["localizer"], opt["boxes"], opt["box_prior"], opt["proposals"]) == (
        "keypoints", "subimages", "difference_product", "selective")  # fmt: skip
    assert opt["not_comparable"] == "fallback" and opt["difference"]["box_score"] == "ratio"
    assert opt["keypoints"]["geometry"] == "fundamental" and "local" not in opt
    al = pd.read_csv(b / "alignment.csv")
    assert len(al) == rec["query_frames"] and set(al["align"]) <= {"fundamental", "none"}
    assert sum(rec["alignment"].values()) == len(al)
    fitted = al[al["align"] == "fundamental"]
    assert len(fitted) and (fitted["inliers"] >= 8).all()  # a fundamental matrix's minimum
    assert (al.loc[al["align"] == "none", "inliers"] == 0).all()
    t = pd.read_csv(b / "tableD.csv")
    rows = t["row"].tolist()
    assert rows[:6] == [
        "detector",
        "random scores, same boxes (one draw)",
        "box area alone (no pixel)",
        "cover count alone (no pixel)",
        "plain difference, registered, its own boxes (pixels, no localizer; reference recipe)",
        "plain difference on the detector's boxes (pixels, no localizer)",
    ]
    apart = t[t["row"].str.startswith("detector, ")]
    fr = pd.read_parquet(b / "frames.parquet")
    assert int(t.iloc[0]["not_comparable_frames"]) == int(apart["not_comparable_frames"].max())
    assert set(fr.loc[~fr["comparable"].astype(bool), "compared_by"]) <= {"colour"}
    d = t.iloc[0]
    assert d.best_no_pixel in ("size_prior", "cover_count", "plain_difference",
                               "difference_same_boxes")  # fmt: skip
    # the verdict: above only when clear of chance and of the best baseline row (paired)
    assert d.verdict in ("above", "baseline", "chance")
    if d.verdict != "chance":
        assert d.verdict == ("above" if d.vs_no_pixel_ci_low > 0 else "baseline")
    md = (b / "tableD.md").read_text()
    assert "box area alone (no pixel)" in md and "(boxes: subimages)" in md
    assert "WHAT LOCALIZATION ADDS: the detector's AP50 is" in md
    page = (b / "detect.html").read_text()  # the command's last output, the page
    assert "boxes: subimages" in page and "cover count alone (no pixel)" in page
    assert "WHAT LOCALIZATION ADDS" in page and "data-not-comparable=" in page
    assert "data-align='all'" in page and "Pairs aligned (method §13.3)" in page
    # the paper's detector into a copy of that directory: the local run's alignment.csv goes
    out = tmp_path / "local"
    shutil.copytree(b, out)
    shutil.copytree(paper_detected / "cache", out / "cache", dirs_exist_ok=True)  # its model
    _run(["detect", "--config", "datasets/fixture.toml", "--map", MAP, "--query", QUERY,
          "--query", "2012-08-04", "--out", str(out), "--data-root",
          str(local_run[0].cfg.data_root), *PAPER])  # fmt: skip
    assert not (out / "alignment.csv").exists()
    assert "alignment" not in json.loads((out / "detect.json").read_text())
    c = rec["local_counts"]  # every subimage ranked or counted by its reason
    assert c["ranked"] == c["query_subimages"] - c["no_rank_box_outside"] > 0
    assert c["pairs_fundamental"] + c["pairs_none"] == len(al)
