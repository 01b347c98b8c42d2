"""Dataset folders: write, index, reopen, atomicity, determinism, validation, COCO export."""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pycocotools.coco import COCO

from omnigen.checks import check_dataset
from omnigen.cli import main as cli
from omnigen.formats.coco import export_coco, to_coco
from omnigen.conventions import FLIP_IDX, SKELETON
from omnigen.dataset import MANIFEST, Dataset, DatasetError, record_files, record_path
from omnigen.splits import write_split
from omnigen.fakes import random_frame, write_fake_dataset
from omnigen.files import TMP_PREFIX, atomic_write_bytes, link_file
from omnigen.index import INDEX_FILE, DatasetIndex, records_fingerprint, write_index
from omnigen.record import RecordError
from omnigen.taxonomy import load_taxonomy
from omnigen.writer import DatasetWriter, update_records_digest


@pytest.fixture()
def dataset(tmp_path: Path) -> Dataset:
    return write_fake_dataset(tmp_path / "ds", n_frames=24, objects_per_frame=5, seed=1)


def test_reopened_dataset_equals_what_was_written(dataset: Dataset):
    again = Dataset.open(dataset.root)
    assert len(again) == 24
    for i in range(len(again)):
        written = json.loads(record_path(dataset.root, again.frames[i]["frame_id"]).read_text())
        assert again[i].to_dict() == written
    assert len(again.objects) == sum(len(r.objects) for r in again)
    assert again.manifest["counts"]["objects"] == len(again.objects)


def test_index_is_rebuilt_when_records_change(dataset: Dataset):
    root = dataset.root
    rec = random_frame(seed=99, index=500, n_objects=3)
    DatasetWriter(root).write(rec)
    again = Dataset.open(root)
    assert len(again) == 25 and again.frame(rec.frame_id).to_dict() == rec.to_dict()
    record_path(root, rec.frame_id).unlink()
    assert len(Dataset.open(root)) == 24


def test_a_corrupt_index_is_ignored(dataset: Dataset):
    (dataset.root / INDEX_FILE).write_bytes(b"not an npz")
    assert len(Dataset.open(dataset.root)) == 24


def test_interrupted_writes_leave_no_file_a_reader_accepts(tmp_path: Path, monkeypatch):
    target = tmp_path / "records" / "synthetic-000001.json"

    def boom(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b'{"half": ')
    monkeypatch.undo()
    assert not target.exists()
    assert not [p for p in target.parent.iterdir()]  # the temporary file is cleaned up too
    # A temporary file left by a killed process is skipped by readers.
    ds_root = tmp_path / "ds"
    write_fake_dataset(ds_root, n_frames=3, objects_per_frame=2)
    (ds_root / "records" / f"{TMP_PREFIX}junk").write_text('{"half": ')
    assert len(Dataset.open(ds_root)) == 3


def test_written_files_are_as_readable_as_open_makes_them_and_relinking_leaves_no_temporary(tmp_path: Path):
    # mkstemp alone gives 0600: other users of a shared cluster could not read the dataset
    atomic_write_bytes(tmp_path / "a.json", b"{}")
    umask = os.umask(0o022)
    os.umask(umask)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o666 & ~umask  # 0o644 under the usual 022
    # placing an image again where a rerun already hard-linked it: rename() keeps both names then
    src = tmp_path / "src.png"
    src.write_bytes(b"png")
    for _ in range(2):
        assert link_file(src, tmp_path / "images" / "f.png") == "hardlink"
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == ["f.png"]


def test_bad_record_file_is_named(dataset: Dataset):
    path = record_path(dataset.root, dataset.frames[0]["frame_id"])
    d = json.loads(path.read_text())
    d["objects"][0]["keypoints"] = d["objects"][0]["keypoints"][:7]
    path.write_text(json.dumps(d))
    with pytest.raises(RecordError) as err:
        Dataset.open(dataset.root)
    assert str(path) in str(err.value) and "objects[0].keypoints" in str(err.value)


def test_writing_twice_is_byte_identical(tmp_path: Path):
    a = write_fake_dataset(tmp_path / "a", n_frames=10, objects_per_frame=4, seed=5)
    b = write_fake_dataset(tmp_path / "b", n_frames=10, objects_per_frame=4, seed=5)
    for f in sorted((a.root / "records").iterdir()):
        assert f.read_bytes() == (b.root / "records" / f.name).read_bytes()
    assert (a.root / MANIFEST).read_bytes() == (b.root / MANIFEST).read_bytes()


def _index_members(root: Path) -> dict[str, bytes]:
    """The index's arrays as stored, less the header (it holds the records' fingerprint: their mtimes)."""
    with zipfile.ZipFile(root / INDEX_FILE) as z:
        return {n: z.read(n) for n in z.namelist() if n != "header.npy"}


@pytest.mark.parametrize("source", ["synthetic", "kitti"])  # kitti: objects with source attributes
def test_a_dataset_assembled_from_finished_records_is_what_the_writer_writes_frame_by_frame(tmp_path: Path, source):
    """The writer's API for a merge: finished records linked or written as bytes, the index from
    columns in hand, the manifest last. The result must be the dataset finalize() gives for the
    same records, index and manifest byte for byte, and the index must be the one a reader rebuilds."""
    src = write_fake_dataset(tmp_path / "src", n_frames=6, objects_per_frame=3, seed=4, source=source)
    out = tmp_path / "out"
    writer = DatasetWriter(out, durable=False)
    (out / "records" / "stale-000000.json").write_text("{}")  # an earlier job's record
    (out / MANIFEST).write_text("{}")
    writer.unseal()
    assert not (out / MANIFEST).exists()
    assert writer.drop_records_except(src.frame_ids) == ["stale-000000"]
    digest = hashlib.sha256()
    for i, e in enumerate(record_files(src.root)):
        data = Path(e.path).read_bytes()
        if i % 2:
            writer.write_record_bytes(e.name[:-5], data)
        else:
            assert writer.link_record(e.name[:-5], e.path) == "hardlink"
        update_records_digest(digest, e.name, data)
    assert not list((out / "records").glob(f"{TMP_PREFIX}*"))  # every record placed atomically
    assert src.has_source_attributes == (source == "kitti")
    ds = writer.index_columns(src.table, src.objects, src.source_attributes if src.has_source_attributes else None)
    assert not (out / MANIFEST).exists()  # indexed, not sealed
    extra = {"name": src.manifest["name"]}
    writer.seal(ds, digest.hexdigest(), extra)
    for rel in {rel for r in src if r.synthetic for rel in (r.synthetic.depth, r.synthetic.instance)} | set(src.table.image):
        link_file(src.path(rel), out / rel)
    assert check_dataset(out, show_progress=False)[1] == []
    assert (out / MANIFEST).read_bytes() == (src.root / MANIFEST).read_bytes()
    assert _index_members(out) == _index_members(src.root)
    written = _index_members(out)
    reopened = Dataset.open(out, rebuild=True, show_progress=False)  # rebuilt from records/
    assert _index_members(out) == written and [r.to_dict() for r in reopened] == [r.to_dict() for r in src]


def test_the_writer_refuses_an_index_of_other_frames_than_its_records(dataset: Dataset, tmp_path: Path):
    writer = DatasetWriter(tmp_path / "out")
    for e in record_files(dataset.root)[1:]:
        writer.link_record(e.name[:-5], e.path)
    with pytest.raises(DatasetError, match="not those of records/"):
        writer.index_columns(dataset.table, dataset.objects, None)
    assert not (tmp_path / "out" / INDEX_FILE).exists()
    shuffled = dataset.objects.take(np.arange(len(dataset.objects))[::-1])
    with pytest.raises(ValueError, match="grouped by frame"):
        DatasetIndex.from_columns(dataset.table, shuffled, None)


def test_validate_lists_every_problem(dataset: Dataset, capsys):
    assert cli(["validate", str(dataset.root)]) == 0
    root = dataset.root
    ids = dataset.frame_ids
    (root / dataset.frame(ids[0]).image).unlink()  # missing image
    p = record_path(root, ids[1])
    d = json.loads(p.read_text())
    d["objects"][0]["keypoints"][0] = [float("nan"), 1.0]
    p.write_text(json.dumps(d))  # json.dumps writes NaN
    p = record_path(root, ids[2])
    d = json.loads(p.read_text())
    p.rename(p.with_name("synthetic-999999.json"))  # file name no longer matches the frame id
    n, problems = check_dataset(root, show_progress=False)
    assert n == 24
    text = "\n".join(map(str, problems))
    assert f"{dataset.frame(ids[0]).image} not found" in text
    assert "objects[0].keypoints[0]" in text
    assert "does not match the file name" in text
    assert "records_sha256: does not match records/" in text  # the manifest no longer seals them
    assert len(problems) == 4
    assert cli(["validate", str(root)]) == 1
    assert "INVALID (4 problems)" in capsys.readouterr().out


def test_coco_export_loads_in_pycocotools(dataset: Dataset, tmp_path: Path):
    out = tmp_path / "coco.json"
    assert cli(["export", "coco", str(dataset.root), "--out", str(out)]) == 0
    coco = COCO(str(out))
    assert len(coco.getImgIds()) == len(dataset)
    assert len(coco.getAnnIds()) == len(dataset.objects)
    cat = coco.loadCats(coco.getCatIds())[0]
    assert len(cat["keypoints"]) == 8 and len(cat["skeleton"]) == 12
    assert sorted(map(tuple, cat["skeleton"])) == sorted((a + 1, b + 1) for a, b in SKELETON)
    for img in coco.loadImgs(coco.getImgIds()):
        rec = dataset.frame(img["frame_id"])
        assert img["file_name"] == rec.image and np.allclose(img["K"], rec.K)
        assert img["depth_file"] == rec.synthetic.depth and img["instance_file"] == rec.synthetic.instance
        anns = coco.loadAnns(coco.getAnnIds(imgIds=img["id"]))
        assert len(anns) == len(rec.objects)
        for ann, obj in zip(anns, rec.objects):
            x1, y1, x2, y2 = obj.bbox
            assert ann["bbox"] == pytest.approx([x1, y1, x2 - x1, y2 - y1])
            assert ann["area"] == pytest.approx((x2 - x1) * (y2 - y1))
            kp = np.array(ann["keypoints"]).reshape(8, 3)
            v = obj.visibility
            assert (kp[:, 2] == v).all()
            assert (kp[v == 0] == 0).all()
            assert np.allclose(kp[v > 0, :2], obj.keypoints[v > 0])
            assert ann["num_keypoints"] == int((v > 0).sum())
            assert np.allclose(ann["box3d"]["rotation"], obj.box.rotation)
            assert ann["instance_id"] == obj.instance_id


def test_coco_split_and_taxonomy(dataset: Dataset, tmp_path: Path):
    ids = dataset.frame_ids
    write_split(dataset.root, "test", ids[:5])
    coarse = load_taxonomy("coarse")
    coco = to_coco(Dataset.open(dataset.root), split="test", taxonomy=coarse)
    assert {im["frame_id"] for im in coco["images"]} == set(ids[:5])
    assert [c["name"] for c in coco["categories"]] == ["vehicle", "person", "bike"]
    fine = {a["fine_category"] for a in coco["annotations"]}
    assert not fine & {"barrow", "traffic_cone", "misc"}
    with pytest.raises(Exception, match="no split 'val'"):
        export_coco(dataset, tmp_path / "x.json", split="val")


def test_flip_idx_is_an_involution_that_swaps_left_and_right():
    assert [FLIP_IDX[i] for i in FLIP_IDX] == list(range(8))
    assert all(FLIP_IDX[i] != i for i in range(8))


# --- issue 27: read-only datasets, records filed under another id -----------------------------


def _read_only(monkeypatch, root: Path) -> None:
    """Writes into `root` fail as on a read-only mount (EROFS). Tests run as root, where chmod
    stops no write, so the one place every atomic write creates its file is made to refuse."""
    import errno

    import omnigen.files as files

    real = files.make_temp
    top = str(root.resolve())

    def refusing(folder, suffix=""):
        if str(Path(folder).resolve()).startswith(top):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(folder))
        return real(folder, suffix)

    monkeypatch.setattr(files, "make_temp", refusing)


@pytest.mark.parametrize("index", ["missing", "stale"])
def test_a_read_only_dataset_is_read_with_an_index_in_memory(tmp_path: Path, monkeypatch, capsys, index):
    """Issue 27: export, stats, show, train and merge failed with EROFS writing .index.npz."""
    from omnigen.detector.data.samples import KeypointDataset

    root = write_fake_dataset(tmp_path / "ds", n_frames=6, objects_per_frame=2, seed=3, source="kitti").root
    if index == "missing":
        (root / INDEX_FILE).unlink()
    else:  # a plain `cp -r` gives the records new times: the index no longer matches
        for p in (root / "records").iterdir():
            os.utime(p, ns=(1, 1))
    before = sorted(p.name for p in root.rglob("*"))
    _read_only(monkeypatch, root)
    with pytest.raises(OSError):  # the simulation holds: a write into the dataset fails
        atomic_write_bytes(root / "probe", b"x")
    capsys.readouterr()
    out = tmp_path / "out"
    assert cli(["export", "coco", str(root), "--out", str(out / "c.json")]) == 0
    assert cli(["export", "yolo", str(root), "--out", str(out / "yolo")]) == 0
    assert cli(["stats", str(root), "--out", str(out / "stats"), "--gallery", "0", "--no-check-images",
                "--jobs", "1"]) == 0
    assert cli(["show", str(root), "kitti-000001", "--out", str(out / "f.png")]) == 0
    assert cli(["merge", str(root), "--out", str(out / "uov")]) == 0
    assert len(KeypointDataset(root, load_taxonomy("fine"), 64)) == 6  # what train reads
    notes = [line for line in capsys.readouterr().err.splitlines() if "built in memory" in line]
    assert len(notes) == 6 and notes[0].startswith(f"{root}: cannot write {INDEX_FILE} (Read-only file system)")
    assert sorted(p.name for p in root.rglob("*")) == before  # nothing written into it
    # a writer of the dataset still fails loudly (a merge's index is its output, not a cache)
    ds = Dataset.open(root, show_progress=False)
    with pytest.raises(OSError):
        write_index(root, DatasetIndex(ds.table, ds.offsets, ds.objects, None), "key")
    with pytest.raises(OSError):
        DatasetWriter(root).index_columns(ds.table, ds.objects, None)


def _refile(root: Path, frame_id: str, as_id: str) -> Path:
    """Give record `frame_id` the id `as_id` inside, keeping its file name."""
    path = record_path(root, frame_id)
    d = json.loads(path.read_text())
    d["frame_id"] = as_id
    path.write_text(json.dumps(d))
    return path


def test_a_record_filed_under_another_id_is_refused_by_every_consumer(tmp_path: Path, capsys):
    """Issue 27: `export yolo` reported 13 frames and wrote 12, `export coco` wrote a duplicate id,
    `train` died with a KeyError; only validate saw it."""
    from omnigen.detector.data.samples import KeypointDataset
    from omnigen.dataset import read_record

    root = write_fake_dataset(tmp_path / "ds", n_frames=13, objects_per_frame=2, seed=5, source="kitti").root
    bad = _refile(root, "kitti-000005", "kitti-000004")
    for args in (["export", "yolo", str(root), "--out", str(tmp_path / "y")],
                 ["export", "coco", str(root), "--out", str(tmp_path / "c.json")],
                 ["stats", str(root), "--out", str(tmp_path / "s"), "--gallery", "0"],
                 ["merge", str(root), "--out", str(tmp_path / "m")]):
        assert cli(args) == 1, args
        err = capsys.readouterr().err
        assert f"{bad}: frame_id: 'kitti-000004' does not match the file name 'kitti-000005.json'" in err, args
    with pytest.raises(Exception, match="does not match the file name"):
        KeypointDataset(root, load_taxonomy("fine"), 64)
    assert not (tmp_path / "c.json").exists() and not (tmp_path / "y" / "data.yaml").exists()
    # an index written before the check (holding the mismatched record) is not trusted either
    entries = record_files(root)
    write_index(root, DatasetIndex.from_records(read_record(e.path) for e in entries), records_fingerprint(entries))
    with pytest.raises(Exception, match="does not match the file name"):
        Dataset.open(root)
    # validate names it
    assert cli(["validate", str(root)]) == 1
    assert f"{bad}: frame_id: 'kitti-000004' does not match the file name" in capsys.readouterr().out


def test_the_assembling_writer_refuses_a_misnamed_record_and_unseals_before_dropping(dataset: Dataset):
    """write_record_bytes files a record only under its own frame_id; drop_records_except removes
    the manifest before the first record goes, so an interrupted job never looks finished."""
    from omnigen.dataset import MANIFEST, DatasetError, record_path
    from omnigen.writer import DatasetWriter

    root = dataset.root
    first, second = (dataset.frames[i]["frame_id"] for i in (0, 1))
    data = record_path(root, first).read_bytes()
    writer = DatasetWriter(root, durable=False)
    with pytest.raises(DatasetError, match="does not match the file name"):
        writer.write_record_bytes(second, data)
    assert record_path(root, second).read_bytes() != data  # nothing written
    with pytest.raises(Exception, match="not a JSON object"):
        writer.write_record_bytes(first, b"[1, 2]")
    assert (root / MANIFEST).exists()
    assert writer.drop_records_except({first}) and not (root / MANIFEST).exists()
    assert [p.stem for p in (root / "records").glob("*.json")] == [first]


def test_index_columns_and_old_index_rebuilt(tmp_path: Path):
    """The schema-2 fields travel through the index's columns; an index of the previous version
    (without those columns) is rebuilt from the records instead of read with them missing."""
    ds = write_fake_dataset(tmp_path / "ds", n_frames=12, objects_per_frame=4, seed=3, sequence=True)
    t = ds.table
    assert t.sequence[:2] == ["synthetic-seq000"] * 2 and t.sequence[11] == "synthetic-seq001"
    assert t.pair[3] == "synthetic-seq000-pair000001" and np.allclose(t.timestamp[:3], [0.0, 0.1, 0.2])
    assert t.camera_to_world.shape == (12, 4, 4) and np.array_equal(t.camera_to_world[:, 3], np.tile([0, 0, 0, 1.0], (12, 1)))
    assert ds.objects.track_id.dtype == np.int64 and (ds.objects.track_id >= 1).all()
    assert ds.objects.velocity.shape == (len(ds.objects), 3) and np.isfinite(ds.objects.velocity).all()
    for i in range(len(ds)):
        assert ds[i].to_dict() == json.loads(record_path(ds.root, ds.frame_ids[i]).read_text())

    with np.load(ds.root / INDEX_FILE) as z:  # the index as the previous version wrote it
        old = {k: z[k] for k in z.files if k not in ("obj_track_id", "obj_velocity", "frm_timestamp",
                                                      "frm_camera_to_world")}
    header = json.loads(old["header"].tobytes())
    old["header"] = np.frombuffer(json.dumps({**header, "version": 2}).encode(), dtype=np.uint8)
    np.savez(ds.root / INDEX_FILE, **old)
    again = Dataset.open(ds.root)
    assert np.array_equal(again.objects.track_id, ds.objects.track_id)
    assert np.array_equal(again.table.camera_to_world, ds.table.camera_to_world)
    with np.load(ds.root / INDEX_FILE) as z:
        assert json.loads(z["header"].tobytes())["version"] == 3 and "obj_track_id" in z.files


def test_schema1_records_read_with_null_fields(tmp_path: Path):
    """A dataset written before schema 2 opens, its new columns absent (NaN, -1, None), and each
    record read back equals its file upgraded (the new keys null); validate accepts it."""
    ds = write_fake_dataset(tmp_path / "old", n_frames=6, objects_per_frame=3, seed=4, sequence=True, schema=1)
    assert set(ds.table.schema_version.tolist()) == {1}
    assert ds.table.sequence == [None] * 6 and np.isnan(ds.table.timestamp).all()
    assert np.isnan(ds.table.camera_to_world).all() and (ds.objects.track_id == -1).all()
    assert np.isnan(ds.objects.velocity).all()
    rec = ds[2]
    assert rec.schema_version == 1 and rec.camera_to_world is None and rec.objects[0].track_id is None
    n, problems = check_dataset(ds.root, show_progress=False)
    assert n == 6 and not problems
