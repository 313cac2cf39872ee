"""Before any work: the fixture generated where asked, its spec, names and inputs checked."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from harness.descriptors import REGISTRY
from harness.errors import AnnotationError, ConfigError, IngestError
from harness.fixture import FixtureSpec, generate
from harness.fixture.generate import read_spec
from harness.ingest.logs import READERS, detect_format, known_formats
from harness.inputs import check_input
from harness.pipeline.context import Context
from harness.runtime.cache import (
    write_text,
)

log = logging.getLogger(__name__)


def generate_fixture(p: Context) -> None:
    """Generate the fixture into ``data_root`` when ``[fixture] generate`` and it is absent.

    An existing fixture is reused as it is. A ``data_root`` that exists and holds anything else
    is never touched: that is someone's data, and the error says so.
    """
    fx, root = p.cfg.fixture, p.cfg.data_root
    if not fx.generate:
        return
    if (root / "fixture.json").exists():
        check_fixture_spec(p)
        return
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ConfigError(
            f"{root}: [fixture] generate = true, but data_root exists and holds no "
            "generated fixture "
            "(no fixture.json); the harness never writes into it. Set generate = false for "
            "real data, "
            "or point data_root (--data-root) at a new directory"
        )

    log.info("fixture: generating into %s", root)
    spec = FixtureSpec.chosen(fx)
    t0 = time.perf_counter()
    try:
        generate(root, spec, formats=fx.formats or None)
    except ValueError as err:
        raise ConfigError(f"[fixture] {err}") from None
    p.timings["fixture"] = time.perf_counter() - t0
    if p.cfg.annotations is not None and not p.cfg.annotations.exists():
        p.cfg.annotations.parent.mkdir(parents=True, exist_ok=True)
        write_text(p.cfg.annotations, (root / "annotations.csv").read_text())


def check_fixture_spec(p: Context) -> None:
    """An existing generated fixture must be the one ``[fixture]`` describes.

    Raises:
        ConfigError: it was generated with other settings (naming them); it is never replaced
            silently: the message says to remove it so that the next run generates it again.
    """
    fx, root = p.cfg.fixture, p.cfg.data_root
    try:
        have = read_spec(root)
    except (OSError, ValueError, KeyError):
        return  # an unreadable record: ingest reports what is wrong with the data
    want = {
        "seed": fx.seed,
        "frames": fx.frames,
        "width": fx.width,
        "height": fx.height,
        "objects": fx.objects,
        "loop_scale": fx.loop_scale,
        "render_scale": fx.render_scale,
    }
    diff = {k: (have.get(k), v) for k, v in want.items() if k in have and have.get(k) != v}
    if diff:
        raise ConfigError(
            f"{root}: a fixture generated with other [fixture] settings ("
            + ", ".join(f"{k} {a!r} there, {b!r} in the config" for k, (a, b) in diff.items())
            + f"); remove {root} (the harness generated it) and run again to regenerate it"
        )


def check_names(p: Context) -> None:
    """Registry names of the config, checked before the fixture is generated or anything read.

    A descriptor registered at run time counts.

    Raises:
        ConfigError: An unknown descriptor or log format, naming the known ones.
    """
    cfg = p.cfg
    for loc in p.localizer_list:
        if loc.descriptor is not None and loc.descriptor.name not in REGISTRY:
            where = "[descriptor]" if not cfg.localizers else f"localizer {loc.name}: descriptor"
            raise ConfigError(
                f"{where} name = {loc.descriptor.name!r}: unknown; known: {sorted(REGISTRY)}"
            )
    for sc in cfg.sessions:
        if sc.format != "auto" and sc.format not in known_formats():
            raise ConfigError(
                f"sessions {sc.name}: format = {sc.format!r}: unknown; known: "
                f"{list(known_formats())}"
            )


def preflight(p: Context) -> None:
    """Every input the config names checked before any stage runs (nothing half done).

    Every session's log (present, readable, of a known format, an NCLT session's camera), the
    annotation file and a proposal table.

    Raises:
        HarnessError: Naming the key or the file and what is wrong.
    """
    cfg = p.cfg
    for sc in cfg.sessions:
        src = Path(sc.source)
        check_input(src, f"log of session {sc.name}", IngestError, directory=src.is_dir())
        fmt = detect_format(src) if sc.format == "auto" else sc.format
        rec = READERS.get(fmt)
        if rec is not None and rec.check is not None:  # a layout's own check (nclt: the camera)
            rec.check(sc)
    if cfg.annotations is None:
        if not p.annotations_optional:
            raise ConfigError(
                "missing required key 'annotations': the tables measure change against an "
                "annotation file (harness detect runs without one)"
            )
    else:
        check_input(cfg.annotations, "annotation file", AnnotationError)
    if "file" in cfg.proposals.methods and cfg.proposals.file:
        check_input(cfg.proposals.file, "[proposals] file", ConfigError)
