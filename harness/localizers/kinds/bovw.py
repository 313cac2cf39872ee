"""Kind ``bovw``: a bag of visual words (method §11), ranked by the harness's engine."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun, options_of
from harness.retrieval import stage as retrieval_stage
from harness.retrieval.config import BovwConfig, RetrievalConfig, check_bovw
from harness.runtime.stage import RankTable, Table


def prepare(bw: BovwConfig, where: str, base: Path, root: Path) -> BovwConfig:
    """The ``bovw`` table checked at load."""
    check_bovw(bw, f"{where}.bovw")
    return bw


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """Vocabulary, words, then the same ranking engine on the sparse vectors."""
    bc = options_of(loc, loc.bovw)
    vocab = retrieval_stage.bovw_vocabulary(p, bc, frames, pairs, mine)
    words, nofeat = retrieval_stage.bovw_words(p, bc, loc.name, frames, mine, vocab)
    out = p.query_ranks(frames, pairs, words, rc, p.descriptor_device)
    out.counts["bovw"] = {"no_feature_subimages": nofeat}
    return out


def summary(rec: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The page's words: its features and vocabulary size."""
    bw = rec.get("bovw", {})
    return f"bag of visual words ({bw.get('features')}, k = {bw.get('k')})"


KIND = LocalizerKind("bovw", BovwConfig, prepare, ranks=ranks, summary=summary)
