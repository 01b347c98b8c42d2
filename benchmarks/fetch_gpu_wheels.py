"""Fetch what benchmarks/gpu_validate.py needs on a GPU machine that has no network: wheels and EGL's loaders.

    python benchmarks/fetch_gpu_wheels.py --out /tmp/gpu-wheels            # where PyPI (and apt) answer
    python benchmarks/fetch_gpu_wheels.py --out DIR --have pip-freeze.txt   # that machine's own `pip freeze`
    python benchmarks/fetch_gpu_wheels.py --check                           # which distributions the code paths import

The GPU machine it is for (docs/gpu.md): Linux x86_64, Python 3.12, PyTorch with CUDA, numpy 2.x and
OpenCV installed, nothing of ours, no network. gpu_validate runs our code from the checkout (our
pyproject pins Python 3.11, numpy<2 and a CPU torch, so `pip install -e .` is no option there) and
installs from this folder, with `--no-index --no-deps`, only the distributions it cannot import.

What is fetched, and why exactly this:
- NEEDS (in benchmarks/common.py): the distributions that the commands gpu_validate runs (render
  --backend raster, convert kitti, merge, train, eval) import, read off the code (ENTRY_MODULES;
  tests/benchmarks/test_gpu_validate.py imports them and checks that NEEDS and the image's packages
  cover every distribution they load, and that NEEDS holds nothing they do not), less what the
  machine's image already has (IMAGE_HAS, or --have). Versions are constraints.txt's (those the
  tests ran with), except PyOpenGL: the 3.1.0 that pyrender pins has no wheel, its sources do not
  byte-compile on Python >= 3.7, and it finds libEGL through ldconfig alone; 3.1.10 dlopens
  `libEGL.so.1`, so LD_LIBRARY_PATH reaches it. pyrender's metadata pins 3.1.0, hence `--no-deps` at
  install time.
- The wheels are cp312 manylinux x86_64 (or pure Python), whatever this machine is.
- EGL's loaders (Debian packages, `apt-get download`): the GPU image has the NVIDIA driver's EGL
  (libEGL_nvidia) but not glvnd's libEGL.so.1 / libOpenGL.so.0 that PyOpenGL opens; the lent
  machine's README (device tool) names this list. gpu_validate unpacks them into its working
  folder and points LD_LIBRARY_PATH there when the machine cannot load libEGL.so.1 itself.
- At most --limit-mb (40) in all: the total is printed; what would pass the limit is skipped,
  named, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import NEEDS, Need  # noqa: E402  (the list gpu_validate.py installs from)

MB = 10**6  # the limit is in megabytes, as the issue states it


# Newer than constraints.txt, with the reason in the module docstring.
VERSION_OVERRIDES = {"pyopengl": "3.1.10"}

# The modules whose imports make up what gpu_validate runs: the commands' modules, and what they
# import inside functions (lazily) on those paths.
ENTRY_MODULES = (
    "omnigen.cli", "omnigen.rigs.render", "omnigen.scenes.generate", "omnigen.scenes.raster_backend", "omnigen.converters.kitti", "omnigen.merge",
    "omnigen.detector.train_command", "omnigen.detector.training.train", "omnigen.detector.eval_command", "omnigen.detector.evaluation.oks_eval", "omnigen.detector.prediction.predict",
    "omnigen.detector.bev.lift", "benchmarks.gpu_validate",
    # lazy: GLRaster's context, the depth EXR writer, the shader compiler, training's progress bar
    "pyrender.platforms.egl", "OpenEXR", "OpenGL.GL.shaders", "OpenGL.EGL", "PIL.Image", "tqdm",
)

# The lent GPU machines' image ('cuda'), as /work/.library/device/KINDS.md listed it on 2026-11-17:
# Python 3.12.3, torch 2.11.0, numpy 2.5.2, torchvision 0.26.0. --have replaces it.
IMAGE_HAS = frozenset("""
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna
imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe
matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy
peft pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout pytest-xdist
python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core scikit-image
scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six sortedcontainers
statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope
triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray xxhash yarl zipp
""".split())

# glvnd's loaders for headless EGL on the NVIDIA driver (the device tool's README lists them).
EGL_DEBS = ("libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")

PLATFORMS = ("manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_27_x86_64", "manylinux_2_28_x86_64",
             "manylinux_2_24_x86_64", "manylinux_2_31_x86_64", "manylinux_2_34_x86_64", "manylinux_2_35_x86_64",
             "manylinux1_x86_64")


def canonical(name: str) -> str:
    """PEP 503's normal form: the same distribution however it is spelled (PyOpenGL, pyopengl)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def pinned_versions(path: Path = ROOT / "constraints.txt") -> dict[str, str]:
    """canonical name -> version, from a `name==version` file (constraints.txt, `pip freeze`)."""
    out = {}
    for line in path.read_text().splitlines():
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*==\s*([^\s;#]+)", line)
        if m:
            out[canonical(m.group(1))] = m.group(2)
    return out


def read_have(path: Path) -> frozenset[str]:
    """The distributions a machine has, from its `pip freeze` / `pip list` output or one name a line."""
    names = set()
    for line in path.read_text().splitlines():
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", line)
        if m and not line.lstrip().startswith(("#", "-", "Package")):
            names.add(canonical(m.group(1)))
    return frozenset(names)


def missing_needs(have: frozenset[str] = IMAGE_HAS) -> list[Need]:
    """The needed distributions a machine with `have` lacks."""
    have = frozenset(canonical(n) for n in have)
    return [n for n in NEEDS if canonical(n.dist) not in have]


def wanted_version(dist: str, pins: dict[str, str]) -> str:
    key = canonical(dist)
    version = VERSION_OVERRIDES.get(key) or pins.get(key)
    if not version:
        raise SystemExit(f"fetch_gpu_wheels: constraints.txt pins no version of {dist}")
    return version


def download_wheel(dist: str, version: str, out: Path) -> Path:
    """`pip download` one cp312 manylinux x86_64 (or pure Python) wheel of dist==version into out."""
    before = set(out.glob("*.whl"))
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
           "--python-version", "3.12", "--implementation", "cp", "--abi", "cp312", "--abi", "abi3", "--abi", "none",
           *(f"--platform={p}" for p in PLATFORMS), "--platform=any", "-d", str(out), f"{dist}=={version}"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"fetch_gpu_wheels: no cp312 manylinux x86_64 wheel of {dist}=={version}:\n{r.stderr[-2000:]}")
    new = sorted(set(out.glob("*.whl")) - before)
    if new:
        return new[0]
    # already there from an earlier run: the wheel whose name carries this version
    prefix = canonical(dist).replace("-", "_")
    return next(p for p in out.glob("*.whl") if canonical(p.name.split("-")[0]).replace("-", "_") == prefix
                and p.name.split("-")[1] == version)


def download_debs(names: tuple[str, ...], out: Path) -> list[Path]:
    """`apt-get download` the amd64 packages into out, from package lists kept in a temporary folder
    (the device tool README's recipe: works unprivileged and on an arm64 machine too)."""
    if shutil.which("apt-get") is None:
        raise SystemExit("fetch_gpu_wheels: no apt-get here: fetch the EGL packages on a Debian or Ubuntu "
                         f"machine ({' '.join(names)}), or pass --no-debs")
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as lists:
        Path(lists, "partial").mkdir()
        opts = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={lists}",
                "-oDebug::NoLocking=1", "-qq"]
        for cmd, cwd in (([*opts, "update"], None), ([*opts, "download", *names], out)):
            r = subprocess.run(["apt-get", *cmd], cwd=cwd, capture_output=True, text=True)
            if r.returncode:
                raise SystemExit(f"fetch_gpu_wheels: apt-get {cmd[-1]} failed:\n{r.stderr[-2000:]}")
    return sorted(out.glob("*.deb"))


def imported_distributions(modules: tuple[str, ...] = ENTRY_MODULES, python: str = sys.executable) -> dict[str, str]:
    """distribution -> one module it loaded, over everything that importing `modules` (in a fresh
    interpreter, from the checkout) loads from installed distributions; a module is traced to its
    distribution by the files each distribution records as installed."""
    probe = f"""
import importlib, importlib.metadata as md, json, os, sys
sys.path.insert(0, {str(ROOT)!r})
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
before = set(sys.modules)
for name in {list(modules)!r}:
    importlib.import_module(name)
loaded = {{}}
for name, mod in list(sys.modules.items()):
    path = getattr(mod, "__file__", None)
    if name not in before and path:
        loaded.setdefault(os.path.normpath(path), name)
out = {{}}
for d in md.distributions():
    for f in d.files or []:
        name = loaded.get(os.path.normpath(d.locate_file(f)))
        if name:
            out.setdefault(d.metadata["Name"], name)
print(json.dumps(out))
"""
    r = subprocess.run([python, "-c", probe], capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise SystemExit(f"fetch_gpu_wheels: importing the code paths failed:\n{r.stderr[-3000:]}")
    found = json.loads(r.stdout.strip().splitlines()[-1])
    return {d: m for d, m in found.items() if canonical(d) != "omnigen"}


def size_mb(paths: list[Path]) -> float:
    return sum(p.stat().st_size for p in paths) / MB


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="folder for the wheels (and debs/ beside them)")
    ap.add_argument("--have", type=Path, help="the GPU machine's `pip freeze` (default: its image's list, IMAGE_HAS)")
    ap.add_argument("--all", action="store_true", help="fetch every needed wheel, whatever the machine has")
    ap.add_argument("--no-debs", action="store_true", help="skip EGL's Debian packages")
    ap.add_argument("--limit-mb", type=float, default=40.0, help="the most the folder may hold (MB)")
    ap.add_argument("--check", action="store_true",
                    help="print the distributions the code paths import here and which NEEDS entry or image package covers each")
    args = ap.parse_args(argv)

    if args.check:
        have = read_have(args.have) if args.have else IMAGE_HAS
        needs = {canonical(n.dist) for n in NEEDS}
        for dist, module in sorted(imported_distributions().items(), key=lambda kv: canonical(kv[0])):
            key = canonical(dist)
            where = "NEEDS" if key in needs else "image" if key in have else "MISSING"
            print(f"{where:8s} {dist} ({module})")
        return 0
    if args.out is None:
        ap.error("--out is required (or --check)")
    if platform.machine() not in ("x86_64", "AMD64"):
        print(f"fetch_gpu_wheels: this machine is {platform.machine()}; the wheels are for x86_64 all the same")
    args.out.mkdir(parents=True, exist_ok=True)
    pins = pinned_versions()
    needs = list(NEEDS) if args.all else missing_needs(read_have(args.have) if args.have else IMAGE_HAS)
    files: list[Path] = []
    skipped: list[str] = []
    limit = args.limit_mb * MB
    for need in needs:
        wheel = download_wheel(need.dist, wanted_version(need.dist, pins), args.out)
        if (sum(p.stat().st_size for p in files) + wheel.stat().st_size) > limit:
            wheel.unlink()
            skipped.append(need.dist)
            continue
        files.append(wheel)
        print(f"  {wheel.name:60s} {wheel.stat().st_size / MB:6.2f} MB  ({need.why})")
    if not args.no_debs:
        for deb in download_debs(EGL_DEBS, args.out / "debs"):
            if size_mb(files) + deb.stat().st_size / MB > args.limit_mb:
                deb.unlink()
                skipped.append(deb.name)
                continue
            files.append(deb)
            print(f"  debs/{deb.name:55s} {deb.stat().st_size / MB:6.2f} MB  (EGL loader)")
    stray = sorted(set(args.out.glob("*.whl")) - set(files))
    if stray:
        print(f"fetch_gpu_wheels: also in {args.out}, not fetched now (remove them): {', '.join(p.name for p in stray)}")
    print(f"fetch_gpu_wheels: {len(files)} files, {size_mb(files):.1f} MB in {args.out} (limit {args.limit_mb:g} MB)"
          + (f"; skipped to stay under it: {', '.join(skipped)}" if skipped else ""))
    return 1 if skipped else 0


if __name__ == "__main__":
    sys.exit(main())
