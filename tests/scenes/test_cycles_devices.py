"""Issue 26, part 1: `omnigen render --device` selects Cycles' compute devices.

The decision (scenes/cycles_devices.py) is tested on fake device lists, so the GPU cases run on
machines without a GPU; two CLI runs with bpy check the error and the CPU fallback for real, and
that the device is no argument a resumed render compares.
"""

from __future__ import annotations

import json

import pytest

from omnigen.cli import main
from omnigen.scenes.cycles_devices import DEVICE_KINDS, CyclesDevice, DeviceUnavailable, choose_devices

CPU = CyclesDevice("CPU", "AMD EPYC 7763", "CPU")
A100 = [CyclesDevice("CUDA", "NVIDIA A100", "CUDA_0"), CyclesDevice("CUDA", "NVIDIA A100", "CUDA_1")]
A100_OPTIX = [CyclesDevice("OPTIX", "NVIDIA A100", "CUDA_0_OptiX"), CyclesDevice("OPTIX", "NVIDIA A100", "CUDA_1_OptiX")]
MI250 = [CyclesDevice("HIP", "AMD Instinct MI250", "HIP_0")]
ARC = [CyclesDevice("ONEAPI", "Intel Arc A770", "ONEAPI_0")]
M2 = [CyclesDevice("METAL", "Apple M2 Max (GPU - 38 cores)", "METAL_0")]
BUILD = ("CUDA", "OPTIX", "HIP", "ONEAPI")  # what bpy 5.0's Linux wheel offers
CUEW = "CUEW initialization failed: Error opening the library"
HIPEW = "HIPEW initialization failed: Error opening HIP dynamic library"


@pytest.mark.parametrize("found, best", [
    ([CPU, *A100, *A100_OPTIX, *MI250], "OPTIX"),
    ([CPU, *A100, *MI250, *ARC], "CUDA"),
    ([CPU, *ARC, *MI250], "HIP"),
    ([CPU, *ARC, *M2], "ONEAPI"),
    ([CPU, *M2], "METAL"),
])
def test_auto_takes_the_best_gpu_type_and_all_its_devices_without_the_cpu(found, best):
    choice = choose_devices("auto", found)
    assert choice.compute_device_type == best and choice.gpu and choice.scene_device == "GPU"
    assert choice.devices == tuple(d for d in found if d.type == best)
    assert CPU not in choice.devices
    assert best in choice.note and "\n" not in choice.note


def test_auto_without_a_gpu_falls_back_to_the_cpu_with_a_one_line_note():
    choice = choose_devices("auto", [CPU], BUILD, (CUEW, HIPEW))
    assert (choice.compute_device_type, choice.scene_device, choice.devices) == ("NONE", "CPU", (CPU,))
    assert "CPU" in choice.note and CPU.name in choice.note and "\n" not in choice.note


def test_a_requested_gpu_type_that_is_present_is_used_alone():
    choice = choose_devices("cuda", [CPU, *A100, *A100_OPTIX])
    assert choice.compute_device_type == "CUDA" and choice.devices == tuple(A100)
    assert choose_devices("hip", [CPU, *A100, *MI250]).devices == tuple(MI250)


def test_cpu_is_the_cpu_even_beside_gpus():
    choice = choose_devices("CPU", [CPU, *A100_OPTIX])
    assert (choice.compute_device_type, choice.scene_device, choice.devices, choice.note) == ("NONE", "CPU", (CPU,), "")


def test_a_missing_gpu_type_is_an_error_naming_what_was_found_and_why():
    with pytest.raises(DeviceUnavailable) as err:
        choose_devices("cuda", [CPU, *MI250], BUILD, (CUEW, HIPEW))
    msg = str(err.value)
    assert msg.startswith("--device cuda: Cycles found no CUDA device") and "\n" not in msg
    assert f"CPU ({CPU.name})" in msg and "HIP (AMD Instinct MI250)" in msg  # what is there
    assert CUEW in msg and HIPEW not in msg  # CUDA's loader failing, not HIP's
    assert "--device auto" in msg
    # OptiX runs on CUDA GPUs only: a CUDA-only list (OptiX unusable) is an error for optix
    with pytest.raises(DeviceUnavailable, match="no OPTIX device.*CUDA \\(NVIDIA A100\\)"):
        choose_devices("optix", [CPU, *A100], BUILD)


def test_a_gpu_type_the_build_lacks_says_so():
    with pytest.raises(DeviceUnavailable, match="has no METAL support \\(it has CUDA, OPTIX, HIP, ONEAPI\\)"):
        choose_devices("metal", [CPU], BUILD)


def test_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="choose from auto, cpu, cuda"):
        choose_devices("vulkan", [CPU])
    assert DEVICE_KINDS == ("auto", "cpu", "cuda", "optix", "hip", "oneapi", "metal")


def test_device_is_not_a_recorded_render_argument(tmp_path):
    """A cluster resumes a folder on nodes of another kind: the device must not refuse it."""
    from omnigen.rigs.render import RenderJob, claim_render_folder, render_args

    jobs = [RenderJob(rig="pole", frames=2, out=tmp_path, scene="tiny", width=64, height=48, device=d)
            for d in ("optix", "cpu", "auto")]
    args = [render_args(j) for j in jobs]
    assert args[0] == args[1] == args[2] and not any("device" in k for k in args[0])
    for job, a in zip(jobs, args):
        claim_render_folder(job, a)  # no refusal
    assert not any("device" in k for k in json.loads((tmp_path / ".render-args.json").read_text()))


def test_raster_refuses_a_gpu_device(tmp_path, capsys):
    out = tmp_path / "r"
    rc = main(["render", "--rig", "pole", "--frames", "1", "--out", str(out), "--backend", "raster",
               "--device", "optix"])
    err = capsys.readouterr().err
    assert rc == 2 and "--device optix needs --backend cycles" in err and not out.exists()


# ---------------------------------------------------------------------------------------------
# With bpy: the real enumeration on this machine
# ---------------------------------------------------------------------------------------------


def _render(out, device: str) -> list[str]:
    return ["render", "--rig", "pole", "--frames", "1", "--out", str(out), "--scene", "tiny", "--width", "64",
            "--height", "48", "--backend", "cycles", "--quality", "preview", "--device", device]


def test_cli_missing_cuda_fails_in_one_line_before_writing(tmp_path, capsys):
    pytest.importorskip("bpy", reason="bpy not installed")
    from omnigen.scenes.blender_backend import cycles_devices

    try:
        cycles_devices("cuda")
        pytest.skip("this machine has a CUDA device")
    except DeviceUnavailable:
        pass
    out = tmp_path / "r"
    rc = main(_render(out, "cuda"))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and not out.exists()
    assert err.startswith("omnigen render: --device cuda: Cycles found no CUDA device") and "\n" not in err
    assert "found CPU (" in err and "Traceback" not in err


def test_cli_auto_renders_and_resumes_on_another_device(tmp_path, capsys):
    pytest.importorskip("bpy", reason="bpy not installed")
    import bpy

    from omnigen.scenes.blender_backend import cycles_devices

    expected = cycles_devices("auto")
    out = tmp_path / "r"
    assert main(_render(out, "auto")) == 0
    assert expected.note in capsys.readouterr().err.splitlines()
    assert len(list((out / "records").glob("*.json"))) == 1
    # the selection was applied to Cycles
    prefs = bpy.context.preferences.addons["cycles"].preferences
    assert bpy.context.scene.cycles.device == expected.scene_device
    assert prefs.compute_device_type == expected.compute_device_type
    assert {(d.type, d.id) for d in prefs.devices if d.use} == {(d.type, d.id) for d in expected.devices}
    # the same folder on a machine of another kind resumes (nothing left to render), not refused
    record = next((out / "records").glob("*.json"))
    written = record.stat().st_mtime_ns
    assert main(_render(out, "cpu")) == 0
    assert record.stat().st_mtime_ns == written and len(list((out / "records").glob("*.json"))) == 1
