"""Install torch into the virtual environment that runs this script: the Makefile's torch step.

torch is the one package the lock leaves out, since its build depends on the machine. By default
this installs its **CPU build**, ``torch==VERSION+cpu``, with no dependencies (the lock holds them):

1. from a folder of wheels that pip's own configuration names (``find-links``), where that folder
   holds it: nothing is downloaded and no index is asked;
2. else from ``--index`` (the Makefile's ``TORCH_INDEX``: PyTorch's CPU wheel index by default, or
   any PEP 503 index, given as a URL or a local folder). The index's page for torch is read first
   (a few kilobytes), so an index that cannot be reached, or that has no CPU build of this version
   for this Python, is one ``ERROR:`` line within seconds, before any large download.

With ``--build cuda`` it installs ``torch==VERSION`` with its dependencies (the CUDA libraries)
from ``--index`` or, where that is empty, from pip's own index, where the Linux wheel is the CUDA
build. A build already installed at this version is left as it is; the other build is replaced.

What was installed, and from where, is written to ``torch-source.json`` in the environment; every
run's ``run.json`` records it beside the versions. Standard library only: it runs before anything
else is installed. Exit 0 when torch is in place, 1 after one ``ERROR:`` line.
"""

from __future__ import annotations

import argparse
import html.parser
import json
import os
import re
import subprocess
import sys
import urllib.error
import urllib.parse
import urllib.request
from importlib import metadata
from pathlib import Path

SOURCE_FILE = "torch-source.json"
#: The builds the step installs (the Makefile's ``TORCH``).
BUILDS = ("cpu", "cuda")
PROBE_TIMEOUT_S = 20.0


class StepError(Exception):
    """What stops the step, said in one line."""


class _Links(html.parser.HTMLParser):
    """The file names an index page links to (PEP 503: one anchor a file)."""

    def __init__(self) -> None:
        super().__init__()
        self.names: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        href = dict(attrs).get("href") if tag == "a" else None
        if href:
            path = urllib.parse.urlsplit(href).path
            self.names.append(urllib.parse.unquote(path.rsplit("/", 1)[-1]))


def index_url(index: str) -> str:
    """``index`` as a URL pip takes: a local folder becomes a ``file:`` URL."""
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", index):
        return index.rstrip("/")
    folder = Path(index).expanduser().resolve()
    if not folder.is_dir():
        raise StepError(f"TORCH_INDEX={index} is neither a URL nor a folder")
    return folder.as_uri()


def index_files(url: str) -> list[str]:
    """The file names the index lists for the project ``torch`` (its page ``URL/torch/``)."""
    page = f"{url}/torch/"
    if page.startswith("file:"):
        folder = Path(urllib.request.url2pathname(urllib.parse.urlsplit(page).path))
        if not folder.is_dir():
            raise StepError(f"{folder} does not exist")
        listing = folder / "index.html"
        if not listing.is_file():  # pip reads a local project folder's files directly
            return sorted(p.name for p in folder.iterdir())
        text = listing.read_text(encoding="utf-8", errors="replace")
    else:
        request = urllib.request.Request(page, headers={"Accept": "text/html"})
        try:
            with urllib.request.urlopen(request, timeout=PROBE_TIMEOUT_S) as response:
                text = response.read().decode("utf-8", errors="replace")
        except urllib.error.HTTPError as err:
            raise StepError(f"{page} answered HTTP {err.code}") from err
        except (urllib.error.URLError, OSError) as err:
            reason = getattr(err, "reason", err)
            raise StepError(f"{page} could not be reached ({reason})") from err
    parser = _Links()
    parser.feed(text)
    return parser.names


def wanted_wheels(names: list[str], version: str, build: str) -> list[str]:
    """The wheels among ``names`` of this torch version and build for this Python on Linux."""
    local = re.escape(f"+{build}") if build == "cpu" else r"(\+cu\d+)?"
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    pattern = re.compile(
        rf"^torch-{re.escape(version)}{local}-{tag}-{tag}-\S*linux\S*_{re.escape(_machine())}\.whl$"
    )
    return [n for n in names if pattern.match(n)]


def _machine() -> str:
    return os.uname().machine


def installed() -> str | None:
    """The torch version installed in this environment, or None."""
    try:
        return metadata.version("torch")
    except metadata.PackageNotFoundError:
        return None


def pip(*args: str) -> tuple[subprocess.CompletedProcess[str], str]:
    """``python -m pip install -q --no-compile ARGS`` in this environment, its output captured.

    Returns:
        pip's process and the address of the torch file it installed ('' where none).
    """
    report = Path(sys.prefix) / "torch-install-report.json"
    report.unlink(missing_ok=True)
    command = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "-q",
        "--no-compile",
        "--report",
        str(report),
    ]
    proc = subprocess.run([*command, *args], capture_output=True, text=True, check=False)
    url = ""
    if proc.returncode == 0 and report.is_file():
        for item in json.loads(report.read_text()).get("install", []):
            if item.get("metadata", {}).get("name", "").lower() == "torch":
                url = item.get("download_info", {}).get("url", "")
    report.unlink(missing_ok=True)
    return proc, url


def _last_error(proc: subprocess.CompletedProcess[str]) -> str:
    lines = [ln.strip() for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("ERROR")]
    return (errors or lines or ["pip failed with no message"])[-1].removeprefix("ERROR: ")


def install(version: str, build: str, index: str) -> dict[str, str] | None:
    """Put torch ``version`` of ``build`` in place.

    Returns:
        What was installed and the file it came from; None where it was in place already.
    """
    requirement = f"torch=={version}+cpu" if build == "cpu" else f"torch=={version}"
    have = installed()
    if (
        have is not None
        and have.split("+")[0] == version
        and have.endswith("+cpu") == (build == "cpu")
    ):
        return None
    if have is not None:  # the other build, or another version: replaced
        subprocess.run(
            [sys.executable, "-m", "pip", "uninstall", "-q", "-y", "torch"],
            capture_output=True,
            check=False,
        )
    if build == "cpu":
        # 1. a folder of wheels named by pip's own configuration: no index is asked
        proc, got = pip("--no-index", "--no-deps", requirement)
        if proc.returncode == 0:
            return {"torch": installed() or "?", "build": build, "from": got or "find-links"}
    url = index_url(index) if index else ""
    if url:
        # 2. the index: its page for torch first (kilobytes), then the wheel itself
        files = wanted_wheels(index_files(url), version, build)
        if not files:
            py = f"{sys.version_info.major}.{sys.version_info.minor}"
            raise StepError(
                f"{url}/torch/ lists no {build.upper()} build of torch {version} for "
                f"Python {py} on Linux {_machine()}"
            )
    args = ["--index-url", url] if url else []
    if build == "cpu":
        args.append("--no-deps")  # its dependencies are in the lock, hashed
    proc, got = pip(*args, requirement)
    if proc.returncode != 0:
        raise StepError(f"pip could not install {requirement}: {_last_error(proc)}")
    return {"torch": installed() or "?", "build": build, "from": got or url or "pip's index"}


def main(argv: list[str] | None = None) -> int:
    """The step: install, record, and one ``ERROR:`` line where torch cannot be had."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--version", required=True, help="torch's version, e.g. 2.13.0")
    ap.add_argument("--build", default="cpu", help="cpu or cuda (the Makefile's TORCH)")
    ap.add_argument("--index", default="", help="a PEP 503 index (URL or folder); '' for pip's")
    args = ap.parse_args(argv)
    if args.build not in BUILDS:
        print(
            f"ERROR: TORCH={args.build}: not a torch build; {' or '.join(BUILDS)}", file=sys.stderr
        )
        return 1
    try:
        if args.build == "cpu" and not args.index.strip():
            raise StepError("TORCH_INDEX is empty; the CPU build needs an index to come from")
        source = install(args.version, args.build, args.index.strip())
    except StepError as err:
        hint = (
            "set TORCH_INDEX to a PyTorch CPU wheel index (a URL or a folder) that this machine "
            "reaches, or TORCH=cuda for the GPU build from pip's own index"
            if args.build == "cpu"
            else "set TORCH_INDEX to an index that holds it"
        )
        print(
            f"ERROR: torch {args.version} ({args.build.upper()} build) could not be had: {err}; "
            f"{hint}",
            file=sys.stderr,
        )
        return 1
    record = Path(sys.prefix) / SOURCE_FILE
    if source is None:
        print(f"torch {installed()} ({args.build} build) is installed already")
        return 0
    record.write_text(json.dumps(source, indent=1) + "\n")
    print(f"torch {source['torch']} ({source['build']} build) from {source['from']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
