"""Write an UrbanOmniView dataset as a KITTI object tree (label_2, calib, image_2) for KITTI tools.

Records are already in their image's camera, so every calib has P2 = [K | 0] and every location is
in that camera. KITTI can only say upright boxes in a level camera; for pitched cameras the rule is
geometry.box_to_kitti's: location = centre + (0, h/2, 0) along the camera's y (so KITTI tools
get the true centre back), rotation_y = the heading of the box's forward axis projected onto the
camera's x-z plane; the tilt is lost. Details and every choice: docs/converters-kitti.md.
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

import numpy as np

from omnigen.conventions import KITTI_CLASSES
from omnigen.dataset import Dataset
from omnigen.files import LINK_MODES, atomic_write_bytes, atomic_write_text, link_file
from omnigen.geometry import box_to_kitti, kitti_alpha
from omnigen.ownership import claim_output
from omnigen.progress import print_table, progress
from omnigen.record import FrameRecord, ObjectRecord
from omnigen.splits import read_split

KITTI_NAMES: dict[str, str] = {fine: name for name, fine in KITTI_CLASSES.items() if name != "Person_sitting"}
"""Fine class -> KITTI name (car -> Car, ..., pedestrian -> Pedestrian)."""
FALLBACK_NAME = "Misc"
"""For fine classes KITTI has no name for (bus, motorcyclist, tricyclist, barrow, traffic_cone):
KITTI's own catch-all, which its evaluation ignores, rather than a name KITTI tools reject."""

MAPPING_FILE = "mapping.txt"
"""One line per exported frame: `<kitti file number> <frame_id>`."""

TR_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
"""There is no LiDAR: a virtual one at the camera centre with KITTI's axes (x forward, y left, z
up), so tools that insist on the matrix get a valid one."""
TR_IMU_TO_VELO = np.hstack([np.eye(3), np.zeros((3, 1))])

_KITTI_FRAME = re.compile(r"^kitti-(?:testing-)?(\d{6})$")
_OWN_KEYS = ("truncated", "occluded", "alpha")


def _num(v: float) -> str:
    """Shortest text that reads back as the same double: exports round-trip exactly."""
    return repr(float(v))


def kitti_file_names(frame_ids: list[str]) -> dict[str, str]:
    """Frame id -> KITTI file number.

    Converted KITTI frames keep their own number (kitti-000123 -> 000123) when that is unambiguous,
    so an exported KITTI split lines up with the original; any other dataset is numbered
    000000, 000001, ... in frame-id order.
    """
    matches = [_KITTI_FRAME.match(f) for f in frame_ids]
    if all(matches):
        numbers = [m.group(1) for m in matches if m]
        if len(set(numbers)) == len(numbers):
            return dict(zip(frame_ids, numbers))
    return {f: f"{i:06d}" for i, f in enumerate(sorted(frame_ids))}


def kitti_name(obj: ObjectRecord) -> str:
    """The object's KITTI class: its original name where it had one (keeps Person_sitting)."""
    original = obj.source_attributes.get("class")
    if isinstance(original, str) and KITTI_CLASSES.get(original) == obj.category:
        return original
    return KITTI_NAMES.get(obj.category, FALLBACK_NAME)


def _own_values(record: FrameRecord, obj: ObjectRecord) -> dict | None:
    """KITTI's own truncated / occluded / alpha where the record kept them (converted KITTI)."""
    attrs = obj.source_attributes
    if record.source == "kitti" and all(k in attrs for k in _OWN_KEYS):
        return attrs
    return None


def label_line(record: FrameRecord, obj: ObjectRecord, derived: bool = False) -> str:
    """One label_2 line. Values KITTI wrote itself are written back unless `derived`; else
    truncated = truncation, occluded = occlusion_level (3 = unknown), alpha from the location and
    rotation_y, 2D box = bbox."""
    h, w, l, x, y, z, ry = box_to_kitti(obj.box)
    own = None if derived else _own_values(record, obj)
    if own is not None:
        truncated, occluded, alpha = float(own["truncated"]), int(own["occluded"]), float(own["alpha"])
        box2d = obj.bbox_source if obj.bbox_source is not None else obj.bbox
    else:
        truncated, occluded, alpha = obj.truncation, int(obj.occlusion_level), kitti_alpha(ry, x, z)
        box2d = obj.bbox
    numbers = [alpha, *box2d, h, w, l, x, y, z, ry]
    return f"{kitti_name(obj)} {_num(truncated)} {occluded} " + " ".join(_num(v) for v in numbers)


def dont_care_line(bbox: np.ndarray) -> str:
    return "DontCare -1 -1 -10 " + " ".join(_num(v) for v in bbox) + " -1 -1 -1 -1000 -1000 -1000 -10"


def label_text(record: FrameRecord, derived: bool = False) -> str:
    """Objects in record order (instance ids ascending for converted KITTI), then ignore regions."""
    lines = [label_line(record, o, derived) for o in record.objects]
    lines += [dont_care_line(r.bbox) for r in record.ignore_regions]
    return "".join(f"{line}\n" for line in lines)


def calib_text(K: np.ndarray) -> str:
    """KITTI's seven calib lines. Every P is [K | 0]: the record's camera is the only camera."""
    P = np.hstack([np.asarray(K, dtype=np.float64), np.zeros((3, 1))])
    rows = [(f"P{i}", P) for i in range(4)]
    rows += [("R0_rect", np.eye(3)), ("Tr_velo_to_cam", TR_VELO_TO_CAM), ("Tr_imu_to_velo", TR_IMU_TO_VELO)]
    return "".join(f"{name}: " + " ".join(_num(v) for v in m.ravel()) + "\n" for name, m in rows)


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


def export_kitti(ds: Dataset, out: str | Path, split: str | None = None, link: str = "hardlink",
                 derived: bool = False) -> ExportReport:
    """Write out/{label_2,calib,image_2}/<number>.* and, last, out/mapping.txt; returns the counts.

    A re-export into the same folder starts from nothing: the numbers are given afresh each time,
    so a file left from an earlier export would label another frame. mapping.txt goes first.
    """
    start = time.perf_counter()
    out = Path(out)
    keep = None if split is None else set(read_split(ds.root, split))  # a bad --split fails before any deletion
    claim_output(out, "export kitti", _exported_by_us)
    (out / MAPPING_FILE).unlink(missing_ok=True)
    for folder in ("label_2", "calib", "image_2"):
        shutil.rmtree(out / folder, ignore_errors=True)
    frame_ids = ds.frame_ids
    indices = [i for i, f in enumerate(frame_ids) if keep is None or f in keep]
    names = kitti_file_names([frame_ids[i] for i in indices])
    report = ExportReport()
    for i in progress(indices, desc="export kitti", unit="frame"):
        record = ds[i]
        number = names[record.frame_id]
        # not fsynced one by one (that dominates on a busy disk): one flush before mapping.txt
        atomic_write_bytes(out / "label_2" / f"{number}.txt", label_text(record, derived).encode(), durable=False)
        atomic_write_bytes(out / "calib" / f"{number}.txt", calib_text(record.K).encode(), durable=False)
        suffix = Path(record.image).suffix
        report.link_modes[link_file(ds.path(record.image), out / "image_2" / f"{number}{suffix}", link)] += 1
        report.frames += 1
        report.objects += len(record.objects)
        report.dont_care += len(record.ignore_regions)
    os.sync()
    mapping = sorted((number, frame_id) for frame_id, number in names.items())
    atomic_write_text(out / MAPPING_FILE, "".join(f"{n} {f}\n" for n, f in mapping))
    report.seconds = time.perf_counter() - start
    return report


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output folder (gets label_2/, calib/, image_2/, mapping.txt)")
    p.add_argument("--split", default=None, help="only frames of this split (splits/<name>.txt)")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink",
                   help="how images are placed: hardlink (falls back to symlink, then copy), symlink or copy")
    p.add_argument("--derived", action="store_true",
                   help="write truncated, occluded, alpha and the 2D box derived from the records even where "
                        "they keep KITTI's own values")


def run(args: argparse.Namespace) -> int:
    report = export_kitti(Dataset.open(args.dataset), args.out, args.split, args.link, args.derived)
    links = ", ".join(f"{k} {v}" for k, v in sorted(report.link_modes.items())) or "-"
    print_table(f"export kitti -> {args.out}", ["frames", "objects", "DontCare", "images", "seconds"],
                [[report.frames, report.objects, report.dont_care, links, round(report.seconds, 2)]])
    return 0
