"""Content digests of a fixture run's stage files and reports, for the byte-identity regression.

A stage entry's directory name is its key, which includes the code fingerprint, so paths that
name an entry (``{out}/cache/ingest/<key>/...`` in the frame table) are masked; timings
(``seconds``) are dropped from JSON; a checkpoint is digested by its tensors. Everything else is
digested byte for byte. Regenerate the committed file after an intended change of results:

    .venv/bin/python -m tests.stage_digests results/fixture datasets/fixture \
        --values tests/regression > tests/regression/stages.json

(a run of ``datasets/fixture.toml`` on the default fixture and its data root: ``make
reproduce-table``.)

Across machines, the files in :data:`TOLERANT` are compared by value, not by digest: they hold
full-precision floats summed by numpy, whose SIMD dispatch (e.g. ``AVX512_ICL`` against
``AVX512_SKX``) can move the last bits between two machines that report the same torch CPU
capability. Their committed values (``tests/regression/<name>.csv``, floats written with ``%r``)
must match within :data:`RTOL` / :data:`ATOL`, every other column exactly. On one machine a
rerun is byte-identical (the determinism tests check that).
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
#: Report files compared by value within a tolerance across machines (committed values file name).
TOLERANT = {"splits/summary.parquet": "summary.csv"}
#: Relative and absolute tolerance of that comparison: a few hundred ulps of an AP near 1, far
#: below the two decimals any table prints.
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
        h.update(df.to_csv(index=False, float_format="%r").encode())
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


def digests(out: Path, data_root: Path | None = None) -> dict[str, list[str]]:
    """Digests of every file of a run directory, by path with entry keys masked (sorted lists).

    ``data_root`` (the config's) is masked too, so runs on fixtures in other places compare.
    """
    res: dict[str, list[str]] = {}
    for p in sorted(Path(out).rglob("*")):
        if not p.is_file() or p.name in SKIP or p.name.startswith("."):
            continue
        rel = p.relative_to(out).parts
        name = f"cache/{rel[1]}/*/{'/'.join(rel[3:])}" if rel[0] == "cache" else "/".join(rel)
        res.setdefault(name, []).append(digest(p, data_root))
    return {k: sorted(v) for k, v in sorted(res.items())}


def values_frame(path: Path) -> pd.DataFrame:
    """A parquet report's values as written to its committed CSV (floats to full precision)."""
    return pd.read_parquet(path).reset_index(drop=True)


def write_values(out: Path, dst: Path) -> None:
    """Write the committed values of every :data:`TOLERANT` file of run ``out`` into ``dst``."""
    for rel, name in TOLERANT.items():
        values_frame(out / rel).to_csv(dst / name, index=False, float_format="%r")


def values_differ(got: Path, want_csv: Path) -> list[str]:
    """What differs between a report and its committed values beyond the stated tolerance.

    Float columns within ``RTOL``/``ATOL`` (NaN equals NaN), every other column exactly; an empty
    list when they agree.
    """
    g = values_frame(got)
    w = pd.read_csv(want_csv, keep_default_na=False, na_values=["NaN", "nan", ""])
    if list(g.columns) != list(w.columns) or len(g) != len(w):
        return [f"shape or columns: {list(g.columns)} x {len(g)} vs {list(w.columns)} x {len(w)}"]
    bad = []
    for c in g.columns:
        if pd.api.types.is_float_dtype(g[c]):
            a, b = g[c].to_numpy(float), w[c].to_numpy(float)
            ok = np.isclose(a, b, rtol=RTOL, atol=ATOL, equal_nan=True)
            if not ok.all():
                i = int(np.flatnonzero(~ok)[0])
                bad.append(f"{c}: {(~ok).sum()} values, first row {i}: {a[i]!r} vs {b[i]!r}")
        elif not (g[c].astype(str).to_numpy() == w[c].astype(str).to_numpy()).all():
            bad.append(f"{c}: differs")
    return bad


def cpu_capability() -> str:
    """torch's CPU kernel level on this machine (e.g. ``AVX512``, ``AVX2``)."""
    import torch

    return str(torch.backends.cpu.get_cpu_capability())


if __name__ == "__main__":
    if "--values" in sys.argv:
        write_values(Path(sys.argv[1]), Path(sys.argv[sys.argv.index("--values") + 1]))
    json.dump(
        {
            "cpu_capability": cpu_capability(),
            "files": digests(Path(sys.argv[1]), Path(sys.argv[2])),
        },
        sys.stdout,
        indent=1,
        sort_keys=True,
    )
    print()
