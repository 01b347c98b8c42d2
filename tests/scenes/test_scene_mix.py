"""A mix of presets (`--scene downtown,suburban,arterial,intersection`): one preset per city
seed, drawn from the seed; recorded in the render arguments, the manifest and every record;
validate renders with the mix."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.preset import mix_names, preset_for_seed

MIX = "downtown,suburban,arterial,intersection"


def test_each_seed_draws_one_preset_of_the_mix_and_consecutive_seeds_cover_it():
    assert [preset_for_seed(MIX, s) for s in range(5)] == ["downtown", "suburban", "arterial", "intersection", "downtown"]
    assert preset_for_seed("arterial", 7) == "arterial"  # one name is a mix of one
    assert {SceneGenerator(MIX, s).preset.name for s in range(4)} == set(MIX.split(","))
    gen = SceneGenerator(MIX, 6)
    assert gen.preset.name == "arterial" and gen.city.preset == "arterial"


def test_a_mix_with_an_unknown_or_empty_name_is_refused():
    with pytest.raises(ValueError, match="unknown preset 'downtwn'"):
        mix_names("downtown,downtwn")
    with pytest.raises(ValueError, match="empty name"):
        mix_names("downtown,,suburban")


def test_the_render_folder_records_the_preset_the_seed_drew(tmp_path):
    from omnigen.rigs.render import RenderJob, render_args, render_info

    job = RenderJob(rig="pole", frames=1, out=tmp_path, seed=3, scene=MIX, backend="raster")
    args = render_args(job)
    assert args["scene"] == "intersection" and args["scene_mix"] == MIX
    assert render_info(job)["scene"] == "intersection"
    single = render_args(RenderJob(rig="pole", frames=1, out=tmp_path, seed=3, scene="intersection", backend="raster"))
    assert "scene_mix" not in single
    # the frames depend on the preset drawn, not on how it was named: the same definition hash
    assert single["scene_sha256"] == args["scene_sha256"]


def test_validate_renders_the_mix():
    import benchmarks.validate as v

    ns = argparse.Namespace(frames=4, cities=2, seed=0, size=64, backend="raster", scene=v.SCENE_MIX)
    jobs = v.render_jobs(Path("/nonexistent-validate-work"), ns)
    assert jobs and all(argv[argv.index("--scene") + 1] == v.SCENE_MIX for argv, _ in jobs)
    assert "scene" in v.DATA_ARGUMENTS
    assert set(mix_names(v.SCENE_MIX)) == {"downtown", "suburban", "arterial", "intersection"}


@pytest.mark.parametrize("rig", ["ego", "pole", "drone"])
def test_intersection_and_the_mix_render_from_every_rig(rig, tmp_path):
    pytest.importorskip("pyrender", reason="pyrender not installed")
    pytest.importorskip("OpenGL", reason="PyOpenGL not installed")
    import json

    from omnigen.cli import main

    for scene, seed, drawn in (("intersection", 0, "intersection"), (MIX, 2, "arterial")):
        out = tmp_path / f"{rig}-{seed}"
        assert main(["render", "--rig", rig, "--frames", "1", "--seed", str(seed), "--scene", scene, "--width", "96",
                     "--height", "72", "--backend", "raster", "--out", str(out)]) == 0
        records = list((out / "records").glob("*.json"))
        assert len(records) == 1
        rec = json.loads(records[0].read_text())
        assert rec["synthetic"]["scene"] == drawn and rec["group"] == f"synthetic-{drawn}-{seed}"
        assert json.loads((out / "manifest.json").read_text())["render"]["scene"] == drawn
