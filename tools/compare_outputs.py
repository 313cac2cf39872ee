"""Whether two runs' outputs are the same, file by file: the check a change of no behaviour owes.

    python tools/compare_outputs.py BEFORE AFTER

``BEFORE`` and ``AFTER`` are folders holding the same runs (each a subfolder written by
``harness reproduce`` or ``harness detect``, with the same names), made by the code before and
after a change. Every file but the cache is compared byte for byte once three things that are not
the outputs' content are put aside: the run folder's own path (and the source tree's, where the
two were run from different checkouts), the cache keys (16 hex digits: they hold a fingerprint of
the code, so any change of the code changes them) and the measured times (``timings_s``,
``total_s``, ``ms_per_query_frame``, the cost columns, a page's "time" row). Prints each file that
differs, with the first JSON field or line where it does, and exits 1 if any does.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

#: JSON fields that are measurements of time, not outputs.
TIMES = frozenset({"timings_s", "total_s", "ms_per_query_frame", "build_s", "costs", "argv"})
KEY = re.compile(r"\b[0-9a-f]{16}\b")
#: A report page's row of the run's measured times.
TIME_ROW = re.compile(r"<tr><td>time</td><td>[^<]*</td></tr>")


def _text(t: str, roots: tuple[str, ...]) -> str:
    for r in roots:
        t = t.replace(r, "ROOT")
    return KEY.sub("KEY", t)


def _json(x: Any, roots: tuple[str, ...]) -> Any:
    if isinstance(x, dict):
        return {k: _json(v, roots) for k, v in x.items() if k not in TIMES}
    if isinstance(x, list):
        return [_json(v, roots) for v in x]
    if isinstance(x, float) and x != x:
        return "NaN"
    return _text(x, roots) if isinstance(x, str) else x


def _first_difference(a: Any, b: Any, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{path}/{k}: in one only"
            d = _first_difference(a[k], b[k], f"{path}/{k}")
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} items against {len(b)}"
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            d = _first_difference(u, v, f"{path}[{i}]")
            if d:
                return d
        return None
    return None if a == b else f"{path}: {str(a)[:60]!r} against {str(b)[:60]!r}"


def compare_file(
    a: Path, b: Path, roots_a: tuple[str, ...], roots_b: tuple[str, ...]
) -> str | None:
    """None where the two files hold the same outputs, else where they first differ."""
    da, db = a.read_bytes(), b.read_bytes()
    if da == db:
        return None
    try:
        ta, tb = da.decode(), db.decode()
    except UnicodeDecodeError:
        return "binary files differ"
    if a.suffix == ".json":
        ja = _json(json.loads(ta), roots_a)
        jb = _json(json.loads(tb), roots_b)
        return _first_difference(ja, jb)
    la = TIME_ROW.sub("", _text(ta, roots_a)).splitlines()
    lb = TIME_ROW.sub("", _text(tb, roots_b)).splitlines()
    for i, (u, v) in enumerate(zip(la, lb, strict=False)):
        if u != v:
            return f"line {i + 1}"
    return None if len(la) == len(lb) else f"{len(la)} lines against {len(lb)}"


def main() -> int:
    """Compare the folders named on the command line; exit 1 where any output differs."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--source", nargs=2, metavar=("BEFORE_TREE", "AFTER_TREE"), default=None,
                    help="the checkouts the two were run from, where they differ")  # fmt: skip
    a = ap.parse_args()
    for d in (a.before, a.after):
        if not d.is_dir() or not any(d.iterdir()):
            print(f"ERROR: {d}: not a folder of runs (absent or empty)", file=sys.stderr)
            return 1
    same, differ = 0, []
    for fa in sorted(p for p in a.before.rglob("*") if p.is_file()):
        rel = fa.relative_to(a.before)
        if "cache" in rel.parts or rel.name.startswith(".dbl-harness") or rel.suffix == ".log":
            continue
        fb = a.after / rel
        ra = (str(a.before / rel.parts[0]), *((a.source[0] + "/",) if a.source else ()))
        rb = (str(a.after / rel.parts[0]), *((a.source[1] + "/",) if a.source else ()))
        why = "missing after" if not fb.is_file() else compare_file(fa, fb, ra, rb)
        if why:
            differ.append(f"{rel}: {why}")
        else:
            same += 1
    print(f"{same} files the same, {len(differ)} differ")
    for d in differ:
        print(f"  {d}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
