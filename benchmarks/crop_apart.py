"""How to train the crop stage apart: omnigen train-crop's recipe varied, each scored on the same crops.

    .venv/bin/python benchmarks/crop_apart.py runs/validate/uov runs/validate/runs/n-p2/last.pt \
        [--steps 2000] [--variant NAME:key=value,key=value ...] [--threads 0]

Why: `omnigen train-crop` (detector/crop_train.py) trains the crop stage alone, on clean crops, with
the joint training's three terms (corners, heading, classes) and class-balanced draws. Whether each
of those choices helps the corners is measured here, not assumed: every variant is a
CropTrainConfig (steps, batch, lr, copies, balance, heading_gain, class_gain, seed) and a net
(`split`: the classes from a net of their own, crop_stage.SplitCropNet, or from the corners') trained from the
same seed on the same crops (cut once: the train split's objects about moved boxes, as the
command cuts them) and scored as the command scores (crop_train.score_stage on the test split's
crops about moved boxes), beside the detector's own stage (trained with it).

Default variants: `default` (the command's: uniform draws, a tenth of the joint training's heading
gain, the classes from a net of their own), `one-net` (the classes from the corners' net),
`joint-recipe` (one net, with the joint training's class-balanced draws and gains) and `corners`
(one net, no heading and no class term: the layout alone, as benchmarks/crop_layout.py trains).
A variant without the heading term faces its corners as the untrained heading says, so compare it
on `placed rel` (the corners as the net placed them) or `layout rel` (the 180-degree turn forgiven).

Last line: `crop_apart: best layout rel NAME X (the detector's stage Y); default X0`.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

JOINT = "the detector's stage"
DEFAULT_VARIANTS = ("default:", "one-net:split=0", "joint-recipe:split=0,balance=0.5,heading_gain=1",
                    "corners:split=0,heading_gain=0,class_gain=0")


def parse_variant(text: str, steps: int, copies: int = 4):
    """'NAME:key=value,...' -> (NAME, CropTrainConfig, split, position): the command's defaults,
    `steps`, `copies` (the crops are cut once for every variant) and the keys given (CropTrainConfig's
    fields but copies; `split`: 1, the default, names the classes with a net of their own
    (crop_stage.SplitCropNet), 0 with the corners' net; `position`: 1 tells the corners' net where
    each crop was cut, crop_stage.crop_position. Unlike train-crop's, its default is 0, so that the
    variants written down before it existed print what they printed; `offset_gain` likewise
    defaults to 0 here, 0.3 in train-crop); a clear exit naming a bad key or value."""
    from omnigen.detector.crop_train_config import CropTrainConfig

    name, _, spec = text.partition(":")
    if not name:
        raise SystemExit(f"crop_apart: --variant {text!r}: NAME:key=value,... (a name first)")
    types = {f.name: f.type for f in fields(CropTrainConfig) if f.name != "copies"}
    types["split"] = "int"
    types["position"] = "int"
    # offset_gain 0 unless given, unlike train-crop's 0.3: the variants written down before it print what they printed
    values: dict[str, object] = {"steps": steps, "copies": copies, "offset_gain": 0.0}
    for item in filter(None, spec.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in types:
            raise SystemExit(f"crop_apart: --variant {text!r}: {key!r} is not one of {', '.join(types)}")
        try:
            values[key] = value if types[key] in (str, "str") else int(value) if types[key] in (int, "int") \
                else float(value)
        except ValueError:
            raise SystemExit(f"crop_apart: --variant {text!r}: {key}={value!r} is not a number") from None
    split = bool(values.pop("split", 1))
    position = bool(values.pop("position", 0))
    try:
        return name, CropTrainConfig(**values), split, position
    except ValueError as exc:
        raise SystemExit(f"crop_apart: --variant {text!r}: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset with train and test splits")
    ap.add_argument("weights", type=Path, help="a detector checkpoint: its input size, classes, crop side and stage")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--variant", action="append", default=None, metavar="NAME:key=value,...",
                    help="a CropTrainConfig to train (repeatable); default: " + " ".join(DEFAULT_VARIANTS))
    ap.add_argument("--copies", type=int, default=4, help="crops cut per train object (the command's --copies)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    variants = [parse_variant(v, a.steps, a.copies) for v in (a.variant or DEFAULT_VARIANTS)]
    if len({v[0] for v in variants}) != len(variants):
        raise SystemExit("crop_apart: two variants share a name")

    import torch

    from omnigen.detector.checkpoint import checkpoint_taxonomy, load_checkpoint
    from omnigen.detector.crop_train import detector_stage, new_stage, score_stage, split_crops, train_stage
    from omnigen.detector.model import DetectorConfig
    from omnigen.detector.predict import trained_imgsz
    from omnigen.progress import print_table

    if a.threads:
        torch.set_num_threads(a.threads)
    state = load_checkpoint(a.weights)
    det = DetectorConfig.from_dict(state["config"])
    if not det.heading_crop:
        raise SystemExit(f"crop_apart: {a.weights}: has no crop stage to compare with (trained without --heading-crop)")
    taxonomy, imgsz, size = checkpoint_taxonomy(state), trained_imgsz(state), det.heading_crop
    nc = len(taxonomy.classes) if det.crop_classes else 0
    gen = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    sets = {split: split_crops(a.dataset, taxonomy, imgsz, split, size, a.copies if split == "train" else 1, gen)
            for split in ("train", "test")}
    print(f"crops: train {len(sets['train'])}, test {len(sets['test'])} ({time.perf_counter() - t0:.1f} s)", flush=True)
    scores = {JOINT: (score_stage(detector_stage(state), sets["test"]), "-", "-")}
    for name, cfg, split, position in variants:
        net = new_stage(size, nc, cfg.seed, split and nc > 0, position)
        t = time.perf_counter()
        history = train_stage(sets["train"], net, cfg)
        seconds = time.perf_counter() - t
        last = sum(h["crop_corners"] for h in history[-100:]) / min(len(history), 100)
        scores[name] = (score_stage(net, sets["test"]), f"{seconds:.0f}", f"{last:.3f}")
        print(f"{name}: {asdict(cfg)}, split {split and nc > 0}, position {position} trained in {seconds:.0f} s",
              flush=True)
    print_table(f"crop stage trained apart, {a.steps} steps a variant: test crops about moved boxes",
                ["stage", "objects", "corner rel", "placed rel", "layout rel", "vertical rel", "front right",
                 "placed front", "class acc", "train s", "corner L1, last 100"],
                [(n, s.objects, s.corner_rel, s.placed_rel, s.layout_rel, s.vertical_rel, s.front, s.placed_front,
                  s.class_acc, sec, l1)
                 for n, (s, sec, l1) in scores.items()])
    trained = {n: s for n, (s, _, _) in scores.items() if n != JOINT}
    best = min(trained, key=lambda n: trained[n].layout_rel)
    first = next(iter(trained))
    print(f"crop_apart: best layout rel {best} {trained[best].layout_rel:.3f} ({JOINT} "
          f"{scores[JOINT][0].layout_rel:.3f}); {first} {trained[first].layout_rel:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
