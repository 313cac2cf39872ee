"""The Makefile's torch step on a machine that is not ours: pip's configuration emptied.

The step (``tools/install_torch.py``, run by ``make``) takes torch's CPU build from
``TORCH_INDEX``. Here the index is a PEP 503 folder that the test builds around the CPU wheel it
finds on this machine, standing in for PyTorch's CPU index; and an index that is not there must
stop the set-up within seconds with one ``ERROR:`` line naming ``TORCH_INDEX``, before any large
download, leaving no stamp that a second ``make`` would take for a finished environment.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import ROOT

TORCH_VERSION = re.search(r"^TORCH_VERSION := (\S+)$", (ROOT / "Makefile").read_text(), re.M)[1]  # type: ignore[index]
TAG = f"cp{sys.version_info.major}{sys.version_info.minor}"


def _clean_env() -> dict[str, str]:
    """This process's environment less pip's configuration (no file, no PIP_* variable)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "UV_"))}
    env["PIP_CONFIG_FILE"] = os.devnull
    env.pop("MAKEFLAGS", None)
    env.pop("MFLAGS", None)
    return env


def _cpu_wheel() -> Path:
    """torch's CPU wheel for this Python, from the folders pip's configuration names."""
    folders = os.environ.get("PIP_FIND_LINKS", "").split()
    got = subprocess.run(
        [sys.executable, "-m", "pip", "config", "get", "global.find-links"],
        capture_output=True,
        text=True,
        check=False,
    )
    folders += got.stdout.split()
    for folder in folders:
        path = Path(folder.removeprefix("file://"))
        if path.is_dir():
            found = sorted(path.glob(f"torch-{TORCH_VERSION}+cpu-{TAG}-{TAG}-*linux*.whl"))
            if found:
                return found[0]
    pytest.skip(
        f"no torch {TORCH_VERSION} CPU wheel for {TAG} in pip's find-links here to build a "
        "local index from"
    )


def _index(tmp: Path, wheel: Path | None) -> Path:
    """A PEP 503 index in ``tmp`` whose project ``torch`` lists ``wheel`` (or nothing)."""
    page = tmp / "torch"
    page.mkdir(parents=True)
    links = f'<a href="{wheel.as_uri()}">{wheel.name}</a>' if wheel else ""
    (page / "index.html").write_text(f"<!DOCTYPE html><html><body>{links}</body></html>\n")
    return tmp


def _make(
    target: str, venv: Path, index: str, *more: str
) -> tuple[subprocess.CompletedProcess[str], float]:
    start = time.monotonic()
    proc = subprocess.run(
        ["make", "--no-print-directory", f"VENV={venv}", f"TORCH_INDEX={index}", *more, target],
        cwd=ROOT,
        env=_clean_env(),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    return proc, time.monotonic() - start


def _packages(venv: Path) -> list[str]:
    listed = subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "list", "--format", "json"],
        capture_output=True,
        text=True,
        env=_clean_env(),
        check=True,
    )
    return [p["name"].lower() for p in json.loads(listed.stdout)]


def test_the_torch_step_stops_on_an_index_that_cannot_serve_then_takes_the_cpu_build(
    tmp_path: Path,
) -> None:
    """An index that cannot serve: one ERROR: line before the lock's packages are downloaded, no
    stamp, and the same again (CPU, or ``TORCH=cuda`` where the index has no GPU build); then, in
    the same half-made environment, the CPU build from a PEP 503 index and nothing of CUDA."""
    wheel = _cpu_wheel()
    empty = str(_index(tmp_path / "empty", None))
    venv = tmp_path / "venv"
    # port 9 (discard) on loopback refuses the connection: an index that is not there; twice, as
    # the second make must not take the half-made environment for finished
    cases = [
        ("cpu", "http://127.0.0.1:9/whl/cpu", "could not be reached"),
        ("cpu", "http://127.0.0.1:9/whl/cpu", "could not be reached"),
        ("cpu", empty, "lists no CPU build"),
        ("cuda", empty, "lists no CUDA build"),
    ]
    for build, index, why in cases:
        proc, took = _make("setup", venv, index, f"TORCH={build}")
        assert proc.returncode != 0
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("ERROR:")]
        assert len(errors) == 1, proc.stderr
        assert "TORCH_INDEX" in errors[0] and why in errors[0], errors[0]
        assert f"torch {TORCH_VERSION} ({build.upper()} build)" in errors[0]
        assert "Traceback" not in proc.stderr
        assert took < 60
        assert not (venv / ".packages").exists() and not (venv / ".installed").exists()
        assert not (venv / f".torch-{build}").exists()
    proc, _ = _make("setup", venv, empty, "TORCH=rocm")  # a build the step does not know
    assert proc.returncode != 0
    assert [ln for ln in proc.stderr.splitlines() if ln.startswith("ERROR:")] == [
        "ERROR: TORCH=rocm: not a torch build; cpu or cuda"
    ]
    names = _packages(venv)  # nothing downloaded: not even the lock
    assert "torch" not in names and "numpy" not in names

    index = _index(tmp_path / "cpu", wheel)
    proc, _ = _make(f"{venv}/.torch-cpu", venv, str(index))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"torch {TORCH_VERSION}+cpu (cpu build) from {wheel.as_uri()[:20]}" in proc.stdout
    source = json.loads((venv / "torch-source.json").read_text())
    assert source["torch"] == f"{TORCH_VERSION}+cpu" and source["build"] == "cpu"
    assert Path(re.sub("%2B", "+", source["from"]).removeprefix("file://")) == wheel
    names = _packages(venv)
    assert "torch" in names
    assert not [n for n in names if n.startswith(("nvidia-", "cuda-"))], names
    # a second make finds it in place and asks nothing
    again, _ = _make(f"{venv}/.torch-cpu", venv, str(tmp_path / "not-there"))
    assert again.returncode == 0 and "is up to date" in again.stdout + again.stderr
