"""Sessions without poses (SPEC 13.2): folders of images alone, pairs by retrieval.

The README's two-folder command runs here as typed, on images the test writes; the pairing's
kernel is checked against a brute-force computation, the place by order by hand, and the images
format's times and order on small folders.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.cli import main

from ..readme_text import README as README_PATH

README = README_PATH.read_text()


def _write_images(folder: Path, images: list[np.ndarray], names: list[str]) -> None:
    folder.mkdir(parents=True)
    for im, n in zip(images, names, strict=True):
        cv2.imwrite(str(folder / n), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))


def _session_images(world: Path, fmt_glob: str, tmp: Path, n: int) -> list[np.ndarray]:
    """The first ``n`` upright RGB frames of a fixture session, ingested by the harness."""
    from harness.config.schema import IngestConfig, SessionConfig
    from harness.imagestore import read_image
    from harness.ingest import ingest_session

    src = sorted(world.glob(fmt_glob))[0]
    ingest_session(SessionConfig(name="s", source=str(src)), IngestConfig(), tmp)
    fr = pd.read_parquet(tmp / "frames.parquet").sort_values("utime").head(n)
    return [read_image(str(tmp / u)) for u in fr["image"]]


def test_an_images_folder_is_a_session_in_name_order_with_no_pose(tmp_path: Path) -> None:
    from harness.config.schema import IngestConfig, SessionConfig
    from harness.ingest import ingest_session
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
    from harness.retrieval.pairing import best_frames

    rng = np.random.default_rng(1)
    db = rng.normal(size=(60, 8)).astype(np.float32)
    db_frame = np.repeat(np.arange(12), 5)
    q = rng.normal(size=(21, 8)).astype(np.float32)
    q_frame = np.repeat(np.arange(3), 7)
    d2 = ((q[:, None, :].astype(np.float64) - db[None]) ** 2).sum(-1)
    per = np.stack([d2[:, db_frame == f].min(1) for f in range(12)], 1)
    mean = np.stack([per[q_frame == i].mean(0) for i in range(3)])
    for chunk, mem in ((7, 1e-6), (60, 1.0), (1, 1e-4)):
        qf, best, score = best_frames(q, q_frame, db, db_frame, chunk_rows=chunk, memory_mb=mem)
        assert qf.tolist() == [0, 1, 2]
        assert best.tolist() == mean.argmin(1).tolist()
        assert np.allclose(score, mean.min(1), rtol=1e-5)


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
    _write_images(tmp_path / "map", m, [f"m{i:02d}.png" for i in range(len(m))])
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
    assert list((out / "locmaps").glob("*.npy"))
    rec = json.loads((out / "detect.json").read_text())
    assert rec["map"] == "map" and rec["queries"] == ["query"] and rec["query_frames"] == 2
    assert rec["pairing"] == {"by": "retrieval", "place_frames": 2}  # no poses: nothing to compare
    assert "pairs by retrieval (SPEC 13.2)" in printed and "no poses to compare with" in printed
    fr = pd.read_parquet(out / "frames.parquet")
    assert fr["x"].isna().all() and len(fr) == 2
    page = (out / "detect.html").read_text()
    assert 'id="trajectory">When</h2>' in page and "have no poses" in page
    # the README's second form: the fixture's small-frame settings from a config
    line = next(
        x
        for x in README.splitlines()
        if x.startswith("harness detect --config datasets/fixture-detect.toml --map-images")
    )
    argv = line.split()[1:]
    argv[argv.index("--map-images") + 1] = str(tmp_path / "map")
    argv[argv.index("--query-images") + 1] = str(tmp_path / "new")
    argv[argv.index("--out") + 1] = str(tmp_path / "out2")
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0
    rec2 = json.loads((tmp_path / "out2" / "detect.json").read_text())
    assert rec2["pairing"]["by"] == "retrieval" and rec2["query_frames"] == 2
    assert (tmp_path / "out2" / "detect.html").exists()


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
    assert "Pairs by retrieval (SPEC 13.2)" in (tmp_path / "tableS.md").read_text()
    assert rec["reports"] is not None


def _descriptor_keys(out: Path) -> dict[str, str]:
    """Session -> its descriptor entry, from the entries' manifests."""
    got = {}
    for e in (out / "cache" / "descriptors").iterdir():
        idx = pd.read_parquet(e / "index.parquet", columns=["session"])
        if len(idx):
            got.setdefault(str(idx["session"].iloc[0]), e.name)
    return got
