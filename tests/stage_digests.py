"""Content digests of a fixture run's stage files and reports, for the byte-identity regression.

A stage entry's directory name is its key, which includes the code fingerprint, so paths that
name an entry (``{out}/cache/ingest/<key>/...`` in the frame table) are masked; timings
(``seconds``) are dropped from JSON; a checkpoint is digested by its tensors. Everything else is
digested byte for byte. Regenerate the committed file after an intended change of results:

    .venv/bin/python -m tests.stage_digests results/fixture datasets/fixture \
        --values tests/regression > tests/regression/stages.json

(a run of ``datasets/fixture.toml`` on the default fixture and its data root: ``make
reproduce-table``.)

Across machines, the files in :data:`TOLERANT` are compared by value, not by digest: their float
columns come from numpy's SIMD kernels (trigonometry and interpolation of poses in ingest, sums in
the summary), whose last bits differ between CPUs of one kind (e.g. ``AVX512_SKX`` against
``AVX2``: SVML's ``arctan2``). Their committed values (``tests/regression/values/``, floats written
in full with ``repr``) must match within :data:`RTOL` / :data:`ATOL`, every other column exactly
(a file is found by the digest of its non-float columns). On one machine a rerun is
byte-identical (the determinism tests check that).
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

#: Stages computed without floating-point kernels whose results could depend on the CPU: their
#: files must match on every machine. The rest (proposals on, and the reports) must match on a
#: machine with the same torch CPU capability as the one that wrote the regression.
PORTABLE = ("cache/ingest/", "cache/frames/", "cache/pairs/")
SKIP = {"manifest.json", "run.json", "report.html"}
#: Files compared by value within a tolerance across machines (see the module docstring).
TOLERANT = (
    "cache/ingest/*/frames.parquet",
    "cache/frames/*/frames.parquet",
    "cache/pairs/*/pairs.parquet",
    "splits/summary.parquet",
    "splits/season_pairs_stratified.parquet",
)
#: Relative and absolute tolerance of that comparison: a few hundred ulps of an AP near 1 or of a
#: pose in metres, far below the two decimals any table prints.
RTOL, ATOL = 1e-9, 1e-12
_KEY = re.compile(r"cache/([a-z_]+)/[0-9a-f]{16}")


def _mask(s: str, root: str | None) -> str:
    s = _KEY.sub(r"cache/\1/*", s)
    return s.replace(root, "{data_root}") if root else s


def _json(obj: Any, root: str | None) -> Any:
    if isinstance(obj, dict):
        return {k: _json(v, root) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_json(v, root) for v in obj]
    return _mask(obj, root) if isinstance(obj, str) else obj


def digest(path: Path, data_root: Path | None = None) -> str:
    """The content digest of one output file (see the module docstring for what is masked)."""
    h = hashlib.sha256()
    root = str(Path(data_root).resolve()) if data_root is not None else None
    if path.suffix == ".parquet":
        df = pd.read_parquet(path)
        for c in df.columns:
            if df[c].dtype == object or str(df[c].dtype).startswith("str"):
                df[c] = df[c].map(lambda v: _mask(v, root) if isinstance(v, str) else v)
        h.update(str(list(zip(df.columns, map(str, df.dtypes), strict=True))).encode())
        h.update(_csv(df).encode())
    elif path.suffix == ".json":
        h.update(json.dumps(_json(json.loads(path.read_text()), root), sort_keys=True).encode())
    elif path.suffix == ".pt":
        import torch

        state = torch.load(path, map_location="cpu", weights_only=True)
        state = state.get("state_dict", state) if isinstance(state, dict) else state
        for k in sorted(state):
            v = state[k]
            h.update(k.encode())
            h.update(v.numpy().tobytes() if hasattr(v, "numpy") else repr(v).encode())
    else:
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _csv(df: pd.DataFrame) -> str:
    """``df.to_csv(index=False, float_format="%r")``, the digests' text of a table, written column
    by column where every value's text is plain (the same bytes; pandas's writer took 15 s of the
    four-localizer run's digests); any other table through pandas itself."""
    cols = [_column_text(df[c]) for c in df.columns] if len(df.columns) > 1 else [None]
    if any(t is None for t in cols) or any(_special(str(c)) for c in df.columns):
        return df.to_csv(index=False, float_format="%r")
    rows = [",".join(map(str, df.columns)), *map(",".join, zip(*cols, strict=True))]  # type: ignore[arg-type]
    return "\n".join(rows) + "\n"


def _special(text: str) -> bool:
    return text == "" or any(ch in text for ch in ',"\r\n')


def _column_text(col: pd.Series) -> list[str] | None:
    """Each value's text as ``to_csv(float_format="%r")`` writes it, or None where that needs
    pandas (quoting, an unusual type)."""
    kind = col.dtype.kind if isinstance(col.dtype, np.dtype) else None
    v = col.to_numpy()
    if kind == "f" and v.dtype == np.float64:  # numpy's repr of a float64: Python's digits, named
        return ["" if x != x else f"np.float64({x!r})" for x in v.tolist()]
    if kind == "f":
        return ["" if x != x else repr(x) for x in v]
    if kind is not None and kind in "iub":
        return [str(x) for x in v.tolist()]
    if kind == "O" or str(col.dtype).startswith("str"):
        values = v.tolist()
        try:
            distinct = set(values)
        except TypeError:  # lists or arrays in a cell
            return None
        for x in distinct:
            missing = x is None or (isinstance(x, float) and x != x)
            if not missing and not (isinstance(x, str) and not _special(x)):
                return None
        return [x if isinstance(x, str) else "" for x in values]
    return None


def digests(out: Path, data_root: Path | None = None) -> dict[str, list[str]]:
    """Digests of every file of a run directory, by path with entry keys masked (sorted lists).

    ``data_root`` (the config's) is masked too, so runs on fixtures in other places compare.
    """
    res: dict[str, list[str]] = {}
    for name, p in _names(out):
        res.setdefault(name, []).append(digest(p, data_root))
    return {k: sorted(v) for k, v in sorted(res.items())}


def _names(out: Path) -> list[tuple[str, Path]]:
    """(name with entry keys masked, path) of every file of a run directory, as digests names."""
    res = []
    for p in sorted(Path(out).rglob("*")):
        if not p.is_file() or p.name in SKIP or p.name.startswith("."):
            continue
        rel = p.relative_to(out).parts
        name = f"cache/{rel[1]}/*/{'/'.join(rel[3:])}" if rel[0] == "cache" else "/".join(rel)
        res.append((name, p))
    return res


def values_frame(path: Path, data_root: Path | None = None) -> pd.DataFrame:
    """A parquet file's values with the data root masked in its strings."""
    root = str(Path(data_root).resolve()) if data_root is not None else None
    df = pd.read_parquet(path).reset_index(drop=True)
    for c in df.columns:
        if not pd.api.types.is_float_dtype(df[c]) and not pd.api.types.is_integer_dtype(df[c]):
            df[c] = df[c].map(lambda v: _mask(v, root) if isinstance(v, str) else v).astype(str)
    return df


def key_digest(df: pd.DataFrame) -> str:
    """The digest of a frame's columns, dtypes and non-float values: which file it is."""
    h = hashlib.sha256(str([(c, str(df[c].dtype)) for c in df.columns]).encode())
    keep = [c for c in df.columns if not pd.api.types.is_float_dtype(df[c])]
    h.update(df[keep].astype(str).to_csv(index=False).encode())
    return h.hexdigest()[:16]


def values_file(pattern: str) -> str:
    """The committed values file of a :data:`TOLERANT` pattern, under ``tests/regression/``."""
    return "values/" + pattern.replace("/*/", "__").replace("/", "__").removesuffix(".parquet")


def write_values(out: Path, data_root: Path | None, dst: Path) -> None:
    """Write the values of every :data:`TOLERANT` file of run ``out`` under ``dst/values/``."""
    (dst / "values").mkdir(parents=True, exist_ok=True)
    files = _names(out)
    for pattern in TOLERANT:
        frames = []
        for name, p in files:
            if name == pattern:
                df = values_frame(p, data_root)
                df.insert(0, "_file", key_digest(df))
                frames.append(df)
        allv = pd.concat(frames, ignore_index=True).sort_values("_file", kind="stable")
        allv.to_csv(
            dst / f"{values_file(pattern)}.csv",
            index=False,
            float_format=lambda v: repr(float(v)),
        )


def frame_differs(got: pd.DataFrame, want: pd.DataFrame, atol: float = ATOL) -> list[str]:
    """What differs between two frames of the same file beyond the stated tolerance.

    Float columns within ``RTOL``/``atol`` (NaN equals NaN), every other column exactly.
    """
    if list(got.columns) != list(want.columns) or len(got) != len(want):
        return [f"columns or rows: {list(got.columns)} x {len(got)} vs {list(want.columns)} x "
                f"{len(want)}"]  # fmt: skip
    bad = []
    for c in got.columns:
        if pd.api.types.is_float_dtype(got[c]):
            a = got[c].to_numpy(float)
            b = pd.to_numeric(want[c], errors="coerce").to_numpy(float)
            ok = np.isclose(a, b, rtol=RTOL, atol=atol, equal_nan=True)
            if not ok.all():
                i = int(np.flatnonzero(~ok)[0])
                bad.append(f"{c}: {(~ok).sum()} values, first row {i}: {a[i]!r} vs {b[i]!r}")
        elif not (got[c].astype(str).to_numpy() == want[c].astype(str).to_numpy()).all():
            bad.append(f"{c}: differs")
    return bad


def values_differ(
    out: Path,
    data_root: Path | None,
    committed: Path,
    patterns: tuple[str, ...] = TOLERANT,
    atol: float = ATOL,
) -> list[str]:
    """What of run ``out``'s :data:`TOLERANT` files (or ``patterns`` of them) differs from the
    committed values (floats within ``RTOL`` and ``atol``)."""
    bad = []
    files = _names(out)
    for pattern in patterns:
        want = pd.read_csv(
            committed / f"{values_file(pattern)}.csv", dtype=str, keep_default_na=False
        )
        got = [values_frame(p, data_root) for name, p in files if name == pattern]
        if len(got) != want["_file"].nunique():
            bad.append(f"{pattern}: {len(got)} files, committed {want['_file'].nunique()}")
        for df in got:
            rows = want[want["_file"] == key_digest(df)].drop(columns="_file")
            if not len(rows):
                bad.append(
                    f"{pattern}: a file whose non-float values differ from every committed one"
                )
                continue
            bad += [f"{pattern}: {b}" for b in frame_differs(df, rows.reset_index(drop=True), atol)]
    return bad


#: The fixture's trained autoencoder: the file every other float figure of a run follows from.
MODEL = "cache/model/*/autoencoder.pt"
#: The fixture model the figures quoted in README.md and docs/decisions.md were measured with (its
#: digest, and what trained it). Since issue 50 every AMD CPU of the kind measured trains it (the
#: kernels are pinned at AVX2, ``precision = "auto"`` is fp32): ``stages.json`` records the same
#: model, and ``tests/kernels`` fails where a CPU of that vendor trains another (an Intel Xeon
#: trains another: ``tests/cpu_vendor.py``; the kept model is copied there as everywhere).
DOCS_MODEL = {"digest": "978dd804b216655a", "machine": "torch kernels AVX2, fp32"}


def _machine() -> str:
    """What decides the fixture model here: torch's kernel level and the default precision."""
    from harness.runtime.hardware import resolve_precision

    return f"torch kernels {cpu_capability()}, {resolve_precision('auto', 'cpu')}"


def other_model(out: Path, regression: bool = False) -> str | None:
    """Why the figures recorded in the docs (or, ``regression``, in ``stages.json``) cannot hold
    here, or None.

    Each record was measured on one CPU kind. torch's kernels on another CPU (AVX-512
    convolutions; a native bf16 product, where ``[descriptor] precision = "auto"`` trains in
    bfloat16) train another autoencoder from the same seed, and every figure downstream of it then
    differs, in the second decimal. ``out`` is a run of the default fixture: where its model is
    the recorded one, this machine trains like the recording machine and every recorded figure
    must hold.
    """
    got = [digest(p) for name, p in _names(out) if name == MODEL]
    if regression:
        want = json.loads((Path(__file__).parent / "regression" / "stages.json").read_text())
        rec, machine = want["files"][MODEL], want["machine"]
    else:
        rec, machine = [DOCS_MODEL["digest"]], DOCS_MODEL["machine"]
    if got == rec:
        return None
    what = "regression's" if regression else "docs'"
    return (
        f"this machine ({_machine()}) trains another fixture model than the {what} (recorded on "
        f"{machine}): the recorded figures are that model's"
    )


def skip_unless_recorded_model(out: Path, regression: bool = False) -> None:
    """Skip the rest of a test (its checks of recorded figures) where :func:`other_model` says."""
    import pytest

    why = other_model(out, regression)
    if why is not None:
        pytest.skip(why)


#: A run's stages in the order the pipeline computes them: (the stage's name, the paths of the
#: run directory that are its files, masked as :func:`digests` names them). A file no stage claims
#: is a report ("tables and reports", last).
STAGES = (
    ("ingest", ("cache/ingest/",)),
    ("frames", ("cache/frames/",)),
    ("pairs", ("cache/pairs/", "cache/pairs_retrieval/")),
    ("proposals", ("cache/proposals/",)),
    ("descriptor model", ("cache/model/",)),
    ("descriptors", ("cache/descriptor_shards/", "cache/descriptors/")),
    ("projection", ("cache/projection/",)),
    ("bovw features", ("bovw-features",)),
    ("bovw vocabulary", ("cache/bovw_vocab/",)),
    ("bovw words", ("cache/bovw_shards/", "cache/bovw_words/")),
    ("ranks", ("cache/ranks/", "ranks.parquet", "ranks.parquet#")),
    ("fused LoC", ("cache/samples/",)),
)
REPORTS = "tables and reports"


def stage_of(name: str) -> str:
    """The stage a file of :func:`digests` belongs to (``ranks.parquet#hsv``: hsv's ranks)."""
    for stage, prefixes in STAGES:
        if name.startswith(prefixes):
            return f"ranks of {name.partition('#')[2]}" if "#" in name else stage
    return REPORTS


def stage_order(name: str) -> tuple[int, str]:
    """Sort key: the pipeline's order of the stages, then the name."""
    st = stage_of(name)
    names = [s for s, _ in STAGES]
    if st == REPORTS:
        return len(names), name
    return names.index("ranks" if st.startswith("ranks of") else st), name


def cpu_record() -> dict[str, Any]:
    """What this CPU is: its model, family and the flags that choose kernels."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    first = dict(
        (k.strip(), v.strip()) for k, _, v in (x.partition(":") for x in info.splitlines()[:30])
    )
    flags = sorted(
        f for f in first.get("flags", "").split() if f.startswith(("avx", "amx", "fma", "f16c"))
    )
    return {
        "model": f"{first.get('model name', '?')} (family {first.get('cpu family', '?')}, "
        f"model {first.get('model', '?')})",
        "flags": flags,
    }


def first_stage_differing(
    got: dict[str, list[str]], want: dict[str, list[str]], recorded_on: dict[str, Any] | None
) -> str | None:
    """None where every file has its recorded digests; else the message a run on another CPU
    hands back: the first stage (pipeline order) whose files differ, those files, and the CPUs."""
    bad = sorted((k for k in set(got) | set(want) if got.get(k) != want.get(k)), key=stage_order)
    if not bad:
        return None
    stage = stage_of(bad[0])
    files = [k for k in bad if stage_of(k) == stage]
    later = sorted({stage_of(k) for k in bad} - {stage}, key=lambda s: bad.index(
        next(k for k in bad if stage_of(k) == s)))  # fmt: skip
    here, rec = cpu_record(), recorded_on or {}
    return (
        f"the first stage that differs from the record is {stage!r} ({len(files)} file(s): "
        f"{', '.join(files[:4])}{' ...' if len(files) > 4 else ''}); later stages that differ: "
        f"{', '.join(later) or 'none'}. This CPU: {here['model']}, {' '.join(here['flags'])}. "
        f"Recorded on: {rec.get('model', '?')}, {' '.join(rec.get('flags', []))}. "
        "docs/decisions.md, One answer on every CPU, lists what is measured to hold across CPUs."
    )


def localizer_digests(out: Path, data_root: Path | None, features: dict[str, str]) -> dict:
    """A several-localizer run's digests, stage by stage: its cache, each localizer's ranks
    (``ranks.parquet#<localizer>``), BoVW's features (``features``: name -> digest, computed by
    the caller) and its tables (Table L without its measured costs and timings)."""
    got = {k: v for k, v in digests(out, data_root).items()  # ranks: each localizer's, below
           if (k.startswith("cache/") and not k.startswith("cache/ranks/"))
           or k in LOCALIZER_TABLES}  # fmt: skip
    pose = {t for t in TOLERANT if t.startswith(PORTABLE)}
    rounded: dict[str, list[str]] = {}
    for name, p in _names(out):  # the pose tables' floats at 10 digits (module docstring)
        if name in pose:
            csv = values_frame(p, data_root).to_csv(index=False, float_format="%.10g")
            rounded.setdefault(name, []).append(hashlib.sha256(csv.encode()).hexdigest()[:16])
    got.update({k: sorted(v) for k, v in rounded.items()})
    ranks = pd.read_parquet(out / "ranks.parquet")
    for name, rows in ranks.groupby("localizer", sort=True):
        h = hashlib.sha256(rows.to_csv(index=False, float_format="%r").encode())
        got[f"ranks.parquet#{name}"] = [h.hexdigest()[:16]]
    table_l = pd.read_csv(out / "tableL.csv").drop(columns=list(TABLE_L_COSTS))
    got["tableL.csv (without costs)"] = [
        hashlib.sha256(table_l.to_csv(index=False).encode()).hexdigest()[:16]
    ]
    got.update({f"bovw-features/{k}": [v] for k, v in features.items()})
    for k in [k for k in got if k.startswith("cache/model/") and not k.endswith(".pt")]:
        del got[k]  # the loss curve's plot and record: the weights are what matter
    return got


def bovw_feature_digests(
    out: Path, data_root: Path, features: str = "rootsift", rows: int = 240
) -> dict[str, str]:
    """The digest of BoVW's local features (the fixture's BoVW options) of the first ``rows``
    proposals of every session of run ``out``: the stage before the vocabulary, which no cache
    entry holds on its own."""
    from harness.imagestore import local_uri
    from harness.retrieval.bovw import iter_features
    from harness.retrieval.config import BovwConfig

    bc = BovwConfig(features=features, k=256, input_size=64, step=8, patch=16)
    (frames_file,) = Path(out).glob("cache/frames/*/frames.parquet")
    frames = pd.read_parquet(frames_file)
    frames["image"] = [local_uri(u, Path(out), Path(data_root)) for u in frames["image"]]
    res = {}
    for f in sorted(Path(out).glob("cache/proposals/*/proposals.parquet")):
        props = pd.read_parquet(f).head(rows)
        h = hashlib.sha256()
        feats: dict[int, np.ndarray] = {}
        for idx, fs in iter_features(bc, props, frames, "bovw features"):
            feats.update(zip(idx.tolist(), fs, strict=True))
        for i in sorted(feats):
            h.update(np.ascontiguousarray(feats[i]).tobytes())
        res[f"{features} of {props['session'].iloc[0]}"] = h.hexdigest()[:16]
    return res


#: The several-localizer run's tables in its record; Table L's cost columns are measured times.
LOCALIZER_TABLES = ("table1.csv", "tableS.csv", "tableP.csv", "localization.csv")
TABLE_L_COSTS = ("descriptor_bytes", "map_kib_per_frame", "encode_ms", "rank_ms", "build_s")


def cpu_capability() -> str:
    """torch's CPU kernel level on this machine (e.g. ``AVX512``, ``AVX2``)."""
    import torch

    return str(torch.backends.cpu.get_cpu_capability())


if __name__ == "__main__":
    if "--localizers" in sys.argv:  # python -m tests.stage_digests --localizers RUN DATA_ROOT
        i = sys.argv.index("--localizers")
        got = localizer_digests(
            Path(sys.argv[i + 1]),
            Path(sys.argv[i + 2]),
            bovw_feature_digests(Path(sys.argv[i + 1]), Path(sys.argv[i + 2])),
        )
        json.dump({"cpu": cpu_record(), "machine": _machine(), "files": got}, sys.stdout,
                  indent=1, sort_keys=True)  # fmt: skip
        print()
        sys.exit(0)
    if "--values" in sys.argv:
        write_values(
            Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[sys.argv.index("--values") + 1])
        )
    json.dump(
        {
            "cpu_capability": cpu_capability(),
            "machine": _machine(),
            "files": digests(Path(sys.argv[1]), Path(sys.argv[2])),
        },
        sys.stdout,
        indent=1,
        sort_keys=True,
    )
    print()
