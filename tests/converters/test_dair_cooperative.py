"""`omnigen convert dair` on a DAIR-V2X-C cooperative root: both sides, paired, placed in the world.

The fixture (omnigen.converters.dair_fixture.write_cooperative_tree) builds each pair from one set
of world boxes, so a shared object's two records must meet in the world through camera_to_world;
the expected poses here are composed from the calibration files by hand.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from omnigen.cli import main
from omnigen.converters.dair_fixture import C_BATCH, VEHICLE_DELAY_US, write_cooperative_tree

N_PAIRS = 12


def convert(src: Path, out: Path, capsys, *extra: str) -> tuple[int, str]:
    code = main(["convert", "dair", str(src), "--out", str(out), "--workers", "1", *extra])
    return code, capsys.readouterr().out


def records(out: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((out / "records").glob("*.json"))}


def read(path: Path) -> dict:
    return json.loads(path.read_text())


def rigid(calib: dict) -> np.ndarray:
    calib = calib.get("transform", calib)
    m = np.eye(4)
    m[:3, :3] = np.array(calib["rotation"], dtype=np.float64)
    m[:3, 3] = np.array(calib["translation"], dtype=np.float64).reshape(3)
    return m


@pytest.fixture(scope="module")
def fixture(tmp_path_factory):
    return write_cooperative_tree(tmp_path_factory.mktemp("dair-c") / "root", N_PAIRS, seed=5)


@pytest.fixture(scope="module")
def converted(fixture, tmp_path_factory) -> dict[str, dict]:
    out = tmp_path_factory.mktemp("out") / "ds"
    assert main(["convert", "dair", str(fixture.root), "--out", str(out), "--workers", "1"]) == 0
    return records(out) | {"__manifest__": read(out / "manifest.json")}


def world_centres(rec: dict, shift: tuple[float, float] = (0.0, 0.0)) -> dict[int, np.ndarray]:
    """World centre per fixture world id (infrastructure: label index; vehicle: fixture_world_id)."""
    m = np.array(rec["camera_to_world"])
    m[:2, 3] -= shift
    out = {}
    for o in rec["objects"]:
        key = o["source_attributes"].get("fixture_world_id", o["instance_id"] - 1)
        out[key] = (m @ np.append(o["box3d"]["center"], 1.0))[:3]
    return out


def test_vehicle_side_is_an_ego_view_with_its_own_intrinsics_and_labels(fixture, converted):
    vroot = fixture.root / "vehicle-side"
    for i, key in enumerate(fixture.vehicle_keys):
        rec = converted[f"dair-v2x-c-veh-{key}"]
        assert (rec["view"], rec["source"], rec["width"], rec["height"]) == ("ego", "dair-v2x-c", 128, 72)
        K = np.array(read(vroot / "calib/camera_intrinsic" / f"{key}.json")["cam_K"]).reshape(3, 3)
        assert np.allclose(rec["K"], K)
        infra = converted[f"dair-v2x-c-{fixture.infrastructure.keys[fixture.pair_infra[i]]}"]
        assert not np.allclose(rec["K"], infra["K"])
        # boxes in the vehicle camera through calib/lidar_to_camera, from label/camera
        l2c = rigid(read(vroot / "calib/lidar_to_camera" / f"{key}.json"))
        labels = read(vroot / "label/camera" / f"{key}.json")
        assert len(rec["objects"]) + len(rec["ignore_regions"]) == len(labels) > 0
        for o in rec["objects"]:
            loc = labels[o["instance_id"] - 1]["3d_location"]
            expected = (l2c @ [loc["x"], loc["y"], loc["z"], 1.0])[:3]
            assert np.allclose(o["box3d"]["center"], expected, atol=1e-9)


def test_a_pair_shares_its_id_group_sequence_and_clock(fixture, converted):
    infra_keys = fixture.infrastructure.keys
    for i, (vkey, j) in enumerate(zip(fixture.vehicle_keys, fixture.pair_infra)):
        veh, infra = converted[f"dair-v2x-c-veh-{vkey}"], converted[f"dair-v2x-c-{infra_keys[j]}"]
        assert veh["pair"] == f"dair-v2x-c-pair-{vkey}"
        assert veh["group"] == infra["group"] == veh["sequence"] == f"dair-v2x-c-batch-{j // C_BATCH}"
        assert veh["timestamp"] == pytest.approx((j % C_BATCH) * 0.1 + VEHICLE_DELAY_US / 1e6)
        assert infra["timestamp"] == pytest.approx((j % C_BATCH) * 0.1)
        if i < N_PAIRS:
            assert infra["pair"] == veh["pair"]
    # infrastructure frame 0 is in two pairs: it keeps the first, and the second is counted
    assert converted[f"dair-v2x-c-{infra_keys[0]}"]["pair"] == f"dair-v2x-c-pair-{fixture.vehicle_keys[0]}"
    assert converted["__manifest__"]["conversion_stats"]["infrastructure_frames_in_a_later_pair"] == 1
    assert converted["__manifest__"]["conversion"]["side"] == "both"


def test_merge_never_splits_a_pair_even_with_one_group_per_frame(fixture, tmp_path, capsys):
    # --group-by time with a zero gap gives every infrastructure frame its own group (0.1 s apart):
    # only the vehicle frame's group (and merge's pair join) keep a pair together
    out = tmp_path / "ds"
    assert convert(fixture.root, out, capsys, "--group-by", "time", "--group-gap", "0")[0] == 0
    recs = records(out)
    assert len({r["group"] for r in recs.values() if r["view"] == "infrastructure"}) == N_PAIRS
    assert main(["merge", str(out), "--out", str(tmp_path / "merged"), "--test-fraction", "0.5", "--seed", "3"]) == 0
    test = set((tmp_path / "merged/splits/test.txt").read_text().split())
    assert 0 < len(test) < len(recs)
    for rec in recs.values():
        partner = [r for r in recs.values() if r["pair"] is not None and r["pair"] == rec["pair"]]
        assert len({r["frame_id"] in test for r in partner}) <= 1, rec["pair"]


def test_shared_objects_agree_in_the_world_and_the_offset_is_applied(fixture, converted):
    shared = 0
    for i, (vkey, j) in enumerate(zip(fixture.vehicle_keys[:N_PAIRS], fixture.pair_infra)):
        veh, infra = converted[f"dair-v2x-c-veh-{vkey}"], converted[f"dair-v2x-c-{fixture.infrastructure.keys[j]}"]
        v, w = world_centres(veh), world_centres(infra)
        common = sorted(set(v) & set(w))
        shared += len(common)
        assert max((np.linalg.norm(v[k] - w[k]) for k in common), default=0.0) < 0.01
        offset = fixture.offsets[i]
        if offset is not None and common:  # ignoring system_error_offset, they disagree by it
            raw = world_centres(infra, offset)
            for k in common:
                assert np.allclose((v[k] - raw[k])[:2], offset, atol=0.01)
    assert shared >= 3 * N_PAIRS
    for rec in converted.values():
        if "camera_to_world" in rec:
            r = np.array(rec["camera_to_world"])[:3, :3]
            assert np.abs(r.T @ r - np.eye(3)).max() < 1e-9 and np.linalg.det(r) > 0


def test_vehicle_pose_is_novatel_to_world_after_lidar_to_novatel_after_camera_to_lidar(fixture, converted):
    vroot, key = fixture.root / "vehicle-side", fixture.vehicle_keys[2]
    calib = {name: rigid(read(vroot / "calib" / name / f"{key}.json"))
             for name in ("novatel_to_world", "lidar_to_novatel", "lidar_to_camera")}
    expected = calib["novatel_to_world"] @ calib["lidar_to_novatel"] @ np.linalg.inv(calib["lidar_to_camera"])
    assert np.allclose(converted[f"dair-v2x-c-veh-{key}"]["camera_to_world"], expected, atol=1e-6)


def test_missing_world_calibration_gives_null_camera_to_world(fixture, tmp_path, capsys):
    root = tmp_path / "root"
    write_cooperative_tree(root, 3, seed=5)
    (root / "vehicle-side/calib/novatel_to_world/010001.json").unlink()
    (root / "infrastructure-side/calib/virtuallidar_to_world/000002.json").unlink()
    code, text = convert(root, tmp_path / "ds", capsys)
    recs = records(tmp_path / "ds")
    assert code == 0 and len(recs) == 7
    nulls = {fid for fid, r in recs.items() if r["camera_to_world"] is None}
    assert nulls == {"dair-v2x-c-veh-010001", "dair-v2x-c-000002"}
    assert "frames without camera_to_world (a world calibration absent): 2" in text


def test_side_infrastructure_gives_todays_output(fixture, tmp_path, capsys):
    """--side infrastructure converts the root as without cooperative/: as the side folder alone."""
    assert convert(fixture.root, tmp_path / "a", capsys, "--side", "infrastructure")[0] == 0
    assert convert(fixture.root / "infrastructure-side", tmp_path / "b", capsys)[0] == 0
    a, b = tmp_path / "a/records", tmp_path / "b/records"
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir()) and len(names) == N_PAIRS
    assert all((a / n).read_bytes() == (b / n).read_bytes() for n in names)
    assert all(json.loads((a / n).read_text())["pair"] is None for n in names)


def test_side_vehicle_converts_the_vehicle_frames_only(fixture, tmp_path, capsys):
    assert convert(fixture.root, tmp_path / "ds", capsys, "--side", "vehicle")[0] == 0
    recs = records(tmp_path / "ds")
    assert sorted(recs) == [f"dair-v2x-c-veh-{k}" for k in fixture.vehicle_keys]
    assert all(r["pair"] and r["group"] for r in recs.values())


def test_side_vehicle_without_a_cooperative_root_is_one_line(fixture, tmp_path, capsys):
    code = main(["convert", "dair", str(fixture.root / "infrastructure-side"), "--out", str(tmp_path / "ds"),
                 "--side", "vehicle"])
    captured = capsys.readouterr()
    text = (captured.out + captured.err).strip()
    assert code != 0 and "cooperative/data_info.json" in text and "--side vehicle" in text
    assert not (tmp_path / "ds").exists()


def test_a_bad_novatel_to_world_is_one_line_naming_file_and_field(tmp_path, capsys):
    root = tmp_path / "root"
    write_cooperative_tree(root, 3, seed=5)
    bad = root / "vehicle-side/calib/novatel_to_world/010001.json"
    bad.write_text(json.dumps({"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 3]], "translation": [0, 0, 0]}))
    code, text = convert(root, tmp_path / "ds", capsys)
    lines = [line for line in text.splitlines() if line.strip().startswith("skipped:")]
    assert len(lines) == 1 and f"{bad}: rotation: not a rotation matrix" in lines[0], text
    assert sorted(records(tmp_path / "ds")) == ["dair-v2x-c-000000", "dair-v2x-c-000001", "dair-v2x-c-000002",
                                                "dair-v2x-c-veh-010000", "dair-v2x-c-veh-010002", "dair-v2x-c-veh-010003"]


def test_cooperative_fixture_is_deterministic(tmp_path):
    a = write_cooperative_tree(tmp_path / "a", 2, seed=9).root
    b = write_cooperative_tree(tmp_path / "b", 2, seed=9).root
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files and all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
