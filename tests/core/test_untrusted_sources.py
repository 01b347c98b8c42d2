"""Untrusted source files (issue 27): paths that leave SRC, files that are not files, sizes, values, images.

Each test builds the hostile input an adversarial probe used and checks that it is now a skip (or a
validate problem) naming the file and the field, that the good frames beside it still convert, and
that nothing outside the source tree reaches the output. docs/untrusted-inputs.md states the promise.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import struct
import time
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnigen.converters import dair, kitti
from omnigen.converters.common import TEXT_FILE_MAX_BYTES, SourceError
from omnigen.converters.dair_fixture import tiny_jpeg, write_dair_tree
from omnigen.converters.kitti_fixture import write_kitti_tree, write_kitti_zips
from omnigen.cli import main
from omnigen.images import MAX_IMAGE_PIXELS, ImageError, check_image, image_size, load_rgb
from omnigen.untrusted import UntrustedFileError, read_regular, resolve_inside

pytestmark = pytest.mark.filterwarnings("ignore::PIL.Image.DecompressionBombWarning")  # the bombs are the point


@contextlib.contextmanager
def deadline(seconds: int):
    """Fail (rather than hang the suite) if the block blocks: a FIFO opened for reading waits for ever."""
    def expired(signum, frame):
        raise TimeoutError(f"blocked for {seconds} s (a FIFO was opened?)")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def convert_dair(src: Path, out: Path, capsys) -> tuple[int, list[str]]:
    with deadline(60):
        code = main(["convert", "dair", str(src), "--out", str(out), "--workers", "1"])
    out_text = capsys.readouterr().out
    return code, [line.strip() for line in out_text.splitlines() if line.strip().startswith("skipped:")]


def convert_kitti(src: Path, out: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    with deadline(60):
        code = main(["convert", "kitti", str(src), "--out", str(out), "--workers", "1", *extra])
    out_text = capsys.readouterr().out
    return code, [line.strip() for line in out_text.splitlines() if line.strip().startswith("skipped:")]


def skip_for(skips: list[str], *parts: str) -> str:
    """The one skip line holding every part; fails naming the lines when there is none."""
    found = [s for s in skips if all(p in s for p in parts)]
    assert len(found) == 1, (parts, skips)
    return found[0]


def edit_data_info(root: Path, edit) -> None:
    info = json.loads((root / "data_info.json").read_text())
    edit(info)
    (root / "data_info.json").write_text(json.dumps(info))


def written_frames(out: Path) -> set[str]:
    return {p.stem for p in (out / "records").glob("*.json")}


def bomb_png(width: int = 13000, height: int = 13000) -> bytes:
    """A PNG of a few dozen bytes whose header claims width x height RGB pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b""))


def png_bytes(width: int, height: int, seed: int = 0) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------
# DAIR-V2X: paths named by data_info.json, and links in the tree
# ---------------------------------------------------------------------------------------------


def test_dair_paths_leaving_src_are_skips_naming_frame_and_field(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 7, seed=3, variant="i")
    outside = tmp_path / "outside"
    outside.mkdir()
    # valid files outside SRC, so that following a path would succeed and the test could not pass by accident
    shutil.copy(root / "calib/camera_intrinsic/000000.json", outside / "intrinsic.json")
    shutil.copy(root / "label/camera/000001.json", outside / "label.json")
    shutil.copy(root / "label/camera/000002.json", outside / "label2.json")
    (outside / "stolen.jpg").write_bytes(tiny_jpeg((96, 54), tag=99))
    stolen_inode = (outside / "stolen.jpg").stat().st_ino

    def edit(info):
        info[0]["calib_camera_intrinsic_path"] = str(outside / "intrinsic.json")  # absolute
        info[1]["label_camera_std_path"] = "../outside/label.json"  # ..
        info[4]["calib_virtuallidar_to_camera_path"] = "/dev/zero"  # grew memory without bound
    edit_data_info(root, edit)
    (root / "label/camera/000002.json").unlink()
    (root / "label/camera/000002.json").symlink_to(outside / "label2.json")  # a link out of the tree
    (root / "image/000003.jpg").unlink()
    (root / "image/000003.jpg").symlink_to(outside / "stolen.jpg")  # was hard-linked into the output
    (root / "label/camera/000005.json").write_bytes(b"[" + b" " * TEXT_FILE_MAX_BYTES + b"]")  # oversize

    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 6, skips
    skip_for(skips, "frame 000000", "leads outside", "data_info.json[0].calib_camera_intrinsic_path")
    skip_for(skips, "frame 000001", "leads outside", "data_info.json[1].label_camera_std_path")
    skip_for(skips, "frame 000002", "leads outside", "outside/label2.json", "data_info.json[2].label_camera_std_path")
    skip_for(skips, "frame 000003", "leads outside", "stolen.jpg", "data_info.json[3].image_path")
    skip_for(skips, "frame 000004", "/dev/zero", "leads outside", "calib_virtuallidar_to_camera_path")
    skip_for(skips, "000005.json", "more than the", "allowed", "[5].label_camera_std_path, frame 000005")
    assert written_frames(tmp_path / "out") == {"dair-v2x-i-000006"}
    linked = [p for p in (tmp_path / "out").rglob("*") if p.is_file() and p.stat().st_ino == stolen_inode]
    assert linked == [] and not any((tmp_path / "out" / "images").glob("*000003*"))


def test_dair_links_inside_src_are_followed(tmp_path, capsys):
    """Containment judges where a link leads: a link that stays inside SRC is fine."""
    root = tmp_path / "src"
    write_dair_tree(root, 2, seed=3, variant="i")
    (root / "store").mkdir()
    (root / "label/camera/000001.json").rename(root / "store/label.json")
    (root / "label/camera/000001.json").symlink_to("../../store/label.json")
    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 0 and skips == [] and len(written_frames(tmp_path / "out")) == 2


def test_dair_fifo_and_non_regular_files_are_skips_and_do_not_hang(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 4, seed=3, variant="i")
    (root / "calib/camera_intrinsic/000000.json").unlink()
    os.mkfifo(root / "calib/camera_intrinsic/000000.json")  # hung the run: nobody ever writes to it
    (root / "image/000001.jpg").unlink()
    os.mkfifo(root / "image/000001.jpg")
    (root / "label/camera/000002.json").unlink()
    (root / "label/camera/000002.json").mkdir()
    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 3, skips
    skip_for(skips, "camera_intrinsic/000000.json", "not a regular file (a FIFO)")
    skip_for(skips, "image/000001.jpg", "not a regular file (a FIFO)")
    skip_for(skips, "label/camera/000002.json", "not a regular file (a folder)")
    assert written_frames(tmp_path / "out") == {"dair-v2x-i-000003"}


def test_dair_images_found_with_images_dir_stay_inside_it(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 2, seed=3, variant="i")
    images = tmp_path / "images"
    images.mkdir()
    for p in (root / "image").iterdir():
        p.rename(images / p.name)
    (tmp_path / "secret.jpg").write_bytes(tiny_jpeg((96, 54), tag=5))
    (images / "000001.jpg").unlink()
    (images / "000001.jpg").symlink_to(tmp_path / "secret.jpg")
    with deadline(60):
        code = main(["convert", "dair", str(root), "--out", str(tmp_path / "out"), "--workers", "1",
                     "--images", str(images)])
    out = capsys.readouterr().out
    assert code == 1 and "frame 000001: leads outside" in out and "looked up in --images" in out
    assert written_frames(tmp_path / "out") == {"dair-v2x-i-000000"}


def test_read_regular_refuses_devices_fifos_and_oversize_files_before_reading(tmp_path):
    with pytest.raises(UntrustedFileError, match="not a regular file \\(a character device\\)"):
        read_regular("/dev/zero", 1000)
    os.mkfifo(tmp_path / "fifo")
    with deadline(10), pytest.raises(UntrustedFileError, match="a FIFO"):
        read_regular(tmp_path / "fifo", 1000)
    (tmp_path / "big").write_bytes(b"x" * 1001)
    with pytest.raises(UntrustedFileError, match="1001 bytes, more than the 1000 allowed"):
        read_regular(tmp_path / "big", 1000)
    assert read_regular(tmp_path / "big", 1001) == b"x" * 1001
    with pytest.raises(FileNotFoundError):
        read_regular(tmp_path / "none", 1000)


def test_resolve_inside_judges_where_a_path_leads(tmp_path):
    (tmp_path / "root/a").mkdir(parents=True)
    (tmp_path / "root/out").symlink_to(tmp_path)
    root = tmp_path / "root"
    assert resolve_inside(root, "a/../a/x.json") == (root / "a/x.json").resolve()
    for bad in ("../x.json", "a/../../x.json", "/etc/passwd", "out/x.json", "out/root/../x.json"):
        with pytest.raises(UntrustedFileError, match="leads outside"):
            resolve_inside(root, bad)
    assert resolve_inside(root, "out/root/a") == (root / "a").resolve()  # a link that leads back in


# ---------------------------------------------------------------------------------------------
# Values: finite is not yet plausible
# ---------------------------------------------------------------------------------------------


def test_dair_absurd_values_are_skips_naming_file_and_field(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 9, seed=4, variant="i", objects=(2, 4))
    label = lambda k: root / "label/camera" / f"{k:06d}.json"  # noqa: E731

    def set_label(k: int, field: str, sub: str, value) -> None:
        objs = json.loads(label(k).read_text())
        objs[0][field][sub] = value
        label(k).write_text(json.dumps(objs))

    set_label(0, "3d_dimensions", "l", "1e300")
    set_label(1, "3d_dimensions", "w", "-1")
    set_label(2, "3d_dimensions", "h", "nan")
    set_label(3, "3d_location", "x", 1e30)
    objs = json.loads(label(4).read_text())
    objs[0]["rotation"] = "1e30"
    label(4).write_text(json.dumps(objs))
    set_label(5, "2d_box", "xmax", 1e300)
    intr = root / "calib/camera_intrinsic/000006.json"
    k = json.loads(intr.read_text())
    k["cam_K"][0] = 1e300
    intr.write_text(json.dumps(k))
    ext = root / "calib/virtuallidar_to_camera/000007.json"
    e = json.loads(ext.read_text())
    e["translation"] = [[1e9], [0.0], [0.0]]
    ext.write_text(json.dumps(e))

    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 8, skips
    skip_for(skips, "label/camera/000000.json: [0]", "dimensions (l w h)", "MAX_OBJECT_SIZE_M")
    skip_for(skips, "label/camera/000001.json: [0].3d_dimensions", "must be positive")
    skip_for(skips, "label/camera/000002.json: [0].3d_dimensions.h", "finite")
    skip_for(skips, "label/camera/000003.json: [0]", "location", "MAX_OBJECT_DISTANCE_M")
    skip_for(skips, "label/camera/000004.json: [0]", "heading", "MAX_ABS_ANGLE_RAD")
    skip_for(skips, "label/camera/000005.json: [0].2d_box", "MAX_PIXEL_COORDINATE")
    skip_for(skips, "camera_intrinsic/000006.json: cam_K", "focal length fx", "FOCAL_RANGE_PX")
    skip_for(skips, "virtuallidar_to_camera/000007.json: translation", "MAX_SENSOR_OFFSET_M")
    assert written_frames(tmp_path / "out") == {"dair-v2x-i-000008"}


def test_kitti_absurd_values_are_skips_naming_file_line_and_field(tmp_path, capsys):
    src = tmp_path / "kitti"
    write_kitti_tree(src, 6, seed=2)
    labels = src / "training/label_2"

    def set_field(kid: int, field: str, value: str) -> int:
        path = labels / f"{kid:06d}.txt"
        lines = path.read_text().splitlines()
        n = next(i for i, line in enumerate(lines) if not line.startswith("DontCare"))
        tokens = lines[n].split()
        tokens[kitti.LABEL_FIELDS.index(field)] = value
        lines[n] = " ".join(tokens)
        path.write_text("\n".join(lines) + "\n")
        return n + 1

    line_z = set_field(0, "z", "1e30")
    line_l = set_field(1, "length", "1e300")
    line_a = set_field(2, "alpha", "1e30")
    line_b = set_field(3, "bbox_right", "1e300")
    calib = src / "training/calib/000004.txt"
    text = calib.read_text().splitlines()
    n = next(i for i, line in enumerate(text) if line.startswith("P2:"))
    tokens = text[n].split()
    tokens[1] = "1e300"  # fx
    text[n] = " ".join(tokens)
    calib.write_text("\n".join(text) + "\n")

    code, skips = convert_kitti(src, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 5, skips
    skip_for(skips, f"label_2/000000.txt: line {line_z}", "location", "MAX_OBJECT_DISTANCE_M")
    skip_for(skips, f"label_2/000001.txt: line {line_l}", "dimensions (h w l)", "MAX_OBJECT_SIZE_M")
    skip_for(skips, f"label_2/000002.txt: line {line_a}", "alpha", "MAX_ABS_ANGLE_RAD")
    skip_for(skips, f"label_2/000003.txt: line {line_b}", "2D box", "MAX_PIXEL_COORDINATE")
    skip_for(skips, f"calib/000004.txt: line {n + 1}", "focal length fx", "FOCAL_RANGE_PX")
    assert written_frames(tmp_path / "out") == {"kitti-000005"}


# ---------------------------------------------------------------------------------------------
# Structure and encoding
# ---------------------------------------------------------------------------------------------


def test_a_deeply_nested_dair_label_is_a_skip_naming_the_file(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 3, seed=5, variant="i")
    (root / "label/camera/000000.json").write_text("[" * 100_000 + "]" * 100_000)
    objs = json.loads((root / "label/camera/000001.json").read_text())
    nested: object = 1
    for _ in range(600):  # within orjson's parsing limit, beyond its writing limit
        nested = [nested]
    objs[0]["note"] = nested
    (root / "label/camera/000001.json").write_text(json.dumps(objs))
    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 2, skips
    skip_for(skips, "label/camera/000000.json", "nested too deeply")
    skip_for(skips, "label/camera/000001.json: [0].note", "nested")
    assert written_frames(tmp_path / "out") == {"dair-v2x-i-000002"}


def test_kitti_label_and_calib_with_a_byte_order_mark_are_read(tmp_path, capsys):
    src = tmp_path / "kitti"
    write_kitti_tree(src, 2, seed=2)
    assert convert_kitti(src, tmp_path / "plain", capsys) == (0, [])
    for path in (src / "training/label_2/000000.txt", src / "training/calib/000001.txt"):
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert convert_kitti(src, tmp_path / "bom", capsys) == (0, [])
    for name in ("kitti-000000.json", "kitti-000001.json"):
        assert (tmp_path / "bom/records" / name).read_bytes() == (tmp_path / "plain/records" / name).read_bytes()


def test_dair_json_with_a_byte_order_mark_is_read(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 1, seed=5, variant="i")
    assert convert_dair(root, tmp_path / "plain", capsys) == (0, [])
    for path in (root / "label/camera/000000.json", root / "calib/camera_intrinsic/000000.json"):
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert convert_dair(root, tmp_path / "bom", capsys) == (0, [])
    name = "records/dair-v2x-i-000000.json"
    assert (tmp_path / "bom" / name).read_bytes() == (tmp_path / "plain" / name).read_bytes()


def test_kitti_links_out_of_the_tree_and_oversize_zip_members_are_skips(tmp_path, capsys, monkeypatch):
    src = tmp_path / "kitti"
    write_kitti_tree(src, 3, seed=2)
    zips = tmp_path / "zips"
    write_kitti_zips(src, zips)
    outside = tmp_path / "outside.png"
    shutil.copy(src / "training/image_2/000000.png", outside)
    (src / "training/image_2/000000.png").unlink()
    (src / "training/image_2/000000.png").symlink_to(outside)
    (src / "training/calib/000001.txt").unlink()
    os.mkfifo(src / "training/calib/000001.txt")
    code, skips = convert_kitti(src, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 2, skips
    skip_for(skips, "image_2/000000.png", "frame 000000: leads outside")
    skip_for(skips, "calib/000001.txt", "not a regular file (a FIFO)")
    assert written_frames(tmp_path / "out") == {"kitti-000002"}

    monkeypatch.setattr(kitti, "TEXT_FILE_MAX_BYTES", 200)  # every calib member is larger
    code, skips = convert_kitti(zips, tmp_path / "out-zip", capsys)
    assert code == 1 and len(skips) == 3 and all("calib" in s and "more than the 200 allowed" in s for s in skips)


# ---------------------------------------------------------------------------------------------
# Images: the header is a claim
# ---------------------------------------------------------------------------------------------


def test_a_tiny_file_claiming_a_huge_image_is_refused_without_decoding(tmp_path):
    path = tmp_path / "bomb.png"
    path.write_bytes(bomb_png())
    assert path.stat().st_size < 100 and 13000 * 13000 > MAX_IMAGE_PIXELS
    tracemalloc.start()
    try:
        for read in (check_image, image_size, load_rgb):
            with pytest.raises(ImageError, match="13000x13000 pixels, more than"):
                read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10 * 2**20  # decoding would take 507 MB
    with pytest.raises(ImageError, match="more than"):
        check_image(bomb_png(), "bytes.png")


def test_a_truncated_png_fails_conversion_and_validate(tmp_path, capsys):
    src = tmp_path / "kitti"
    write_kitti_tree(src, 3, seed=2, image_size=(124, 38))
    assert convert_kitti(src, tmp_path / "good", capsys, "--link", "copy") == (0, [])
    image = src / "training/image_2/000001.png"
    whole = png_bytes(124, 38)
    image.write_bytes(whole[: len(whole) // 2])
    with Image.open(image) as im:
        assert im.size == (124, 38)  # the header alone passes: what conversion used to read
    code, skips = convert_kitti(src, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 1 and "image_2/000001.png: unreadable image" in skips[0] and "runcated" in skips[0]
    (src / "training/image_2/000002.png").write_bytes(whole[:-10])  # pixels whole, IEND cut
    code, skips = convert_kitti(src, tmp_path / "out2", capsys)
    assert code == 1 and len(skips) == 2, skips

    good = tmp_path / "good"
    assert main(["validate", str(good)]) == 0
    capsys.readouterr()
    (good / "images/kitti-000001.png").write_bytes(whole[: len(whole) // 2])
    (good / "images/kitti-000002.png").write_bytes(png_bytes(100, 38))  # whole, but not the record's size
    (good / "images/kitti-000000.png").write_bytes(bomb_png())
    assert main(["validate", str(good)]) == 1
    out = capsys.readouterr().out
    assert "kitti-000001.json: image: images/kitti-000001.png: unreadable image: Truncated" in out
    assert "kitti-000002.json: image: images/kitti-000002.png is 100x38, the record says " in out
    assert "kitti-000000.json: image: images/kitti-000000.png: header claims 13000x13000" in out


def test_dair_image_claiming_a_huge_size_is_a_skip(tmp_path, capsys):
    root = tmp_path / "src"
    write_dair_tree(root, 2, seed=3, variant="i")
    (root / "image/000000.jpg").write_bytes(bomb_png())
    data = (root / "image/000001.jpg").read_bytes()
    (root / "image/000001.jpg").write_bytes(data[: len(data) // 2])
    code, skips = convert_dair(root, tmp_path / "out", capsys)
    assert code == 1 and len(skips) == 2, skips
    skip_for(skips, "image/000000.jpg", "13000x13000 pixels, more than")
    skip_for(skips, "image/000001.jpg", "unreadable image", "runcated")


def test_show_draws_a_placeholder_for_an_image_claiming_a_huge_size(tmp_path, capsys):
    src = tmp_path / "kitti"
    write_kitti_tree(src, 1, seed=2)
    assert convert_kitti(src, tmp_path / "ds", capsys, "--link", "copy") == (0, [])
    (tmp_path / "ds/images/kitti-000000.png").write_bytes(bomb_png())
    start = time.perf_counter()
    assert main(["show", str(tmp_path / "ds"), "kitti-000000", "--out", str(tmp_path / "x.png")]) == 0
    assert time.perf_counter() - start < 30  # decoding 13000 x 13000 would take far longer, and 3.4 GB
    captured = capsys.readouterr()
    assert "13000x13000" in captured.out + captured.err
    with Image.open(tmp_path / "x.png") as im:
        assert im.width < 13000


def test_source_error_from_an_image_check_names_the_file(tmp_path):
    (tmp_path / "x.png").write_bytes(b"not an image")
    with pytest.raises(SourceError, match="x.png: unreadable image: not a format PIL can identify"):
        kitti.image_size(tmp_path / "x.png", str(tmp_path / "x.png"))


def test_a_relative_root_is_judged_from_the_working_folder_of_the_call(tmp_path, monkeypatch):
    """The root is resolved at each call: after a change of working folder the same relative root
    names the new folder's tree, never the first one's (a cached resolution would keep it)."""
    from omnigen.untrusted import resolve_inside

    for name in ("a", "b"):
        (tmp_path / name / "src").mkdir(parents=True)
        (tmp_path / name / "src" / "f").write_text(name)
    monkeypatch.chdir(tmp_path / "a")
    assert resolve_inside("src", "f") == (tmp_path / "a" / "src" / "f").resolve()
    monkeypatch.chdir(tmp_path / "b")
    assert resolve_inside("src", "f") == (tmp_path / "b" / "src" / "f").resolve()
