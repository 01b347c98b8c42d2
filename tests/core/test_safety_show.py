"""Issue 44 (data safety): where `omnigen show` writes, and how large a picture it draws.

Hole 1: `cd DS/images && omnigen show .. FRAME --out IMAGE` saved the picture by truncating IMAGE,
the frame's own image, a hard link into the DAIR-V2X tree the dataset came from: the source image
was overwritten and the command exited 0. docs/untrusted-inputs.md states the promise.
"""

from __future__ import annotations

import io

import json
from pathlib import Path

import pytest
from PIL import Image

from omnigen.cli import main
from omnigen.converters.dair_fixture import write_dair_tree
from omnigen.outputs import png_made_by

FRAME = "dair-v2x-i-000000"


def snapshot(*folders: Path) -> dict[str, bytes]:
    """Every file under the folders, by path, with its bytes: what 'left untouched' compares."""
    return {str(p): p.read_bytes() for folder in folders for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def linked(tmp_path, capsys) -> tuple[Path, Path]:
    """(source tree, dataset): a DAIR-V2X tree of two frames converted with hard links."""
    src, ds = tmp_path / "dair", tmp_path / "ds"
    write_dair_tree(src, 2, seed=3, variant="i")
    assert main(["convert", "dair", str(src), "--out", str(ds), "--workers", "1"]) == 0
    capsys.readouterr()
    assert (ds / f"images/{FRAME}.jpg").stat().st_ino == (src / "image/000000.jpg").stat().st_ino
    return src, ds


def test_show_onto_the_frames_image_is_refused_and_the_source_tree_is_untouched(linked, monkeypatch, capsys):
    src, ds = linked
    before = snapshot(src, ds)
    monkeypatch.chdir(ds / "images")
    assert main(["show", "..", FRAME, "--out", f"{FRAME}.jpg"]) == 1
    assert "refusing to write" in capsys.readouterr().err
    # the source's name of the same file, a new name inside the dataset, the default name in it
    for out in (src / "image/000000.jpg", ds / "preview.png", None):
        assert main(["show", str(ds), FRAME] + ([] if out is None else ["--out", str(out)])) == 1
        assert "refusing to write" in capsys.readouterr().err
    assert snapshot(src, ds) == before


def test_show_reruns_onto_its_own_picture_and_refuses_any_other_file(linked, tmp_path, capsys):
    _, ds = linked
    out = tmp_path / "pictures" / "frame.png"
    assert main(["show", str(ds), FRAME, "--out", str(out)]) == 0
    assert png_made_by("show")(out)
    alone = out.read_bytes()
    assert main(["show", str(ds), FRAME, "--out", str(out), "--bev"]) == 0  # its own: replaced
    assert out.read_bytes() != alone and Image.open(out).width > Image.open(io.BytesIO(alone)).width  # the BEV beside
    theirs = tmp_path / "theirs.png"
    Image.new("RGB", (4, 4)).save(theirs)
    kept = theirs.read_bytes()
    assert main(["show", str(ds), FRAME, "--out", str(theirs)]) == 1
    assert "was not written by 'omnigen show'" in capsys.readouterr().err and theirs.read_bytes() == kept
    assert main(["show", str(ds), FRAME, "--out", str(out.parent)]) == 1  # a folder
    assert "is a folder" in capsys.readouterr().err
    assert main(["show", str(ds), FRAME, "--out", str(tmp_path / "frame.webp")]) == 1  # PNG bytes under .webp
    assert "name the file .png or .jpg" in capsys.readouterr().err and not (tmp_path / "frame.webp").exists()


def test_a_record_claiming_a_huge_image_is_refused_before_it_is_drawn(linked, tmp_path, capsys):
    """The grey placeholder was allocated at the record's size: 65535 x 65535 RGB is 12.9 GB."""
    _, ds = linked
    path = ds / "records" / f"{FRAME}.json"
    rec = json.loads(path.read_text())
    rec["width"] = rec["height"] = 65535
    path.write_text(json.dumps(rec))
    (ds / f"images/{FRAME}.jpg").unlink()  # no image: the picture is drawn on grey at the record's size
    assert main(["show", str(ds), FRAME, "--out", str(tmp_path / "x.png")]) == 1
    assert "the picture would be 65535x" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("option, value", [("--scale", "0"), ("--scale", "-1"), ("--scale", "nan"), ("--scale", "100"),
                                           ("--margin", "-0.1"), ("--margin", "5"), ("--margin", "inf")])
def test_scale_and_margin_are_refused_when_parsed(option, value, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["show", "ds", "frame", option, value])
    assert exit_.value.code == 2 and f"argument {option}" in capsys.readouterr().err
