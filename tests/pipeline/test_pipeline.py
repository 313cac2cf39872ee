"""The whole pipeline on the fixture.

Caching, resumption, determinism and the CI regression table.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.pipeline.chain import Pipeline

from ..conftest import ROOT, no_figures
from ..readme_text import manual_text

#: Largest allowed absolute difference from the committed two-decimal tables. Same machine, same
#: bytes (tested below); between machines BLAS and CPU differences move the trained autoencoder's
#: descriptors slightly: the largest drift measured so far is one rounding step, 0.01.
TOLERANCE = 0.011


def _copy_cache(out: Path, dst: Path) -> None:
    """A run directory with another run's cache (and the harness's marker, so it is writable)."""
    shutil.copytree(out / "cache", dst / "cache")
    shutil.copy(out / ".dbl-harness.json", dst / ".dbl-harness.json")


@pytest.fixture()
def run(local_run: tuple[Pipeline, dict, Path]) -> tuple[Pipeline, dict, Path]:
    return local_run


def test_outputs_exist(run: tuple) -> None:
    _, _rec, out = run
    for name in (
        "table1.md",
        "table1.csv",
        "table1.tex",
        "tableS.md",
        "tableS.csv",
        "tableS.tex",
        "tableP.md",
        "tableP.csv",
        "tableP.tex",
        "localization.md",
        "localization.csv",
        "localization.tex",
        "comparisons.md",
        "ranks.parquet",
        "run.json",
        "splits/summary.parquet",
        "splits/roc_max_0.03.parquet",
        "plots/pr_roc_max_0.03.png",
    ):
        assert (out / name).exists(), name
    assert list((out / "locmaps").glob("*.png"))
    rep = pd.read_parquet(out / "splits" / "roc_max_0.01.parquet")
    for col in (
        "q_session",
        "q_utime",
        "season_pair",
        "x1",
        "original",
        "N",
        "RoC",
        "SoB",
        "label",
        "loc_rank_fusion",
        "loc_score_sum",
    ):
        assert col in rep.columns
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    assert {"all", "grid5", "edges"} <= set(summ["proposal_method"])
    assert len(set(summ["season_pair"]) - {"all"}) >= 9


def regression_diff(out: Path) -> dict[str, float]:
    """Largest absolute difference of a run's Table I and localization table from the regression."""
    got = pd.read_csv(out / "table1.csv", index_col=0)
    want = pd.read_csv(ROOT / "tests" / "regression" / "table1.csv", index_col=0)
    assert list(got.index) == list(want.index) and list(got.columns) == list(want.columns)
    loc = pd.read_csv(out / "localization.csv")
    loc = loc[loc["season_pair"] == "all"].set_index("proposal_method")
    want_loc = pd.read_csv(ROOT / "tests" / "regression" / "localization.csv").set_index(
        "proposal_method"
    )
    cols = ["recall_at_1", "recall_at_5", "median_r", "clean_recall_at_1"]
    return {
        "table1": float(np.nanmax(np.abs(got.to_numpy() - want.to_numpy()))),
        "localization": float(
            np.abs(loc.loc[want_loc.index, cols].to_numpy() - want_loc[cols].to_numpy()).max()
        ),
    }


def test_regression_table_matches_the_committed_one(run: tuple) -> None:
    _, _, out = run
    got = pd.read_csv(out / "table1.csv", index_col=0)
    want = pd.read_csv(ROOT / "tests" / "regression" / "table1.csv", index_col=0)
    assert np.array_equal(np.isnan(got.to_numpy()), np.isnan(want.to_numpy()))
    diff = regression_diff(out)
    assert diff["table1"] <= TOLERANCE and diff["localization"] <= TOLERANCE, diff


def test_sample_counts_are_exactly_the_committed_ones(run: tuple) -> None:
    """Counts depend on proposals, annotations and the closure only, not on floating point.

    Exact.
    """
    _, _, out = run
    s = pd.read_parquet(out / "splits" / "summary.parquet")
    got = s[
        (s["table"] == "I")
        & (s["proposal_method"] == "all")
        & (s["season_pair"] == "all")
        & s["fusion"].isin(["rank_fusion", "rank_no_fusion"])
    ]
    want = pd.read_csv(ROOT / "tests" / "regression" / "counts.csv")
    merged = want.merge(got, on=["fusion", "roc_max"], suffixes=("", "_got"), how="left")
    for c in ("positives", "negatives", "left_out", "query_images"):
        assert (merged[c] == merged[f"{c}_got"]).all(), merged[["fusion", "roc_max", c, f"{c}_got"]]


def test_an_untrained_autoencoder_fails_the_regression(
    run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mutant that skips training must be caught: the regression is not blind to the model."""
    import harness.descriptors.autoencoder_descriptor as ad

    p, _, _ = run
    monkeypatch.setattr(ad, "train", lambda *a, **k: [])  # epochs
    monkeypatch.setattr(ad, "train_budget", lambda *a, **k: ([], {}))  # train_samples (fixture)
    # without the kept models (datasets/models): a copied model would not call training at all
    cfg = no_figures(p.cfg)
    cfg = dataclasses.replace(
        cfg, descriptor=dataclasses.replace(cfg.descriptor, trained_models="")
    )
    Pipeline(cfg, tmp_path / "mutant").run()
    diff = regression_diff(tmp_path / "mutant")
    assert max(diff.values()) > 5 * TOLERANCE, diff


def test_the_papers_orderings_show_on_the_fixture(run: tuple) -> None:
    """Under the paper's splits: rank fusion above rank w/o fusion, and the ascending variant far
    below rank fusion (the paper: it "did not work well"); every method above the random baseline
    by a margin; AP never below the floor of interpolated AP (the positive rate)."""
    _, _, out = run
    s = pd.read_parquet(out / "splits" / "summary.parquet")
    main = s[
        (s["table"] == "I") & (s["proposal_method"] == "all") & (s["season_pair"] == "all")
    ].set_index(["fusion", "roc_max"])
    for r in (0.01, 0.03, 0.05):
        ap = {
            m: main.loc[(m, r), "ap"]
            for m in ("rank_fusion", "rank_no_fusion", "rank_fusion_asc", "random", "score_max")
        }
        assert ap["rank_fusion"] > ap["rank_no_fusion"] + 0.2, (r, ap)
        assert ap["rank_fusion_asc"] < ap["rank_fusion"] - 0.5, (r, ap)
        assert ap["score_max"] > ap["random"] + 0.5, (r, ap)
        row = main.loc[("rank_fusion", r)]
        assert row["ap"] >= row["positive_rate"] - 1e-9
        assert row["ci_low"] <= row["ap"] <= row["ci_high"]


def test_table1_recomputed_from_ranks_with_spec_formulas_alone(run: tuple) -> None:
    """Every cell of Table I from OUT/ranks.parquet and the annotations, with an independent
    implementation of method §7-9 (brute-force closure, the LoC formulas, labels, AP)."""
    import itertools

    from harness.ingest.annotations import load_annotations

    p, _, out = run
    ranks = pd.read_parquet(out / "ranks.parquet")
    ann = load_annotations(p.cfg.annotations)
    frames = pd.read_parquet(next((out / "cache" / "frames").glob("*/frames.parquet")))
    size = {(r.session, r.camera, int(r.utime)): (r.width, r.height) for r in frames.itertuples()}
    changes: dict[tuple, list] = {}
    for r in ann.itertuples():
        changes.setdefault((r.session, r.camera, int(r.utime)), [])
        if r.status == "change":
            changes[(r.session, r.camera, int(r.utime))].append((r.x1, r.y1, r.x2, r.y2))

    def union_area_in(b: tuple, rects: list) -> float:
        xs = sorted({b[0], b[2], *(v for q in rects for v in (q[0], q[2]) if b[0] < v < b[2])})
        ys = sorted({b[1], b[3], *(v for q in rects for v in (q[1], q[3]) if b[1] < v < b[3])})
        area = 0.0
        for x0, x1 in itertools.pairwise(xs):
            for y0, y1 in itertools.pairwise(ys):
                if any(q[0] <= x0 and x1 <= q[2] and q[1] <= y0 and y1 <= q[3] for q in rects):
                    area += (x1 - x0) * (y1 - y0)
        return area

    # every method whose LoC is a formula of the ranks; le2/le3 and random also draw seeded random
    # numbers
    samples = {
        m: []
        for m in (
            "rank_fusion",
            "rank_no_fusion",
            "score_max",
            "score_sum",
            "rank_fusion_asc",
            "rank_fusion_raw",
            "size_prior",
            "cover_count",
            "rrf",
            "combmnz",
            "borda",
            "isr",
        )
    }
    for key, g in ranks.groupby(["q_session", "q_camera", "q_utime", "r_session"]):
        qk = (key[0], key[1], int(key[2]))
        if qk not in changes:
            continue
        w, h = size[qk]
        orig = [
            (tuple(b), rank, L, d)
            for b, rank, L, d in zip(
                g[["x1", "y1", "x2", "y2"]].itertuples(index=False, name=None),
                g["rank"],
                g["L"],
                g["d"],
                strict=True,
            )
        ]
        closure = {o[0] for o in orig}
        while True:
            new = {
                (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
                for a in closure
                for b in closure
            }
            new = {b for b in new if b[2] > b[0] and b[3] > b[1]} - closure
            if not new:
                break
            closure |= new

        def roc_sob(b: tuple, qk: tuple = qk, w: float = w, h: float = h) -> tuple[float, float]:
            a = (b[2] - b[0]) * (b[3] - b[1])
            return union_area_in(b, changes[qk]) / a, a / (w * h)

        for b in closure:
            cov = [
                o
                for o in orig
                if o[0][0] <= b[0] and o[0][1] <= b[1] and o[0][2] >= b[2] and o[0][3] >= b[3]
            ]
            n = len(cov)
            rc, sb = roc_sob(b)
            samples["rank_fusion"].append(
                (rc, sb, n * sum(L / (L + 1 - rank) for _, rank, L, _ in cov))
            )
            samples["rank_fusion_asc"].append(
                (rc, sb, 1 / (n * sum(L / rank for _, rank, L, _ in cov)))
            )
            samples["rank_fusion_raw"].append(
                (rc, sb, n * sum(1 / (L + 1 - rank) for _, rank, L, _ in cov))
            )
            samples["score_max"].append((rc, sb, max(d for *_, d in cov)))
            samples["score_sum"].append((rc, sb, sum(d for *_, d in cov)))
            samples["size_prior"].append((rc, sb, 1 - sb))
            samples["cover_count"].append((rc, sb, float(n)))
            # method §14, with rank' = L + 1 - rank
            samples["rrf"].append((rc, sb, sum(1 / (60 + L + 1 - rank) for _, rank, L, _ in cov)))
            samples["combmnz"].append((rc, sb, n * sum(rank / L for _, rank, L, _ in cov)))
            samples["borda"].append((rc, sb, sum((rank - 1) / L for _, rank, L, _ in cov) / n))
            samples["isr"].append(
                (rc, sb, n * sum(1 / (L + 1 - rank) ** 2 for _, rank, L, _ in cov))
            )
        for b, rank, L, _ in orig:
            samples["rank_no_fusion"].append((*roc_sob(b), rank / L))

    def ap101(labels: list, scores: list) -> float:
        pts = []
        for t in sorted(set(scores), reverse=True):
            sel = [y for y, s in zip(labels, scores, strict=True) if s >= t]
            pts.append((sum(sel) / sum(labels), sum(sel) / len(sel)))
        return (
            sum(
                max([p for rec, p in pts if rec >= R - 1e-12], default=0.0)
                for R in [i / 100 for i in range(101)]
            )
            / 101
        )

    table = pd.read_csv(out / "table1.csv", index_col=0)
    for m, rows in samples.items():
        for rmax in (0.01, 0.02, 0.03, 0.04, 0.05):
            lab = [
                (1 if 0.9 <= rc <= 1 and sb <= 0.4 else 0)
                for rc, sb, _ in rows
                if (0.9 <= rc <= 1 and sb <= 0.4) or (rc <= rmax and 0.4 <= sb <= 1)
            ]
            sc = [
                v
                for rc, sb, v in rows
                if (0.9 <= rc <= 1 and sb <= 0.4) or (rc <= rmax and 0.4 <= sb <= 1)
            ]
            assert round(ap101(lab, sc), 2) == pytest.approx(
                table.loc[m, f"{rmax:.2f}"], abs=1e-9
            ), (m, rmax)


def test_changed_subimages_rank_worse_than_unchanged(run: tuple) -> None:
    _p, _, out = run
    s = pd.read_parquet(out / "splits" / "roc_max_0.05.parquet")
    orig = s[(s["proposal_method"] == "all") & s["loc_rank_no_fusion"].notna()]
    changed = orig[orig["RoC"] >= 0.5]["loc_rank_no_fusion"].mean()
    unchanged = orig[orig["RoC"] == 0]["loc_rank_no_fusion"].mean()
    assert changed > 1.5 * unchanged


def test_rerun_does_no_work_and_gives_the_same_bytes(run: tuple) -> None:
    p, _, out = run
    before = (out / "table1.csv").read_bytes(), (out / "splits" / "summary.parquet").read_bytes()
    again = Pipeline(p.cfg, out)
    again.run()
    assert sum(again.ran.values()) == 0
    assert (out / "table1.csv").read_bytes() == before[0]
    assert (out / "splits" / "summary.parquet").read_bytes() == before[1]


def test_changing_one_option_reruns_only_what_depends_on_it(run: tuple, tmp_path: Path) -> None:
    p, _, out = run
    _copy_cache(out, tmp_path)
    cfg = dataclasses.replace(p.cfg, fusion=dataclasses.replace(p.cfg.fusion, seed=5))
    q = Pipeline(no_figures(cfg), tmp_path)
    q.run()
    assert q.ran.get("samples") == 1
    assert all(
        q.ran.get(s, 0) == 0 for s in ("ingest", "proposals", "model", "descriptors", "ranks")
    )


def test_encoding_options_never_retrain_the_autoencoder(run: tuple, tmp_path: Path) -> None:
    """encode_batch and dtype change how descriptors are computed and stored, not the model."""
    p, _, out = run
    _copy_cache(out, tmp_path)
    cfg = dataclasses.replace(
        p.cfg,
        descriptor=dataclasses.replace(
            p.cfg.descriptor, encode_batch=5, dtype="float32", num_workers=1
        ),
    )
    q = Pipeline(no_figures(cfg), tmp_path)
    q.run()
    assert q.ran.get("model", 0) == 0
    assert q.ran.get("descriptors", 0) == len(cfg.sessions)


def test_interrupted_run_resumes(run: tuple, tmp_path: Path) -> None:
    p, _, out = run
    cache = tmp_path / "out"
    _copy_cache(out, cache)
    # lose the last stages, as if the run died after the descriptors
    for stage in ("ranks", "samples"):
        shutil.rmtree(cache / "cache" / stage)
    q = Pipeline(no_figures(p.cfg), cache)
    q.run()
    assert q.ran.get("ranks") == 4 and q.ran.get("descriptors", 0) == 0
    assert (cache / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_faiss_engine_reports_its_recall_against_exact(run: tuple, tmp_path: Path) -> None:
    p, _, out = run
    _copy_cache(out, tmp_path)
    cfg = dataclasses.replace(p.cfg, retrieval=dataclasses.replace(p.cfg.retrieval, engine="faiss"))
    rec = Pipeline(no_figures(cfg), tmp_path).run()
    counts = rec["counts"]["rank_counts"]
    for ref, c in counts.items():
        assert c["faiss_checked"] > 0, ref
        # a flat index with k = 256 over a few hundred subimages sees every frame; ranks can still
        # differ at near-ties, where faiss and torch round the float32 distances differently
        assert c["faiss_rank_equal_exact"] >= 0.99 * c["faiss_checked"]


def test_descriptor_extraction_resumes_at_the_next_shard(
    run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p, _, out = run
    _copy_cache(out, tmp_path)
    for stage in ("descriptor_shards", "descriptors", "ranks", "samples"):
        shutil.rmtree(tmp_path / "cache" / stage)
    cfg = dataclasses.replace(
        no_figures(p.cfg), descriptor=dataclasses.replace(p.cfg.descriptor, shard_frames=16)
    )
    from harness.descriptors import AutoencoderDescriptor

    real = AutoencoderDescriptor.encode
    calls = {"n": 0}

    def dying(self: AutoencoderDescriptor, crops: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] == 12:
            raise KeyboardInterrupt
        return real(self, crops)

    monkeypatch.setattr(AutoencoderDescriptor, "encode", dying)
    with pytest.raises(KeyboardInterrupt):
        Pipeline(cfg, tmp_path).run()
    done = len(list((tmp_path / "cache" / "descriptor_shards").glob("*/manifest.json")))
    assert done >= 1
    monkeypatch.setattr(AutoencoderDescriptor, "encode", real)
    q = Pipeline(cfg, tmp_path)
    q.run()
    total = len(list((tmp_path / "cache" / "descriptor_shards").glob("*/manifest.json")))
    assert q.ran["descriptor_shards"] == total - done  # only the unfinished shards ran
    # shard size is an execution option: same descriptors, same table
    assert (tmp_path / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_stage_files_and_tables_are_identical_to_the_regression(run: tuple) -> None:
    """Every stage file and report of the fixture run has the committed content (entry keys masked).

    ``tests/regression/stages.json`` was written by the code before the runner was restructured
    into stage functions; the restructured code reproduces it file for file. Ingest, frames and
    pairs must match anywhere; the float stages only where torch runs the same CPU kernels, and the
    full-precision summary within ``RTOL``/``ATOL`` of its committed values (numpy's SIMD dispatch
    moves its last bits between machines of one kind; see ``tests/stage_digests.py``). On a CPU of
    another vendor than the recording one, the stages before the descriptors must match and the
    summary within one step of two decimals (``tests/cpu_vendor.py``).
    """
    from ..cpu_vendor import CROSS_VENDOR_ATOL, differ_before_descriptors, other_vendor
    from ..stage_digests import (
        ATOL,
        PORTABLE,
        TOLERANT,
        cpu_capability,
        digests,
        first_stage_differing,
        skip_unless_recorded_model,
        values_differ,
    )

    p, _, out = run
    want = json.loads((ROOT / "tests" / "regression" / "stages.json").read_text())
    got = digests(out, p.cfg.data_root)
    regen = "regenerate with python -m tests.stage_digests (see its docstring)"
    portable = [k for k in got if k.startswith(PORTABLE)]
    assert len(portable) >= 5
    assert {k for k in want["files"] if k.startswith(PORTABLE)} == set(portable)
    exact = [k for k in portable if k not in TOLERANT]  # the images: bytes anywhere
    msg = first_stage_differing({k: got[k] for k in exact}, {k: want["files"][k] for k in exact},
                                want.get("cpu"))  # fmt: skip
    assert msg is None, msg
    tolerant_portable = tuple(t for t in TOLERANT if t.startswith(PORTABLE))
    bad = values_differ(out, p.cfg.data_root, ROOT / "tests" / "regression", tolerant_portable)
    assert not bad, f"{bad}; {regen}"
    skip_unless_recorded_model(out, regression=True)  # the rest follows from the model
    assert set(got) == set(want["files"]), set(got) ^ set(want["files"])
    # on a CPU of another vendor: the summary within one step of two decimals, and every stage
    # before the descriptors the same bytes (tests/cpu_vendor.py says why, and what was measured)
    cross = other_vendor(want.get("cpu"))
    bad = values_differ(out, p.cfg.data_root, ROOT / "tests" / "regression",
                        atol=CROSS_VENDOR_ATOL if cross else ATOL)  # fmt: skip
    assert not bad, f"{bad}; {regen}"
    if cross:
        ours = {k: v for k, v in got.items() if k not in TOLERANT}
        theirs = {k: v for k, v in want["files"].items() if k not in TOLERANT}
        early = differ_before_descriptors(ours, theirs)
        assert not early, first_stage_differing(ours, theirs, want.get("cpu"))
        return
    if cpu_capability() != want["cpu_capability"]:
        pytest.skip(
            f"float stages written on {want['cpu_capability']}, this machine runs "
            f"{cpu_capability()} kernels"
        )
    exact_want = {k: v for k, v in want["files"].items() if k not in TOLERANT}
    msg = first_stage_differing({k: v for k, v in got.items() if k not in TOLERANT}, exact_want,
                                want.get("cpu"))  # fmt: skip
    assert msg is None, f"{msg}; {regen}"


def test_the_tolerant_comparison_passes_last_bits_and_catches_real_changes(
    run: tuple, tmp_path: Path
) -> None:
    """The committed values' comparison: a last-bit change of every float passes; a change of
    1e-6 in one AP or one pose, or one count, is caught and named."""
    from ..stage_digests import frame_differs, values_frame

    _, _, out = run
    for rel, col in (("splits/summary.parquet", "ap"), ("ranks.parquet", "x1")):
        df = values_frame(out / rel)
        floats = [c for c in df.columns if pd.api.types.is_float_dtype(df[c])]
        assert col in floats and len(floats) >= 3
        want = tmp_path / "want.csv"
        df.to_csv(want, index=False, float_format=lambda v: repr(float(v)))
        committed = pd.read_csv(want, dtype=str, keep_default_na=False)
        assert frame_differs(df, committed) == []
        nudged = df.copy()
        for c in floats:
            nudged[c] = np.nextafter(nudged[c].to_numpy(), np.inf)
        assert frame_differs(nudged, committed) == []
        moved = df.copy()
        moved.loc[3, col] = moved.loc[3, col] + 1e-6
        assert frame_differs(moved, committed) == [
            f"{col}: 1 values, first row 3: {moved.loc[3, col]!r} vs {df.loc[3, col]!r}"
        ]
        ints = [c for c in df.columns if pd.api.types.is_integer_dtype(df[c])]
        counted = df.copy()
        counted.loc[0, ints[0]] += 1
        assert frame_differs(counted, committed) == [f"{ints[0]}: differs"]


def test_a_moved_data_root_resumes_without_recomputing(local_run: tuple, tmp_path: Path) -> None:
    """Keys name inputs relative to the data root: moving it (or a copy that keeps file times)
    recomputes nothing, and the images are read from the new place."""
    import dataclasses
    import shutil

    p, _, run = local_run
    shutil.copytree(p.cfg.data_root, tmp_path / "a")  # keeps sizes and modification times
    out = tmp_path / "o"
    shutil.copytree(run / "cache", out / "cache")
    shutil.copy(run / ".dbl-harness.json", out)
    for root in ("a", "b"):
        if root == "b":
            shutil.move(str(tmp_path / "a"), str(tmp_path / "b"))
        sessions = tuple(
            dataclasses.replace(
                sc, source=sc.source.replace(str(p.cfg.data_root), str(tmp_path / root))
            )
            for sc in p.cfg.sessions
        )
        cfg = dataclasses.replace(p.cfg, data_root=tmp_path / root, sessions=sessions)
        cfg = dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, plots=False))
        q = Pipeline(cfg, out)  # the page reads the images (below); the figures are not checked
        q.run()
        assert sum(q.ran.values()) == 0, q.ran
        assert (out / "table1.csv").read_bytes() == (run / "table1.csv").read_bytes()
    assert not (tmp_path / "a").exists() and (out / "report.html").exists()  # read from b


def test_the_readme_quotes_the_holm_counts_as_comparisons_md_prints_them(run: tuple) -> None:
    """README's *Reading the tables* item 5 (issue 38): its example difference, its Holm counts
    per table and its sentence are what this run's ``comparisons.md`` says."""
    from ..stage_digests import skip_unless_recorded_model

    _, _, out = run
    cmp = (out / "comparisons.md").read_text()
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    for table in ("I", "S", "P"):  # the counts are the summary's columns
        t = summ[(summ["table"] == table) & (summ["holm_tested"] > 0)]
        assert f"Table {table}: {int(t['holm_survives'].sum())} of the {len(t)} " in cmp
    skip_unless_recorded_model(out)
    readme = " ".join(manual_text().split())
    example = re.search(r"`(rank w/o fusion - rank fusion = [^`]+)`", readme)
    assert example is not None
    line = next(x for x in cmp.splitlines() if example.group(1) in x)
    assert "[Holm]" not in line  # "The difference above ... is not among them"
    sentence = re.search(r'"(Table I: \d+ of the \d+ differences [^"]+)"', readme)
    assert sentence is not None and sentence.group(1) in cmp
    for table, kept, tested in re.findall(r"Table ([SP]): (\d+) of (\d+)", readme):
        assert f"Table {table}: {kept} of the {tested} differences" in cmp


def test_recall_at_is_the_share_ranked_within_n(run: tuple) -> None:
    """``[report] recall_at``: one ``recall_at_N`` (and ``clean_``) column per N, each the share of
    query subimages whose place ranks within the first N; the defaults are 1, 5, 10, 20."""
    from harness.evaluate.localization import localization_stats
    from harness.ingest.annotations import load_annotations

    p, _, out = run
    assert p.cfg.report.recall_at == (1, 5, 10, 20)
    loc = pd.read_csv(out / "localization.csv")
    assert [c for c in loc.columns if c.startswith("recall_at_")] == [
        "recall_at_1", "recall_at_5", "recall_at_10", "recall_at_20"
    ]  # fmt: skip
    ranks = pd.read_parquet(out / "ranks.parquet")
    frames = pd.read_parquet(next((out / "cache" / "frames").glob("*/frames.parquet")))
    ann = load_annotations(p.cfg.annotations, frames)
    mine = localization_stats(ranks, frames, ann, (1, 3, 7))
    row = mine[(mine["proposal_method"] == "all") & (mine["season_pair"] == "all")].iloc[0]
    for n in (1, 3, 7):
        assert row[f"recall_at_{n}"] == pytest.approx((ranks["rank"] <= n).mean())
    assert "recall_at_5" not in mine.columns and "clean_recall_at_7" in mine.columns


def test_a_second_place_radius_ranks_again_without_touching_the_run(
    run: tuple, tmp_path: Path
) -> None:
    """``[report] gt_radius_also``: the localization table again with a wider place.

    The same descriptors ranked under a 5 m place (its ranks' keys hold the radius, the
    descriptors' do not): R@1 can only rise, the change tables are the run's own (they rest on
    ``gt_radius_m``), and the config the run holds is never swapped.
    """
    p, _, out = run
    cfg = dataclasses.replace(p.cfg, report=dataclasses.replace(p.cfg.report, gt_radius_also=5.0))
    _copy_cache(out, tmp_path)
    q = Pipeline(cfg, tmp_path)
    q.run()
    assert q.cfg is cfg and q.cfg.retrieval.gt_radius_m == p.cfg.retrieval.gt_radius_m
    assert q.ran["descriptor_shards"] == 0 and q.ran["ranks"] > 0  # ranked again, not encoded
    base = pd.read_csv(tmp_path / "localization.csv")
    wide = pd.read_csv(tmp_path / "localization_also.csv")
    assert set(wide["gt_radius_m"]) == {5.0}
    key = ["proposal_method", "season_pair"]
    both = base.merge(wide, on=key, suffixes=("", "_also"))
    assert len(both) == len(base)
    assert (both["recall_at_1_also"] >= both["recall_at_1"] - 1e-12).all()
    assert (both["recall_at_1_also"] > both["recall_at_1"]).any()
    assert (tmp_path / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
