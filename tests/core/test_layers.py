"""The layers, read from the source with `ast`: the core imports no part, the detector no converter,
bpy lives in one file, and the installed package is the only way in (issue 28).

The core is every module of the package outside a part (omnigen/*.py, omnigen/stats/ and
omnigen/formats/); the parts are the folders scenes/, rigs/, converters/ and detector/, installed
as omnigen.scenes, omnigen.rigs, omnigen.converters and omnigen.detector (pyproject's
package-dir). omnigen/cli.py is the command registry: it names the parts' command modules as
strings and is the one core module allowed to.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE_DIRS = {"omnigen": "omnigen", "scenes": "omnigen.scenes", "rigs": "omnigen.rigs",
                "converters": "omnigen.converters", "detector": "omnigen.detector"}
PARTS = ("omnigen.scenes", "omnigen.rigs", "omnigen.converters", "omnigen.detector")
BARE_PARTS = ("scenes", "rigs", "converters", "detector")  # the pre-03da7bb names, no longer importable
REGISTRY = "omnigen.cli"
PART_NAME = re.compile(r"omnigen\.(scenes|rigs|converters|detector)(\.\w+)*")


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    parts = [PACKAGE_DIRS[rel.parts[0]], *rel.parts[1:-1]]
    if rel.stem != "__init__":
        parts.append(rel.stem)
    return ".".join(parts)


def _modules() -> dict[str, tuple[Path, str]]:
    """Every module of the installed package: name -> (file, source)."""
    found = {}
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            found[_module_name(path)] = (path, path.read_text(encoding="utf-8"))
    return found


def imports(source: str, module: str, is_package: bool = False) -> set[str]:
    """Absolute names a module's source imports anywhere (top level or inside functions).

    `from a import b` counts as a and a.b (b may be a submodule); relative imports are resolved
    against the module's own package; importlib.import_module("literal") counts too, since a
    string import is still an import.
    """
    package = module if is_package else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            names.add(base)
            names.update(f"{base}.{a.name}" for a in node.names if a.name != "*")
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and getattr(node.func, "attr", getattr(node.func, "id", None)) in ("import_module", "__import__")
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names.add(node.args[0].value)
    return names


def _within(name: str, packages: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def part_imports(source: str, module: str, is_package: bool = False) -> set[str]:
    return {n for n in imports(source, module, is_package) if _within(n, PARTS)}


def part_names_in_strings(source: str) -> set[str]:
    """String constants that are a part's module name, as a registry writes them ("omnigen.rigs.render_command")."""
    return {node.value for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and PART_NAME.fullmatch(node.value)}


def _is_core(module: str) -> bool:
    return not _within(module, PARTS)


# ---------------------------------------------------------------------------------------------
# the checker checks: synthetic sources it must flag and must pass
# ---------------------------------------------------------------------------------------------


def test_the_checker_sees_every_kind_of_import():
    src = ("import omnigen.scenes.generate\n"
           "from omnigen.rigs import render\n"
           "def f():\n"
           "    from omnigen import detector\n"
           "    import importlib\n"
           "    return importlib.import_module('omnigen.converters.kitti')\n")
    assert part_imports(src, "omnigen.x") == {"omnigen.scenes.generate", "omnigen.rigs", "omnigen.rigs.render",
                                              "omnigen.detector", "omnigen.converters.kitti"}
    assert part_imports("from omnigen.dataset import Dataset\nimport numpy\n", "omnigen.x") == set()
    # relative imports resolve against the module's package: inside the detector's bev stage, `...converters` is a part
    assert part_imports("from ...converters.kitti_export import export_kitti\n", "omnigen.detector.bev.lift") \
        == {"omnigen.converters.kitti_export", "omnigen.converters.kitti_export.export_kitti"}
    assert imports("from . import common\n", "omnigen.converters", is_package=True) \
        == {"omnigen.converters", "omnigen.converters.common"}
    assert part_names_in_strings('"""Mentions omnigen.scenes in prose."""\nX = {"a": "omnigen.rigs.render_command"}\n') \
        == {"omnigen.rigs.render_command"}


def test_module_names_follow_the_package_dirs():
    assert _module_name(ROOT / "detector" / "bev" / "lift.py") == "omnigen.detector.bev.lift"
    assert _module_name(ROOT / "scenes" / "assets" / "__init__.py") == "omnigen.scenes.assets"
    assert _module_name(ROOT / "omnigen" / "stats" / "report.py") == "omnigen.stats.report"
    assert _is_core("omnigen.stats.report") and _is_core("omnigen.cli") and not _is_core("omnigen.rigs.render")


# ---------------------------------------------------------------------------------------------
# the repository's layers
# ---------------------------------------------------------------------------------------------


MODULES = _modules()


def test_the_scan_covers_every_folder():
    for folder, package in PACKAGE_DIRS.items():
        assert any(_within(m, (package,)) for m in MODULES), folder
    assert {"omnigen.cli", "omnigen.stats.report", "omnigen.scenes.blender_backend", "omnigen.detector.bev.lift"} <= set(MODULES)


def test_the_core_imports_no_part():
    """Only the command registry (omnigen/cli.py) reaches the parts, and only by naming them as strings."""
    found = {}
    for module, (path, source) in MODULES.items():
        if not _is_core(module):
            continue
        is_package = path.name == "__init__.py"
        bad = sorted(part_imports(source, module, is_package))
        if module != REGISTRY:
            bad += sorted(part_names_in_strings(source))
        if bad:
            found[str(path.relative_to(ROOT))] = bad
    assert not found, f"core modules that import or name a part: {found}"
    # cli.py imports none either: the registry holds strings, imported when the parser is built
    path, source = MODULES[REGISTRY]
    assert part_imports(source, REGISTRY) == set()
    assert part_names_in_strings(source), "the registry names the parts' command modules"


def test_the_detector_imports_no_converter():
    found = {str(path.relative_to(ROOT)): sorted(n for n in imports(source, module, path.name == "__init__.py")
                                                 if _within(n, ("omnigen.converters",)))
             for module, (path, source) in MODULES.items() if _within(module, ("omnigen.detector",))}
    found = {k: v for k, v in found.items() if v}
    assert not found, f"detector modules that import a converter: {found}"


# the parts each part may import besides itself and the core (docs/architecture.md draws them)
PART_BENEATH = {
    "omnigen.scenes": set(),
    "omnigen.rigs": {"omnigen.scenes"},  # a rig draws its camera in a generated city and renders it
    "omnigen.converters": set(),
    "omnigen.detector": set(),
}


def test_parts_import_only_the_parts_beneath_them():
    found = {}
    for module, (path, source) in MODULES.items():
        part = next((p for p in PARTS if _within(module, (p,))), None)
        if part is None:
            continue
        allowed = (part,) + tuple(PART_BENEATH[part])
        bad = sorted(n for n in part_imports(source, module, path.name == "__init__.py") if not _within(n, allowed))
        if bad:
            found[str(path.relative_to(ROOT))] = bad
    assert not found, f"part modules that import a part above or beside them: {found}"
    assert set(PART_BENEATH) == set(PARTS)


def test_bpy_is_imported_by_the_blender_backend_only():
    users = sorted(module for module, (path, source) in MODULES.items()
                   if any(_within(n, ("bpy",)) for n in imports(source, module, path.name == "__init__.py")))
    assert users == ["omnigen.scenes.blender_backend"]


def test_nothing_imports_the_bare_part_names():
    found = {module: sorted(n for n in imports(source, module, path.name == "__init__.py") if _within(n, BARE_PARTS))
             for module, (path, source) in MODULES.items()}
    assert not {k: v for k, v in found.items() if v}


def test_only_command_modules_import_the_registry():
    """The CLI sits on top: the parts and the core never import it; verbs with subcommands of their own may."""
    users = {module for module, (path, source) in MODULES.items()
             if REGISTRY in imports(source, module, path.name == "__init__.py")}
    assert users - {"omnigen.__main__"}, "export and convert plug their formats in through the registry"
    assert all(m.endswith("_command") for m in users - {"omnigen.__main__"}), sorted(users)


def test_the_installed_package_is_the_only_way_in(tmp_path):
    """From outside the checkout the parts import as omnigen.*, and the bare folder names do not exist."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    ok = subprocess.run([sys.executable, "-c", "import omnigen.scenes, omnigen.rigs, omnigen.converters, omnigen.detector"],
                        cwd=tmp_path, env=env, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    for bare in ("scenes", "detector"):
        code = (f"try:\n    import {bare}\nexcept ModuleNotFoundError as e:\n    print('missing', e.name)\n"
                f"else:\n    print('found', {bare}.__file__)")
        out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert out.stdout.strip() == f"missing {bare}", out.stdout + out.stderr
