"""``harness gc OUT``: unreachable cache entries go, what the last run used stays."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from harness.cli import main
from harness.pipeline.chain import Pipeline

from ..conftest import no_figures


def test_gc_removes_only_what_the_last_run_did_not_use(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    p, _, out = local_run
    cfg = no_figures(p.cfg)
    run_dir = tmp_path / "o"
    shutil.copytree(out, run_dir)
    # an older config leaves entries behind: another fusion seed gives other samples
    Pipeline(
        dataclasses.replace(cfg, fusion=dataclasses.replace(cfg.fusion, seed=9)), run_dir
    ).run()
    Pipeline(cfg, run_dir).run()  # the last run: back to the config's seed
    used = json.loads((run_dir / "run.json").read_text())["cache_entries"]
    entries = {f"{s.name}/{e.name}" for s in (run_dir / "cache").iterdir() for e in s.iterdir()}
    stale = entries - {f"{s}/{k}" for s, ks in used.items() for k in ks}
    assert stale and all(e.startswith("samples/") for e in stale)
    assert main(["gc", str(run_dir), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "would remove 1 cache entries" in text and all(f"cache/{e}" in text for e in stale)
    assert all((run_dir / "cache" / e).exists() for e in stale)  # a dry run removes nothing
    assert main(["gc", str(run_dir)]) == 0
    assert "removed 1 cache entries" in capsys.readouterr().out
    assert not any((run_dir / "cache" / e).exists() for e in stale)
    again = Pipeline(cfg, run_dir)
    again.run()
    assert sum(again.ran.values()) == 0  # everything the run needs is still there
    assert main(["gc", str(tmp_path / "elsewhere")]) == 1
    assert "no run.json here" in capsys.readouterr().err
