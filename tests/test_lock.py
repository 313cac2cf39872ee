"""Dependencies chosen, not floating (issue 50): `make setup` installs `requirements.lock`.

``pyproject.toml`` keeps ranges for people who import the package; the lock holds one exact,
hashed version of every other package (``make lock`` upgrades it deliberately). OpenCV is 4.x by
measurement: ``python -m bench.opencv_calls`` runs every cv2 call the harness makes under two
releases; 5.0 changed MSER (3 regions where 4.14 finds 34 on the same frame), so the ``mser``
proposer gave 0-2 boxes instead of its 12.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, version

import numpy as np

from .conftest import ROOT

LOCK = ROOT / "requirements.lock"


def _locked() -> dict[str, str]:
    """``name: version`` of every package in the lock (names normalised as PEP 503 does)."""
    pins = re.findall(r"^([A-Za-z0-9_.\-]+)==([^\s\\]+)", LOCK.read_text(), flags=re.M)
    return {re.sub(r"[-_.]+", "-", n).lower(): v for n, v in pins}


def _norm(req: str) -> str:
    return re.sub(r"[-_.]+", "-", re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0]).lower()


def test_every_locked_package_is_hashed_and_torch_is_left_to_its_exact_wheel() -> None:
    text = LOCK.read_text()
    locked = _locked()
    assert len(locked) > 40
    blocks = re.split(r"\n(?=[A-Za-z0-9])", text.split("\n", 2)[-1])
    assert all("--hash=sha256:" in b for b in blocks if "==" in b)
    assert "torch" not in locked and not any(n.startswith("nvidia-") for n in locked)
    assert locked["opencv-contrib-python-headless"].startswith("4.")
    assert "opencv-python-headless" not in locked  # two packages of one cv2 overwrite each other


def test_every_dependency_of_pyproject_is_in_the_lock() -> None:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [*meta["dependencies"], *meta["optional-dependencies"]["dev"]]
    missing = {_norm(r) for r in reqs} - set(_locked()) - {"torch"}
    assert not missing, missing


def test_the_installed_packages_are_the_locked_ones() -> None:
    """``make setup`` installed the lock: a package at another version means the venv drifted."""
    differ = {}
    for name, want in _locked().items():
        try:
            got = version(name)
        except PackageNotFoundError:
            got = "absent"
        if got != want:
            differ[name] = (got, want)
    assert not differ, f"{differ}: rerun make setup (or make lock to upgrade deliberately)"


def _cv2_calls(tree: ast.AST) -> set[str]:
    return {
        n.func.attr
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        and isinstance(n.func, ast.Attribute)
        and isinstance(n.func.value, ast.Name)
        and n.func.value.id == "cv2"
    }


def test_the_opencv_measurement_covers_every_cv2_call_of_the_harness() -> None:
    used: set[str] = set()
    for f in (ROOT / "harness").rglob("*.py"):
        used |= _cv2_calls(ast.parse(f.read_text()))
    measured = _cv2_calls(ast.parse((ROOT / "bench" / "opencv_calls.py").read_text()))
    # cv2.dnn.* calls are attributes of cv2.dnn, checked by name in the measurement's source
    dnn = set(re.findall(r"cv2\.dnn\.(\w+)\(", "".join(
        f.read_text() for f in (ROOT / "harness").rglob("*.py"))))  # fmt: skip
    src = (ROOT / "bench" / "opencv_calls.py").read_text()
    assert used - measured - {"imread", "imwrite"} == set(), used - measured
    assert all(f"cv2.dnn.{d}(" in src for d in dnn), dnn
    assert {"imencode", "imdecode"} <= measured  # imread/imwrite: the same codecs, from a file


def test_mser_proposals_find_regions_on_a_textured_frame() -> None:
    """The measurement that chose OpenCV 4: 5.0's MSER gave this frame 0-2 boxes."""
    import cv2

    from harness.proposals.builtin import mser_boxes
    from harness.proposals.config import MserConfig

    rng = np.random.default_rng(0)
    img = np.full((240, 320, 3), 90, np.uint8)
    for _ in range(14):
        x, y = int(rng.integers(0, 280)), int(rng.integers(0, 200))
        colour = tuple(int(v) for v in rng.integers(0, 255, 3))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(10, 60)), y + 30), colour, -1)
    boxes, _ = mser_boxes(img, MserConfig())
    assert len(boxes) >= 6, (cv2.__version__, len(boxes))


def test_the_opencv_measurement_runs_as_the_readme_types_it(tmp_path) -> None:
    """``python -m bench.opencv_calls --out A.json`` (``--quick``: the small frame once), then
    ``--compare A B``: a markdown row per call, the same bytes against itself."""
    run = [sys.executable, "-m", "bench.opencv_calls"]
    out = tmp_path / "a.json"
    subprocess.run([*run, "--quick", "--out", str(out)], cwd=ROOT, check=True, capture_output=True)
    table = subprocess.run(
        [*run, "--compare", str(out), str(out)], cwd=ROOT, check=True, capture_output=True,
        text=True,
    ).stdout  # fmt: skip
    rows = [x for x in table.splitlines() if x.startswith("| 240x320")]
    assert len(rows) >= 20 and all("| yes |" in x for x in rows), table
    assert any("MSER" in x for x in rows) and any("SIFT" in x for x in rows)
