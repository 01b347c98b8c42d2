"""The write rule's remaining holes (a review of issue 44): merge and convert into their own
inputs, a FIFO where a folder's job marker goes, a file that appears at a single-file output while
the command works."""

from __future__ import annotations

import os
import signal

import pytest

from omnigen.cli import main
from omnigen.fakes import write_fake_dataset


def _tree(root) -> dict[str, bytes]:
    return {os.path.relpath(os.path.join(d, f), root): open(os.path.join(d, f), "rb").read()
            for d, _, files in os.walk(root) for f in files}


def test_merge_into_a_folder_inside_its_source_is_refused_and_the_source_untouched(tmp_path, capsys):
    ds = tmp_path / "ds"
    write_fake_dataset(ds, 4)
    before = _tree(ds)
    assert main(["merge", str(ds), "--out", str(ds / "merged")]) == 1
    assert "lies inside" in capsys.readouterr().err and _tree(ds) == before


def test_convert_into_its_source_tree_is_refused_and_the_tree_untouched(tmp_path, capsys):
    from omnigen.converters.kitti_fixture import write_kitti_tree

    src = tmp_path / "kitti"
    write_kitti_tree(src, 2)
    before = _tree(src)
    assert main(["convert", "kitti", str(src), "--out", str(src / "training" / "converted")]) == 1
    assert "lies inside" in capsys.readouterr().err and _tree(src) == before


def test_a_fifo_as_the_job_marker_is_refused_not_waited_on(tmp_path, capsys):
    ds = tmp_path / "ds"
    write_fake_dataset(ds, 2)
    out = tmp_path / "yolo"
    out.mkdir()
    os.mkfifo(out / ".omnigen-job")

    def hang(*_):
        raise TimeoutError("export waited on the FIFO")

    signal.signal(signal.SIGALRM, hang)
    signal.alarm(20)
    try:
        assert main(["export", "yolo", str(ds), "--out", str(out)]) == 1
    finally:
        signal.alarm(0)
    assert "cannot be read as a job marker" in capsys.readouterr().err


def test_a_file_that_appears_at_the_output_during_the_work_is_not_replaced(tmp_path, monkeypatch):
    """eval checks --out before its work (a refusal costs nothing) and again before the rename:
    a file of the user's that appeared at that name meanwhile is kept."""
    from omnigen import outputs

    out = tmp_path / "eval.json"
    outputs.check_output_file(out, "eval", outputs.json_made_by("eval"))  # the check before the work
    out.write_text("mine\n")  # ... during the work
    with pytest.raises(outputs.OutputError, match="was not written by 'omnigen eval'"):
        outputs.write_output_file(out, b'{"omnigen":"eval"}\n', "eval", outputs.json_made_by("eval"))
    assert out.read_text() == "mine\n"
    out.unlink()
    outputs.write_output_file(out, b'{"omnigen":"eval"}\n', "eval", outputs.json_made_by("eval"))
    outputs.write_output_file(out, b'{"omnigen":"eval","n":2}\n', "eval", outputs.json_made_by("eval"))
    assert out.read_text() == '{"omnigen":"eval","n":2}\n'
