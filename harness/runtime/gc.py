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

from harness.errors import HarnessError
from harness.runtime.outdirs import claim_dir, is_temp_name, read_run_record, run_lock


@dataclass
class GcResult:
    """What ``gc`` removed (or would remove).

    Attributes:
        removed: Entries as ``stage/key``.
        bytes_removed: Their size in bytes.
        kept: Entries the last run used.
        foreign: Paths under ``cache/`` that the harness did not write (never touched), each
            with the reason it was left alone.
    """

    removed: list[str] = field(default_factory=list)
    bytes_removed: int = 0
    kept: int = 0
    foreign: list[str] = field(default_factory=list)


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def _not_ours(stage: str, entry: Path) -> str | None:
    """Why ``entry`` is not a cache entry the harness wrote (None: it is one, and only that).

    A harness entry is a directory (not a link) whose ``manifest.json`` names its stage and key
    and lists every file in it.
    """
    if entry.is_symlink():
        return "a symbolic link"
    if not entry.is_dir():
        return "not a directory"
    try:
        man = json.loads((entry / "manifest.json").read_text())
    except (OSError, ValueError):
        return "no readable manifest.json"
    if not isinstance(man, dict) or man.get("stage") != stage or man.get("key") != entry.name:
        return "its manifest.json names another entry"
    listed = set((man.get("files") or {}).keys()) | {"manifest.json"}
    for p in sorted(entry.rglob("*")):
        rel = str(p.relative_to(entry))
        if p.is_symlink() or (p.is_file() and rel not in listed):
            return f"holds {rel!r}, which its manifest does not list"
    return None


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
    run = read_run_record(out)
    keep = run.get("cache_entries")
    if not isinstance(keep, dict):
        raise HarnessError(
            f"{out}/run.json has no cache_entries (written by an older harness); rerun "
            "`harness reproduce` first"
        )
    res = GcResult()
    with run_lock(out):
        cache = out / "cache"
        stages = (
            sorted(p for p in cache.iterdir() if p.is_dir() and not p.is_symlink())
            if cache.is_dir()
            else []
        )
        for stage in stages:
            wanted = set(keep.get(stage.name, []))
            for entry in sorted(p for p in stage.iterdir() if not is_temp_name(p.name)):
                if entry.name in wanted:
                    res.kept += 1
                    continue
                why = _not_ours(stage.name, entry)
                if why is not None:
                    res.foreign.append(f"cache/{stage.name}/{entry.name} ({why})")
                    continue
                res.removed.append(f"{stage.name}/{entry.name}")
                res.bytes_removed += _size(entry)
                if not dry_run:
                    shutil.rmtree(entry)
    return res
