"""Write the sequences of an UrbanOmniView dataset as a KITTI tracking tree, for tracking tools.

One KITTI sequence per (sequence, view): frames of one view of one run, numbered by timestamp.
`image_02/<nnnn>/<ffffff>.<ext>`, `label_02/<nnnn>.txt` (lines `frame track_id` and then the KITTI
object fields of omnigen.formats.kitti.label_line; objects without a track and DontCare regions
get track id -1, as KITTI's own DontCare lines do), `calib/<nnnn>.txt` (P2 = [K | 0]: K must be
the same in every frame of it), `pose/<nnnn>.txt` (camera_to_world's top 3x4 rows per frame,
where every frame has one) and `mapping.txt` (`<nnnn> <sequence> <view>`). Frames without a
sequence are skipped and counted. Box conventions: converters/kitti_export.py.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnigen.converters.kitti_export import KittiTree, add_tree_arguments
from omnigen.dataset import Dataset, record_path
from omnigen.files import atomic_write_bytes, link_file
from omnigen.formats.checks import naming_frame
from omnigen.formats.kitti import calib_text, dont_care_line, kitti_number, label_line
from omnigen.progress import print_table

JOB = "export kitti-tracking"
FOLDERS = ("label_02", "calib", "image_02", "pose")
NO_TRACK = -1


@dataclass
class TrackingReport:
    sequences: int = 0
    frames: int = 0
    objects: int = 0
    skipped: int = 0  # frames without a sequence
    seconds: float = 0.0


def _never_before_the_marker(folder: Path) -> bool:
    """No export of this job predates the .omnigen-job marker: only a marked folder is one of ours."""
    return False


def kitti_sequences(ds: Dataset, indices: list[int]) -> dict[tuple[str, str], list[int]]:
    """(sequence, view) -> its frames by timestamp (no timestamp last), then frame id; sorted keys."""
    ft = ds.table
    groups: dict[tuple[str, str], list[int]] = defaultdict(list)
    for i in indices:
        if ft.sequence[i] is not None:
            groups[(ft.sequence[i], ft.view[i])].append(i)

    def when(i: int) -> tuple[bool, float, str]:
        t = ft.timestamp[i]
        return bool(np.isnan(t)), 0.0 if np.isnan(t) else float(t), ft.frame_id[i]

    return {key: sorted(groups[key], key=when) for key in sorted(groups)}


def sequence_texts(ds: Dataset, frames: list[int]) -> tuple[str, str, str | None]:
    """label_02, calib and pose text of one KITTI sequence; a K that changes within it, or a value
    that is not finite, refused naming the frame's record file."""
    K = ds.table.K[frames[0]]
    labels = []
    for n, i in enumerate(frames):
        if not np.array_equal(ds.table.K[i], K):
            raise ValueError(f"{record_path(ds.root, ds.table.frame_id[i])}: K: differs from the K of "
                             f"{ds.table.frame_id[frames[0]]}, and one KITTI tracking sequence has one calib")
        record = ds[i]
        with naming_frame(ds, i):
            labels += [f"{n} {NO_TRACK if o.track_id is None else o.track_id} "
                       f"{label_line(record, o, where=f'objects[{k}]')}" for k, o in enumerate(record.objects)]
            labels += [f"{n} {NO_TRACK} {dont_care_line(r.bbox, f'ignore_regions[{k}].bbox')}"
                       for k, r in enumerate(record.ignore_regions)]
    with naming_frame(ds, frames[0]):
        calib = calib_text(K)
    poses = ds.table.camera_to_world[frames]
    pose = None if np.isnan(poses).any() else "".join(
        " ".join(kitti_number(v) for v in p[:3].ravel()) + "\n" for p in poses)
    return "".join(f"{line}\n" for line in labels), calib, pose


def export_kitti_tracking(ds: Dataset, out: str | Path, split: str | None = None,
                          link: str = "hardlink") -> TrackingReport:
    """Write the tree (mapping.txt last); every text is made before anything is deleted, so a
    refused export leaves the folder as it was."""
    start = time.perf_counter()
    tree = KittiTree(Path(out), JOB, FOLDERS, _never_before_the_marker)
    indices = tree.frames(ds, split)
    sequences = kitti_sequences(ds, indices)
    texts = [sequence_texts(ds, frames) for frames in sequences.values()]
    tree.clear()
    report = TrackingReport(sequences=len(sequences))
    for s, (frames, (label, calib, pose)) in enumerate(zip(sequences.values(), texts)):
        atomic_write_bytes(tree.out / "label_02" / f"{s:04d}.txt", label.encode(), durable=False)
        atomic_write_bytes(tree.out / "calib" / f"{s:04d}.txt", calib.encode(), durable=False)
        if pose is not None:
            atomic_write_bytes(tree.out / "pose" / f"{s:04d}.txt", pose.encode(), durable=False)
        for n, i in enumerate(frames):
            image = ds.table.image[i]
            link_file(ds.path(image), tree.out / "image_02" / f"{s:04d}" / f"{n:06d}{Path(image).suffix}", link)
            report.objects += int(ds.offsets[i + 1] - ds.offsets[i])
        report.frames += len(frames)
    report.skipped = len(indices) - report.frames
    tree.finish("".join(f"{s:04d} {seq} {view}\n" for s, (seq, view) in enumerate(sequences)))
    report.seconds = time.perf_counter() - start
    return report


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_tree_arguments(p, "label_02/, calib/, image_02/, pose/, mapping.txt", "export kitti-tracking")


def run(args: argparse.Namespace) -> int:
    report = export_kitti_tracking(Dataset.open(args.dataset), args.out, args.split, args.link)
    print_table(f"export kitti-tracking -> {args.out}", ["sequences", "frames", "objects", "skipped", "seconds"],
                [[report.sequences, report.frames, report.objects, report.skipped, round(report.seconds, 2)]])
    if report.skipped:
        print(f"{report.skipped} frames without a sequence were skipped")
    return 0
