"""Sessions without poses (method §13.2): image folders, their pairs, masks and file names.

The README's two-folder command runs here as typed, on images the test writes; the pairing's
kernel is checked against a brute-force computation, the place by order by hand, and the images
format's times and order on small folders.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.cli import main

from ..conftest import ROOT
from ..readme_text import manual_text

README = manual_text()  # the README and the manual's pages


def _write_images(folder: Path, images: list[np.ndarray], names: list[str]) -> None:
    folder.mkdir(parents=True)
    for im, n in zip(images, names, strict=True):
        cv2.imwrite(str(folder / n), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))


def _session_images(world: Path, fmt_glob: str, tmp: Path, n: int) -> list[np.ndarray]:
    """The first ``n`` upright RGB frames of a fixture session, ingested by the harness."""
    from harness.imagestore import read_image
    from harness.ingest import ingest_session
    from harness.ingest.config import IngestConfig, SessionConfig

    src = sorted(world.glob(fmt_glob))[0]
    ingest_session(SessionConfig(name="s", source=str(src)), IngestConfig(), tmp)
    fr = pd.read_parquet(tmp / "frames.parquet").sort_values("utime").head(n)
    return [read_image(str(tmp / u)) for u in fr["image"]]


def test_an_images_folder_is_a_session_in_name_order_with_no_pose(tmp_path: Path) -> None:
    from harness.ingest import ingest_session
    from harness.ingest.config import IngestConfig, SessionConfig
    from harness.ingest.logs import detect_format

    rng = np.random.default_rng(0)
    ims = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(3)]
    plain, timed, named = tmp_path / "plain", tmp_path / "timed", tmp_path / "named"
    _write_images(plain, ims, ["b.png", "a.png", "c.png"])
    _write_images(timed, ims, ["x1.png", "x2.png", "x3.png"])
    (timed / "times.txt").write_text("10.5\n11.0\n12.25\n")
    _write_images(named, ims, ["100.5.png", "101.png", "99.png"])
    from harness.errors import IngestError

    def ingest(d: Path) -> tuple[dict, pd.DataFrame]:
        o = d.parent / f"o-{d.name}"
        rep = ingest_session(SessionConfig(name=d.name, source=str(d)), IngestConfig(), o)
        return rep, pd.read_parquet(o / "frames.parquet")

    got = {}
    for d in (plain, timed):
        assert detect_format(d) == "images"
        rep, fr = ingest(d)
        assert rep["topics"]["pose_source"] == "none" and rep["frames_written"] == 3
        assert fr[["x", "y", "z", "roll", "pitch", "yaw"]].isna().all(axis=None)
        got[d.name] = fr["utime"].tolist()
    assert got["plain"] == [0, 1_000_000, 2_000_000]  # a.png, b.png, c.png: one second apart
    assert got["timed"] == [10_500_000, 11_000_000, 12_250_000]  # times.txt
    # names as seconds: in file-name order ("100.5", "101", "99") they do not increase
    with pytest.raises(IngestError, match="must increase in file-name order"):
        ingest(named)
    (named / "99.png").rename(named / "102.png")
    assert ingest(named)[1]["utime"].tolist() == [100_500_000, 101_000_000, 102_000_000]


def test_the_best_frame_is_the_brute_force_one_in_any_chunking() -> None:
    from harness.pairs.retrieval import best_frames

    rng = np.random.default_rng(1)
    db = rng.normal(size=(60, 8)).astype(np.float32)
    db_frame = np.repeat(np.arange(12), 5)
    q = rng.normal(size=(21, 8)).astype(np.float32)
    q_frame = np.repeat(np.arange(3), 7)
    d2 = ((q[:, None, :].astype(np.float64) - db[None]) ** 2).sum(-1)
    per = np.stack([d2[:, db_frame == f].min(1) for f in range(12)], 1)
    mean = np.stack([per[q_frame == i].mean(0) for i in range(3)])
    # the runner-up: the best frame more than 2 frames away from the best one, by hand
    far = np.abs(np.arange(12)[None, :] - mean.argmin(1)[:, None]) > 2
    runner = np.where(far, mean, np.inf).min(1)
    for chunk, mem in ((7, 1e-6), (60, 1.0), (1, 1e-4)):
        qf, best, score, second = best_frames(
            q, q_frame, db, db_frame, chunk_rows=chunk, memory_mb=mem, exclude=2
        )
        assert qf.tolist() == [0, 1, 2]
        assert best.tolist() == mean.argmin(1).tolist()
        assert np.allclose(score, mean.min(1), rtol=1e-5)
        assert np.allclose(second, runner, rtol=1e-5)


def test_a_pair_is_as_confident_as_its_best_match_beats_the_best_elsewhere() -> None:
    from harness.pairs.retrieval import pair_confidence

    got = pair_confidence(np.array([1.0, 2.0, 0.0, 3.0]), np.array([4.0, 2.0, 5.0, np.inf]))
    assert got.tolist() == [0.75, 0.0, 1.0, 1.0]  # 1 - 1/4; a tie; exact; no rival at all


def _frames(session: str, utimes: list[int]) -> pd.DataFrame:
    nan = float("nan")
    return pd.DataFrame(
        {"session": session, "camera": "Cam5", "utime": utimes, "x": nan, "y": nan, "yaw": nan}
    )


def test_pairs_by_name_and_by_order_as_spec_13_2_declares_them() -> None:
    """Names pair by stem (``a/0007.png`` with ``0007.jpg``), whatever the order; order pairs
    the i-th frames; a query with no such map frame is counted, not paired."""
    from harness.pairs.declared import declared_pairs

    frames = pd.concat([_frames("map", [10, 20, 30]), _frames("new", [1, 2, 3, 4])])
    names = pd.DataFrame(
        {
            "session": ["map"] * 3 + ["new"] * 4,
            "camera": "Cam5",
            "utime": [10, 20, 30, 1, 2, 3, 4],
            "name": ["c.png", "a.png", "b.png", "sub/b.jpg", "c.png", "zz.png", "a.tif"],
        }
    )
    queries = _frames("new", [1, 2, 3, 4])
    pairs, summary = declared_pairs(frames, names, "name", {}, queries)
    assert list(zip(pairs["q_utime"], pairs["r_utime"], strict=True)) == [(1, 30), (2, 10), (4, 20)]
    assert (pairs["pair_confidence"] == 1.0).all() and pairs["distance_m"].isna().all()
    assert summary["queries"] == 4 and summary["queries_without_any_reference"] == 1  # zz.png
    pairs, summary = declared_pairs(frames, names, "order", {}, queries)
    assert list(zip(pairs["q_utime"], pairs["r_utime"], strict=True)) == [(1, 10), (2, 20), (3, 30)]
    assert summary["queries_without_any_reference"] == 1  # the 4th query: the map has 3 frames


def test_frame_names_are_the_files_relative_to_their_folder(tmp_path: Path) -> None:
    from harness.ingest.config import SessionConfig
    from harness.ingest.names import session_names

    rng = np.random.default_rng(0)
    ims = [rng.integers(0, 255, (8, 8, 3), dtype=np.uint8) for _ in range(2)]
    _write_images(tmp_path / "f", ims, ["1403715273262142976.png", "1403715273312142976.png"])
    got = session_names([SessionConfig(name="s", source=str(tmp_path / "f"))])
    assert got.to_dict("list") == {
        "session": ["s", "s"],
        "camera": ["Cam5", "Cam5"],
        "utime": [1403715273262142, 1403715273312142],  # ns names, frames in µs
        "name": ["1403715273262142976.png", "1403715273312142976.png"],
    }
    assert not len(session_names([SessionConfig(name="x", source=str(tmp_path / "gone"))]))


def test_the_place_by_order_is_the_frame_and_its_neighbours() -> None:
    from harness.retrieval.places import places_by_order

    ref = pd.DataFrame({"utime": [50, 10, 40, 20, 30]})
    got = places_by_order(ref, np.array([10, 30, 50, 99]), 1)
    assert {k: v.tolist() for k, v in got.items()} == {
        10: [10, 20], 30: [20, 30, 40], 50: [40, 50], 99: [99]
    }  # fmt: skip
    assert places_by_order(ref, np.array([30]), 0)[30].tolist() == [30]


def test_two_image_folders_from_nothing_as_the_readme_types_it(
    small_world: Path, tmp_path: Path
) -> None:
    """``harness detect --map-images DIR --query-images DIR --out OUT``: every output, no pose."""
    line = next(x for x in README.splitlines() if x.startswith("harness detect --map-images"))
    assert line == "harness detect --map-images DIR --query-images DIR --out OUT"
    m = _session_images(small_world, "ros1/2012-03-31*", tmp_path / "im", 2)
    q = _session_images(small_world, "ros2/2012-08-04*", tmp_path / "iq", 2)
    ns = [f"{1403715273262142976 + i * 50_000_000}.png" for i in range(len(m))]  # EuRoC's names
    _write_images(tmp_path / "map", m, ns)
    _write_images(tmp_path / "new", q, [f"q{i:02d}.png" for i in range(len(q))])
    argv = line.split()[1:]
    argv[argv.index("--map-images") + 1] = str(tmp_path / "map")
    argv[argv.index("--query-images") + 1] = str(tmp_path / "new")
    argv[argv.index("--out") + 1] = str(tmp_path / "out")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    printed = buf.getvalue()
    out = tmp_path / "out"
    for f in ("detections.json", "images.json", "frames.parquet", "frames.csv", "alarms.csv",
              "trajectory.png", "detect.html", "detect.json"):  # fmt: skip
        assert (out / f).stat().st_size > 0, f
    rec = json.loads((out / "detect.json").read_text())
    # the most changed places (their LoC maps) are the frames whose pairs were registered
    ok = rec["not_comparable"]["of_frames"] - rec["not_comparable"]["frames"]
    assert len(list((out / "locmaps").glob("*.npy"))) == min(ok, 10)
    assert rec["map"] == "map" and rec["queries"] == ["query"] and rec["query_frames"] == 2
    # names the folders do not share: pairs by sequence, each with its confidence; no frame here
    # is too dark to carry a place, no map frame is a hub, and there are no poses to compare with
    pairing = rec["pairing"]
    assert {k: pairing[k] for k in ("by", "place_frames")} == {"by": "sequence", "place_frames": 2}
    assert pairing["no_place"]["frames"] == [] and pairing["hubs"] == []
    assert "agreement_with_pose_pairs" not in pairing
    assert "pairs by sequence (method §13.2)" in printed and "no poses to compare with" in printed
    fr = pd.read_parquet(out / "frames.parquet")
    assert fr["x"].isna().all() and len(fr) == 2
    assert fr["pair_confidence"].between(0, 1).all() and fr["uncertain_pair"].dtype == bool
    assert fr["name"].tolist() == ["q00.png", "q01.png"]  # the user's file names
    assert set(fr["r_name"]) <= set(ns)  # the map's ns-named files, read as times in ns
    page = (out / "detect.html").read_text()
    assert 'id="trajectory">When</h2>' in page and "have no poses" in page
    assert "nan" not in page.split('id="places"')[1]  # no coordinates where there are none
    # the README's second form, the fixture's small-frame settings from a config, on two folders
    # that share their names (written in another order): pairs by name, every one right
    rng = np.random.default_rng(3)
    m = _session_images(small_world, "ros1/2012-03-31*", tmp_path / "im6", 6)
    q = _session_images(small_world, "ros2/2012-08-04*", tmp_path / "iq6", 6)
    names = [f"tile_{i:03d}.png" for i in rng.choice(1000, 6, replace=False)]
    for d, ims in (("same-map", m), ("same-new", q)):
        order = rng.permutation(6)  # the files are written to disk in another order
        _write_images(tmp_path / d, [ims[i] for i in order], [names[i] for i in order])
    line = next(
        x
        for x in README.splitlines()
        if x.startswith("harness detect --config datasets/fixture-detect.toml --map-images")
    )
    argv = line.split()[1:]
    argv[argv.index("--map-images") + 1] = str(tmp_path / "same-map")
    argv[argv.index("--query-images") + 1] = str(tmp_path / "same-new")
    argv[argv.index("--out") + 1] = str(tmp_path / "out2")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    printed = buf.getvalue()
    out2 = tmp_path / "out2"
    rec2 = json.loads((out2 / "detect.json").read_text())
    assert rec2["pairing"]["by"] == "name" and rec2["query_frames"] == 6
    assert "pairs by name (method §13.2)" in printed
    fr2 = pd.read_csv(out2 / "frames.csv")
    assert (fr2["name"] == fr2["r_name"]).all() and sorted(fr2["name"]) == sorted(names)
    assert (fr2["pair_confidence"] == 1).all() and not fr2["uncertain_pair"].any()
    images = json.loads((out2 / "images.json").read_text())["images"]
    assert sorted(i["file_name"] for i in images) == sorted(names)
    assert all(Path(i["path"]).parent == tmp_path / "same-new" for i in images)
    page = (out2 / "detect.html").read_text()
    # the console and the page name frames by their files: the most changed of the pairs that
    # registered, and every pair that did not (these small frames hold few keypoints)
    ok = fr2[fr2["comparable"].astype(bool)]
    for name in fr2.loc[~fr2["comparable"].astype(bool), "name"]:
        assert name in page.split('data-not-comparable="')[1].split("</p>")[0], name
    if len(ok):
        top = ok.sort_values("score", ascending=False)["name"].iloc[0]
        assert f"  {top}: " in printed
        assert f"<figcaption>query {top} (" in page and f"<figcaption>map {top}<" in page
        assert f">1. {top}: change score" in page
    # the local localizer on folders paired by name: no model, every subimage ranked in its pair
    argv_local = ["detect", "--map-images", str(tmp_path / "same-map"), "--query-images",
                  str(tmp_path / "same-new"), "--localizer", "local", "--boxes", "subimages",
                  "--out", str(tmp_path / "out-local")]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv_local) == 0
    rec_l = json.loads((tmp_path / "out-local" / "detect.json").read_text())
    assert rec_l["pairing"]["by"] == "name" and rec_l["localizers"] == ["local"]
    assert not (tmp_path / "out-local" / "cache" / "model").exists()
    assert sum(rec_l["local_counts"].values()) > 0
    # folders paired by name are no sequence: the no-change null is perturbed copies of the six
    # map frames, and the alarms say against what (docs/decisions.md, *Calibrated alarms*)
    said = [x for x in printed.splitlines() if x.startswith("alarms: ")]
    assert rec2["calibration"]["method"] == "null", rec2["calibration"]
    assert rec2["calibration"]["construction"] == "perturbed"
    assert rec2["calibration"]["pairs"] == 100 and rec2["calibration"]["copies_per_map_frame"] == 17
    assert re.fullmatch(r"alarms: \d of 6 frames and \d+ of \d+ change boxes exceed the "
                        r"false-alarm rate 0\.01 \(null: 100 no-change pairs from the map, "
                        r"perturbed; alarms\.csv\)", said[0]), said  # fmt: skip
    flagged = int(said[0].split()[1])
    assert page.count('data-alarmed="1"') == min(flagged, 6)
    assert f"data-alarms='{flagged}' data-calibration='null'" in page
    # the README's annotated forms, as typed, on the first run's folders and into its run
    # directory (its model and descriptors are reused): a mask with a change and an empty one,
    # then an annotation CSV by file name
    (tmp_path / "masks").mkdir()
    h, w = cv2.imread(str(tmp_path / "new" / "q00.png")).shape[:2]
    mask = np.zeros((h, w), np.uint8)
    mask[h // 4 : h // 2, w // 4 : w // 2] = 255
    cv2.imwrite(str(tmp_path / "masks" / "q00.png"), mask)
    cv2.imwrite(str(tmp_path / "masks" / "q01.png"), np.zeros((h, w), np.uint8))
    csv = tmp_path / "ann.csv"
    csv.write_text("image,status,x1,y1,x2,y2,label\nq00.png,change,2,3,20,30,box\n"
                   "q01.png,no-change,,,,,\n")  # fmt: skip
    for flag, value in (("--masks", tmp_path / "masks"), ("--annotations", csv)):
        line = next(x for x in README.splitlines() if x.startswith("harness detect --map-images")
                    and flag in x)  # fmt: skip
        argv = line.split()[1:]
        for k, v in (("--map-images", tmp_path / "map"), ("--query-images", tmp_path / "new"),
                     (flag, value), ("--out", out)):  # fmt: skip
            argv[argv.index(k) + 1] = str(v)
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(argv) == 0, flag
        d = pd.read_csv(out / "tableD.csv")
        assert (int(d["annotated_frames"].iloc[0]), int(d["change_boxes"].iloc[0])) == (2, 1)
        rec = json.loads((out / "detect.json").read_text())
        if flag == "--masks":  # the masks are also the truth of a pixel AP (method §13.2)
            px = pd.read_csv(out / "tableD_pixel.csv")
            assert list(px["masked_frames"].unique()) == [2] and len(rec["table_d_pixel"]) == 5
            # the rows: the LoC map, random, the two no-pixel rows, and the plain difference
            # (each box's score in the registered pair's difference: pixels, no localizer)
            assert px["row"].str.startswith("plain difference").sum() == 1
            # the change is a quarter by a quarter of q00: 1/16 of one image's pixels in two
            assert px["positive_rate"].iloc[0] == pytest.approx(1 / 32, abs=1e-4)
            assert set(px["verdict"]) == {"few"}  # one positive image earns no verdict
            assert "data-table='DP'" in (out / "detect.html").read_text()
        else:
            assert rec["table_d_pixel"] is None and not (out / "tableD_pixel.csv").exists()
    assert (
        not (out / "cache" / "model").exists()
        or len(list((out / "cache" / "model").iterdir())) == 1
    )


def test_image_folder_flags_are_checked_in_one_line(tmp_path: Path, capsys) -> None:
    from ..conftest import one_error

    (tmp_path / "m").mkdir()
    for argv, says in (
        (["--map-images", str(tmp_path / "m")], "go together"),
        (["--map-images", str(tmp_path / "nope"), "--query-images", str(tmp_path / "m")],
         "is not a folder of images"),
        (["--map", "x", "--map-images", str(tmp_path / "m"), "--query-images", str(tmp_path / "m")],
         "omit them"),
        ([], "--map-images DIR and --query-images DIR"),
        (["--map-images", str(tmp_path / "m"), "--query-images", str(tmp_path / "m")],
         "holds no image file"),
    ):  # fmt: skip
        assert main(["detect", *argv, "--out", str(tmp_path / "o")]) == 1
        assert says in one_error(capsys)


def test_pairs_by_name_of_sessions_without_file_names_is_one_error(
    default_world: Path, tmp_path: Path, capsys
) -> None:
    from ..conftest import ROOT, one_error

    cfg = (ROOT / "datasets" / "fixture.toml").read_text()
    cfg = cfg.replace('queries = "annotated"', 'queries = "annotated"\nby = "name"')
    cfg = cfg.replace('"annotations/', f'"{ROOT}/annotations/').replace(
        '"datasets/models"', f'"{ROOT}/datasets/models"'
    )
    (tmp_path / "c.toml").write_text(cfg)
    argv = ["pairs", "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "o"),
            "--data-root", str(default_world)]  # fmt: skip
    assert main(argv) == 1
    err = one_error(capsys)
    assert "by = 'name'" in err and "no session is a folder of images" in err


@pytest.mark.parametrize("key", ["db_stride_m", "gt_radius_also"])
def test_retrieval_pairs_refuse_what_needs_poses(tmp_path: Path, key: str, capsys) -> None:
    from ..conftest import ROOT, one_error

    cfg = (ROOT / "datasets" / "fixture.toml").read_text()
    cfg = cfg.replace('queries = "annotated"', 'queries = "annotated"\nby = "retrieval"')
    if key == "db_stride_m":
        cfg += "\n[retrieval]\ndb_stride_m = 4.0\n"
    else:
        cfg = cfg.replace("[report]", "[report]\ngt_radius_also = 4.0")
    (tmp_path / "c.toml").write_text(cfg)
    assert main(["pairs", "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "o")]) == 1
    err = one_error(capsys)
    assert key in err and "by = 'retrieval'" in err


def test_reproduce_by_retrieval_pairs_as_the_descriptors_say_and_agrees_as_the_readme_quotes(
    local_run: tuple, tmp_path: Path
) -> None:
    """``[pairs] by = "retrieval"`` on the fixture, from a copy of the pose run's cache (the same
    proposals, model and descriptors): one pair recomputed from the descriptor files by hand, the
    agreement with the pose pairs recomputed from both runs' pair files, the README's figures."""
    import dataclasses
    import shutil

    from harness.pipeline.chain import Pipeline

    text = README

    p, rec0, out = local_run
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    cfg = dataclasses.replace(p.cfg, pairs=dataclasses.replace(p.cfg.pairs, by="retrieval"))
    q = Pipeline(cfg, tmp_path)
    rec = q.run()
    assert q.ran.get("model", 0) == 0 and q.ran.get("descriptors", 0) == 0  # reused
    run = json.loads((tmp_path / "run.json").read_text())
    agree = run["pairing"]["agreement_with_pose_pairs"]
    # the retrieval pairs, and one of them by hand from the descriptor files
    (entry,) = (tmp_path / "cache" / "pairs_retrieval").iterdir()
    rp = pd.read_parquet(entry / "pairs.parquet")
    row = rp.iloc[0]
    desc = {
        s: tmp_path / "cache" / "descriptors" / k for s, k in _descriptor_keys(tmp_path).items()
    }

    def rows(session: str) -> tuple[pd.DataFrame, np.ndarray]:
        idx = pd.read_parquet(desc[session] / "index.parquet")
        keep = (idx["proposal_method"] == "grid5").to_numpy()
        return idx[keep], np.load(desc[session] / "desc.npy")[keep].astype(np.float64)

    qi, qd = rows(row.q_session)
    qd = qd[(qi["utime"] == row.q_utime).to_numpy()]
    ri, rd = rows(row.r_session)
    per_frame = {
        u: (((qd[:, None] - rd[(ri["utime"] == u).to_numpy()][None]) ** 2).sum(-1)).min(1).mean()
        for u in sorted(ri["utime"].unique())
    }
    assert min(per_frame, key=per_frame.get) == row.r_utime
    # agreement, from the pose run's pairs and the frames
    pose = pd.read_parquet(out / "cache" / "pairs" / rec0["keys"]["pairs"] / "pairs.parquet")
    frames = pd.read_parquet(out / "cache" / "frames" / rec0["keys"]["frames"] / "frames.parquet")
    xy = frames.set_index(["session", "camera", "utime"])[["x", "y"]]
    m = rp.merge(pose, on=["q_session", "q_camera", "q_utime", "r_session"], suffixes=("", "_p"))
    a = xy.loc[list(zip(m.r_session, m.r_camera, m.r_utime, strict=True))].to_numpy()
    b = xy.loc[list(zip(m.r_session, m.r_camera_p, m.r_utime_p, strict=True))].to_numpy()
    dist = np.linalg.norm(a - b, axis=1)
    assert agree["compared"] == len(m) and agree["agree"] == int((dist <= 10.0).sum())
    assert agree["median_m"] == pytest.approx(float(np.median(dist)), abs=1e-3)
    # chance: a map frame drawn uniformly from the session, within 10 m of the pose pair's frame
    chance = [
        float((np.linalg.norm(xy.loc[s].to_numpy() - p_, axis=1) <= 10.0).mean())
        for s, p_ in zip(m.r_session, b, strict=True)
    ]
    assert agree["chance_share"] == pytest.approx(np.mean(chance), abs=1e-4)
    assert agree["share_ci_low"] < agree["share"] < agree["share_ci_high"]
    # the README quotes this run
    share = round(100 * agree["agree"] / agree["compared"])
    r1 = pd.read_csv(tmp_path / "localization.csv")
    r1_pose = pd.read_csv(out / "localization.csv")

    def all_r1(df: pd.DataFrame) -> float:
        sel = (df["proposal_method"] == "all") & (df["season_pair"] == "all")
        return float(df[sel]["recall_at_1"].iloc[0])

    ci = f"{100 * agree['share_ci_low']:.0f}-{100 * agree['share_ci_high']:.0f}%"
    quoted = (
        f"{agree['agree']} of the {agree['compared']} retrieval pairs ({share}%, 95% interval "
        f"{ci}) lie within 10 m of the pose pair, where a map frame drawn at random would in "
        f"{100 * agree['chance_share']:.0f}%"
    )
    flat = " ".join(text.split())
    assert " ".join(quoted.split()) in flat
    assert f"R@1 then reads {all_r1(r1):.2f} against {all_r1(r1_pose):.2f} by pose" in flat
    assert f"(median {agree['median_m']:g} m" in flat
    assert "Pairs by retrieval (method §13.2)" in (tmp_path / "tableS.md").read_text()
    assert rec["reports"] is not None


def _descriptor_keys(out: Path) -> dict[str, str]:
    """Session -> its descriptor entry, from the entries' manifests."""
    got = {}
    for e in (out / "cache" / "descriptors").iterdir():
        idx = pd.read_parquet(e / "index.parquet", columns=["session"])
        if len(idx):
            got.setdefault(str(idx["session"].iloc[0]), e.name)
    return got


def test_each_pairing_mode_agrees_with_the_pose_pairs_as_the_readme_quotes(
    local_run: tuple,
) -> None:
    """method §13.2's modes on a set with known truth: the fixture's four traverses, every frame a
    query of each other session (twelve pairs of traverses), the poses the truth. Each mode's
    share of pairs within 10 m of the pose pair, from the fixture run's own descriptors, is the
    README's; sequence beats retrieval (the default for folders that share no names)."""
    from harness.pairs.agreement import pose_agreement
    from harness.pairs.config import PairsConfig
    from harness.pairs.declared import declared_pairs
    from harness.pairs.pose import build_pairs
    from harness.pairs.retrieval import candidate_pairs, retrieval_pairs

    _, rec, out = local_run
    frames = pd.read_parquet(out / "cache" / "frames" / rec["keys"]["frames"] / "frames.parquet")
    desc = {}
    for d in (out / "cache" / "descriptors").iterdir():
        desc[str(pd.read_parquet(d / "index.parquet")["session"].iloc[0])] = d
    seasons = {s: s for s in frames["session"].unique()}
    cand = candidate_pairs(frames, seasons)
    pose, _ = build_pairs(frames, PairsConfig(), seasons)
    none = pd.DataFrame(columns=["session", "camera", "utime", "name"])
    got = {"order": pose_agreement(declared_pairs(frames, none, "order", seasons)[0], pose,
                                   frames, 10.0)}  # fmt: skip
    left = {}
    for mode, window in (("retrieval", 0), ("sequence", PairsConfig().sequence_frames)):
        pairs, summary = retrieval_pairs(cand, desc, frames, "grid5", 256.0, 2, window)
        got[mode] = pose_agreement(pairs, pose, frames, 10.0)
        left[mode] = len(summary.get("unpaired", []))
    # every query frame paired, or (by sequence) left unpaired and named
    assert {a["compared"] + left.get(m, 0) for m, a in got.items()} == {768}
    assert left["retrieval"] == 0 and left["sequence"] <= 4
    assert got["sequence"]["share"] > got["retrieval"]["share"] > got["order"]["share"]
    from ..stage_digests import skip_unless_recorded_model

    skip_unless_recorded_model(out)  # the README's figures: the recorded model's
    flat = " ".join(README.split())
    for mode, a in got.items():
        quoted = (
            f"| `{mode}` | {a['agree']} of {a['compared']} ({100 * a['share']:.0f}%, "
            f"{100 * a['share_ci_low']:.0f}-{100 * a['share_ci_high']:.0f}%) |"
        )
        assert quoted in flat, quoted


def test_a_mask_becomes_its_components_boxes_and_an_empty_one_a_no_change_row(
    tmp_path: Path,
) -> None:
    """method §13.2's masks by hand: two blobs and one speck under ``min_mask_area``."""
    from harness.ingest.masks import mask_boxes, read_masks

    m = np.zeros((40, 60), np.uint8)
    m[5:15, 10:30] = 255  # 200 pixels: a box [10, 5, 30, 15]
    m[20:36, 40:44] = 255  # 64 pixels: [40, 20, 44, 36]
    m[38, 2] = 255  # 1 pixel: under the area
    boxes, small = mask_boxes(m, 16)
    assert sorted(map(tuple, boxes.tolist())) == [(10, 5, 30, 15), (40, 20, 44, 36)]
    assert small == 1
    (tmp_path / "m").mkdir()
    cv2.imwrite(str(tmp_path / "m" / "a.png"), m)
    cv2.imwrite(str(tmp_path / "m" / "b.png"), np.zeros((40, 60), np.uint8))
    rows, counts = read_masks(tmp_path / "m", 16)
    assert counts == {"masks": 2, "no_change": 1, "change_boxes": 2, "small_components": 1}
    assert rows.groupby("image")["status"].agg(list).to_dict() == {
        "a.png": ["change", "change"],
        "b.png": ["no-change"],
    }
    assert set(rows["mask_width"]) == {60} and set(rows["mask_height"]) == {40}


def test_pixel_ap_of_a_loc_map_against_a_mask_by_hand() -> None:
    """method §9's pixel AP on a 10 x 10 image whose 4 x 4 corner changed, two nested boxes.

    The small box [0, 0, 4, 4] owns the 16 change pixels, the large one [0, 0, 10, 10] the other
    84. Scored small over large, the change pixels come first: AP 1. Scored the other way round,
    the 84 unchanged pixels come first and precision never exceeds 16/100: AP 0.16. The ceiling
    scores each box by its share of change pixels (1 and 0.16): AP 1.
    """
    from harness.detect.pixels import masked_frame
    from harness.evaluate.table_d_pixel import box_change_fraction, pixel_table

    mask = np.zeros((10, 10), np.uint8)
    mask[:4, :4] = 255
    boxes = np.array([[0, 0, 4, 4], [0, 0, 10, 10]], np.float64)
    f = masked_frame(boxes, np.array([0.9, 0.1]), mask)
    assert f.area.sum() == 100
    assert sorted(zip(f.owner.tolist(), f.positive.tolist(), f.area.tolist(), strict=True)) == [
        (0, True, 16.0),
        (1, False, 84.0),
    ]
    assert box_change_fraction(boxes, mask > 0).tolist() == [1.0, 0.16]
    t = pixel_table([f], draws=50, n_boot=20, ci=0.95, seed=0).set_index("row")
    assert t.loc["detector (LoC map)", "pixel_ap"] == pytest.approx(1.0)
    assert t["ceiling"].iloc[0] == pytest.approx(1.0)
    assert t["positive_rate"].iloc[0] == pytest.approx(0.16)
    assert t.loc["detector (LoC map)", "verdict"] == "few"  # one image: no verdict (method §9)
    swapped = masked_frame(boxes, np.array([0.1, 0.9]), mask)
    t2 = pixel_table([swapped], draws=50, n_boot=20, ci=0.95, seed=0).set_index("row")
    assert t2.loc["detector (LoC map)", "pixel_ap"] == pytest.approx(0.16)
    # box area ranks the large box first, as the swapped LoC does
    assert t2.loc["size_prior (box area, no pixel read)", "pixel_ap"] == pytest.approx(0.16)
    # an image no box covers: every pixel takes the lowest score; a mask with no change adds
    # negatives only
    empty = masked_frame(np.zeros((0, 4)), np.zeros(0), np.zeros((10, 10), np.uint8))
    t3 = pixel_table([f, empty], draws=50, n_boot=20, ci=0.95, seed=0).set_index("row")
    assert t3["positive_rate"].iloc[0] == pytest.approx(16 / 200)
    # the empty image's 100 pixels tie with the large box's at the lowest LoC
    assert t3.loc["detector (LoC map)", "pixel_ap"] == pytest.approx(1.0)
    # the plain-difference row scores the boxes by their difference through the same
    # maps: the large box's higher contrast puts the 84 unchanged pixels first, AP 0.16; it is a
    # row only where every masked image has its pair's difference
    row = "plain difference, registered (box contrast, pixels, no localizer)"
    assert row not in t.index
    d = masked_frame(boxes, np.array([0.9, 0.1]), mask, np.array([0.2, 0.7]))
    t4 = pixel_table([d], draws=50, n_boot=20, ci=0.95, seed=0).set_index("row")
    assert t4.loc[row, "pixel_ap"] == pytest.approx(0.16)
    assert t4.loc["detector (LoC map)", "best_no_pixel"] in ("size_prior", "cover_count",
                                                             "difference_same_boxes")  # fmt: skip


def test_rows_that_name_their_image_find_their_frame_or_say_why_in_one_line() -> None:
    from harness.errors import AnnotationError
    from harness.ingest.names import frames_by_image

    names = pd.DataFrame(
        {
            "session": ["map", "map", "query", "query2"],
            "camera": "Cam5",
            "utime": [1, 2, 1, 5],
            "name": ["a.png", "b.png", "a.jpg", "c.png"],
        }
    )
    frames = names.assign(width=60, height=40)
    rows = pd.DataFrame({"image": ["a.png", "c.png"], "status": ["no-change", "no-change"]})
    got = frames_by_image(rows, names, frames, {"map"}, "f.csv")
    assert got[["session", "utime"]].values.tolist() == [["query", 1], ["query2", 5]]
    for bad, says in (
        (pd.DataFrame({"image": ["zz.png"]}), "f.csv: line 2: no image named 'zz.png'"),
        (pd.DataFrame({"image": ["a.png"]}), None),  # the map's is skipped: the query's
        (pd.DataFrame({"image": ["b.png"], "mask_width": [61], "mask_height": [40]}),
         "the mask is 61 x 40 pixels, its image 'b.png' 60 x 40"),
    ):  # fmt: skip
        if says is None:
            assert frames_by_image(bad, names, frames, {"map"}, "f.csv")["session"].tolist() == [
                "query"
            ]
            continue
        with pytest.raises(AnnotationError, match=re.escape(says)):
            frames_by_image(bad, names, frames, {"map"}, "f.csv")
    with pytest.raises(AnnotationError, match="in several sessions"):
        frames_by_image(pd.DataFrame({"image": ["a.png"]}), names, frames, set(), "f.csv")


NORDLAND = ROOT.parent / "shared" / "realdata" / "nordland-dev"


@pytest.mark.skipif(
    not (NORDLAND / "winter").is_dir(),
    reason=f"no real seasons here: {NORDLAND} is absent (shared/realdata is read, never committed)",
)
def test_two_folders_of_real_seasons_pair_without_training(tmp_path: Path) -> None:
    """Issue 64: a train ride filmed in summer and winter, in step (frame i is frame i), the winter
    frames renamed so no name is shared. Paired by sequence with the training-free default
    (SeqSLAM's patch-normalised thumbnails, no model trained): at least 75% of the winter frames
    within 2 frames of their own summer frame, as docs/decisions.md quotes it."""
    winter = tmp_path / "w"
    winter.mkdir()
    for i, f in enumerate(sorted((NORDLAND / "winter").iterdir())):
        shutil.copy(f, winter / f"w{i:04d}.png")
    out = tmp_path / "out"
    # the pairing is what is read here: calibrated within the run, no null scored
    argv = ["detect", "--map-images", str(NORDLAND / "summer"), "--query-images", str(winter),
            "--calibration", "within-run", "--out", str(out)]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0
    rec = json.loads((out / "detect.json").read_text())
    assert rec["pairing"]["by"] == "sequence"
    assert not list((out / "cache").rglob("autoencoder.pt"))  # nothing trained to pair
    fr = pd.read_csv(out / "frames.csv")
    q = fr["name"].str.slice(1, 5).astype(int)
    m = (fr["r_name"].str.extract(r"images-(\d+)")[0].astype(int) - 3010) // 10
    share = float(np.mean(np.abs(m - q) <= 2))
    assert share >= 0.75, share
    quoted = " ".join((ROOT / "docs" / "decisions.md").read_text().split())
    assert f"{round(100 * share)}% of the 300 winter frames within 2 frames" in quoted
