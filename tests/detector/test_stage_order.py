"""The detector's stages import one way, read from the source with `ast` (issue 47): a module
imports only its own stage and the stages below it, lazy imports inside functions included; the
verbs (detector/*_command.py) sit on top and import any. docs/architecture.md draws the order.

Why a test: a package per stage says nothing about which may lean on which; without one order a
newcomer cannot read the detector bottom-up, and each convenient import (the model borrowing
training's box maths, a checkpoint reaching for the trainer's config) makes the next one look
normal. A new stage fails here until the order names it.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DETECTOR = ROOT / "detector"
PACKAGE = "omnigen.detector"

ORDER = ("recipe", "model", "data", "prediction", "bev", "evaluation", "training")
"""The stages bottom-up. The recipe is plain data every stage reads; the model holds the network,
its boxes and detections and the checkpoints (with the run config they record); data feeds it;
prediction runs it; the BEV stage lifts corners to the ground; evaluation scores predictions (with
the BEV stage's lifting); training validates through prediction and evaluation, so it is last."""

COMMANDS = "commands"
"""The verbs, detector/*_command.py: above every stage."""

PACKAGE_INIT = "__init__"
"""omnigen.detector itself: it imports no stage (importing it must not import them all)."""


def rank(stage: str) -> int:
    """Where a stage sits: the package's __init__ under everything, the verbs over everything."""
    if stage == PACKAGE_INIT:
        return -1
    return len(ORDER) if stage == COMMANDS else ORDER.index(stage)


def stage_of_name(part: str) -> str:
    """The stage of `omnigen.detector.<part>...`: a stage's name, a verb, or the name itself
    (one the order does not know, which `unnamed` reports)."""
    return COMMANDS if part.endswith("_command") else part


def module_stage(path: Path, root: Path) -> str:
    """The stage of a file under the detector folder `root`."""
    rel = path.relative_to(root)
    if len(rel.parts) > 1:
        return rel.parts[0]
    return PACKAGE_INIT if rel.stem == "__init__" else stage_of_name(rel.stem)


def module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join((PACKAGE, *parts))


def detector_imports(source: str, module: str, is_package: bool) -> list[tuple[int, str, str]]:
    """(line, imported name, its stage) of every import of a detector stage anywhere in a source
    (top level or in a function). Relative imports are resolved against the module's package;
    `from omnigen.detector import training` imports the training stage."""
    package = module if is_package else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            names = [f"{base}.{a.name}" for a in node.names] if base == PACKAGE else [base]
        else:
            continue
        for name in names:
            if name.startswith(PACKAGE + "."):
                found.append((node.lineno, name, stage_of_name(name.split(".")[2])))
    return sorted(found)


def unnamed(root: Path) -> list[str]:
    """Subpackages and top-level modules of the detector folder that are neither a stage of ORDER
    nor a verb: a new stage must take its place in the order first."""
    found = []
    for path in sorted(root.iterdir()):
        if path.is_dir() and (path / "__init__.py").exists() and path.name not in ORDER:
            found.append(f"{path.relative_to(root.parent)}/: a stage the order does not name")
        elif path.suffix == ".py" and module_stage(path, root) not in (*ORDER, COMMANDS, PACKAGE_INIT):
            found.append(f"{path.relative_to(root.parent)}: neither a stage of the order nor a verb (*_command.py)")
    return found


def violations(root: Path) -> list[str]:
    """Every import of a stage above the importing module's own, as `file:line: what`."""
    found = []
    for path in sorted(root.rglob("*.py")):
        mine = module_stage(path, root)
        if mine not in (*ORDER, COMMANDS, PACKAGE_INIT):
            continue  # unnamed() reports it
        for line, name, theirs in detector_imports(path.read_text(encoding="utf-8"), module_name(path, root),
                                                   path.name == "__init__.py"):
            if theirs != mine and (theirs not in (*ORDER, COMMANDS) or rank(theirs) > rank(mine)):
                found.append(f"{path.relative_to(root.parent)}:{line}: {mine} imports {name}, "
                             f"of {theirs}, above it (bottom-up: {' < '.join(ORDER)} < {COMMANDS})")
    return found


# -- the checker on tiny trees ------------------------------------------------------------------------

def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "detector"
    for rel, source in {"__init__.py": "", **{f"{s}/__init__.py": "" for s in ORDER[1:]}, **files}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(source)
    return root


def test_the_checker_names_the_file_line_and_import_of_a_stage_above(tmp_path):
    root = _tree(tmp_path, {
        "model/outputs.py": "import torch\n\n\ndef f():\n    from omnigen.detector.training.boxes import box_area\n",
        "data/samples.py": "from ..prediction import nms\n",  # relative
        "bev/lift.py": "from omnigen.detector import evaluation\n",
        "recipe.py": "import omnigen.detector.model.network\n",
        "prediction/predict.py": "from omnigen.detector.predict_command import run\n",  # a verb, from a stage
    })
    found = violations(root)
    assert found == [
        "detector/bev/lift.py:1: bev imports omnigen.detector.evaluation, of evaluation, above it "
        f"(bottom-up: {' < '.join(ORDER)} < commands)",
        "detector/data/samples.py:1: data imports omnigen.detector.prediction, of prediction, above it "
        f"(bottom-up: {' < '.join(ORDER)} < commands)",
        "detector/model/outputs.py:5: model imports omnigen.detector.training.boxes, of training, above it "
        f"(bottom-up: {' < '.join(ORDER)} < commands)",
        "detector/prediction/predict.py:1: prediction imports omnigen.detector.predict_command, of commands, above "
        f"it (bottom-up: {' < '.join(ORDER)} < commands)",
        "detector/recipe.py:1: recipe imports omnigen.detector.model.network, of model, above it "
        f"(bottom-up: {' < '.join(ORDER)} < commands)",
    ]


def test_the_checker_passes_imports_from_below_and_the_verbs_importing_anything(tmp_path):
    root = _tree(tmp_path, {
        "recipe.py": "import json\nfrom omnigen.options import number\n",
        "model/crop_stage.py": "from omnigen.detector.model.boxes import box_area\n"
                               "from omnigen.detector.recipe import RECIPE\n",
        "training/train.py": "def f():\n    from omnigen.detector.evaluation.oks_eval import evaluate\n"
                             "from . import loss\nfrom omnigen.detector import prediction, bev\n",
        "bev_command.py": "from omnigen.detector.predict_command import run\n"
                          "from omnigen.detector.training import train\n",
    })
    assert violations(root) == [] and unnamed(root) == []


def test_the_checker_refuses_a_stage_the_order_does_not_name(tmp_path):
    root = _tree(tmp_path, {"tracking/__init__.py": "", "tracking/kalman.py": "from omnigen.detector import model\n",
                            "helpers.py": "", "model/network.py": "from omnigen.detector.tracking import kalman\n"})
    assert unnamed(root) == ["detector/helpers.py: neither a stage of the order nor a verb (*_command.py)",
                             "detector/tracking/: a stage the order does not name"]
    assert violations(root) == ["detector/model/network.py:1: model imports omnigen.detector.tracking, of "
                                f"tracking, above it (bottom-up: {' < '.join(ORDER)} < commands)"]


# -- the repository ------------------------------------------------------------------------------------

def test_every_stage_of_the_order_is_a_package_or_module_of_the_detector():
    for stage in ORDER:
        assert (DETECTOR / stage / "__init__.py").exists() or (DETECTOR / f"{stage}.py").exists(), stage
    assert unnamed(DETECTOR) == []


def test_the_detectors_stages_import_only_their_own_and_those_below():
    assert violations(DETECTOR) == []
    # the scan reaches the stages' lazy imports: training imports evaluation inside a function
    lazy = detector_imports((DETECTOR / "training" / "train.py").read_text(), f"{PACKAGE}.training.train", False)
    assert any(stage == "evaluation" for _, _, stage in lazy)
