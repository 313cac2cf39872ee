"""The README's robot-log path as a user types it: ``harness inspect`` on one of the fixture's
logs, then ``harness reproduce`` of the config that holds a session of each log format.

The fixture lives in a temporary folder here, so ``datasets/fixture`` in the typed lines is that
folder and ``--data-root`` points the config at it; the run starts from the suite's fixture run's
cache (every entry is keyed by its inputs, config and code), so it recomputes nothing it shares.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

from harness.cli import main

from ..conftest import ROOT, seed_cache


def _typed(prefix: str) -> list[str]:
    """The README's line that starts with ``prefix``, split as a shell would."""
    readme = (ROOT / "README.md").read_text()
    line = next(x for x in readme.splitlines() if x.startswith(prefix))
    return line.split()[1:]


def test_the_readmes_robot_log_path_as_typed(
    local_run: tuple, default_world: Path, tmp_path: Path
) -> None:
    argv = _typed("harness inspect datasets/fixture/")
    argv[1] = argv[1].replace("datasets/fixture", str(default_world))
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    said = buf.getvalue()
    # the [[sessions]] lines that would ingest the log, with its image and pose topics
    assert "[[sessions]]" in said and "(ros1)" in said, said[-2000:]
    assert f'source = "{default_world}/ros1/2012-03-31.bag"' in said
    assert re.search(r'image_topic = "/camera/image_raw"', said), said[-2000:]
    argv = _typed("harness reproduce --config datasets/fixture.toml --out results/fixture")
    out = tmp_path / "fixture"
    argv[argv.index("--out") + 1] = str(out)
    seed_cache(local_run[2], out)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main([*argv, "--data-root", str(default_world)]) == 0
    rec = json.loads((out / "run.json").read_text())
    formats = {s: r["format"] for s, r in rec["ingest"].items()}
    assert sorted(formats.values()) == ["mcap", "nclt", "ros1", "ros2"], formats
    assert (out / "report.html").is_file() and "Table I" in buf.getvalue()
