"""The config of ``harness detect`` on two folders of images (method §13.2): no config file."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from harness.config.load import parse_config
from harness.config.schema import Config
from harness.descriptors.config import DescriptorConfig
from harness.errors import ConfigError
from harness.ingest.config import SessionConfig
from harness.inputs import IMAGE_SUFFIXES
from harness.pairs.modes import kind_of

#: The share of a query folder's images that must have a map image of the same name (stem) for
#: two folders to be paired by name by default (method §13.2).
SHARED_NAMES = 0.5


def folder_pairing(map_dir: Path, query_dirs: list[Path]) -> str:
    """``[pairs] by`` for folders without poses where the config does not say (method §13.2).

    ``name`` where every query folder shares names with the map (:data:`SHARED_NAMES` of its
    images), else ``sequence``: on the fixture's twelve pairs of traverses, every frame a query,
    it pairs 95% of the frames within 10 m of the pose pair, retrieval 68% and order 0%
    (docs/decisions.md, *Pairs without poses*).
    """

    def stems(d: Path) -> set[str]:
        return {p.stem for p in Path(d).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}

    have = stems(map_dir)
    for d in query_dirs:
        mine = stems(d)
        if not mine or len(mine & have) < SHARED_NAMES * len(mine):
            return "sequence"
    return "name"


#: The descriptor folders are paired with where no config names one: SeqSLAM's patch-normalised
#: thumbnail of each grid5 box, which needs no training (docs/decisions.md, *Pairs without poses*:
#: the largest worst share over the fixture's traverses and the real seasons of nordland-dev).
PAIRING_DESCRIPTOR = DescriptorConfig(name="seqslam", input_size=64)
PAIRING_PROPOSALS = ("grid5",)


def training_free_pairing(cfg: Config) -> Config:
    """``cfg`` pairing its frames with :data:`PAIRING_DESCRIPTOR` on the whole frame.

    A run never trains a network only to pair its frames; a ``--config`` that names its own
    ``[descriptor]`` (the autoencoder, say) is used as it is.
    """
    return dataclasses.replace(
        cfg,
        descriptor=PAIRING_DESCRIPTOR,
        proposals=dataclasses.replace(cfg.proposals, methods=PAIRING_PROPOSALS),
    )


def image_folders_config(
    map_dir: Path, query_dirs: list[Path], cfg: Config | None = None
) -> tuple[Config, str, list[str]]:
    """The config of ``harness detect --map-images DIR --query-images DIR`` (method §13.2).

    The folders are sessions of images alone (format ``images``): the map is ``map``, the queries
    ``query``, ``query2``, ... Every query frame is paired as ``cfg``'s ``[pairs] by`` says, or,
    where it says ``pose`` (the default, and there are no poses), by name where the folders share
    file names, else by sequence (:func:`folder_pairing`) with the training-free descriptor
    :data:`PAIRING_DESCRIPTOR` where ``cfg`` is None, with ``cfg``'s localizer else. Every other
    setting is ``cfg``'s (a ``--config``), or the defaults; its sessions and fixture are not used,
    its annotations and masks are (rows naming their image, method §13.2; rows of its own sessions
    are left out).

    Returns:
        (the config, the map session's name, the query sessions' names).
    """
    names = ["map", *(f"query{i + 1 if i else ''}" for i in range(len(query_dirs)))]
    dirs = [Path(map_dir), *map(Path, query_dirs)]
    where = "--map-images/--query-images"
    for d in dirs:
        if not d.is_dir():
            raise ConfigError(f"{where}: {d} is not a folder of images")
        if not any(p.suffix.lower() in IMAGE_SUFFIXES for p in d.iterdir()):
            raise ConfigError(
                f"{where}: {d} holds no image file ({', '.join(IMAGE_SUFFIXES)}) in the folder "
                "itself"
            )
    sessions = [
        {"name": n, "source": str(d.expanduser().resolve()), "format": "images", "season": n}
        for n, d in zip(names, dirs, strict=True)
    ]
    base = cfg or parse_config({"name": "image-folders", "sessions": sessions}, Path.cwd(), where)
    by = base.pairs.by if kind_of(base.pairs.by) != "pose" else folder_pairing(dirs[0], dirs[1:])
    if cfg is None and kind_of(by) == "retrieval":
        base = training_free_pairing(base)
    out = dataclasses.replace(
        base,
        sessions=tuple(SessionConfig(**s) for s in sessions),
        annotations=base.annotations,
        fixture=dataclasses.replace(base.fixture, generate=False),
        pairs=dataclasses.replace(base.pairs, by=by, queries="all"),
    )
    if by == "name" and out.detect.local.identity_min_ncc > -1:
        # pairs by name are the same view by declaration (co-registered tiles, a camera that
        # re-shoots its views): one the local localizer cannot align falls back to identity,
        # never lost; alignment.csv and detect.json's alignment count how many did
        local = dataclasses.replace(out.detect.local, identity_min_ncc=-1.0)
        out = dataclasses.replace(out, detect=dataclasses.replace(out.detect, local=local))
    return out, names[0], names[1:]
