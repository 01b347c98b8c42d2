"""Write an UrbanOmniView dataset as a KITTI object tree (label_2, calib, image_2) for KITTI tools.

Records are already in their image's camera, so every calib has P2 = [K | 0] and every location is
in that camera. KITTI can only say upright boxes in a level camera; for pitched cameras the rule is
omnigen.formats.kitti.box_to_kitti's: location = centre + (0, h/2, 0) along the camera's y (so
KITTI tools get the true centre back), rotation_y = the heading of the box's forward axis projected
onto the camera's x-z plane; the tilt is lost. The label and calib text, the class names and the file
numbers are the format's (omnigen.formats.kitti); this module writes the tree. Details and every
choice: docs/converters-kitti.md.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from omnigen.dataset import Dataset
from omnigen.files import LINK_MODES, atomic_write_bytes, atomic_write_text, link_file
from omnigen.formats.checks import naming_frame
from omnigen.outputs import refuse_inputs
from omnigen.formats.kitti import calib_text, kitti_file_names, label_text
from omnigen.ownership import claim_output
from omnigen.progress import print_table, progress
from omnigen.splits import read_split

JOB = "export kitti"
MAPPING_FILE = "mapping.txt"
"""One line per exported frame: `<kitti file number> <frame_id>`."""


@dataclass
class ExportReport:
    frames: int = 0
    objects: int = 0
    dont_care: int = 0
    link_modes: Counter = field(default_factory=Counter)
    seconds: float = 0.0


def _exported_by_us(folder: Path) -> bool:
    """A KITTI export from before the .omnigen-job marker: a mapping.txt of `<number> <frame_id>` lines."""
    try:
        first = (folder / MAPPING_FILE).read_text().split("\n", 1)[0]
    except (OSError, UnicodeDecodeError):
        return False
    return re.fullmatch(r"\d{6} \S+", first) is not None


@dataclass(frozen=True)
class KittiTree:
    """An export into a KITTI-style folder (`export kitti`, `export kitti-tracking`), and the order
    both keep so a refused export leaves the folder as it was and an interrupted one is never
    mistaken for a whole one: check the folder (`frames`), make every text, then `clear` the
    folder's own subfolders and `finish` with mapping.txt, written last."""

    out: Path
    job: str
    folders: tuple[str, ...]
    ours: Callable[[Path], bool]  # an unmarked folder that an export from before the .omnigen-job marker wrote

    def frames(self, ds: Dataset, split: str | None) -> list[int]:
        """The dataset's frames to export (those of `split`, all for None), once the folder is
        known to be one this job may write (outside the dataset, new, empty or its own); a bad
        split fails here, before anything is deleted."""
        keep = None if split is None else set(read_split(ds.root, split))
        refuse_inputs(self.out, [ds.root], self.job)
        claim_output(self.out, self.job, self.ours, mark=False)
        return [i for i, f in enumerate(ds.frame_ids) if keep is None or f in keep]

    def clear(self) -> None:
        """Mark the folder as this job's and remove mapping.txt (first: a folder without it is
        unfinished) and the subfolders an export writes; nothing else in it is touched."""
        claim_output(self.out, self.job, self.ours)
        (self.out / MAPPING_FILE).unlink(missing_ok=True)
        for folder in self.folders:
            shutil.rmtree(self.out / folder, ignore_errors=True)

    def finish(self, mapping: str) -> None:
        """Flush the files written (not fsynced one by one: that dominates on a busy disk), then
        mapping.txt, atomically: its presence says the export is whole."""
        os.sync()
        atomic_write_text(self.out / MAPPING_FILE, mapping)


def _frame_files(ds: Dataset, i: int, derived: bool) -> tuple[str, str]:
    """A frame's label and calib text, a non-finite value refused naming its record file."""
    record = ds[i]
    with naming_frame(ds, i):
        return label_text(record, derived), calib_text(record.K)


def export_kitti(ds: Dataset, out: str | Path, split: str | None = None, link: str = "hardlink",
                 derived: bool = False) -> ExportReport:
    """Write out/{label_2,calib,image_2}/<number>.* and, last, out/mapping.txt; returns the counts.

    A re-export into the same folder starts from nothing: the numbers are given afresh each time,
    so a file left from an earlier export would label another frame. mapping.txt goes first.
    Every text is made before that, so a refused export (a --out it may not clear, a value that
    is not finite) leaves the folder as it was.
    """
    start = time.perf_counter()
    tree = KittiTree(Path(out), JOB, ("label_2", "calib", "image_2"), _exported_by_us)
    indices = tree.frames(ds, split)
    frame_ids = ds.frame_ids
    names = kitti_file_names([frame_ids[i] for i in indices])
    texts = {i: _frame_files(ds, i, derived) for i in progress(indices, desc="export kitti: labels", unit="frame")}
    tree.clear()
    report = ExportReport()
    for i in progress(indices, desc="export kitti", unit="frame"):
        number = names[frame_ids[i]]
        label, calib = texts.pop(i)
        atomic_write_bytes(tree.out / "label_2" / f"{number}.txt", label.encode(), durable=False)
        atomic_write_bytes(tree.out / "calib" / f"{number}.txt", calib.encode(), durable=False)
        image = ds.table.image[i]
        report.link_modes[link_file(ds.path(image), tree.out / "image_2" / f"{number}{Path(image).suffix}", link)] += 1
        report.frames += 1
        report.objects += int(ds.offsets[i + 1] - ds.offsets[i])
        report.dont_care += len(ds.table.extras[i]["ignore_regions"])
    tree.finish("".join(f"{n} {f}\n" for n, f in sorted((number, frame_id) for frame_id, number in names.items())))
    report.seconds = time.perf_counter() - start
    return report


def add_tree_arguments(p: argparse.ArgumentParser, gets: str, job: str) -> None:
    """The options of an export into a KITTI-style tree (`export kitti`, `export kitti-tracking`):
    the dataset, the output folder (which gets `gets`), a split, how images are placed."""
    p.add_argument("dataset", type=Path)
    p.add_argument("--out", type=Path, required=True,
                   help=f"output folder (gets {gets}): new, empty or an earlier {job}; outside the dataset")
    p.add_argument("--split", default=None, help="only frames of this split (splits/<name>.txt)")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink",
                   help="how images are placed: hardlink (falls back to symlink, then copy), symlink or copy")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_tree_arguments(p, "label_2/, calib/, image_2/, mapping.txt", "export kitti")
    p.add_argument("--derived", action="store_true",
                   help="write truncated, occluded, alpha and the 2D box derived from the records even where "
                        "they keep KITTI's own values")


def run(args: argparse.Namespace) -> int:
    report = export_kitti(Dataset.open(args.dataset), args.out, args.split, args.link, args.derived)
    links = ", ".join(f"{k} {v}" for k, v in sorted(report.link_modes.items())) or "-"
    print_table(f"export kitti -> {args.out}", ["frames", "objects", "DontCare", "images", "seconds"],
                [[report.frames, report.objects, report.dont_care, links, round(report.seconds, 2)]])
    return 0
