"""Issue 44, hole 10: two sources holding one frame id with identical records. merge kept the first
source's pixels and counted a duplicate without a word, even where the pixels differed. Now it
names the duplicates it drops (console and manifest) and refuses, naming the ids and the differing
files, when the pixels differ."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

import omnigen.merge as merge_module
from omnigen.cli import main as cli
from omnigen.dataset import Dataset, DatasetError
from omnigen.fakes import write_fake_dataset
from omnigen.merge import DUPLICATES_SHOWN, merge


@pytest.fixture
def twins(tmp_path) -> tuple[Path, Path]:
    """A dataset and a byte-identical copy of it under another path (a re-download, say)."""
    a = write_fake_dataset(tmp_path / "a", n_frames=12, objects_per_frame=2, seed=1, source="kitti").root
    b = tmp_path / "b"
    shutil.copytree(a, b)
    return a, b


def test_a_frame_id_with_other_pixels_in_another_source_is_refused_naming_ids_and_files(twins, tmp_path, capsys):
    a, b = twins
    ds = Dataset.open(b)
    grown, edited = ds.table.image[1], ds.table.image[4]
    with open(b / grown, "ab") as fh:
        fh.write(b"more bytes")  # another size
    data = bytearray((b / edited).read_bytes())
    data[-20] ^= 0xFF  # the same size, other content
    (b / edited).write_bytes(bytes(data))
    with pytest.raises(DatasetError) as exc:
        merge([a, b], tmp_path / "out")
    message = str(exc.value)
    assert message.startswith("frame ids in two sources with identical records but different pixels (2)")
    assert f"{ds.table.frame_id[1]} in {a} and {b}: image {grown} differs (" in message and " bytes)" in message
    assert f"{ds.table.frame_id[4]} in {a} and {b}: image {edited} differs (same size, different content)" in message
    assert not (tmp_path / "out").exists()
    assert cli(["merge", str(a), str(b), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ds.table.frame_id[4] in err


def test_a_rendered_frame_with_another_depth_map_is_refused(tmp_path):
    a = write_fake_dataset(tmp_path / "a", n_frames=3, objects_per_frame=1, seed=2).root
    b = tmp_path / "b"
    shutil.copytree(a, b)
    rec = Dataset.open(b)[2]
    (b / rec.synthetic.depth).write_bytes(b"other depth")
    with pytest.raises(DatasetError, match=f"{rec.frame_id} in .*: depth {rec.synthetic.depth} differs \\("):
        merge([a, b], tmp_path / "out")


def test_duplicates_kept_once_are_named_on_the_console_and_in_the_manifest(twins, tmp_path, capsys):
    a, b = twins
    ids = sorted(Dataset.open(a).table.frame_id)
    capsys.readouterr()
    assert cli(["merge", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    shown = ", ".join(ids[:DUPLICATES_SHOWN])
    assert (f"duplicates: 12 frames are in more than one source with identical records and pixels, kept once: "
            f"{shown} and {12 - DUPLICATES_SHOWN} more") in out
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())["merge"]
    assert manifest["duplicate_frames"] == 12 and manifest["duplicate_frame_ids"] == ids[:DUPLICATES_SHOWN]
    assert len(Dataset.open(tmp_path / "out")) == 12
    report = merge([a, b], tmp_path / "out")
    assert report.duplicate_ids == ids and report.duplicate_frames == 12


def test_pixels_are_compared_cheaply(tmp_path, monkeypatch):
    """One file (a hard link) is the same without reading it; files of other sizes differ without
    reading them; only files of one size are hashed."""
    hashed: list[str] = []
    real = merge_module._file_sha256
    monkeypatch.setattr(merge_module, "_file_sha256", lambda p: hashed.append(str(p)) or real(p))
    a, b, c = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "c.png"
    a.write_bytes(b"pixels")
    os.link(a, b)
    c.write_bytes(b"pixels and more")
    assert merge_module._file_difference(str(a), str(b)) is None and hashed == []
    assert merge_module._file_difference(str(a), str(c)) == "6 and 15 bytes" and hashed == []
    c.write_bytes(b"pixelz")
    assert merge_module._file_difference(str(a), str(c)) == "same size, different content" and len(hashed) == 2
