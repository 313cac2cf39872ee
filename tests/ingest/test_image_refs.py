"""An image's reference (path, rotation, perturbed copy) is read and written in one place.

``harness.imagestore.ImageRef``: a ``#`` in a path, spaces and non-ASCII names belong to the
path; only a trailing ``#rot=`` and ``#perturb=`` are fragments. Here on references made up, and
through ``harness detect`` on two folders whose names and files hold all three.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.imagestore import ImageRef, make_uri, read_image, split_uri
from harness.perturb import Perturbation, fragment

from ..conftest import ROOT, TEST_NULL_PAIRS, blob_wall

PATHS = ["a/b c.png", "dir #1/x #2 é.png", "/abs/ü/#rot=cw.png", "a/x#rot=bad.png", "p.jpg"]


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("rotation", ["none", "cw", "ccw", "180"])
@pytest.mark.parametrize("copy", [None, Perturbation(gain=1.05, offset=-3.0, dx=0.01)])
def test_a_reference_is_written_and_read_back(
    path: str, rotation: str, copy: Perturbation | None
) -> None:
    spec = fragment(copy).removeprefix("#perturb=") if copy is not None else None
    ref = ImageRef(path, rotation, spec)
    assert ImageRef.parse(ref.uri) == ref
    assert ref.name == Path(path).name and ref.uri.startswith(path)
    assert (ref.perturbed is None) == (copy is None)
    if copy is None:  # the two older readers agree with it
        assert split_uri(ref.uri) == (path, rotation) and make_uri(path, rotation) == ref.uri
    else:
        assert ref.perturbed == copy and ref.uri.endswith(fragment(copy))


def test_a_copy_fragment_without_values_is_no_copy_of_anything() -> None:
    ref = ImageRef.parse("a #1.png#rot=cw#perturb=")
    assert (ref.path, ref.rotation, ref.perturbation) == ("a #1.png", "cw", "")
    assert ref.uri == "a #1.png#rot=cw#perturb="
    with pytest.raises(ValueError, match="unknown part"):
        _ = ref.perturbed


def test_a_file_named_with_a_hash_reads_turned_and_copied(tmp_path: Path) -> None:
    img = np.zeros((20, 30, 3), np.uint8)
    img[:5, :5] = 255
    d = tmp_path / "x #1 é"
    d.mkdir()
    f = d / "f #rot=2 ü.png"
    cv2.imwrite(str(f), img)
    assert read_image(str(f)).shape == (20, 30, 3)
    turned = read_image(ImageRef(str(f), "cw").uri)
    assert turned.shape == (30, 20, 3) and turned[:5, -5:].min() == 255
    spec = fragment(Perturbation(gain=0.5)).removeprefix("#perturb=")
    copy = read_image(ImageRef(str(f), "cw", spec).uri)
    assert copy.shape == (30, 20, 3) and 120 <= int(copy[0, -1, 0]) <= 135


def _folders(root: Path, n: int = 6) -> tuple[Path, Path, list[str]]:
    """Two folders of a sliding wall, a square pasted into every other frame of the second."""
    w, h = 160, 120
    wall = blob_wall(3, w + 6 * n, h)
    a, b = root / "the map #1 é", root / "new visit ü #2"
    a.mkdir(parents=True)
    b.mkdir()
    names, rows = [], ["image,status,x1,y1,x2,y2,label"]
    for i in range(n):
        name = f"frame #{i} é.png"
        im = np.ascontiguousarray(wall[:, 6 * i : 6 * i + w])
        q = im.copy()
        if i % 2 == 0:
            q[30:66, 40:76] = (230, 40, 200)
            rows.append(f"{name},change,40,30,76,66,box")
        else:
            rows.append(f"{name},no-change,,,,,")
        assert cv2.imwrite(str(a / name), im[..., ::-1]) and cv2.imwrite(
            str(b / name), q[..., ::-1]
        )
        names.append(name)
    (root / "ann.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return a, b, names


def test_detect_on_folders_and_files_named_with_hashes_spaces_and_accents(tmp_path: Path) -> None:
    """Every output names the files as they are named, the page included."""
    a, b, names = _folders(tmp_path)
    out = tmp_path / "out #3 ö"
    small = tmp_path / "small null.toml"  # the null's own figures are another test's
    small.write_text(f"[detect.null]\npairs = {TEST_NULL_PAIRS}\n")
    cmd = [sys.executable, "-m", "harness.cli", "detect", "--map-images", str(a),
           "--query-images", str(b), "--annotations", str(tmp_path / "ann.csv"),
           "--config", str(small), "--out", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    fr = pd.read_csv(out / "frames.csv")
    assert sorted(fr["name"]) == sorted(names) and sorted(fr["r_name"]) == sorted(names)
    images = json.loads((out / "images.json").read_text(encoding="utf-8"))["images"]
    assert sorted(i["file_name"] for i in images) == sorted(names)
    assert {Path(i["path"]).parent.name for i in images} == {b.name}
    assert all(i["rotation"] == "none" for i in images)
    rec = json.loads((out / "detect.json").read_text(encoding="utf-8"))
    assert rec["folders"] == [a.name, b.name] and rec["calibration"]["construction"] == "perturbed"
    page = (out / "detect.html").read_text(encoding="utf-8")
    assert b.name in page and names[0] in page
    assert f"{b.name} against the map {a.name}" in " ".join(proc.stdout.split())
