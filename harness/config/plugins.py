"""A user's extension files, the users' door: Python files that register methods.

A plugin is one ``.py`` file of the user's that calls the harness's register functions
(``harness.fusion.register_fusion_rule``, ``harness.proposals.register_proposer``,
``harness.localizers.kinds.register_localizer_kind``, ``harness.ingest.logs.register_format``,
``harness.reports.tables.register_table``, or adds a descriptor class). The config lists them
(``plugins = ["my_rule.py"]``, relative to the config file) or the command line does
(``harness --plugin my_rule.py reproduce ...``); each is imported once per process, before the
config's sections are read, so ``[fusion] methods`` may name the rule it adds and
``[fusion.<rule>]`` may hold its options. ``run.json`` records each file's SHA-256.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from collections.abc import Iterable
from pathlib import Path

from harness.errors import ConfigError
from harness.runtime.cache import content_sha

#: The plugins imported in this process: resolved path -> SHA-256 of the file as imported.
LOADED: dict[Path, str] = {}


def load_plugins(paths: Iterable[str | Path], where: str) -> list[Path]:
    """Import each plugin file not yet imported in this process; return the resolved paths.

    Raises:
        ConfigError: a path that is no ``.py`` file, a file whose import fails (its error named),
            or one that registers a name already taken.
    """
    out = []
    for given in paths:
        path = Path(given).expanduser().resolve()
        if path.suffix != ".py" or not path.is_file():
            raise ConfigError(f"{where}: plugin {given}: no such Python (.py) file")
        out.append(path)
        if path in LOADED:
            continue
        sha = content_sha(path, full=True)
        name = f"dbl_harness_plugin_{re.sub(r'[^0-9A-Za-z_]', '_', path.stem)}_{sha[:12]}"
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise ConfigError(f"{where}: plugin {given}: not importable as a Python module")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # inspect.getsource (the cache keys) finds its functions
        try:
            spec.loader.exec_module(module)
        except Exception as err:  # a user's file: whatever it raises is said in one line
            sys.modules.pop(name, None)
            raise ConfigError(
                f"{where}: plugin {given}: {type(err).__name__}: {err}".rstrip(": ")
            ) from None
        LOADED[path] = sha
    return out


def plugin_record() -> list[dict[str, str]]:
    """What ``run.json`` says of the plugins imported in this process: path and SHA-256."""
    return [{"path": str(p), "sha256": s} for p, s in sorted(LOADED.items())]
