"""The walk of ``harness detect``'s arguments through the code: how many files they stay in.

Runs a command line under a profiler and follows, from the command's handler (``cmd_detect``),
each call that hands on what the command line said: the parsed arguments, the overrides, the
assembled config or its detector (``[detect]``; ``--sections``: every config section too). Each
such call is kept once, at its first time, in the order they happen (code a reader can open: not
a dataclass's generated ``__init__``). The walk is the files of those calls in that order; a
*stay* is a run of calls in one file; a *climb* is a stay in a higher layer of the house than the
one before (``tests/test_layout.py``'s layers); a *return* is a stay in a file already left.

    python tools/walk.py -- detect --map-images A --query-images B --out /tmp/walk
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.test_layout import layer_of  # noqa: E402

#: What carries the command line on: its overrides, the assembled config and its detector.
CARRIERS = ("Overrides", "Config", "DetectConfig")


def _carries(value: object, sections: bool = False) -> bool:
    """Whether ``value`` is what the command line said: its arguments or the records made of them.

    ``sections``: any config section too (any ``...Config`` record of the package).
    """
    if isinstance(value, argparse.Namespace):
        return True
    name = type(value).__name__
    return (
        dataclasses.is_dataclass(value)
        and type(value).__module__.startswith("harness.")
        and (name in CARRIERS or (sections and name.endswith("Config")))
    )


def trace(
    argv: list[str], root: str = "cmd_detect", sections: bool = False
) -> list[tuple[str, str]]:
    """The (module, function) of each call that hands on the arguments, first time each."""
    from harness.cli import main

    calls: list[tuple[str, str]] = []
    seen: set[tuple[str, str]] = set()
    inside = [False]

    def prof(frame, event, arg):
        if event != "call":
            return
        code = frame.f_code
        mod = frame.f_globals.get("__name__", "")
        if not mod.startswith("harness.") or code.co_filename.startswith("<"):
            return
        if code.co_name == root:
            inside[0] = True
        if not inside[0]:
            return
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        if code.co_name != root and not any(
            _carries(frame.f_locals.get(n), sections) for n in names
        ):
            return
        key = (mod, code.co_name)
        if key not in seen:
            seen.add(key)
            calls.append(key)

    sys.setprofile(prof)
    try:
        main(argv)
    except SystemExit:
        pass
    finally:
        sys.setprofile(None)
    return calls


def stays(calls: list[tuple[str, str]]) -> list[str]:
    """The files of ``calls`` in order, each run of one file once."""
    out: list[str] = []
    for mod, _ in calls:
        if not out or out[-1] != mod:
            out.append(mod)
    return out


def main() -> int:
    """Print the walk of the command line after ``--``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("argv", nargs=argparse.REMAINDER, help="the harness command line, after --")
    ap.add_argument("--list", action="store_true", help="print each stay")
    ap.add_argument("--sections", action="store_true", help="follow every config section too")
    a = ap.parse_args()
    argv = a.argv[1:] if a.argv[:1] == ["--"] else a.argv
    walk = stays(trace(argv, sections=a.sections))
    climbs = sum(layer_of(b) > layer_of(a) for a, b in itertools.pairwise(walk))
    returns = sum(m in walk[:i] for i, m in enumerate(walk))
    if a.list:
        for m in walk:
            print(f"  {layer_of(m):2d} {m}")
    print(
        f"walk: {len(walk)} stays in {len(set(walk))} files, {climbs} climbs back up a layer, "
        f"{returns} returns to a file already left"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
