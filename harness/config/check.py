"""The root config's checks: each section's own (beside its stage), then cross-section ones.

All run at load time, in the order they always ran.

Each failure is one :class:`~harness.errors.ConfigError` naming the key, the value and what is
allowed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from harness.checks import MAX_SEED, check_device, check_value
from harness.config.schema import Config
from harness.descriptors.config import check_descriptor, check_projection
from harness.detect.config import check_detect
from harness.errors import ConfigError
from harness.evaluate.config import check_recall_at, check_report, check_splits
from harness.fixture.config import check_fixture_section
from harness.fusion.config import check_fusion
from harness.ingest.config import check_ingest_section, check_masks
from harness.pairs.config import check_pairs
from harness.pairs.modes import kind_of
from harness.proposals.config import check_proposals
from harness.retrieval.config import check_import, check_retrieval


def validate(
    cfg: Config, where: str, typed: Mapping[str, str] | None = None, command: str = ""
) -> None:
    """Range checks that a dataclass cannot express, all at load time, before any work.

    The one place a run's config is checked (:func:`harness.config.assemble.with_overrides`),
    once, after the command line's values are in it. One function per section, in the order they
    always ran. ``where``: the file (or folders) the config came from; ``typed``: each
    ``[detect]`` field (and ``seed``) the command line set -> its flag, named with ``command`` in
    the error instead of ``where`` and the key.

    Raises:
        ConfigError: naming the key, the value and the allowed range.
    """
    check_import(cfg.import_, where)
    check_fusion(cfg.fusion, where)
    check_pairs(cfg.pairs, where)
    _check_pairs_without_poses(cfg, where)
    check_masks(cfg.masks, where)
    check_ingest_section(cfg.ingest, where)
    check_retrieval(cfg.retrieval, where)
    _check_seeds(cfg, where, (command, typed["seed"]) if typed and "seed" in typed else None)
    check_projection(cfg.projection, where)
    check_descriptor(cfg.descriptor, where)
    check_proposals(cfg.proposals, where)
    check_splits(cfg.splits, where)
    check_report(cfg.report, where)
    _check_second_radius(cfg, where)
    check_detect(cfg.detect, where, typed, command)
    check_recall_at(cfg.report, where)
    check_fixture_section(cfg.fixture, where, len(cfg.sessions))
    check_device(cfg.descriptor.device, where, "[descriptor] device")
    for i, loc in enumerate(cfg.localizers):
        if loc.descriptor is not None:  # the [descriptor] checks, on the localizer's table
            try:
                validate(dataclasses.replace(cfg, descriptor=loc.descriptor, localizers=()), where)
            except ConfigError as err:
                raise ConfigError(
                    str(err).replace("[descriptor]", f"localizers[{i}] ({loc.name}) descriptor")
                ) from None


def _check_pairs_without_poses(cfg: Config, where: str) -> None:
    """Pairing other than by pose: no option that needs poses (a thinned database, a radius)."""
    c = check_value
    pa = cfg.pairs
    if kind_of(pa.by) != "pose":
        rc, rp = cfg.retrieval, cfg.report
        c(
            rc.db_stride_m == 0,
            where,
            "[retrieval] db_stride_m",
            rc.db_stride_m,
            f"0 with [pairs] by = {pa.by!r} (a database thinned by distance needs poses)",
        )
        c(
            rp.gt_radius_also == 0,
            where,
            "[report] gt_radius_also",
            rp.gt_radius_also,
            f"0 with [pairs] by = {pa.by!r} (a place radius needs poses)",
        )


def _check_seeds(cfg: Config, where: str, flag: tuple[str, str] | None = None) -> None:
    """Every seed, the run's, each section's and each localizer's, in ``0 .. MAX_SEED``.

    ``flag``: (the command, its flag) where the run's seed was typed.
    """
    c = check_value
    at, key = flag or (where, "seed")
    c(0 <= cfg.seed <= MAX_SEED, at, key, cfg.seed, f"0 .. {MAX_SEED}")
    for section in ("descriptor", "projection", "fusion", "proposals", "retrieval"):
        sub = getattr(cfg, section, None)
        if sub is not None and hasattr(sub, "seed"):
            c(0 <= sub.seed <= MAX_SEED, where, f"[{section}] seed", sub.seed, f"0 .. {MAX_SEED}")
    for lc in cfg.localizers:
        if lc.descriptor is not None:
            c(
                0 <= lc.descriptor.seed <= MAX_SEED,
                where,
                f"[[localizers]] {lc.name}: [descriptor] seed",
                lc.descriptor.seed,
                f"0 .. {MAX_SEED}",
            )


def _check_second_radius(cfg: Config, where: str) -> None:
    """``[report] gt_radius_also`` against ``[retrieval]``'s radius and database stride."""
    rp, rc = cfg.report, cfg.retrieval
    check_value(
        rp.gt_radius_also >= 0
        and rp.gt_radius_also != rc.gt_radius_m
        and (rp.gt_radius_also == 0 or rp.gt_radius_also >= rc.db_stride_m / 2),
        where,
        "[report] gt_radius_also",
        rp.gt_radius_also,
        "0 (off) or a second place radius in metres, other than [retrieval] gt_radius_m and at "
        "least half of [retrieval] db_stride_m",
    )
