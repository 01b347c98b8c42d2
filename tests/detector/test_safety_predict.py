"""Issue 44 (data safety): where `omnigen predict`, `omnigen bev` and `omnigen eval --out` write, and
the images predict and bev read.

Hole 1: predict wrote each overlay as OUT/<stem>.jpg by truncating the file of that name. Pointed at
the images folder of a dataset whose images are hard links into the DAIR-V2X tree it came from, it
rewrote the source tree's images and exited 0. Hole 6: predict decoded whatever size an image's
header claimed, crashed (a cv2 traceback) on an image 500 times wider than tall, and lost the whole
run to one unreadable image; a predictions file of a few dozen bytes sized bev's canvas at 40020 x
40020 pixels. docs/untrusted-inputs.md states the promises.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from omnigen.cli import main
from omnigen.converters.dair_fixture import write_dair_tree
from omnigen.outputs import jpeg_made_by, png_made_by

pytestmark = pytest.mark.filterwarnings("ignore::PIL.Image.DecompressionBombWarning")


def snapshot(*folders: Path) -> dict[str, bytes]:
    """Every file under the folders, by path, with its bytes: what 'left untouched' compares."""
    return {str(p): p.read_bytes() for folder in folders for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def linked(tmp_path, capsys) -> tuple[Path, Path]:
    """(source tree, dataset): a DAIR-V2X tree of two frames converted with hard links, so the
    dataset's images/*.jpg are the source's image/*.jpg."""
    src, ds = tmp_path / "dair", tmp_path / "ds"
    write_dair_tree(src, 2, seed=3, variant="i")
    assert main(["convert", "dair", str(src), "--out", str(ds), "--workers", "1"]) == 0
    capsys.readouterr()
    image = sorted((ds / "images").iterdir())[0]
    assert image.stat().st_nlink == 2 and image.stat().st_ino == (src / "image/000000.jpg").stat().st_ino
    return src, ds


@pytest.fixture
def weights(tmp_path, detector_checkpoint) -> Path:
    return detector_checkpoint(tmp_path / "w.pt", 0)


def png(path: Path, width: int, height: int, seed: int = 0) -> Path:
    pixels = np.random.default_rng(seed).integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)
    return path


def bomb_png(width: int, height: int) -> bytes:
    """A PNG of a few dozen bytes whose header claims width x height RGB pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b""))


# ---------------------------------------------------------------------------------------------
# predict: where it writes
# ---------------------------------------------------------------------------------------------


def test_predict_into_the_images_folder_it_reads_is_refused_and_every_input_is_untouched(linked, weights, capsys):
    src, ds = linked
    before = snapshot(src, ds)
    images = ds / "images"
    assert main(["predict", str(weights), str(images), "--out", str(images), "--imgsz", "64"]) == 1
    assert "refusing to write onto an input" in capsys.readouterr().err
    # the source tree itself, the dataset holding the images, a folder inside the images folder
    for out in (src / "image", ds, images / "overlays"):
        assert main(["predict", str(weights), str(images), "--out", str(out), "--imgsz", "64"]) == 1
        assert str(out) in capsys.readouterr().err
    assert snapshot(src, ds) == before  # every byte, through the hard links too, and no new file


def test_predict_claims_its_folder_names_a_file_in_the_way_and_reruns_into_its_own(weights, tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    png(images / "a.png", 64, 48)
    foreign = tmp_path / "theirs"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["predict", str(weights), str(images), "--out", str(foreign), "--imgsz", "64"]) == 1
    assert "notes.txt" in capsys.readouterr().err and (foreign / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    out = tmp_path / "pred"
    assert main(["predict", str(weights), str(images), "--out", str(out), "--imgsz", "64"]) == 0
    assert (out / ".omnigen-job").read_text().strip() == "predict"
    assert jpeg_made_by("predict")(out / "a.jpg")  # the overlay carries predict's mark
    # an overlay replaced by a hard link to a file elsewhere: the rerun renames over the name and
    # never writes through it into the other file
    outside = png(tmp_path / "outside.jpg", 8, 8)
    kept = outside.read_bytes()
    (out / "a.jpg").unlink()
    os.link(outside, out / "a.jpg")
    assert main(["predict", str(weights), str(images), "--out", str(out), "--imgsz", "64"]) == 0
    assert outside.read_bytes() == kept and jpeg_made_by("predict")(out / "a.jpg")


def test_sources_sharing_a_stem_get_an_overlay_each(weights, tmp_path):
    for folder, seed in (("a", 1), ("b", 2)):
        (tmp_path / folder).mkdir()
        png(tmp_path / folder / "x.png", 64, 48, seed)
    out = tmp_path / "pred"
    assert main(["predict", str(weights), str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out),
                 "--imgsz", "64"]) == 0
    images = json.loads((out / "images.json").read_text())
    assert [i["overlay"] for i in images] == ["x.jpg", "x-2.jpg"]
    assert (out / "x.jpg").read_bytes() != (out / "x-2.jpg").read_bytes()


# ---------------------------------------------------------------------------------------------
# predict: the images it reads
# ---------------------------------------------------------------------------------------------


def test_bad_images_are_skipped_and_listed_and_the_others_predicted(weights, tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    png(images / "good.png", 64, 48)
    png(images / "wide.png", 10000, 20)  # one row of a 64 x 64 input: the vertical snap's crop was empty
    (images / "bomb.png").write_bytes(bomb_png(30000, 30000))  # 2.7 GB of pixels, claimed in 60 bytes
    (images / "junk.jpg").write_bytes(b"not an image")
    out = tmp_path / "pred"
    assert main(["predict", str(weights), str(images), "--out", str(out), "--imgsz", "64", "--conf", "0.0001"]) == 1
    captured = capsys.readouterr()
    skips = [line for line in captured.err.splitlines() if line.startswith("skipped: ")]
    assert len(skips) == 2, captured.err
    assert "bomb.png: unreadable image: header claims" in skips[0] and "junk.jpg: unreadable image" in skips[1]
    assert "skipped" in captured.out  # the summary's column
    listed = json.loads((out / "images.json").read_text())
    assert [Path(i["file_name"]).name for i in listed] == ["good.png", "wide.png"]
    assert listed[1]["width"] == 10000 and (out / "wide.jpg").exists()
    preds = json.loads((out / "predictions.json").read_text())
    assert {Path(p["file_name"]).name for p in preds} == {"good.png", "wide.png"}  # wide.png had detections


def test_the_vertical_snap_keeps_the_corners_of_an_image_of_one_input_row():
    """predict.snap_batch on a 10000 x 20 image letterboxed to 64: its content is one row, which the
    PAD_MARGIN rows on each padded side leave empty; cv2.cvtColor failed on the empty crop."""
    import torch

    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.model.outputs import Detections
    from omnigen.detector.prediction.predict import snap_batch

    boxed, lb = letterbox(np.zeros((20, 10000, 3), np.uint8), 64)
    kp = torch.rand(3, 8, 3) * 64
    dets = Detections(torch.zeros(3, 4), torch.ones(3), torch.zeros(3, dtype=torch.long), kp)
    (out,) = snap_batch([boxed], [lb], [dets])
    assert torch.equal(out.keypoints, kp)


@pytest.mark.parametrize("argv", [
    ["predict", "w.pt", "x.png", "--out", "o", "--batch", "-1"],
    ["predict", "w.pt", "x.png", "--out", "o", "--batch", "0"],
    ["predict", "w.pt", "x.png", "--out", "o", "--conf", "1.5"],
    ["predict", "w.pt", "x.png", "--out", "o", "--iou", "-0.1"],
    ["predict", "w.pt", "x.png", "--out", "o", "--iou", "nan"],
    ["predict", "w.pt", "x.png", "--out", "o", "--max-det", "0"],
    ["predict", "w.pt", "x.png", "--out", "o", "--imgsz", "0"],
    ["predict", "w.pt", "x.png", "--out", "o", "--imgsz", "50"],
    ["eval", "w.pt", "ds", "--batch", "0"],
    ["eval", "w.pt", "ds", "--imgsz", "-64"],
    ["bev", "p.json", "--out", "o", "--score-thr", "inf"],
    ["bev", "p.json", "--out", "o", "--ridge-lambda", "-1"],
])
def test_numeric_options_are_refused_when_parsed(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert f"argument {argv[-2]}" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# bev
# ---------------------------------------------------------------------------------------------


def write_predictions(path: Path, bbox: list[float], image_id: int = 1) -> Path:
    path.write_text(json.dumps([{"image_id": image_id, "category_id": 1, "bbox": bbox, "score": 1}]))
    return path


def test_bev_canvas_is_bounded_whatever_the_predictions_claim(tmp_path, capsys):
    from omnigen.detector.bev_command import PLACEHOLDER_MAX_SIDE
    from omnigen.draw import MAX_BEV_SIDE

    preds = write_predictions(tmp_path / "p.json", [0, 0, 40000, 40000])  # a 40020 x 40020 canvas before
    assert len(preds.read_bytes()) < 200
    assert main(["bev", str(preds), "--out", str(tmp_path / "bev")]) == 0
    with Image.open(tmp_path / "bev" / "1.png") as im:
        assert im.width <= PLACEHOLDER_MAX_SIDE + MAX_BEV_SIDE and im.height <= PLACEHOLDER_MAX_SIDE + 40
    assert png_made_by("bev")(tmp_path / "bev" / "1.png")


def test_bev_refuses_a_figure_too_large_to_draw_before_allocating_it():
    from omnigen.detector.bev.draw import BevScene, render_bev_figure

    scene = BevScene(np.zeros((0, 4, 2)), [], None)
    with pytest.raises(ValueError, match=r"image 7: the picture would be \d+x\d+ pixels.*MAX_CANVAS_PIXELS"):
        render_bev_figure(scene, None, 10, 5_000_000, what="image 7")  # a 10 x 5e6 image's panel and its BEV


def test_bev_lists_an_unreadable_image_and_writes_where_it_may(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    (images / "1.png").write_bytes(bomb_png(30000, 30000))
    preds = write_predictions(tmp_path / "p.json", [10, 10, 20, 20])
    for out in (images, tmp_path):  # the images folder; a folder holding the predictions file
        assert main(["bev", str(preds), "--images", str(images), "--out", str(out)]) == 1
        assert "refusing to write" in capsys.readouterr().err
    assert sorted(p.name for p in images.iterdir()) == ["1.png"]
    out = tmp_path / "bev"
    assert main(["bev", str(preds), "--images", str(images), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "skipped: " in err and "1.png: unreadable image: header claims" in err
    assert (out / "1.json").exists() and (out / "1.png").exists()  # drawn on grey
    assert main(["bev", str(preds), "--images", str(images), "--out", str(out)]) == 1  # a rerun into its own
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("x")
    assert main(["bev", str(preds), "--out", str(theirs)]) == 1
    assert "holds notes.txt" in capsys.readouterr().err and sorted(os.listdir(theirs)) == ["notes.txt"]


# ---------------------------------------------------------------------------------------------
# eval --out
# ---------------------------------------------------------------------------------------------


def test_eval_out_is_marked_and_never_written_onto_an_input_or_a_file_of_anyone_else(split_fake_dataset, tmp_path,
                                                                                    capsys):
    ds = split_fake_dataset.root
    preds = tmp_path / "preds.json"
    preds.write_text("[]\n")
    base = ["eval", str(preds), str(ds), "--no-adherence", "--no-sizes", "--out"]
    theirs = tmp_path / "theirs.json"
    theirs.write_text('{"mine": 1}\n')
    before = snapshot(ds) | snapshot(tmp_path)
    for out in (preds, ds / "manifest.json", ds / "report.json", theirs, tmp_path):
        assert main(base + [str(out)]) == 1
        assert str(out) in capsys.readouterr().err
    assert snapshot(ds) | snapshot(tmp_path) == before
    report = tmp_path / "report.json"
    assert main(base + [str(report)]) == 0 and main(base + [str(report)]) == 0  # a rerun onto its own file
    assert next(iter(json.loads(report.read_text()).items())) == ("omnigen", "eval")
