"""Kind ``import``: a user's ranked lists, checked against the run and scored (method §12)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.checks import check_value
from harness.inputs import resolve_config_path
from harness.localizers.config import LocalizerConfig, LocalizerImportConfig
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun, options_of
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.runtime.stage import RankTable, Table


def prepare(im: LocalizerImportConfig, where: str, base: Path, root: Path) -> LocalizerImportConfig:
    """``score_kind`` checked and the file resolved against the config's folder."""
    check_value(
        im.score_kind in ("distance", "similarity"),
        where,
        "import.score_kind",
        im.score_kind,
        "'distance' or 'similarity'",
    )
    return dataclasses.replace(im, file=str(resolve_config_path(im.file, base, root)))


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """The user's ranked lists, checked and scored (method §12)."""
    im = options_of(loc, loc.import_)
    spec = ImportSpec(loc.name, Path(im.file))
    return p.imported_ranks(frames, pairs, mine, spec, im.score_kind, rc)


def summary(rec: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The page's words: the file, its content's sha256 and how its scores read."""
    return (
        f"imported from {rec.get('file')} (sha256 {rec.get('sha256')}, scores as "
        f"{rec.get('score_kind')})"
    )


KIND = LocalizerKind("import", LocalizerImportConfig, prepare, ranks=ranks, summary=summary)
