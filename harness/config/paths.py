"""How a path written in a config resolves (sessions, annotations, networks, imported lists)."""

from __future__ import annotations

from pathlib import Path


def resolve_config_path(value: str, base: Path, root: Path) -> Path:
    """``value`` with ``{data_root}`` and ``~`` expanded, a relative one under ``base``."""
    p = Path(value.replace("{data_root}", str(root))).expanduser()
    return p if p.is_absolute() else base / p
