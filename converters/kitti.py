"""Convert the KITTI 3D object benchmark (training or testing split) into UrbanOmniView.

Input, as users have it: the extracted tree (SRC/training/{image_2,label_2,calib},
SRC/testing/{image_2,calib}), one split folder (SRC/{image_2,label_2,calib}, which is what
`omnigen export kitti` writes), or the three official archives side by side
(SRC/data_object_{image_2,label_2,calib}.zip), read in place: only each frame's own members are
read, nothing is extracted. Every decision (corner flags, difficulty, ground plane, what is left
out) is explained in docs/converters-kitti.md; the code keeps to the why.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from omnigen.converters.common import (
    TEXT_FILE_MAX_BYTES,
    ConvertedFrame,
    ImageSource,
    SourceError,
    add_common_arguments,
    image_relpath,
    print_report,
    read_source_bytes,
    run_conversion,
    select_keys,
    source_image_size,
    source_path,
)
from omnigen.converters.plausible import check_angle, check_box, check_box2d, check_intrinsics, check_offset
from omnigen.conventions import BOTTOM_CORNERS, DIFFICULTIES, KITTI_CLASSES, KITTI_IGNORE
from omnigen.formats.kitti import box_from_kitti, camera_offset_from_projection
from omnigen.geometry import Box3D, Plane, fit_ground, plane_from_height_pitch
from omnigen.images import MAX_IMAGE_BYTES
from omnigen.record import FrameRecord, IgnoreRegion, ObjectRecord

SOURCE = "kitti"
VIEW = "ego"
SPLITS = ("training", "testing")

FOLDERS = ("image_2", "label_2", "calib")
SUFFIXES = {"image_2": ".png", "label_2": ".txt", "calib": ".txt"}
ARCHIVES = {"image_2": "data_object_image_2.zip", "label_2": "data_object_label_2.zip",
            "calib": "data_object_calib.zip"}
"""The official archive holding each folder (both splits in each; labels for training only)."""

LABEL_FIELDS = ("type", "truncated", "occluded", "alpha", "bbox_left", "bbox_top", "bbox_right",
                "bbox_bottom", "height", "width", "length", "x", "y", "z", "rotation_y")
"""A KITTI ground-truth line: 15 fields (result files add a 16th, score; those are not labels)."""

PRIOR_CAMERA_HEIGHT = 1.65
"""Metres: KITTI's cameras sit 1.65 m above the road (the recording platform's documentation)."""
PLANE_MIN_OBJECTS = 3
PLANE_MAX_TILT = math.radians(15.0)
PLANE_HEIGHT_RANGE = (1.0, 2.5)
BOTTOM_DEPTH_RANGE = (1.0, 80.0)
BOTTOM_HEIGHT_RANGE = (0.5, 3.5)
"""A fit is trusted only from >= 3 objects whose bottoms lie where a road can be (depth and
height below the camera, metres) and only if it comes out nearly level (normal within 15 degrees
of the camera's up) at a plausible camera height; otherwise the 1.65 m level prior is used."""

_ID = re.compile(r"^\d+$")


# ---------------------------------------------------------------------------------------------
# Parsing label and calibration files
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KittiLabel:
    """One line of a label_2 file, as KITTI wrote it (camera-0 rectified frame)."""

    line: int
    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: tuple[float, float, float, float]
    hwl: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float

    @property
    def is_ignore(self) -> bool:
        return self.type in KITTI_IGNORE

    @property
    def box_height(self) -> float:
        """Height in pixels of the label's own 2D box: what KITTI's difficulty is defined on."""
        return self.bbox[3] - self.bbox[1]


@dataclass(frozen=True)
class KittiCalib:
    """A calib file: every `NAME: numbers` line by name, with the line it came from."""

    file: str
    values: dict[str, np.ndarray]
    lines: dict[str, int]

    def projection(self, name: str = "P2") -> np.ndarray:
        """The 3x4 matrix `name`, checked to be K [I | t] with K a pinhole (KITTI's rectified P)."""
        if name not in self.values:
            raise SourceError(self.file, name, f"no {name} line (camera 2's projection matrix is needed)")
        where = f"line {self.lines[name]}"
        v = self.values[name]
        if v.size != 12:
            raise SourceError(self.file, where, f"{name} needs 12 numbers, got {v.size}")
        P = v.reshape(3, 4)
        K = P[:, :3]
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.allclose(K[2], [0.0, 0.0, 1.0])):
            raise SourceError(self.file, where, f"{name}'s left 3x3 is not a pinhole K: {K.tolist()}")
        check_intrinsics(K, self.file, where)
        check_offset(camera_offset_from_projection(P), self.file, where, f"{name}'s camera offset from camera 0")
        return P


def decode_text(data: bytes, file: str) -> str:
    """UTF-8 text; a leading byte-order mark (some Windows editors write one) is dropped."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SourceError(file, "", f"not a text file ({exc})") from None


def _numbers(tokens: list[str], field_name: Callable[[int], str], file: str, line: int) -> list[float]:
    """Tokens as finite floats; an error names the first bad token's field (field_name(index))."""
    try:
        values = [float(t) for t in tokens]
        if all(map(math.isfinite, values)):
            return values
    except ValueError:
        pass
    for i, token in enumerate(tokens):  # the slow path, only to say which field is bad
        name = field_name(i)
        try:
            value = float(token)
        except ValueError:
            raise SourceError(file, f"line {line}", f"{name}: {token!r} is not a number") from None
        if not math.isfinite(value):
            raise SourceError(file, f"line {line}", f"{name}: {token!r} is not finite")
    raise AssertionError("unreachable")


def parse_labels(text: str, file: str) -> list[KittiLabel]:
    """Every label line of a label_2 file; a bad line raises SourceError naming file and line."""
    labels = []
    for n, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) != len(LABEL_FIELDS):
            raise SourceError(file, f"line {n}", f"expected {len(LABEL_FIELDS)} fields "
                              f"({' '.join(LABEL_FIELDS)}), got {len(fields)}")
        name = fields[0]
        if name not in KITTI_CLASSES and name not in KITTI_IGNORE:
            known = ", ".join([*KITTI_CLASSES, *KITTI_IGNORE])
            raise SourceError(file, f"line {n}", f"unknown class {name!r} (KITTI's are {known})")
        v = _numbers(fields[1:], lambda i: LABEL_FIELDS[i + 1], file, n)
        label = KittiLabel(line=n, type=name, truncated=v[0], occluded=int(v[1]), alpha=v[2],
                           bbox=(v[3], v[4], v[5], v[6]), hwl=(v[7], v[8], v[9]),
                           location=(v[10], v[11], v[12]), rotation_y=v[13])
        _check_label(label, v[1], file)
        labels.append(label)
    return labels


def _check_label(label: KittiLabel, occluded: float, file: str) -> None:
    where = f"line {label.line}"
    x1, y1, x2, y2 = label.bbox
    if x2 < x1 or y2 < y1:
        raise SourceError(file, where, f"2D box has right < left or bottom < top: {list(label.bbox)}")
    check_box2d(label.bbox, file, where)
    if label.is_ignore:
        return  # DontCare lines carry -1 / -1000 placeholders everywhere but the 2D box
    if not 0.0 <= label.truncated <= 1.0:
        raise SourceError(file, where, f"truncated must lie in [0, 1], got {label.truncated}")
    if occluded != label.occluded or not 0 <= label.occluded <= 3:
        raise SourceError(file, where, f"occluded must be 0, 1, 2 or 3, got {occluded:g}")
    if min(label.hwl) <= 0:
        raise SourceError(file, where, f"dimensions (h w l) must be positive, got {list(label.hwl)}")
    check_box(label.hwl, label.location, label.rotation_y, file, where, "h w l")
    check_angle(label.alpha, file, where, "alpha")


def parse_calib(text: str, file: str) -> KittiCalib:
    """Every `NAME: numbers` line of a calib file (P0..P3, R0_rect, Tr_velo_to_cam, ...)."""
    values: dict[str, np.ndarray] = {}
    lines: dict[str, int] = {}
    for n, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip():
            continue
        name, sep, rest = raw.partition(":")
        name = name.strip()
        if not sep or not name:
            raise SourceError(file, f"line {n}", f"expected 'NAME: numbers', got {raw.strip()[:40]!r}")
        tokens = rest.split()
        values[name] = np.array(_numbers(tokens, lambda i, key=name: f"{key} value {i + 1}", file, n))
        lines[name] = n
    return KittiCalib(file, values, lines)


# ---------------------------------------------------------------------------------------------
# Where the files come from: an extracted tree or the official archives
# ---------------------------------------------------------------------------------------------


class KittiInput(Protocol):
    """One split of KITTI, wherever it lies. Errors are SourceErrors naming the file."""

    def ids(self) -> list[str]:
        """Frame numbers ('000123') found in any of the split's folders, sorted."""

    def read_text(self, folder: str, kid: str) -> tuple[str, str]:
        """(text, file name for messages) of label_2 or calib file `kid`."""

    def image(self, kid: str) -> tuple[ImageSource, tuple[int, int]]:
        """The image to place and its (width, height), read from the header only."""


def folders_for(split: str) -> tuple[str, ...]:
    return FOLDERS if split == "training" else ("image_2", "calib")


def image_size(data: bytes | Path, file: str) -> tuple[int, int]:
    """Width and height of a whole image: the header within the pixel cap, then decoded
    (omnigen.converters.common.source_image_size: the header alone is not trusted)."""
    return source_image_size(data, file)


@dataclass
class TreeInput:
    """An extracted split folder holding image_2/, calib/ and (training) label_2/."""

    root: Path
    split: str

    def __post_init__(self) -> None:
        for folder in folders_for(self.split):
            if not (self.root / folder).is_dir():
                hint = " (the testing split has no labels: --split testing)" if folder == "label_2" else ""
                raise SourceError(self.root / folder, "", f"folder missing{hint}")

    def ids(self) -> list[str]:
        found: set[str] = set()
        for folder in folders_for(self.split):
            with os.scandir(self.root / folder) as it:
                for e in it:
                    stem, suffix = os.path.splitext(e.name)
                    if suffix == SUFFIXES[folder] and _ID.match(stem):
                        found.add(stem)
        return sorted(found)

    def _inside(self, folder: str, kid: str) -> tuple[Path, Path]:
        """(the file, links resolved; its name in the tree): a link out of the tree is a skip."""
        name = self.root / folder / f"{kid}{SUFFIXES[folder]}"
        return source_path(self.root, name.relative_to(self.root), kid), name

    def read_text(self, folder: str, kid: str) -> tuple[str, str]:
        path, name = self._inside(folder, kid)
        try:
            data = read_source_bytes(path)
        except FileNotFoundError:
            raise SourceError(name, "", f"file missing (frame {kid} has other files)") from None
        return decode_text(data, str(name)), str(name)

    def image(self, kid: str) -> tuple[ImageSource, tuple[int, int]]:
        path, name = self._inside("image_2", kid)
        if not path.exists():
            raise SourceError(name, "", f"image missing (frame {kid} has other files)")
        return ImageSource(suffix=".png", path=path), image_size(path, str(name))


class ZipInput:
    """The official archives side by side, read member by member.

    Members are found by pattern (`<split>/<folder>/<digits><suffix>`, with any leading folder),
    so a re-zipped archive with a top folder also works; an archive without a single such member
    is the wrong archive and stops the run. Each process opens its own handles: a ZipFile shares
    its file offset with a forked child, and two processes seeking one offset read garbage.
    """

    def __init__(self, root: Path, split: str):
        self.root = root
        self.split = split
        self.paths = {f: root / ARCHIVES[f] for f in folders_for(split)}
        self.members: dict[str, dict[str, str]] = {}
        self._handles: dict[str, zipfile.ZipFile] = {}
        self._pid = -1
        missing = [p.name for p in self.paths.values() if not p.is_file()]
        if missing:
            raise SourceError(root, "", f"archive(s) missing: {', '.join(missing)} (the image, label and "
                              f"calib archives must lie side by side)")
        for folder in self.paths:
            self.members[folder] = self._index(folder)

    def _index(self, folder: str) -> dict[str, str]:
        pattern = re.compile(rf"^(?:.*/)?{self.split}/{folder}/(\d+){re.escape(SUFFIXES[folder])}$")
        names = self._zip(folder).namelist()
        found = {m.group(1): name for name in names if (m := pattern.match(name))}
        if not found:
            first = names[0] if names else "none: the archive is empty"
            raise SourceError(self.paths[folder], "", f"not the KITTI archive {ARCHIVES[folder]}: no "
                              f"'{self.split}/{folder}/NNNNNN{SUFFIXES[folder]}' entries (first entry: {first})")
        return found

    def _zip(self, folder: str) -> zipfile.ZipFile:
        if self._pid != os.getpid():
            self._handles, self._pid = {}, os.getpid()
        zf = self._handles.get(folder)
        if zf is None:
            path = self.paths[folder]
            try:
                zf = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError) as exc:
                raise SourceError(path, "", f"not a zip archive ({exc}); expected KITTI's {ARCHIVES[folder]}") from None
            self._handles[folder] = zf
        return zf

    def ids(self) -> list[str]:
        return sorted(set().union(*(m.keys() for m in self.members.values())))

    def _read(self, folder: str, kid: str) -> tuple[bytes, str]:
        member = self.members[folder].get(kid)
        if member is None:
            raise SourceError(f"{self.paths[folder]}:{self.split}/{folder}/{kid}{SUFFIXES[folder]}", "",
                              f"{'image' if folder == 'image_2' else 'file'} missing from the archive "
                              f"(frame {kid} has other files)")
        name = f"{self.paths[folder]}:{member}"
        cap = MAX_IMAGE_BYTES if folder == "image_2" else TEXT_FILE_MAX_BYTES
        try:
            size = self._zip(folder).getinfo(member).file_size
            if size > cap:  # the member's declared size, checked before anything is inflated
                raise SourceError(name, "", f"{size} bytes, more than the {cap} allowed")
            return self._zip(folder).read(member), name
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise SourceError(name, "", f"cannot read from the archive: {exc}") from None

    def read_text(self, folder: str, kid: str) -> tuple[str, str]:
        data, name = self._read(folder, kid)
        return decode_text(data, name), name

    def image(self, kid: str) -> tuple[ImageSource, tuple[int, int]]:
        data, name = self._read("image_2", kid)
        return ImageSource(suffix=".png", data=data), image_size(data, name)


def open_input(src: Path, split: str) -> KittiInput:
    """The tree (KITTI root or one split folder) if there is one, else the archives."""
    src = Path(src)
    if src.suffix == ".zip" and src.is_file():  # one of the archives named: the others lie beside it
        src = src.parent
    if (src / split).is_dir():
        return TreeInput(src / split, split)
    if (src / "image_2").is_dir():
        return TreeInput(src, split)
    if any((src / name).exists() for name in ARCHIVES.values()):
        return ZipInput(src, split)
    what = "does not exist" if not src.exists() else "holds no KITTI data"
    raise SourceError(src, "", f"{what}: expected {split}/{{image_2,calib{',label_2' if split == 'training' else ''}}}, "
                      f"a split folder with image_2/ and calib/, or {', '.join(ARCHIVES.values())}")


# ---------------------------------------------------------------------------------------------
# Labels into records
# ---------------------------------------------------------------------------------------------


def kitti_difficulty(box_height: float, occluded: int, truncated: float) -> str | None:
    """KITTI's official difficulty: the easiest level whose limits the object meets, else None.

    As in the devkit, an object counts for a level when its 2D-box height is at least the level's
    minimum and its occlusion and truncation are at most the level's maxima; easy objects also
    count for moderate and hard when evaluating, and consumers filter with that in mind.
    """
    for name, min_height, max_occluded, max_truncated in DIFFICULTIES:
        if box_height >= min_height and occluded <= max_occluded and truncated <= max_truncated:
            return name
    return None


def object_from_label(label: KittiLabel, instance_id: int, K: np.ndarray, camera_offset: np.ndarray,
                      width: int, height: int) -> ObjectRecord | None:
    """The record of one labelled object in camera 2, or None when no part of it is in the image.

    Per-corner `occluded` is the cuboid's self-occlusion (ObjectRecord.from_box's default): KITTI
    says nothing per corner, and its own object-level `occluded` stays in occlusion_level.
    """
    h, w, l = label.hwl
    x, y, z = label.location
    box = box_from_kitti(h, w, l, x, y, z, label.rotation_y, camera_offset)
    return ObjectRecord.from_box(
        KITTI_CLASSES[label.type], instance_id, box, K, width, height,
        occlusion_level=label.occluded,
        bbox_source=np.array(label.bbox, dtype=np.float64),
        difficulty=kitti_difficulty(label.box_height, label.occluded, label.truncated),
        source_attributes={"class": label.type, "truncated": label.truncated, "occluded": label.occluded,
                           "alpha": label.alpha},
    )


def _plausible_bottom(box: Box3D) -> bool:
    x, y, z = box.bottom_center()
    return BOTTOM_DEPTH_RANGE[0] <= z <= BOTTOM_DEPTH_RANGE[1] and BOTTOM_HEIGHT_RANGE[0] <= y <= BOTTOM_HEIGHT_RANGE[1]


CAMERA_UP = np.array([0.0, -1.0, 0.0])
"""A level camera's up (its -y): where the road's normal points, and what its tilt is measured from."""


def ground_plane(boxes: list[Box3D]) -> tuple[Plane, bool]:
    """(plane in the image's camera frame, whether it was fitted rather than the prior).

    Fitted robustly (geometry.fit_ground) through the bottom corners of objects standing where a
    road can be, kept only at a plausible camera height; the prior is a level road 1.65 m below
    the image's camera.
    """
    bottoms = np.array([b.corners()[list(BOTTOM_CORNERS)] for b in boxes if _plausible_bottom(b)]).reshape(-1, 4, 3)
    plane = fit_ground(bottoms, CAMERA_UP, PLANE_MIN_OBJECTS, PLANE_MAX_TILT)
    if plane is not None and PLANE_HEIGHT_RANGE[0] <= plane.camera_height <= PLANE_HEIGHT_RANGE[1]:
        return plane, True
    return plane_from_height_pitch(PRIOR_CAMERA_HEIGHT, 0.0), False


def build_record(frame_id: str, image: str, width: int, height: int, P2: np.ndarray,
                 labels: list[KittiLabel]) -> tuple[FrameRecord, dict[str, int]]:
    """The frame's record and its counts (objects left out, how the ground plane was found).

    Instance ids number the kept objects 1, 2, ... in label order, so that a record exported to
    KITTI and converted again keeps its ids.
    """
    K = P2[:, :3].copy()
    offset = camera_offset_from_projection(P2)
    objects: list[ObjectRecord] = []
    ignore: list[IgnoreRegion] = []
    outside = 0
    for label in labels:
        if label.is_ignore:
            ignore.append(IgnoreRegion(np.array(label.bbox, dtype=np.float64), label.type))
            continue
        obj = object_from_label(label, len(objects) + 1, K, offset, width, height)
        if obj is None:
            outside += 1
        else:
            objects.append(obj)
    plane, fitted = ground_plane([o.box for o in objects])
    record = FrameRecord(frame_id=frame_id, source=SOURCE, view=VIEW, image=image, width=width, height=height,
                         K=K, objects=objects, ignore_regions=ignore, ground_plane=plane,
                         camera_height=plane.camera_height, camera_pitch=plane.camera_pitch + 0.0)  # no -0.0
    stats = {"objects_outside_image": outside, "ground_plane_fitted": int(fitted),
             "ground_plane_prior": int(not fitted)}
    return record, stats


@dataclass
class KittiConverter:
    """Turns one frame number of one split into a ConvertedFrame (safe to call in forked workers)."""

    source: KittiInput
    split: str

    def keys(self) -> list[str]:
        return self.source.ids()

    def frame_id(self, kid: str) -> str:
        """`kitti-000123` for training, `kitti-testing-000123` for testing: the splits never collide."""
        return f"{SOURCE}-{kid}" if self.split == "training" else f"{SOURCE}-{self.split}-{kid}"

    def convert_one(self, kid: str) -> ConvertedFrame:
        image, (width, height) = self.source.image(kid)
        P2 = parse_calib(*self.source.read_text("calib", kid)).projection("P2")
        labels = parse_labels(*self.source.read_text("label_2", kid)) if self.split == "training" else []
        frame_id = self.frame_id(kid)
        record, stats = build_record(frame_id, image_relpath(frame_id, image.suffix), width, height, P2, labels)
        return ConvertedFrame(record, image, stats)


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", type=Path, help="KITTI root (training/, testing/), one split folder, "
                   "or the folder holding data_object_{image_2,label_2,calib}.zip")
    p.add_argument("--split", choices=SPLITS, default="training",
                   help="training (labelled) or testing (images and calibration only)")
    add_common_arguments(p)


def run(args: argparse.Namespace) -> int:
    source = open_input(args.src, args.split)
    converter = KittiConverter(source, args.split)
    keys = select_keys(converter.keys(), args.limit, args.src, f"{args.split} frames")
    report = run_conversion(keys, converter.convert_one, args.out, link=args.link, strict=args.strict,
                            inputs=[args.src], desc=f"kitti {args.split}",
                            manifest_extra={"conversion": {"converter": "kitti", "split": args.split}},
                            workers=args.workers, durable=args.durable)
    s = report.stats
    print(f"kitti: ground plane fitted in {s['ground_plane_fitted']} frames, 1.65 m prior in "
          f"{s['ground_plane_prior']}; objects with no part in the image (left out): {s['objects_outside_image']}")
    return print_report(f"convert kitti ({args.split}) -> {args.out}", report)  # the skips come last
