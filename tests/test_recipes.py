"""docs/architecture.md's "Where to add" recipes, each done for a toy case."""

from __future__ import annotations

import copy
import dataclasses
import re
import shutil
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.pipeline.chain import Pipeline

ROOT = Path(__file__).resolve().parents[1]


def test_recipe_a_toy_descriptor_in_under_30_lines(
    local_run: tuple, tmp_path: Path, monkeypatch
) -> None:
    # --- the recipe: subclass Descriptor, implement encode, register it, select it by name ---
    from harness.descriptors import REGISTRY, Descriptor

    class MeanColour(Descriptor):
        """The crop's mean RGB and its 2x2 block means (15 dims)."""

        name = "mean_colour"

        def encode(self, crops: np.ndarray) -> np.ndarray:
            c = crops.astype(np.float32) / 255
            h, w = c.shape[1] // 2, c.shape[2] // 2
            blocks = [
                c[:, i * h : (i + 1) * h, j * w : (j + 1) * w].mean((1, 2))
                for i in (0, 1)
                for j in (0, 1)
            ]
            return np.concatenate([c.mean((1, 2)), *blocks], axis=1)

    monkeypatch.setitem(REGISTRY, "mean_colour", MeanColour)
    p, _, _ = local_run
    cfg = dataclasses.replace(
        p.cfg, descriptor=dataclasses.replace(p.cfg.descriptor, name="mean_colour")
    )
    # --- end of the recipe (the rest checks it) ---
    q, rec = _rerun(local_run, tmp_path, cfg)
    assert (
        q.ran.get("proposals", 0) == 0 and q.ran["descriptor_shards"] > 0
    )  # only what depends on it reran
    key = rec["cache_entries"]["descriptors"][0]
    assert np.load(tmp_path / "cache" / "descriptors" / key / "desc.npy").shape[1] == 15
    loc = pd.read_csv(tmp_path / "localization.csv")
    assert (
        loc["subimages"].max() > 0
        and 0 < loc.loc[loc["proposal_method"] == "all", "recall_at_1"].iloc[0] < 1
    )
    assert (tmp_path / "table1.csv").exists()


@pytest.fixture()
def registries():
    """The method catalogue's registries as they were before the test (a recipe adds to them)."""
    from harness import methods
    from harness.localizers.kinds import LOCALIZER_KINDS

    regs = (
        methods.PROPOSERS,
        methods.PROPOSER_OPTIONS,
        methods.FUSION_RULES,
        methods.FUSION_OPTIONS,
        methods.METHOD_LABELS,
        LOCALIZER_KINDS,
    )
    saved = [(d, dict(d)) for d in regs]
    yield methods
    for d, before in saved:
        d.clear()
        d.update(before)


def _rerun(local_run: tuple, tmp_path: Path, cfg) -> tuple[Pipeline, dict]:
    """``cfg`` run into ``tmp_path`` from a copy of the fixture run's cache, without the figures
    and the page (no recipe here checks them; they cost seconds per run)."""
    _, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    cfg = dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, plots=False, html=False))
    q = Pipeline(cfg, tmp_path)
    return q, q.run()


def test_recipe_a_toy_proposal_method(local_run: tuple, tmp_path: Path, registries) -> None:
    from harness import methods
    from harness.config.assemble import load_config
    from harness.config.check import validate
    from harness.errors import ConfigError
    from harness.proposals import proposers as proposals

    # --- the recipe: a function of the upright image and its options, registered, listed ---

    @dataclasses.dataclass(frozen=True)
    class CentreOptions:
        frac: float = 0.25  # the box's side, as a share of the image's

    def centre(rgb: np.ndarray, cfg: object) -> tuple[np.ndarray, np.ndarray]:
        """One box: the image's central ``frac`` (x1, y1, x2, y2 pixels), score 1."""
        h, w = rgb.shape[:2]
        f = cfg.options_of("centre").frac  # type: ignore[attr-defined]
        return np.array([[w * (1 - f) / 2, h * (1 - f) / 2, w * (1 + f) / 2, h * (1 + f) / 2]]), [1]

    proposals.register_proposer("centre", centre, options=CentreOptions)
    toml = 'methods = ["grid5", "centre"]\n\n[proposals.centre]\nfrac = 0.5\n'
    # --- end of the recipe (the rest checks it) ---
    p, _, _ = local_run
    text = (ROOT / "datasets" / "fixture.toml").read_text()
    conf = tmp_path / "centre.toml"
    conf.write_text(text.replace('methods = ["grid5", "edges"]\n', toml))
    cfg = load_config(conf, data_root=str(p.cfg.data_root))
    assert cfg.proposals.options_of("centre") == CentreOptions(0.5)
    # its table is checked as the built-ins' are: unknown keys, wrong types
    for wrong, says in (("side = 2", "unknown key(s) ['side']"), ('frac = "half"', "frac")):
        bad = toml.replace("frac = 0.5", wrong)
        conf.write_text(text.replace('methods = ["grid5", "edges"]\n', bad))
        with pytest.raises(ConfigError, match=re.escape(says)):
            load_config(conf, data_root=str(p.cfg.data_root))
    # the new crops retrain the model: a sixth of the fixture's budget is enough to show it
    cfg = dataclasses.replace(
        cfg,
        annotations=p.cfg.annotations,
        descriptor=dataclasses.replace(cfg.descriptor, train_samples=1000),
    )
    validate(cfg, "recipe")  # the name is known to the config check
    with pytest.raises(ValueError, match="exists"):
        proposals.register_proposer("edges", centre)
    with pytest.raises(ValueError, match="exists"):  # [proposals]'s own keys are taken too
        proposals.register_proposer("reduced_decode", centre)
    with pytest.raises(ValueError, match="options must be a dataclass"):
        proposals.register_proposer("half", centre, options=dict)
    q, rec = _rerun(local_run, tmp_path, cfg)
    assert q.ran["proposals"] > 0 and q.ran.get("model", 0) > 0  # the training crops changed
    props = pd.concat(
        pd.read_parquet(tmp_path / "cache" / "proposals" / k / "proposals.parquet")
        for k in rec["cache_entries"]["proposals"]
    )
    cen = props[props["proposal_method"] == "centre"]
    frames = props[["session", "utime"]].drop_duplicates()
    assert len(cen) == len(frames) and set(props["proposal_method"]) == {"grid5", "centre"}
    fr = pd.read_parquet(tmp_path / "cache" / "frames" / rec["keys"]["frames"] / "frames.parquet")
    got = cen.merge(fr, on=["session", "camera", "utime"])
    assert np.allclose(got[["x1", "x2"]], np.c_[got["width"] / 4, 3 * got["width"] / 4])
    assert np.allclose(got[["y1", "y2"]], np.c_[got["height"] / 4, 3 * got["height"] / 4])
    # another value of the option: another proposals key (and nothing else of the config)
    other = dataclasses.replace(cfg.proposals, options={"centre": CentreOptions(0.75)})
    from harness.proposals import keys as proposal_keys

    k = [proposal_keys.proposals(x, "i", []) for x in (cfg.proposals, other)]
    assert k[0] != k[1] and k[0][2]["options"] == {"centre": {"frac": 0.5}}
    assert (
        "options" not in proposal_keys.proposals(p.cfg.proposals, "i", [])[2]
    )  # no table: the key of before
    ranks = pd.read_parquet(tmp_path / "ranks.parquet")
    assert set(ranks["proposal_method"]) == {"grid5", "centre"}  # its own rank engine
    loc = pd.read_csv(tmp_path / "localization.csv")
    assert "centre" in set(loc["proposal_method"]) and (tmp_path / "table1.csv").exists()
    # editing the function changes the proposals' key (its source is hashed into it)
    before = proposals.proposer_fingerprints(["grid5", "centre"])
    assert before.keys() == {"centre"}  # built-ins are covered by the package's own code key

    def centre_edited(rgb: np.ndarray, cfg: object) -> tuple[np.ndarray, np.ndarray]:
        """One box: the image's central half."""
        h, w = rgb.shape[:2]
        return np.array([[w / 8, h / 8, 7 * w / 8, 7 * h / 8]]), np.ones(1)

    record = methods.PROPOSERS["centre"]
    methods.PROPOSERS["centre"] = dataclasses.replace(record, run=centre_edited)  # an edit
    after = proposals.proposer_fingerprints(["grid5", "centre"])
    assert after["centre"] != before["centre"]
    methods.PROPOSERS["centre"] = record  # (the registries fixture undoes it anyway)
    assert proposals.proposer_fingerprints(["centre"]) == before  # the same source, the same key


def test_recipe_a_toy_fusion_method(local_run: tuple, tmp_path: Path, registries) -> None:
    from harness import fusion

    # --- the recipe: LoC from the cover matrix, registered with a label, listed in [fusion] ---

    def best_rank(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
        """The largest 1 / r' among the boxes covering the sample (r' = (L + 1 - rank) / L)."""
        inv = L / (L + 1.0 - r * L)
        return np.where(cover, inv[None, :], 0.0).max(1)

    fusion.register_fusion_rule("best_rank", best_rank, "best single rank")
    p, _, out = local_run
    methods = ("rank_fusion", "score_max", "best_rank")
    cfg = dataclasses.replace(p.cfg, fusion=dataclasses.replace(p.cfg.fusion, methods=methods))
    # --- end of the recipe (the rest checks it) ---
    q, rec = _rerun(local_run, tmp_path, cfg)
    assert q.ran.get("ranks", 0) == 0 and q.ran["samples"] > 0  # ranks reused
    t1 = pd.read_csv(tmp_path / "table1.csv")
    assert t1["fusion"].tolist() == ["rank_fusion", "score_max", "best_rank"]  # after SPEC's
    assert "best single rank" in (tmp_path / "table1.md").read_text()
    # one sample's LoC by hand: the originals containing the sample box, their largest 1/r'
    key = rec["keys"]["samples"]
    s = pd.read_parquet(tmp_path / "cache" / "samples" / key / "samples.parquet")
    s = s[(s["proposal_method"] == "all") & (s["N"] >= 2)].iloc[0]
    ranks = pd.read_parquet(tmp_path / "ranks.parquet")
    img = ranks[
        (ranks["q_session"] == s.q_session)
        & (ranks["q_utime"] == s.q_utime)
        & (ranks["r_session"] == s.r_session)
    ]
    covers = (img["x1"] <= s.x1) & (img["y1"] <= s.y1) & (img["x2"] >= s.x2) & (img["y2"] >= s.y2)
    want = max(
        1.0 / (int(L) + 1 - int(k)) * int(L) for k, L in img.loc[covers, ["rank", "L"]].values
    )
    assert covers.sum() == s.N and np.isclose(s.loc_best_rank, want)
    assert (out / "table1.csv").read_text() != (tmp_path / "table1.csv").read_text()


def test_recipe_a_toy_localizer_kind(local_run: tuple, tmp_path: Path, registries) -> None:
    # --- the recipe: options, a ranks function, one registration; a [[localizers]] entry ---
    import cv2

    from harness.imagestore import read_image
    from harness.localizers.kinds import LocalizerKind, register_localizer_kind
    from harness.pipeline.rank_stages import query_ranks
    from harness.records import FRAME_KEY
    from harness.runtime.cache import write_parquet

    @dataclasses.dataclass(frozen=True)
    class ColourOptions:
        bins: int = 4  # per RGB channel

    def colour_ranks(p, loc, frames, pairs, props, rc):
        """Each subimage's square-rooted RGB histogram, ranked by the harness's engine."""

        def build(rows: pd.DataFrame, tmp: Path) -> dict:
            uris = rows.merge(frames.df[[*FRAME_KEY, "image"]], on=FRAME_KEY, how="left")["image"]
            b, out = loc.options.bins, []
            for r, uri in zip(rows.itertuples(), uris, strict=True):
                crop = read_image(uri)[int(r.y1) : int(r.y2), int(r.x1) : int(r.x2)]
                h = cv2.calcHist([crop], [0, 1, 2], None, [b] * 3, [0, 256] * 3).ravel()
                out.append(np.sqrt(h / max(h.sum(), 1.0)))
            np.save(tmp / "desc.npy", np.asarray(out, np.float32).reshape(len(rows), b**3))
            write_parquet(tmp / "index.parquet", rows)
            return {}

        described = {
            s: p.unit("colour", (loc.options.bins, t.key), partial(build, t.df))
            for s, t in props.items()
        }
        return query_ranks(p, frames, pairs, described, rc)

    register_localizer_kind(LocalizerKind("colour", ColourOptions, ranks=colour_ranks))
    entry = {"name": "rgb-hist", "proposals": ["grid5"], "colour": {"bins": 4}}
    # --- end of the recipe (the rest checks it) ---
    from harness.config.load import parse_localizers
    from harness.errors import ConfigError
    from harness.pipeline.context import localizer_record

    p, _, _ = local_run
    cfg = p.cfg
    locs = parse_localizers([entry], cfg, tmp_path, cfg.data_root, "recipe")
    assert locs[0].kind == "colour" and locs[0].options == ColourOptions(4)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['size'\]"):
        parse_localizers([{"name": "x", "colour": {"size": 2}}], cfg, tmp_path, cfg.data_root, "t")
    with pytest.raises(
        ConfigError, match="one of descriptor, bovw, import, local, keypoints or colour"
    ):
        parse_localizers([{"name": "x"}], cfg, tmp_path, cfg.data_root, "t")
    with pytest.raises(ConfigError, match="taken"):
        register_localizer_kind(LocalizerKind("bovw", ColourOptions, ranks=colour_ranks))
    q, rec = _rerun(local_run, tmp_path, dataclasses.replace(cfg, localizers=locs))
    assert q.ran["colour"] == len(cfg.sessions) and q.ran.get("descriptor_shards", 0) == 0
    assert rec["localizers"][0] == {"name": "rgb-hist", "kind": "colour"}
    assert localizer_record(locs[0])["colour"] == {"bins": 4}  # run.json's, beside others
    desc = np.load(tmp_path / "cache" / "colour" / q.used["colour"].pop() / "desc.npy")
    assert desc.shape[1] == 64 and np.allclose((desc**2).sum(1), 1.0, atol=1e-5)
    loc = pd.read_csv(tmp_path / "localization.csv")
    r1 = loc.loc[loc["proposal_method"] == "all", "recall_at_1"].iloc[0]
    assert loc["subimages"].max() > 0 and 0 < r1 <= 1
    assert (tmp_path / "table1.csv").exists()


def test_recipe_a_toy_log_format(small_world: Path, tmp_path: Path, request) -> None:
    import base64
    import json

    from rosbags.typesys import Stores, get_typestore

    from harness.imagestore import read_image
    from harness.ingest import ingest_session, log_types, logs
    from harness.ingest.config import IngestConfig, SessionConfig

    before = dict(logs.READERS)  # the registry itself, as the harness's modules hold it
    request.addfinalizer(lambda: (logs.READERS.clear(), logs.READERS.update(before)))
    store = get_typestore(Stores.ROS2_HUMBLE)
    # --- the recipe: a reader (detect, topics, messages) registered under a name ---

    class CdrLines:
        """JSON lines, one ``{"topic", "type", "t_ns", "cdr" (base64)}`` record per message."""

        def detect(self, path: Path) -> bool:
            return path.suffix == ".cdrl"

        def topics(self, path: Path) -> dict[str, tuple[str, int]]:
            out: dict[str, tuple[str, int]] = {}
            for rec in map(json.loads, path.read_text().splitlines()):
                out[rec["topic"]] = (rec["type"], out.get(rec["topic"], ("", 0))[1] + 1)
            return out

        def messages(self, path: Path, topics: tuple[str, ...]):
            for rec in map(json.loads, path.read_text().splitlines()):
                if rec["topic"] in topics:
                    msg = store.deserialize_cdr(base64.b64decode(rec["cdr"]), rec["type"])
                    yield log_types.Message(rec["topic"], rec["type"], rec["t_ns"], msg)

    logs.register_format("cdrl", CdrLines())
    # --- end of the recipe (the rest checks it) ---
    with pytest.raises(ValueError, match="exists"):
        logs.register_format("mcap", CdrLines())
    # the fixture's ROS2 bag, rewritten in the toy format with rosbags' own serializer
    bag = sorted((small_world / "ros2").iterdir())[0]
    topics = tuple(logs.list_topics(bag, "ros2"))
    log = tmp_path / f"{bag.name}.cdrl"
    log.write_text(
        "".join(
            json.dumps(
                {
                    "topic": m.topic,
                    "type": m.msgtype,
                    "t_ns": m.log_ns,
                    "cdr": base64.b64encode(store.serialize_cdr(m.msg, m.msgtype)).decode(),
                }
            )
            + "\n"
            for m in logs.stream(bag, "ros2", topics)
        )
    )
    assert logs.detect_format(log) == "cdrl" and logs.detect_format(bag) == "ros2"
    ra = ingest_session(
        SessionConfig(name=bag.name, source=str(bag)), IngestConfig(), tmp_path / "a"
    )
    rb = ingest_session(
        SessionConfig(name=bag.name, source=str(log)), IngestConfig(), tmp_path / "b"
    )
    assert rb["format"] == "cdrl" and rb["dropped"] == ra["dropped"]
    fa, fb = (pd.read_parquet(tmp_path / d / "frames.parquet") for d in ("a", "b"))
    same = [c for c in fa.columns if c not in ("image", "source")]
    assert len(fa) > 0
    pd.testing.assert_frame_equal(fa[same], fb[same])  # poses, times, sizes: the shared path
    for ia, ib in zip(fa["image"][:3], fb["image"][:3], strict=True):
        assert np.array_equal(
            read_image(str(tmp_path / "a" / ia)), read_image(str(tmp_path / "b" / ib))
        )


def test_a_registered_method_with_a_bad_output_is_an_error_naming_it(registries) -> None:
    from harness.errors import ConfigError
    from harness.fusion import fuse as fusion
    from harness.methods import PROPOSERS
    from harness.proposals import proposers as proposals
    from harness.proposals.config import ProposalsConfig

    proposals.register_proposer("bad", lambda rgb, cfg: (np.zeros((2, 3)), np.ones(2)))
    frame = pd.Series({"session": "s", "camera": "Cam5", "utime": 7})
    with pytest.raises(ConfigError, match=r"'bad' on frame s/Cam5/7: .*\(2, 3\)"):
        proposals._checked("bad", frame, *PROPOSERS["bad"].run(None, ProposalsConfig()))
    fusion.register_fusion_rule("flat", lambda cover, r, d, L: np.ones(1), "flat")
    cover = np.ones((3, 2), bool)
    with pytest.raises(ConfigError, match=r"'flat' returned LoC of shape \(1,\), expected \(3,\)"):
        fusion.loc_from_cover(cover, "flat", r=np.ones(2), d=np.ones(2), L=np.ones(2))


def test_recipe_a_toy_report_table(
    local_run: tuple, default_world: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    from harness.cli import main
    from harness.reports import tables as report_tables

    monkeypatch.setattr(
        report_tables, "TABLES", copy.copy(report_tables.TABLES)
    )  # undone after (a Registry still)
    # --- the recipe: a compute function of the report blocks and a spec, registered ---
    from harness.reports.tables import Column, TableSpec

    def by_roc_max(cfg: object, blocks: list) -> pd.DataFrame:
        """Table S rank fusion of the first localizer at each RoC-max."""
        s = blocks[0].summary
        s = s[
            (s["table"] == "S") & (s["fusion"] == "rank_fusion") & (s["proposal_method"] == "all")
        ]
        s = s[s["split"].str.startswith("roc_max_")]
        return pd.DataFrame(
            {"roc_max": s["roc_max"], "query_images": s["query_images"]}
            | {f"S_{k}": s[k] for k in ("ap", "ci_low", "ci_high", "floor")}
        )

    report_tables.register_table(
        TableSpec(
            "R",
            "rank fusion against RoC-max",
            "Table S rank fusion at each RoC-max, with its interval and floor.",
            (
                Column("roc_max", "RoC-max"),
                Column("S", "rank fusion", "ap"),
                Column("query_images", "query images", "int"),
            ),
            by_roc_max,
        )
    )
    # --- end of the recipe (the rest checks it) ---
    with pytest.raises(ValueError, match="exists"):
        report_tables.register_table(report_tables.TABLES["R"])
    with pytest.raises(ValueError, match="letters and digits"):
        report_tables.register_table(dataclasses.replace(report_tables.TABLES["R"], id="S"))
    _, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    # the fixture's config without the figures (the table and the page are what is checked)
    root = Path(__file__).resolve().parents[1]
    config = tmp_path.parent / f"{tmp_path.name}-recipe.toml"
    config.write_text(
        (root / "datasets" / "fixture.toml")
        .read_text()
        .replace('annotations = "annotations', f'annotations = "{root}/annotations')
        .replace('"datasets/models"', f'"{root}/datasets/models"')
        .replace("[report]\n", "[report]\nplots = false\n")
    )
    argv = ["reproduce", "--config", str(config), "--data-root", str(default_world), "--out"]
    assert main([*argv, str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    # the CSV holds what the summary says, row for row (checked against summary.parquet)
    got = pd.read_csv(tmp_path / "tableR.csv")
    summ = pd.read_parquet(tmp_path / "splits" / "summary.parquet")
    want = summ[
        (summ["table"] == "S")
        & (summ["fusion"] == "rank_fusion")
        & (summ["proposal_method"] == "all")
        & summ["split"].str.startswith("roc_max_")
    ]
    assert got["roc_max"].tolist() == want["roc_max"].tolist() == [0.01, 0.02, 0.03, 0.04, 0.05]
    assert np.allclose(got["S_ap"], want["ap"]) and np.allclose(got["S_floor"], want["floor"])
    # one cell, by hand, the same in markdown, LaTeX, console and page
    r = got.iloc[-1]
    text = f"{r.S_ap:.2f} [{r.S_ci_low:.2f}, {r.S_ci_high:.2f}] (floor {r.S_floor:.2f})"
    md = (tmp_path / "tableR.md").read_text()
    assert md.startswith("## Table R: rank fusion against RoC-max")
    assert f"| 0.05 | {text} | {int(r.query_images)} |" in md
    assert text in (tmp_path / "tableR.tex").read_text()
    assert "Table R: rank fusion against RoC-max" in printed and text in printed
    assert "tableR.md" in printed
    page = (tmp_path / "report.html").read_text()
    assert 'data-table="R"' in page and text in page and 'href="#tableR"' in page
    # a rerun in which the table has nothing to show removes its files (the harness wrote them)
    spec = report_tables.TABLES["R"]
    monkeypatch.setattr(
        report_tables, "TABLES", {"R": dataclasses.replace(spec, compute=lambda c, b: None)}
    )
    (tmp_path / "tableR.notes").write_text("the user's own file")  # not the harness's
    assert main([*argv, str(tmp_path)]) == 0
    assert [p.name for p in tmp_path.glob("tableR.*")] == ["tableR.notes"]


def test_recipe_a_column_of_table_s(local_run: tuple) -> None:
    """A column of Tables I, S and P is summary rows: every format renders it from one spec."""
    from rich.console import Console

    from harness.cli.console import print_change_table
    from harness.reports.change import change_table
    from harness.reports.html.cells import change_html
    from harness.reports.render import change_latex, table_csv, table_markdown

    _, _, out = local_run
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    summ = summ[summ["localizer"] == summ["localizer"].iloc[0]]
    # --- the recipe: the summary's rows of the new column (what evaluate/aps.py writes per split;
    # a RoC-max needs only a value in [splits] roc_max) ---
    new = summ[(summ["table"] == "S") & (summ["roc_max"] == 0.05)].copy()
    new["roc_max"], new["split"] = 0.5, "roc_max_0.50"
    new["ap"], new["ci_low"], new["ci_high"] = 0.625, 0.5, 0.75
    new["verdict"] = "above"
    summ = pd.concat([summ, new], ignore_index=True)
    # --- end of the recipe (the rest checks it) ---
    methods = tuple(m for m in summ["fusion"].unique() if isinstance(m, str))
    t = change_table(summ, "S", methods)
    assert t.columns[-1] == 0.5 and t.counts.count("positives") == len(t.columns)
    text = "0.62 [0.50, 0.75]"
    md = table_markdown(t)
    header = next(line for line in md.splitlines() if line.startswith("| AP [95% CI]"))
    assert header.endswith("| 0.05 | 0.50 |")
    rank_fusion = next(line for line in md.splitlines() if line.startswith("| rank fusion |"))
    assert rank_fusion.endswith(f"| {text} ▲ |"), rank_fusion
    assert table_csv(t.frame()).splitlines()[0].endswith(",0.05,0.50")
    assert "& 0.62$^{\\blacktriangle}$ \\\\" in change_latex(t)
    console = Console(record=True, width=240)
    print_change_table(console, t, "recipe")
    assert text in console.export_text()
    page = change_html(t)
    assert "<th>0.50</th>" in page and '>0.62 <span class="ci">[0.50, 0.75]</span></td>' in page
