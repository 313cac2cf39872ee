"""``harness``: one subcommand per stage plus ``reproduce``.

Library errors become one ``ERROR:`` line and exit 1; anything unexpected becomes one
``ERROR: internal error ...`` line and exit 2 (``-v`` shows the traceback).
"""

from __future__ import annotations

import errno
import logging
import sys
import traceback

from harness import kernels
from harness.cli.parser import build_parser
from harness.cli.runs import cmd_detect, cmd_report, cmd_reproduce
from harness.cli.stages import cmd_fixture, cmd_ingest, cmd_pairs, cmd_proposals, cmd_rank, cmd_task
from harness.cli.tools import cmd_annotations, cmd_gc, cmd_inspect
from harness.errors import HarnessError

__all__ = [
    "build_parser",
    "cmd_annotations",
    "cmd_detect",
    "cmd_fixture",
    "cmd_gc",
    "cmd_ingest",
    "cmd_inspect",
    "cmd_pairs",
    "cmd_proposals",
    "cmd_rank",
    "cmd_report",
    "cmd_reproduce",
    "cmd_task",
    "main",
]

log = logging.getLogger("harness")


_FS_ERRORS = {
    errno.ENOSPC: "free disk space (completed stages are kept) and rerun the same command "
    "to resume",
    errno.EDQUOT: "free disk space within the quota and rerun the same command to resume",
    errno.EROFS: "the file system is read-only: choose a writable --out",
    errno.EACCES: "no permission: this path, or a folder on it, is closed to this user; fix "
    "its permissions (for an output: or choose a writable --out)",
    errno.EPERM: "operation not permitted: fix the permissions of this path or its folder (for "
    "an output: or choose another --out)",
    errno.ENOTDIR: "a part of this path is a regular file, not a directory: choose another path",
    errno.EEXIST: "exists and is not a directory: choose another path",
    errno.EISDIR: "is a directory where a file is expected: choose another path",
    errno.ENAMETOOLONG: "the path is too long: choose a shorter one",
}


def _setup_logging(verbose: bool) -> None:
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(show_path=False, rich_tracebacks=False, log_time_format="%H:%M:%S")],
        force=True,
    )


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; library errors become one ``ERROR:`` line.

    Returns:
        The exit status: 0, 1 after an error of the input, 2 after an internal error, 130 when
        interrupted.
    """
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        kernels.level()
    except ValueError as err:
        print(f"ERROR: {err} (the kernels every table is computed with)", file=sys.stderr)
        return 1
    if kernels.LOADED_BEFORE and kernels.caps():
        log.warning(
            "%s was imported before harness: its kernels are this CPU's own, so tables "
            "may differ from other machines' (import harness first)",
            ", ".join(kernels.LOADED_BEFORE),
        )
    try:
        if args.plugin:  # before any config is read: it may name what they register
            from harness.config.plugins import load_plugins

            load_plugins(args.plugin, "--plugin")
        return int(args.func(args))
    except HarnessError as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        if err.errno not in _FS_ERRORS:
            return _internal(args, err)
        where = err.filename or "an output file"
        print(f"ERROR: {where}: {err.strerror or err}; {_FS_ERRORS[err.errno]}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            "ERROR: interrupted; completed stages are cached, rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    except Exception as err:  # the last resort: a bug, said in one line (the traceback under -v)
        return _internal(args, err)


def _internal(args, err: BaseException) -> int:
    """An unexpected error as one ``ERROR: internal error in <command>`` line; exit 2."""
    if args.verbose:
        traceback.print_exception(err, file=sys.stderr)
    message = str(err).strip().splitlines()[0] if str(err).strip() else ""
    print(
        f"ERROR: internal error in {args.cmd}: {type(err).__name__}"
        + (f": {message}" if message else "")
        + " (run with -v for the traceback)",
        file=sys.stderr,
    )
    return 2
