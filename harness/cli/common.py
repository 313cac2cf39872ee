"""What the command handlers share: the run's config, its pipeline, the detector's flags."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from harness.detect.config import DetectConfig
from harness.errors import HarnessError


def overrides_of(args: argparse.Namespace) -> Any:
    """What every command's line sets over its config: ``--data-root`` and ``--seed``."""
    from harness.config.assemble import Overrides

    return Overrides(data_root=getattr(args, "data_root", None), seed=getattr(args, "seed", None))


def run_config(args: argparse.Namespace) -> Any:
    """The assembled config of ``--config`` (``harness.config.assemble``)."""
    from harness.config.assemble import run_config as config_with

    return config_with(Path(args.config), overrides_of(args))


def check_executor_flags(args: argparse.Namespace) -> None:
    """``--executor``, ``--address`` and ``--ray-cpus`` together, for every command with them."""
    if args.executor != "ray" and (args.address is not None or args.ray_cpus is not None):
        raise HarnessError("--address and --ray-cpus need --executor ray")

    if args.ray_cpus is not None and args.ray_cpus < 1:
        raise HarnessError(f"--ray-cpus {args.ray_cpus}: must be >= 1")


def check_plugins_local(args: argparse.Namespace) -> None:
    """Plugins (``--plugin`` or a config's ``plugins``) run on the local executor only."""
    from harness.config.plugins import LOADED

    if args.executor == "ray" and LOADED:
        raise HarnessError(
            "plugins run on the local executor only: Ray's workers would not import the plugin "
            "files, so the methods they register would be unknown there; drop --executor ray"
        )


def pipeline_of(args: argparse.Namespace):
    """The run's :class:`~harness.pipeline.chain.Pipeline`: config, --out, --import, executor."""
    from harness.pipeline.chain import Pipeline
    from harness.runtime.executors import make_executor

    check_executor_flags(args)
    cfg = run_config(args)  # validated before any executor or directory is set up
    check_plugins_local(args)
    rank_import = None
    if getattr(args, "rank_import", None):
        from harness.retrieval.import_file import parse_import_arg

        rank_import = parse_import_arg(args.rank_import)
        if not rank_import.path.is_file():
            raise HarnessError(
                f"{rank_import.path}: --import file not found (localizer {rank_import.name!r})"
            )
    return Pipeline(
        cfg,
        Path(args.out),
        rank_import=rank_import,
        force=bool(getattr(args, "force", False)),
        executor=make_executor(args.executor, args.address, args.ray_cpus),
    )


#: ``harness detect``'s flags that set a ``[detect]`` value, by the key they set (their
#: argparse destination): filled by :func:`detect_flag` as the parser is built, the one list.
DETECT_FLAGS: list[str] = []


def detect_flag(p: argparse.ArgumentParser, *names: str, help: str, **kw: Any) -> None:
    """A flag that sets ``[detect] <key>``: its help ends with the default the config holds."""
    action = p.add_argument(*names, **kw)
    default = getattr(DetectConfig(), action.dest)
    action.help = f"{help} (default: [detect] {action.dest}, {default})"
    if action.dest not in DETECT_FLAGS:
        DETECT_FLAGS.append(action.dest)
