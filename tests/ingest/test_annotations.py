"""Annotation validation (errors name the row) and the labelling-tool importers/exporter."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.errors import AnnotationError
from harness.ingest.annotations import COLUMNS, change_boxes, image_name, validate_annotations
from harness.ingest.label_formats import (
    export_for_labelling,
    import_annotations,
    import_coco,
    import_cvat,
    import_voc,
)

FRAMES = pd.DataFrame(
    {
        "session": ["A", "A"],
        "camera": ["c", "c"],
        "utime": [1, 2],
        "width": [100, 100],
        "height": [80, 80],
    }
)


def _ann(rows: list[tuple]) -> pd.DataFrame:
    return pd.DataFrame(rows, columns=COLUMNS)


GOOD = [
    ("A", "c", 1, "change", 10, 10, 20, 30, "car"),
    ("A", "c", 1, "change", 15, 5, 40, 20, ""),
    ("A", "c", 2, "no-change", np.nan, np.nan, np.nan, np.nan, ""),
]


def test_valid_table_passes_and_groups_boxes() -> None:
    df = validate_annotations(_ann(GOOD), FRAMES, "t.csv")
    cb = change_boxes(df)
    assert cb[("A", "c", 1)].shape == (2, 4) and cb[("A", "c", 2)].shape == (0, 4)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        (("A", "c", 1, "change", 10, 10, 10, 30, ""), "line 5: box has zero or negative area"),
        (("A", "c", 1, "change", 10, 10, 120, 30, ""), "line 5: box ends outside the image"),
        (("A", "c", 1, "change", -1, 10, 12, 30, ""), "line 5: box starts outside the image"),
        (("A", "c", 9, "change", 10, 10, 12, 30, ""), "line 5: unknown frame"),
        (("A", "c", 2, "change", 10, 10, 12, 30, ""), "both change and no-change"),
        (("A", "c", 1, "moved", 10, 10, 12, 30, ""), "line 5: status must be one of"),
        (("A", "c", 1, "change", 10, 10, 20, 30, "car"), "line 5: duplicate row"),
        (
            ("A", "c", 1, "change", np.nan, 10, 20, 30, ""),
            "line 5: a change row needs a numeric box",
        ),
    ],
)
def test_bad_rows_are_named(row: tuple, message: str) -> None:
    with pytest.raises(AnnotationError, match=message):
        validate_annotations(_ann([*GOOD, row]), FRAMES, "t.csv")


def test_coco_voc_cvat_import_to_the_same_table(tmp_path: Path) -> None:
    n1, n2 = image_name("A", "c", 1), image_name("A", "c", 2)
    coco = {
        "images": [{"id": 1, "file_name": n1}, {"id": 2, "file_name": n2}],
        "categories": [{"id": 3, "name": "car"}],
        "annotations": [{"id": 1, "image_id": 1, "category_id": 3, "bbox": [10, 10, 10, 20]}],
    }
    (tmp_path / "c.json").write_text(json.dumps(coco))
    voc = tmp_path / "voc"
    voc.mkdir()
    (voc / "1.xml").write_text(
        f"<annotation><filename>{n1}</filename><object><name>car</name><bndbox><xmin>10</xmin><ymin>10</ymin><xmax>20</xmax><ymax>30</ymax></bndbox></object></annotation>"
    )
    (voc / "2.xml").write_text(f"<annotation><filename>{n2}</filename></annotation>")
    (tmp_path / "cvat.xml").write_text(
        f'<annotations><image id="0" name="{n1}"><box label="car" xtl="10" ytl="10" '
        f'xbr="20" ybr="30"/></image><image id="1" name="{n2}"/></annotations>'
    )
    tables = [
        validate_annotations(f(p), FRAMES, str(p))
        for f, p in (
            (import_coco, tmp_path / "c.json"),
            (import_voc, voc),
            (import_cvat, tmp_path / "cvat.xml"),
        )
    ]
    for t in tables[1:]:
        pd.testing.assert_frame_equal(tables[0], t)
    assert tables[0]["status"].tolist() == ["no-change", "change"] or sorted(
        tables[0]["status"]
    ) == ["change", "no-change"]
    out = tmp_path / "ann.csv"
    import_annotations("coco", tmp_path / "c.json", FRAMES, out)
    assert pd.read_csv(out).shape[0] == 2


def test_import_rejects_foreign_file_names(tmp_path: Path) -> None:
    (tmp_path / "c.json").write_text(
        json.dumps({"images": [{"id": 1, "file_name": "IMG_0001.png"}], "annotations": []})
    )
    with pytest.raises(AnnotationError, match=r"IMG_0001\.png.*<session>__<camera>__<utime>"):
        import_coco(tmp_path / "c.json")


def test_box_drawn_on_the_reference_half_is_rejected(tmp_path: Path) -> None:
    n1 = image_name("A", "c", 1)
    (tmp_path / "cvat.xml").write_text(
        f'<annotations><image id="0" name="{n1}"><box label="x" xtl="150" ytl="10" '
        'xbr="170" ybr="30"/></image></annotations>'
    )
    with pytest.raises(AnnotationError, match="ends outside the image"):
        import_annotations("cvat", tmp_path / "cvat.xml", FRAMES, tmp_path / "o.csv")


def test_exporter_writes_side_by_side_images_and_a_task(tmp_path: Path) -> None:
    import cv2

    for t in (1, 2):
        cv2.imwrite(str(tmp_path / f"{t}.png"), np.full((80, 100, 3), 40 * t, np.uint8))
    frames = pd.DataFrame(
        {
            "session": ["A", "B"],
            "camera": ["c", "c"],
            "utime": [1, 2],
            "image": [str(tmp_path / "1.png"), str(tmp_path / "2.png")],
        }
    )
    pairs = pd.DataFrame(
        {
            "q_session": ["A"],
            "q_camera": ["c"],
            "q_utime": [1],
            "r_session": ["B"],
            "r_camera": ["c"],
            "r_utime": [2],
        }
    )
    out = export_for_labelling(pairs, frames, tmp_path / "task")
    task = json.loads((out / "task.json").read_text())
    assert (
        task["images"][0]["file_name"] == image_name("A", "c", 1)
        and task["images"][0]["query_width"] == 100
    )
    img = cv2.imread(str(out / "images" / image_name("A", "c", 1)))
    assert img.shape == (80, 200, 3) and img[0, 0, 0] == 40 and img[0, 150, 0] == 80


# ------------------------------------------------------------------ inputs that are not what they
# say (issue 26): one ERROR line about that file


def _cli_err(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return err


def test_annotation_imports_of_missing_partial_or_wrong_files(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    from harness.cli import main

    out = str(tmp_path / "ann.csv")
    coco = tmp_path / "coco.json"
    cases = [
        (["coco", str(tmp_path / "none.json")], "COCO annotation file not found"),
        (["coco", str(tmp_path)], "COCO annotation file is a directory"),
        (["voc", str(tmp_path / "no_folder")], "VOC annotation folder not found"),
        (["cvat", str(tmp_path / "none.xml")], "CVAT annotation file not found"),
    ]
    for argv, words in cases:
        assert main(["annotations", "import", *argv, "--out", out]) == 1
        assert words in _cli_err(capsys)
    for text, words in (
        ("[1, 2]", "not a COCO annotation file"),
        ('{"images": [{"id": 1}]}', "not a COCO annotation file: KeyError: 'file_name'"),
        ("{not json", "not a COCO annotation file"),
    ):
        coco.write_text(text)
        assert main(["annotations", "import", "coco", str(coco), "--out", out]) == 1
        assert words in _cli_err(capsys)
    coco.write_text('{"images": [], "annotations": []}')
    (tmp_path / "frames.csv").write_text("session,camera\n")
    argv = ["annotations", "import", "coco", str(coco), "--out", out]
    assert main([*argv, "--frames", str(tmp_path / "frames.csv")]) == 1
    assert "not a readable parquet frame table" in _cli_err(capsys)
    assert not Path(out).exists()


def test_annotation_export_with_wrong_tables(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from harness.cli import main

    frames = tmp_path / "frames.parquet"
    pd.DataFrame({"session": ["a"], "camera": ["c"], "utime": [1], "image": ["x.png"]}).to_parquet(
        frames
    )
    argv = ["annotations", "export", "--frames", str(frames), "--out", str(tmp_path / "t")]
    assert main([*argv, "--pairs", str(tmp_path / "none.parquet")]) == 1
    assert "pair table not found" in _cli_err(capsys)
    assert main([*argv, "--pairs", str(frames)]) == 1
    assert "not a pair table (needs columns" in _cli_err(capsys)
    assert not (tmp_path / "t").exists()


def test_annotations_import_as_typed_with_frames_and_force(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``harness annotations import coco SRC --out CSV --frames F [--force]``: the CSV written, a
    second import refused without --force (the user's CSV kept), replaced with it."""
    from harness.cli import main

    n1, n2 = image_name("A", "c", 1), image_name("A", "c", 2)
    coco = {
        "images": [{"id": 1, "file_name": n1}, {"id": 2, "file_name": n2}],
        "categories": [{"id": 3, "name": "car"}],
        "annotations": [{"id": 1, "image_id": 1, "category_id": 3, "bbox": [10, 10, 10, 20]}],
    }
    src, out, frames = tmp_path / "c.json", tmp_path / "ann.csv", tmp_path / "frames.parquet"
    src.write_text(json.dumps(coco))
    FRAMES.assign(image=["a.png", "b.png"]).to_parquet(frames)
    argv = ["annotations", "import", "coco", str(src), "--out", str(out), "--frames", str(frames)]
    assert main(argv) == 0
    assert f"2 annotation rows -> {out}" in capsys.readouterr().out
    first = pd.read_csv(out)
    assert first[["utime", "status", "x1", "y1", "x2", "y2"]].values.tolist()[0] == [
        1, "change", 10, 10, 20, 30,
    ]  # fmt: skip
    coco["annotations"].append(
        {"id": 2, "image_id": 2, "category_id": 3, "bbox": [0, 0, 5, 5]}
    )  # a second change box, on frame 2
    src.write_text(json.dumps(coco))
    assert main(argv) == 1
    assert "--force" in _cli_err(capsys)
    assert pd.read_csv(out).equals(first)  # the user's CSV is kept
    assert main([*argv, "--force"]) == 0
    assert sorted(pd.read_csv(out)["status"]) == ["change", "change"]
