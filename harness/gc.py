"""``harness gc OUT``: remove the cache entries the last run of ``OUT`` did not use.

Stage keys change whenever a config value or the code changes, so old entries pile up under
``OUT/cache/``. ``run.json`` lists every entry the last ``harness reproduce`` read or wrote
(``cache_entries``); every other entry is unreachable from that run and is removed (``--dry-run``:
listed with its size, nothing removed). The run lock is held meanwhile, so a running pipeline is
never pulled from under.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from .errors import HarnessError
from .outdirs import claim_dir, is_temp_name, run_lock


@dataclass
class GcResult:
    """What ``gc`` removed (or would remove): entries as ``stage/key`` and their bytes."""

    removed: list[str] = field(default_factory=list)
    bytes_removed: int = 0
    kept: int = 0


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def collect_garbage(out: Path, dry_run: bool = False) -> GcResult:
    """Remove the cache entries of ``out`` that its last run did not use.

    With ``dry_run``, only list them.

    Raises:
        HarnessError: ``out`` is no run directory, or its run.json predates ``cache_entries``.
    """
    out = Path(out)
    if not (out / "run.json").exists():
        raise HarnessError(
            f"{out}: no run.json here; gc keeps what the last `harness reproduce` used, so "
            "run it first"
        )
    out = claim_dir(out, "run")
    run = json.loads((out / "run.json").read_text())
    keep = run.get("cache_entries")
    if keep is None:
        raise HarnessError(
            f"{out}/run.json has no cache_entries (written by an older harness); rerun "
            "`harness reproduce` first"
        )
    res = GcResult()
    with run_lock(out):
        cache = out / "cache"
        for stage in sorted(p for p in cache.iterdir() if p.is_dir()) if cache.is_dir() else []:
            wanted = set(keep.get(stage.name, []))
            for entry in sorted(
                p for p in stage.iterdir() if p.is_dir() and not is_temp_name(p.name)
            ):
                if entry.name in wanted:
                    res.kept += 1
                    continue
                res.removed.append(f"{stage.name}/{entry.name}")
                res.bytes_removed += _size(entry)
                if not dry_run:
                    shutil.rmtree(entry)
    return res
