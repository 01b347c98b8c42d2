"""Issue 44: `omnigen export` (coco, yolo, kitti), `stats`, `eval-kitti` and `calib-sensitivity`
never write onto a file they read or did not make, write by temporary name and rename, and an
exporter refuses a value it cannot write as a finite number (docs/untrusted-inputs.md)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from omnigen.cli import main
from omnigen.dataset import Dataset, record_path
from omnigen.fakes import write_fake_dataset

FOLDER_EXPORTS = ("yolo", "kitti")


@pytest.fixture
def ds(tmp_path) -> Dataset:
    return write_fake_dataset(tmp_path / "ds", 4, objects_per_frame=3, seed=2)


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (the marker included) and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    return err


def _export(fmt: str, root: Path, out: Path) -> int:
    return main(["export", fmt, str(root), "--out", str(out)])


# -- hole 2: finite but absurd values give no null, inf or clipped 1.0 in an export ----------------

def _absurd(ds: Dataset, row: int) -> Dataset:
    """`ds` with one object at +-1e308, as a re-sealed dataset holds it (corners and box finite,
    their differences not): the COCO width and area overflow, the YOLO box too, and KITTI's
    location y = centre y + h / 2."""
    t = ds.objects
    t.bbox[row] = [-1e308, 0.0, 1e308, 10.0]
    t.keypoints[row] = 1e308
    t.center[row, 1] = 1.7e308
    t.dims[row, 2] = 1e308
    return ds


@pytest.mark.parametrize("fmt", ["coco", *FOLDER_EXPORTS])
def test_exporters_refuse_non_finite_results_and_write_nothing(fmt, ds, tmp_path, monkeypatch, capsys):
    out = tmp_path / ("out.json" if fmt == "coco" else "out")
    assert _export(fmt, ds.root, out) == 0  # an earlier export, which the refused one must leave as it was
    before = _snapshot(tmp_path / "out") if out.is_dir() else {"": out.read_bytes()}
    row = int(ds.offsets[1]) + 1  # frame 1, objects[1]
    bad = _absurd(Dataset.open(ds.root), row)
    monkeypatch.setattr(Dataset, "open", classmethod(lambda cls, root, **_: bad))
    capsys.readouterr()
    assert _export(fmt, ds.root, out) == 1
    err = _error_line(capsys)
    assert f"{record_path(ds.root, ds.frame_ids[1])}: objects[1]" in err and "not finite" in err, err
    assert (_snapshot(out) if out.is_dir() else {"": out.read_bytes()}) == before


def test_coco_export_names_the_field_it_refuses(ds, tmp_path):
    from omnigen.formats.checks import NonFiniteError
    from omnigen.formats.coco import export_coco

    bad = Dataset.open(ds.root)
    bad.objects.bbox[0] = [-1e308, 0.0, 1e308, 10.0]
    with pytest.raises(NonFiniteError, match=r"objects\[0\]\.bbox: the COCO bbox and area would be .*inf"):
        export_coco(bad, tmp_path / "c.json")
    assert not (tmp_path / "c.json").exists()


# -- export coco: one file, marked, never over an input or a file of anyone else --------------

def test_coco_export_is_marked_and_replaces_only_its_own_file(ds, tmp_path, capsys):
    from pycocotools.coco import COCO

    out = tmp_path / "coco.json"
    assert _export("coco", ds.root, out) == 0
    assert out.read_bytes().startswith(b'{"omnigen":"export coco","info":')
    assert len(COCO(str(out)).getImgIds()) == len(ds)
    assert _export("coco", ds.root, out) == 0  # a rerun replaces its own file
    legacy = json.loads(out.read_text())
    del legacy["omnigen"]  # an export from before the mark is recognised by its first bytes
    out.write_text(json.dumps(legacy, separators=(",", ":")))
    assert _export("coco", ds.root, out) == 0

    mine = tmp_path / "notes.json"
    mine.write_text('{"mine": 1}\n')
    capsys.readouterr()
    assert _export("coco", ds.root, mine) == 1
    assert "was not written by 'omnigen export coco'" in _error_line(capsys)
    assert mine.read_text() == '{"mine": 1}\n'


def test_coco_export_never_writes_onto_the_dataset(ds, tmp_path, capsys):
    manifest = ds.root / "manifest.json"
    before = manifest.read_bytes()
    assert _export("coco", ds.root, manifest) == 1
    assert f"lies inside {ds.root}" in _error_line(capsys)
    assert manifest.read_bytes() == before
    # a hard link elsewhere to a dataset image: refused as a file export coco did not make
    image = ds.path(ds.table.image[0])
    link = tmp_path / "link.json"
    os.link(image, link)
    pixels = image.read_bytes()
    assert _export("coco", ds.root, link) == 1
    assert image.read_bytes() == pixels and os.path.samefile(image, link)


# -- export yolo / kitti: folders, never the dataset's, nor one holding it ----------------------

@pytest.mark.parametrize("fmt", FOLDER_EXPORTS)
def test_folder_export_refuses_an_out_inside_the_dataset(fmt, ds, capsys):
    out = ds.root / "export"
    assert _export(fmt, ds.root, out) == 1
    assert f"lies inside {ds.root}" in _error_line(capsys)
    assert not out.exists()


@pytest.mark.parametrize("fmt", FOLDER_EXPORTS)
def test_folder_export_refuses_its_own_folder_once_it_holds_the_dataset(fmt, ds, tmp_path, capsys):
    """A rerun clears its subfolders (images/, label_2/, ...): a dataset moved into one of them
    would be deleted with them."""
    out = tmp_path / "exp"
    assert _export(fmt, ds.root, out) == 0
    sub = "images" if fmt == "yolo" else "image_2"
    moved = out / sub / "ds"
    ds.root.rename(moved)
    before = _snapshot(moved)
    assert _export(fmt, moved, out) == 1
    assert f"holds {moved}" in _error_line(capsys)
    assert _snapshot(moved) == before


# -- stats: a report folder outside the dataset, figures written by rename --------------------

def test_stats_refuses_an_out_inside_the_dataset(ds, capsys):
    out = ds.root / "report"
    assert main(["stats", str(ds.root), "--out", str(out), "--gallery", "0", "--no-check-images"]) == 1
    assert f"lies inside {ds.root}" in _error_line(capsys)
    assert not out.exists()


def test_stats_figures_and_gallery_are_written_by_rename(ds, tmp_path):
    """savefig(path) and Image.save(path) write through a hard link at the name into another
    tree; the report's files replace the name instead."""
    from matplotlib.figure import Figure

    from omnigen.stats.gallery import pick_gallery, write_gallery
    from omnigen.stats.plots import _save

    theirs = tmp_path / "theirs.png"
    theirs.write_bytes(b"someone else's bytes")
    figure = tmp_path / "report" / "plots" / "overall" / "classes.png"
    figure.parent.mkdir(parents=True)
    os.link(theirs, figure)
    _save(Figure(figsize=(1, 1)), figure)
    frame = ds.frame_ids[pick_gallery(ds, 1)[0]]
    drawn = tmp_path / "report" / "gallery" / f"{frame}.png"
    drawn.parent.mkdir()
    os.link(theirs, drawn)
    write_gallery(ds, tmp_path / "report", 1)
    assert theirs.read_bytes() == b"someone else's bytes"
    assert figure.read_bytes().startswith(b"\x89PNG") and drawn.read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize("option, value", [("--gallery", "-1"), ("--prior-sigma", "0"), ("--prior-sigma", "nan"),
                                           ("--seed", "-1"), ("--jobs", "-2")])
def test_stats_numeric_options_are_checked_when_parsed(option, value, ds, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["stats", str(ds.root), "--out", str(tmp_path / "r"), option, value])
    assert exc.value.code == 2
    assert f"argument {option}" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


# -- eval-kitti and calib-sensitivity: their JSON never lands on an input ------------------------

def _kitti_folders(tmp_path: Path) -> tuple[Path, Path]:
    line = "Pedestrian 0.00 0 -0.20 712.40 143.00 810.73 307.92 1.89 0.48 1.20 1.84 1.47 8.41 0.01"
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    for folder, text in ((gt, line), (pred, line + " 0.8")):
        folder.mkdir()
        (folder / "000000.txt").write_text(text + "\n")
    return gt, pred


def test_eval_kitti_never_writes_onto_a_label_or_a_file_it_did_not_make(tmp_path, capsys):
    gt, pred = _kitti_folders(tmp_path)
    label = gt / "000000.txt"
    before = label.read_bytes()
    assert main(["eval-kitti", "--gt", str(gt), "--pred", str(pred), "--out", str(label)]) == 1
    assert "lies inside" in _error_line(capsys) and label.read_bytes() == before
    mine = tmp_path / "mine.json"
    mine.write_text("{}\n")
    assert main(["eval-kitti", "--gt", str(gt), "--pred", str(pred), "--out", str(mine)]) == 1
    assert "was not written by 'omnigen eval-kitti'" in _error_line(capsys) and mine.read_text() == "{}\n"
    out = tmp_path / "ap.json"
    for _ in range(2):  # a rerun replaces its own file
        assert main(["eval-kitti", "--gt", str(gt), "--pred", str(pred), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["omnigen"] == "eval-kitti"


def test_calib_sensitivity_never_writes_onto_its_predictions(ds, tmp_path, capsys):
    from omnigen.formats.coco import to_coco

    preds = tmp_path / "pred.json"
    preds.write_text(json.dumps([{"image_id": a["image_id"], "category_id": a["category_id"], "score": 1.0,
                                  "keypoints": a["keypoints"], "bbox": a["bbox"]}
                                 for a in to_coco(ds)["annotations"]]))
    before = preds.read_bytes()
    args = ["calib-sensitivity", str(preds), str(ds.root), "--split", "all", "--views", "all"]
    assert main(args + ["--out", str(preds)]) == 1
    assert f"is {preds}" in _error_line(capsys) and preds.read_bytes() == before
    out = tmp_path / "calib.json"
    for _ in range(2):  # a rerun replaces its own file
        assert main(args + ["--out", str(out)]) == 0
    assert out.read_text().startswith('{\n  "omnigen": "calib-sensitivity"')
    assert json.loads(out.read_text())["frames"] == len(ds)
