"""Every input file is opened through here: OS and decode errors become one line about *that* file.

A missing path, a directory where a file belongs (or the reverse), a file the user may not read,
and text that is not UTF-8 each get a message that says which, instead of a traceback or a
misleading guess (an unreadable log is not "truncated", an unreadable config is not the output
directory's fault).
"""

from __future__ import annotations

import os
from pathlib import Path

from harness.errors import HarnessError

#: The image files a folder session reads (``harness.ingest.folders``).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def check_input(
    path: Path | str, what: str, error: type[HarnessError] = HarnessError, directory: bool = False
) -> Path:
    """``path`` when it exists, is of the right kind and is readable; else ``error`` naming it.

    Args:
        path: The input.
        what: What the file is, for the message (``"annotation file"``, ``"log"``).
        error: The error class to raise (the stage's).
        directory: Whether a directory is expected (a ROS2 bag, an NCLT root).

    Raises:
        HarnessError: (of class ``error``) what is wrong with that path.
    """
    p = Path(path)
    try:
        found = p.exists()
    except PermissionError:  # a folder on its path is closed: the file cannot even be looked at
        raise error(
            f"{p}: {what} is not readable: a folder on its path is closed to this user "
            "(permission denied); fix that folder's permissions"
        ) from None
    if not found:
        raise error(f"{p}: {what} not found")
    if directory and not p.is_dir():
        raise error(f"{p}: {what} must be a directory, and this is a file")
    if not directory and p.is_dir():
        raise error(f"{p}: {what} is a directory, not a file")
    if not os.access(p, os.R_OK | (os.X_OK if directory else 0)):
        raise error(f"{p}: {what} is not readable (permission denied)")
    return p


def read_text(path: Path | str, what: str, error: type[HarnessError] = HarnessError) -> str:
    """The UTF-8 text of an input file (see :func:`check_input` for the errors).

    Raises:
        HarnessError: (of class ``error``) missing, a directory, unreadable, or not UTF-8.
    """
    p = check_input(path, what, error)
    try:
        return p.read_text(encoding="utf-8")
    except PermissionError:
        raise error(f"{p}: {what} is not readable (permission denied)") from None
    except UnicodeDecodeError as err:
        line = p.read_bytes()[: err.start].count(b"\n") + 1
        raise error(
            f"{p}: {what} is not UTF-8 text ({err.reason} at byte {err.start}, line {line})"
        ) from None


def resolve_config_path(value: str, base: Path, root: Path) -> Path:
    """``value`` with ``{data_root}`` and ``~`` expanded, a relative one under ``base``."""
    p = Path(value.replace("{data_root}", str(root))).expanduser()
    return p if p.is_absolute() else base / p
