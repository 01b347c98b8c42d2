"""Which Cycles compute devices a render uses: `omnigen render --device KIND`, decided from the
devices Cycles reports. Plain Python, no bpy: scenes/blender_backend.py enumerates and applies,
this module decides, so the decision (and its error text) is tested on machines without a GPU.

Why a decision of its own: clusters render on GPUs of several makes, and a job script that asks
for `--device optix` on a node without one must fail at once with what the node has, not fall
back silently to a CPU render a hundred times slower. `auto` is the one kind that falls back,
and says so in one line.

The device decides how a frame is rendered, not what it shows: Cycles renders the same scene,
camera and sample count on any device (the images differ by noise only), so the device is no
render argument a resumed render compares (rigs/render.py, `render_args`): a cluster may resume
a render folder on machines of another kind.
"""

from __future__ import annotations

from dataclasses import dataclass

DEVICE_KINDS = ("auto", "cpu", "cuda", "optix", "hip", "oneapi", "metal")
# `auto`'s order: OptiX before CUDA (the same NVIDIA GPUs, OptiX traces with their RT cores);
# then AMD (HIP), Intel (oneAPI), Apple (Metal).
GPU_PREFERENCE = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")

# Words in Cycles' messages about a type's driver library (CUEW loads CUDA's, HIPEW HIP's):
# the error quotes those of the requested type only.
_LOADER_WORDS = {"OPTIX": ("CUEW", "CUDA", "OPTIX"), "CUDA": ("CUEW", "CUDA"), "HIP": ("HIPEW", "HIP"),
                 "ONEAPI": ("ONEAPI", "SYCL", "LEVEL ZERO", "LEVEL_ZERO"), "METAL": ("METAL",)}


class DeviceUnavailable(RuntimeError):
    """The requested kind of device is not on this machine (or not in this Blender build)."""


@dataclass(frozen=True)
class CyclesDevice:
    """One device as Cycles lists it (`_cycles.available_devices`): its type (CPU, CUDA, OPTIX,
    HIP, ONEAPI, METAL), name and persistent id. A GPU with OptiX support is listed twice, as
    CUDA and as OPTIX."""

    type: str
    name: str
    id: str = ""


@dataclass(frozen=True)
class DeviceChoice:
    """What to set: the preferences' compute_device_type ("NONE" for the CPU), the devices to
    enable (every other one is disabled, the CPU too when GPUs render) and a one-line note for
    the user (empty for an explicit `--device cpu`)."""

    compute_device_type: str
    devices: tuple[CyclesDevice, ...]
    note: str = ""

    @property
    def gpu(self) -> bool:
        return self.compute_device_type != "NONE"

    @property
    def scene_device(self) -> str:
        """`scene.cycles.device`."""
        return "GPU" if self.gpu else "CPU"


def _found(devices) -> str:
    """'CPU (Intel Xeon), CUDA (NVIDIA A100)': every device Cycles listed, by type, once each."""
    seen: dict[tuple[str, str], None] = {}
    for d in devices:
        seen.setdefault((d.type, d.name), None)
    return ", ".join(f"{t} ({n})" for t, n in seen) or "no device at all"


def choose_devices(requested: str, found, offered: tuple[str, ...] | None = None,
                   diagnostics: tuple[str, ...] = ()) -> DeviceChoice:
    """The devices a render of kind `requested` (one of DEVICE_KINDS) uses, from the devices
    Cycles `found` (CyclesDevice); `offered` are the GPU types this Blender build supports
    (None: not known, then any); `diagnostics` are Cycles' own messages from the enumeration
    ("CUEW initialization failed: ..."), quoted in the error since they say why a GPU is missing.

    Raises ValueError for an unknown kind and DeviceUnavailable when the kind is not there,
    naming what was found.
    """
    kind = str(requested).lower()
    if kind not in DEVICE_KINDS:
        raise ValueError(f"--device {requested!r}: choose from {', '.join(DEVICE_KINDS)}")
    found = tuple(found)
    if kind == "cpu":
        return DeviceChoice("NONE", tuple(d for d in found if d.type == "CPU"))
    by_type = {t: tuple(d for d in found if d.type == t) for t in GPU_PREFERENCE}
    if kind == "auto":
        best = next((t for t in GPU_PREFERENCE if by_type[t]), None)
        if best is None:
            return DeviceChoice("NONE", tuple(d for d in found if d.type == "CPU"),
                                f"Cycles renders on the CPU: no GPU found (--device auto; found {_found(found)})")
        return _on_gpu(best, by_type[best], " (--device auto)")
    t = kind.upper()
    if by_type[t]:
        return _on_gpu(t, by_type[t])
    why = f"this Blender build's Cycles has no {t} support (it has {', '.join(offered) or 'none'})" \
        if offered is not None and t not in offered else f"Cycles found no {t} device on this machine"
    said = [m for m in diagnostics if any(w in m.upper() for w in _LOADER_WORDS[t])]
    said = f"; Cycles said: {' / '.join(said)}" if said else ""
    raise DeviceUnavailable(f"--device {kind}: {why}; it found {_found(found)}{said}; "
                            "use --device auto to take the best there is")


def _on_gpu(t: str, devices: tuple[CyclesDevice, ...], suffix: str = "") -> DeviceChoice:
    return DeviceChoice(t, devices, f"Cycles renders on {t}: {', '.join(d.name for d in devices)}{suffix}")
