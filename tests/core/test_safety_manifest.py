"""Issue 44, hole 3: a hand-edited or downloaded manifest.json. It is checked against its schema
before anything reads it (one line naming the file and the field), a taxonomy it names is a preset
or an embedded mapping, never a file to open, and taxonomy files are read only where the user named
one on the command line, as a regular, size-capped file."""

from __future__ import annotations

import json
import os
import re
import threading
from pathlib import Path
from typing import Any, Callable

import pytest

from omnigen.checks import check_dataset
from omnigen.cli import main as cli
from omnigen.dataset import MANIFEST, Dataset, DatasetError, ManifestError
from omnigen.fakes import write_fake_dataset
from omnigen.merge import merge
from omnigen.taxonomy import TAXONOMY_MAX_BYTES, load_taxonomy


def finishes(call: Callable[[], Any], seconds: float = 20.0) -> Any:
    """call()'s result, failing (rather than hanging the suite) if it blocks: opening a FIFO for
    reading waits for a writer for ever. The thread is a daemon, so a blocked one dies with pytest."""
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as exc:  # handed to the test's thread
            outcome["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"blocked for {seconds} s (a FIFO was opened?)"
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    return write_fake_dataset(tmp_path_factory.mktemp("src") / "kit", n_frames=3, objects_per_frame=2, seed=1,
                              source="kitti").root


@pytest.fixture
def merged(source, tmp_path) -> Path:
    out = tmp_path / "uov"
    merge([source], out)
    return out


def edit_manifest(root: Path, edit: Callable[[dict], Any]) -> None:
    manifest = json.loads((root / MANIFEST).read_text())
    replaced = edit(manifest)
    (root / MANIFEST).write_text(json.dumps(manifest if replaced is None else replaced))


def one_line_error(argv: list[str], capsys) -> str:
    """Run a command that must fail with exit 1 and one line on stderr (no traceback); that line."""
    capsys.readouterr()
    assert finishes(lambda: cli(argv)) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    return err


def manifest_problems(root: Path) -> list[tuple[str, str]]:
    return [(p.file, p.field) for p in finishes(lambda: check_dataset(root, show_progress=False))[1]]


def test_a_manifest_that_is_a_json_list_is_one_line_everywhere(merged, tmp_path, capsys):
    edit_manifest(merged, lambda m: [m])
    path = str(merged / MANIFEST)
    assert manifest_problems(merged) == [(path, "<manifest>")]
    for argv in (["stats", str(merged), "--out", str(tmp_path / "stats"), "--gallery", "0"],
                 ["export", "coco", str(merged), "--out", str(tmp_path / "c.json")],
                 ["export", "yolo", str(merged), "--out", str(tmp_path / "yolo")]):
        err = one_line_error(argv, capsys)
        assert f"{path}: field '<manifest>': expected an object, got list" in err


@pytest.mark.parametrize("kind", ["device", "fifo", "toml file"])
def test_a_taxonomy_a_manifest_names_is_never_opened(merged, tmp_path, capsys, kind):
    """`taxonomy: {"name": "/dev/zero"}` had export read gigabytes, a FIFO there hung export and
    merge --update for ever, and a TOML file anywhere was read; validate called all of them valid."""
    if kind == "device":
        name = "/dev/zero"
    elif kind == "fifo":
        name = str(tmp_path / "fifo.toml")
        os.mkfifo(name)
    else:
        name = str(tmp_path / "mine.toml")
        Path(name).write_text('name = "mine"\n[classes]\ncar = "vehicle"\n')
    edit_manifest(merged, lambda m: m.update(taxonomy={"name": name}))
    path = str(merged / MANIFEST)
    assert manifest_problems(merged) == [(path, "taxonomy.name")]
    err = one_line_error(["export", "coco", str(merged), "--out", str(tmp_path / "c.json")], capsys)
    assert f"{path}: field 'taxonomy.name': {name!r} is not a preset (coarse, fine)" in err
    assert "field 'taxonomy.name'" in one_line_error(["merge", "--update", "--out", str(merged)], capsys)


MALFORMED_TAXONOMIES = [
    ("fine", "taxonomy", "expected an object"),
    ({"name": "mine", "mapping": [["car", "vehicle"]]}, "taxonomy.mapping", "must be a table"),
    ({"name": "mine", "mapping": {"spaceship": "vehicle"}}, "taxonomy.mapping.spaceship", "not a fine class"),
    ({"name": "mine", "mapping": {"car": 3}}, "taxonomy.mapping.car", "non-empty string"),
    ({"mapping": {"car": "vehicle"}}, "taxonomy.name", "non-empty string"),
    ({"name": "mine", "mapping": {"car": "vehicle"}, "classes": ["vehicle", "person"]}, "taxonomy.classes",
     "each target class of the mapping once"),
    ({"name": "mine", "mapping": {"car": "vehicle"}, "classes": "vehicle"}, "taxonomy.classes",
     "each target class of the mapping once"),
]


@pytest.mark.parametrize("entry, field, message", MALFORMED_TAXONOMIES)
def test_a_malformed_taxonomy_mapping_names_the_file_and_the_field(merged, tmp_path, capsys, entry, field, message):
    edit_manifest(merged, lambda m: m.update(taxonomy=entry))
    path = str(merged / MANIFEST)
    assert manifest_problems(merged) == [(path, field)]
    err = one_line_error(["export", "yolo", str(merged), "--out", str(tmp_path / "yolo")], capsys)
    assert f"{path}: field '{field}': " in err and message in err


WRONG_TYPES = [
    (lambda m: m["merge"].update(test_fraction="0.1"), "merge.test_fraction"),
    (lambda m: m["merge"].update(test_fraction=1.5), "merge.test_fraction"),
    (lambda m: m["merge"].update(seed=-1), "merge.seed"),
    (lambda m: m["merge"].update(sources={"path": "/x"}), "merge.sources"),
    (lambda m: m["merge"]["sources"][0].update(path="relative/src"), "merge.sources[0].path"),
    (lambda m: m["merge"]["sources"][0].update(path=7), "merge.sources[0].path"),
    (lambda m: m.update(merge=["sources"]), "merge"),
    (lambda m: m.update(name={"first": "uov"}), "name"),
    (lambda m: m["counts"].update(frames_by_source=[3]), "counts.frames_by_source"),
    (lambda m: m.update(render="ego"), "render"),
    (lambda m: m.update(conversion={"converter": ["kitti"]}), "conversion.converter"),
]


@pytest.mark.parametrize("edit, field", WRONG_TYPES)
def test_a_manifest_field_of_the_wrong_type_names_the_file_and_the_field(merged, capsys, edit, field):
    edit_manifest(merged, edit)
    path = str(merged / MANIFEST)
    assert manifest_problems(merged) == [(path, field)]
    with pytest.raises(ManifestError, match=re.escape(f"field '{field}'")):
        Dataset.open(merged)
    assert f"{path}: field '{field}': " in one_line_error(["merge", "--update", "--out", str(merged)], capsys)


def test_a_manifest_that_is_a_fifo_or_too_large_is_refused_unread(merged, capsys):
    manifest = merged / MANIFEST
    manifest.unlink()
    os.mkfifo(manifest)
    assert manifest_problems(merged) == [(str(manifest), "<file>")]
    with pytest.raises(DatasetError, match="not a regular file"):
        finishes(lambda: Dataset.open(merged))
    manifest.unlink()
    manifest.symlink_to("/dev/zero")
    assert manifest_problems(merged) == [(str(manifest), "<file>")]


def test_a_deeply_nested_manifest_or_record_is_a_problem_not_a_crash(merged, capsys):
    nested = "[" * 100_000 + "]" * 100_000
    (merged / MANIFEST).write_text(nested)
    record = sorted((merged / "records").glob("*.json"))[0]
    record.write_text(nested)
    problems = finishes(lambda: check_dataset(merged, show_progress=False))[1]
    assert {(p.file, p.field, p.message) for p in problems} == {
        (str(merged / MANIFEST), "<json>", "JSON nested too deeply to read"),
        (str(record), "<json>", "JSON nested too deeply to read")}
    assert cli(["validate", str(merged)]) == 1 and "INVALID (2 problems)" in capsys.readouterr().out


def test_a_taxonomy_file_named_on_the_command_line_is_read_as_a_capped_regular_file(source, tmp_path, capsys):
    fifo = tmp_path / "classes.toml"
    os.mkfifo(fifo)
    err = one_line_error(["merge", str(source), "--out", str(tmp_path / "a"), "--taxonomy", str(fifo)], capsys)
    assert f"{fifo}: not a regular file (a FIFO)" in err
    big = tmp_path / "big.toml"
    big.write_text('name = "big"\n[classes]\ncar = "vehicle"\n' + "#" * TAXONOMY_MAX_BYTES)
    with pytest.raises(ValueError, match=f"more than the {TAXONOMY_MAX_BYTES} allowed"):
        load_taxonomy(big)
    with pytest.raises(ValueError, match="field 'name'"):
        (tmp_path / "named.toml").write_text('name = 3\n[classes]\ncar = "vehicle"\n')
        load_taxonomy(tmp_path / "named.toml")
    assert not (tmp_path / "a").exists()


def test_merge_options_are_checked_when_parsed(source, tmp_path, capsys):
    for option, value, message in (("--test-fraction", "1", "1 is outside [0, 1)"),
                                   ("--test-fraction", "nan", "nan is not a finite number"),
                                   ("--test-fraction", "-0.1", "-0.1 is outside [0, 1)"),
                                   ("--seed", "-1", "--seed: -1 is outside [0, ")):
        with pytest.raises(SystemExit) as exc:
            cli(["merge", str(source), "--out", str(tmp_path / "m"), option, value])
        assert exc.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
