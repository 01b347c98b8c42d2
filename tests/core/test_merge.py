"""merge, splits and the YOLO and COCO exports of a merged dataset."""

from __future__ import annotations

import json
import shutil
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

import omnigen.writer as writer_module
from omnigen.checks import check_dataset
from omnigen.cli import main as cli
from omnigen.formats.coco import to_coco
from omnigen.dataset import Dataset, DatasetError
from omnigen.fakes import write_fake_dataset
from omnigen.index import INDEX_FILE
from omnigen.merge import merge
from omnigen.splits import read_assignments, read_split
from omnigen.taxonomy import load_taxonomy
from omnigen.writer import DatasetWriter


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("sources")
    syn = write_fake_dataset(root / "syn", n_frames=90, objects_per_frame=4, seed=1).root
    kit = write_fake_dataset(root / "kit", n_frames=60, objects_per_frame=4, seed=2, source="kitti").root
    return syn, kit


def _tree_bytes(root: Path) -> dict[str, bytes]:
    """Every file of a dataset but the index, a cache that holds file modification times."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != INDEX_FILE}


def test_merge_is_valid_deterministic_and_keeps_groups(sources, tmp_path):
    a = merge(list(sources), tmp_path / "a" / "uov", seed=3)
    merge(list(sources), tmp_path / "b" / "uov", seed=3)
    assert a.frames == 150 and a.objects == sum(len(Dataset.open(s).objects) for s in sources)
    n, problems = check_dataset(tmp_path / "a" / "uov", show_progress=False)
    assert n == 150 and not problems
    assert _tree_bytes(tmp_path / "a" / "uov") == _tree_bytes(tmp_path / "b" / "uov")
    ds = Dataset.open(tmp_path / "a" / "uov")
    split = read_assignments(ds.root)
    # Groups whole, test share near 10% in every source/view stratum.
    by_group = defaultdict(set)
    strata = defaultdict(list)
    for i, fid in enumerate(ds.table.frame_id):
        by_group[(ds.table.source[i], ds.table.group[i])].add(split[fid])
        strata[f"{ds.table.source[i]}/{ds.table.view[i]}"].append(split[fid] == "test")
    assert all(len(s) == 1 for s in by_group.values())
    for name, flags in strata.items():
        assert 0 < sum(flags) <= 0.2 * len(flags), name
    # Another seed draws another test set.
    c = merge(list(sources), tmp_path / "c" / "uov", seed=4)
    assert c.frames == 150
    assert read_split(tmp_path / "c" / "uov", "test") != read_split(ds.root, "test")
    manifest = ds.manifest
    assert manifest["taxonomy"]["name"] == "fine"
    assert {s["frames"] for s in manifest["merge"]["sources"]} == {90, 60}
    assert manifest["splits"]["test"]["frames"] == len(read_split(ds.root, "test"))


def test_duplicate_images_share_a_file_and_a_side(tmp_path):
    src = write_fake_dataset(tmp_path / "s", n_frames=20, objects_per_frame=2, seed=5).root
    # Frame 13 gets the pixels of frame 2 (another group): they must end on the same side.
    ds = Dataset.open(src)
    (src / ds.table.image[13]).write_bytes((src / ds.table.image[2]).read_bytes())
    out = tmp_path / "m"
    for seed in range(6):
        report = merge([src], out, test_fraction=0.3, seed=seed)
        assert report.unique_images == 19
        split = read_assignments(out)
        assert split[ds.table.frame_id[13]] == split[ds.table.frame_id[2]]
    merged = Dataset.open(out)
    assert merged.table.image[13] == merged.table.image[2]


def test_merge_writes_records_index_and_manifest_through_the_writer(tmp_path, monkeypatch):
    """Issue 28: merge wrote records, index and manifest by hand and read a Dataset's private
    attribute blob. Now the dataset's files go through DatasetWriter (atomic writes, the index
    checked against records/, the manifest last): each record passes through it once, linked or,
    with its paths rewritten, written as bytes; the index once; the seal once; and with the seal
    withheld no manifest appears."""
    a = write_fake_dataset(tmp_path / "a", n_frames=4, objects_per_frame=2, seed=1, source="kitti").root
    b = tmp_path / "b"  # a's pixels under other frame ids: shared images, clashing paths rewritten
    shutil.copytree(a, b)
    for p in list((b / "records").glob("*.json")):
        d = json.loads(p.read_text())
        d["frame_id"] = d["frame_id"].replace("kitti-", "kitti-b")
        (b / "records" / f"{d['frame_id']}.json").write_text(json.dumps(d))
        p.unlink()
    images = Dataset.open(a).table.image
    (b / images[0]).write_bytes((a / images[1]).read_bytes())  # b's first frame: the pixels of a's second
    calls: Counter = Counter()
    for name in ("unseal", "drop_records_except", "link_record", "write_record_bytes", "index_columns", "seal"):
        def spy(self, *args, _real=getattr(DatasetWriter, name), _name=name, **kwargs):
            calls[_name] += 1
            return _real(self, *args, **kwargs)
        monkeypatch.setattr(DatasetWriter, name, spy)
    report = merge([a, b], tmp_path / "m")
    assert report.frames == 8 and report.unique_images == 4  # b's pixels are all a's
    assert calls["link_record"] == 7 and calls["write_record_bytes"] == 1  # one record points at another file
    assert Dataset.open(tmp_path / "m").frame("kitti-b000000").image == images[1]
    assert {k: calls[k] for k in ("unseal", "drop_records_except", "index_columns", "seal")} == dict.fromkeys(
        ("unseal", "drop_records_except", "index_columns", "seal"), 1)
    merged = Dataset.open(tmp_path / "m")
    assert merged.has_source_attributes and len(merged.source_attributes) == len(merged.objects)
    assert check_dataset(tmp_path / "m", show_progress=False)[1] == []
    monkeypatch.setattr(DatasetWriter, "seal", lambda self, ds, digest, extra: ds)
    merge([a, b], tmp_path / "unsealed")
    assert (tmp_path / "unsealed" / INDEX_FILE).exists() and not (tmp_path / "unsealed" / "manifest.json").exists()


def test_update_keeps_existing_assignments(sources, tmp_path):
    syn, kit = sources
    out = tmp_path / "uov"
    merge([syn], out, seed=0)
    before = read_assignments(out)
    assert cli(["merge", str(kit), "--out", str(out), "--update"]) == 0
    after = read_assignments(out)
    assert len(after) == 150
    assert all(after[f] == s for f, s in before.items())
    assert any(f.startswith("kitti-") and s == "test" for f, s in after.items())
    assert len(Dataset.open(out).manifest["merge"]["sources"]) == 2


def test_update_keeps_the_earlier_merges_taxonomy_and_draw(sources, tmp_path):
    syn, kit = sources
    mine = tmp_path / "mine.toml"  # a custom taxonomy, gone by the time the dataset is updated and exported
    mine.write_text('name = "mine"\n[classes]\ncar = "vehicle"\nvan = "vehicle"\npedestrian = "person"\n')
    out = tmp_path / "uov"
    assert cli(["merge", str(syn), "--out", str(out), "--taxonomy", str(mine), "--test-fraction", "0.3",
                "--seed", "5"]) == 0
    mine.unlink()
    assert cli(["merge", str(kit), "--out", str(out), "--update"]) == 0
    manifest = Dataset.open(out).manifest
    assert manifest["taxonomy"]["name"] == "mine" and manifest["taxonomy"]["classes"] == ["vehicle", "person"]
    assert (manifest["merge"]["seed"], manifest["merge"]["test_fraction"]) == (5, 0.3)
    assert cli(["export", "yolo", str(out), "--out", str(tmp_path / "yolo")]) == 0
    assert '0: "vehicle"' in (tmp_path / "yolo" / "data.yaml").read_text()
    assert cli(["export", "coco", str(out), "--out", str(tmp_path / "coco.json")]) == 0
    cats = json.loads((tmp_path / "coco.json").read_text())["categories"]
    assert [c["name"] for c in cats] == ["vehicle", "person"]


def test_a_bare_id_of_two_sources_is_refused_and_unmatched_lines_are_counted(tmp_path):
    kit = write_fake_dataset(tmp_path / "kit", n_frames=3, objects_per_frame=1, seed=2, source="kitti").root
    dair = write_fake_dataset(tmp_path / "dair", n_frames=3, objects_per_frame=1, seed=3, source="dair-v2x-i").root
    val = tmp_path / "val.txt"
    val.write_text("000001\n")  # kitti-000001 or dair-v2x-i-000001?
    with pytest.raises(ValueError, match="val.txt: '000001' names a frame of more than one source"):
        merge([kit, dair], tmp_path / "uov", split_files=[val])
    val.write_text("kitti-000001\n000099\n")
    report = merge([kit, dair], tmp_path / "uov", split_files=[val])
    in_val = read_split(tmp_path / "uov", "val")  # kitti-000001 and the frames of its group
    assert "kitti-000001" in in_val and not any(f.startswith("dair") for f in in_val)
    assert report.unmatched_lines == {str(val): 1}


def test_split_files_are_honoured(sources, tmp_path):
    syn, kit = sources
    val = tmp_path / "val.txt"
    val.write_text("000001\n000002\n")  # KITTI-style bare ids: the only source with these suffixes
    merge([kit], tmp_path / "kitti-only", split_files=[val])
    assert set(read_split(tmp_path / "kitti-only", "val")) >= {"kitti-000001", "kitti-000002"}
    val.write_text("kitti-000001\nkitti-000002\nsynthetic-000005\n")  # beside synthetic-000001: full ids
    merge([syn, kit], tmp_path / "uov", split_files=[val])
    assert set(read_split(tmp_path / "uov", "val")) >= {"kitti-000001", "kitti-000002", "synthetic-000005"}


def test_conflicting_frame_ids_are_refused(tmp_path):
    a = write_fake_dataset(tmp_path / "a", n_frames=3, objects_per_frame=2, seed=1).root
    b = write_fake_dataset(tmp_path / "b", n_frames=3, objects_per_frame=2, seed=2).root
    with pytest.raises(DatasetError, match="different records"):
        merge([a, b], tmp_path / "out")
    assert merge([a, a], tmp_path / "same").frames == 3  # the same input twice is one source


def test_interrupted_merge_never_validates(sources, tmp_path, monkeypatch):
    out = tmp_path / "uov"
    merge([sources[0]], out)  # a finished merge; then a re-merge with one more source dies in its records
    real = writer_module.link_file  # records are placed by the writer; pixels by merge itself
    calls = {"n": 0}

    def dying(src, dst, mode="hardlink"):
        calls["n"] += "records" in str(dst)
        if calls["n"] == 20:  # the pixels are placed; 19 records are
            raise KeyboardInterrupt
        return real(src, dst, mode)

    monkeypatch.setattr(writer_module, "link_file", dying)
    with pytest.raises(KeyboardInterrupt):
        merge(list(sources), out)
    monkeypatch.undo()
    assert calls["n"] == 20 and not (out / "manifest.json").exists()  # unsealed before any record changed
    _, problems = check_dataset(out, show_progress=False)
    assert any(p.field == "manifest.json" for p in problems)
    merge(list(sources), out)  # a rerun finishes it
    assert check_dataset(out, show_progress=False)[1] == []


def test_refuses_to_overwrite_a_dataset_it_did_not_make(sources, tmp_path):
    syn, _ = sources
    with pytest.raises(DatasetError, match="did not make"):
        merge([sources[1]], syn)
    # an unfinished render (no manifest yet) mistyped as --out: nothing of it is deleted
    unfinished = write_fake_dataset(tmp_path / "render", n_frames=3, seed=7).root
    (unfinished / "manifest.json").unlink()
    before = sorted(p.name for p in unfinished.rglob("*"))
    with pytest.raises(DatasetError, match="did not make"):
        merge([sources[1]], unfinished)
    assert sorted(p.name for p in unfinished.rglob("*")) == before
    # a folder a converter claimed is not merge's either
    (tmp_path / "conv").mkdir()
    (tmp_path / "conv" / ".omnigen-job").write_text("convert kitti\n")
    with pytest.raises(DatasetError, match="made by 'omnigen convert kitti'"):
        merge([sources[1]], tmp_path / "conv")


def test_coco_ground_truth_scores_one_against_itself(sources, tmp_path):
    out = tmp_path / "uov"
    merge(list(sources), out, taxonomy=load_taxonomy("coarse"))
    ds = Dataset.open(out)
    coco_dict = to_coco(ds, split="test", taxonomy=load_taxonomy(ds.manifest["taxonomy"]["name"]))
    path = tmp_path / "gt.json"
    path.write_text(json.dumps(coco_dict))
    gt = COCO(str(path))
    dets = [{"image_id": a["image_id"], "category_id": a["category_id"], "keypoints": a["keypoints"],
             "score": 1.0, "bbox": a["bbox"]} for a in coco_dict["annotations"] if a["num_keypoints"] > 0]
    dt = gt.loadRes(dets)
    ev = COCOeval(gt, dt, "keypoints")
    ev.params.kpt_oks_sigmas = np.array([0.125] * 8)
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)


def test_a_yolo_export_again_after_the_splits_changed_keeps_each_frame_in_one_split(sources, tmp_path):
    out, yolo = tmp_path / "uov", tmp_path / "yolo"
    merge(list(sources), out, seed=0)
    assert cli(["export", "yolo", str(out), "--out", str(yolo)]) == 0
    merge(list(sources), out, seed=1)  # another draw: frames change sides
    assert cli(["export", "yolo", str(out), "--out", str(yolo)]) == 0
    placed = defaultdict(list)
    for label in (yolo / "labels").rglob("*.txt"):
        placed[label.stem].append(label.parent.name)
    assignments = read_assignments(out)
    assert placed == {f: [assignments[f]] for f in assignments}
    assert sorted(p.name for p in (yolo / "images").rglob("*.*")) == sorted(f"{f}.png" for f in assignments)
    (yolo / ".omnigen-job").unlink()  # an export from before the marker: known by its data.yaml
    assert cli(["export", "yolo", str(out), "--out", str(yolo)]) == 0
    # a folder with files of its own is not an export's to clear
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert cli(["export", "yolo", str(out), "--out", str(tmp_path / "mine")]) == 1
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]
    (tmp_path / "mine" / "data.yaml").write_text("path: .\nnames:\n  0: cat\n")  # someone else's YOLO dataset
    assert cli(["export", "yolo", str(out), "--out", str(tmp_path / "mine")]) == 1
    # a merge that fails on its sources leaves no claim on its (empty) output
    with pytest.raises(DatasetError):
        merge([tmp_path / "no-such-source"], tmp_path / "empty")
    assert not (tmp_path / "empty" / ".omnigen-job").exists()


def test_yolo_labels_pass_ultralytics_checks(sources, tmp_path):
    out = tmp_path / "uov"
    merge(list(sources), out)
    assert cli(["export", "yolo", str(out), "--out", str(tmp_path / "yolo")]) == 0
    yaml = (tmp_path / "yolo" / "data.yaml").read_text()
    assert "kpt_shape: [8, 3]" in yaml and "flip_idx: [1, 0, 3, 2, 5, 4, 7, 6]" in yaml
    assert "train: images/train" in yaml and "val: images/test" in yaml
    ds = Dataset.open(out)
    n_classes = yaml.count('\n  ')
    n_objects = 0
    for label in (tmp_path / "yolo" / "labels").rglob("*.txt"):
        image = next((tmp_path / "yolo" / "images" / label.parent.name).glob(label.stem + ".*"))
        assert image.stat().st_ino == (out / ds.frame(label.stem).image).stat().st_ino  # linked
        rows = np.loadtxt(label, ndmin=2)
        if rows.size == 0:
            continue
        n_objects += len(rows)
        # verify_image_label: 5 + 8 * 3 columns, class ids valid, coordinates normalised.
        assert rows.shape[1] == 5 + 8 * 3
        assert (rows[:, 0] >= 0).all() and (rows[:, 0] < n_classes).all()
        assert rows.min() >= 0 and rows[:, 1:5].max() <= 1
        kp = rows[:, 5:].reshape(-1, 8, 3)
        assert kp[..., :2].max() <= 1
        assert (kp[kp[..., 2] == 0][:, :2] == 0).all()
        assert set(np.unique(kp[..., 2])) <= {0, 1, 2}
        rec = ds.frame(label.stem)
        x1, y1, x2, y2 = rec.objects[0].bbox
        assert rows[0, 1] == pytest.approx(((x1 + x2) / 2 + 0.5) / rec.width, abs=1e-5)
    assert n_objects == len(ds.objects)


def test_taxonomy_file_errors_name_the_field(tmp_path):
    bad = tmp_path / "tax.toml"
    bad.write_text('name = "mine"\n[classes]\nspaceship = "vehicle"\n')
    with pytest.raises(ValueError, match="classes.spaceship"):
        load_taxonomy(bad)
    good = tmp_path / "good.toml"
    good.write_text('name = "mine"\n[classes]\ncar = "vehicle"\nbus = "vehicle"\npedestrian = "walker"\n')
    t = load_taxonomy(good)
    assert t.classes == ["vehicle", "walker"] and t.class_id("bus") == 0 and t.class_id("van") is None


def test_assign_test_split_properties():
    from omnigen.splits import assign_test_split

    rng = np.random.default_rng(0)
    frames = [f"f{i:05d}" for i in range(3000)]
    groups = {f: f"g{int(rng.integers(600))}" for f in frames}
    strata = {f: ("kitti/ego", "dair-v2x-i/infrastructure", "synthetic/aerial")[int(rng.integers(3))] for f in frames}
    a = assign_test_split(groups, strata, 0.1, seed=1)
    assert a == assign_test_split(dict(reversed(list(groups.items()))), strata, 0.1, seed=1)  # order-free
    assert a != assign_test_split(groups, strata, 0.1, seed=2)
    sides = defaultdict(set)
    for f, s in a.items():
        sides[groups[f]].add(s)
    assert all(len(s) == 1 for s in sides.values())
    for stratum in set(strata.values()):
        fs = [f for f in frames if strata[f] == stratum]
        share = sum(a[f] == "test" for f in fs) / len(fs)
        assert share == pytest.approx(0.1, abs=0.02), stratum
    pinned = assign_test_split(groups, strata, 0.1, seed=1, fixed={frames[0]: "test"})
    assert all(pinned[f] == "test" for f in frames if groups[f] == groups[frames[0]])
    # two frames of one group pinned to two splits: that group would leak, so it is refused
    mate = next(f for f in frames[1:] if groups[f] == groups[frames[0]])
    with pytest.raises(ValueError, match=f"{frames[0]} \\(test\\) and {mate} \\(train\\) are one group"):
        assign_test_split(groups, strata, 0.1, seed=1, fixed={frames[0]: "test", mate: "train"})


def test_a_taxonomy_read_back_from_a_manifest_keeps_its_class_order():
    # manifests are written with sorted keys: the mapping comes back alphabetical, the ids must not
    from omnigen.taxonomy import Taxonomy, recorded_taxonomy

    for name in ("fine", "coarse"):
        t = load_taxonomy(name)
        stored = json.loads(json.dumps({"taxonomy": t.to_dict()}, sort_keys=True))
        assert recorded_taxonomy(stored).classes == t.classes
        assert Taxonomy.from_dict(stored["taxonomy"]).class_id("pedestrian") == t.class_id("pedestrian")


def test_a_small_merge_of_several_groups_has_a_test_split(tmp_path, capsys):
    """Issue 27: 19 frames in groups of 10 and 9 at --test-fraction 0.1 made no test split at all
    (each group is larger than the whole target), and `export --split test` then failed."""
    src = write_fake_dataset(tmp_path / "kit", n_frames=19, objects_per_frame=2, seed=3, source="kitti").root
    out = tmp_path / "uov"
    assert cli(["merge", str(src), "--out", str(out), "--test-fraction", "0.1"]) == 0
    test = read_split(out, "test")
    assert test and len(test) < 19
    ds = Dataset.open(out)
    test_groups = {ds.table.group[ds.index_of(f)] for f in test}
    assert all(ds.table.group[i] not in test_groups for i in range(len(ds)) if ds.table.frame_id[i] not in test)
    assert f"test split: {len(test)} of 19 frames ({len(test) / 19:.3f}; asked 0.1)" in capsys.readouterr().out
    assert cli(["export", "coco", str(out), "--split", "test", "--out", str(tmp_path / "test.json")]) == 0
    # one group only: nothing can be held out without emptying train
    one = write_fake_dataset(tmp_path / "one", n_frames=5, objects_per_frame=1, seed=4, source="kitti").root
    assert merge([one], tmp_path / "uov1", test_fraction=0.1).by_split == {"train": 5}


def test_a_second_merge_into_a_locked_folder_fails_and_touches_nothing(sources, tmp_path):
    import fcntl
    import os

    out = tmp_path / "uov"
    merge([sources[1]], out)
    before = _tree_bytes(out)
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)  # as a merge running in another process holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(DatasetError, match="another job is writing this folder now"):
            merge(list(sources), out)
        assert cli(["merge", str(sources[0]), "--out", str(out)]) == 1
    finally:
        os.close(fd)
    assert _tree_bytes(out) == before
    assert merge(list(sources), out).frames == 150  # the lock is gone with its holder
    # a merge that fails on its inputs leaves no folder it made
    with pytest.raises(DatasetError):
        merge([tmp_path / "no-such-source"], tmp_path / "new")
    assert not (tmp_path / "new").exists()


def test_merge_schema1_with_schema2(tmp_path):
    """A dataset written before schema 2 merges with one that has sequences and tracks: each
    record keeps its own schema (files are placed as they are), and the merged index, assembled
    from the sources' columns, equals the one the records give when read again."""
    old = write_fake_dataset(tmp_path / "old", n_frames=20, objects_per_frame=3, seed=1, schema=1).root
    new = write_fake_dataset(tmp_path / "new", n_frames=20, objects_per_frame=3, seed=2, source="kitti",
                             sequence=True).root
    report = merge([old, new], tmp_path / "uov", seed=0)
    assert report.frames == 40
    n, problems = check_dataset(tmp_path / "uov", show_progress=False)
    assert n == 40 and not problems
    ds = Dataset.open(tmp_path / "uov")
    again = Dataset.open(tmp_path / "uov", rebuild=True)
    for name in ("timestamp", "camera_to_world", "schema_version"):
        assert np.array_equal(getattr(ds.table, name), getattr(again.table, name), equal_nan=name != "schema_version")
    assert ds.table.sequence == again.table.sequence and ds.table.pair == again.table.pair
    assert np.array_equal(ds.objects.track_id, again.objects.track_id)
    assert np.array_equal(ds.objects.velocity, again.objects.velocity, equal_nan=True)
    by_source = {s: {int(v) for v, src in zip(ds.table.schema_version, ds.table.source) if src == s}
                 for s in ("synthetic", "kitti")}
    assert by_source == {"synthetic": {1}, "kitti": {2}}
    kitti = [i for i, s in enumerate(ds.table.source) if s == "kitti"]
    assert all(ds.table.sequence[i] for i in kitti) and not any(ds.table.sequence[i] for i in range(40) if i not in kitti)
    assert (ds.objects.track_id[np.isin(ds.objects.frame, kitti)] >= 1).all()
    assert (ds.objects.track_id[~np.isin(ds.objects.frame, kitti)] == -1).all()
