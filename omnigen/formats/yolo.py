"""`omnigen export yolo`: the Ultralytics pose layout, which its trainers read unchanged.

    OUT/
      data.yaml                  path, train/val, names, kpt_shape [8, 3], flip_idx
      images/<split>/<frame_id>.<ext>   linked, not copied
      labels/<split>/<frame_id>.txt     one line per object: class cx cy w h (x y v) * 8

Coordinates are normalised by the image size. Ultralytics measures from the image's top-left
corner while our pixel centres are integers, so x_norm = (x + 0.5) / W. Corners with v = 0 (outside
the image or behind the camera) are written `0 0 0`; every other value lies in [0, 1], which is
what Ultralytics' label checker (verify_image_label) demands. Ignore regions have no YOLO form and
are left out. Ultralytics needs a `val` entry: it points at our `test` split when there is one.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from omnigen.conventions import FLIP_IDX, NUM_KEYPOINTS, V_OUTSIDE, coco_visibility
from omnigen.dataset import Dataset
from omnigen.files import atomic_write_bytes, atomic_write_text, link_file
from omnigen.formats.checks import check_object_columns
from omnigen.outputs import refuse_inputs
from omnigen.progress import progress
from omnigen.ownership import claim_output
from omnigen.splits import read_assignments
from omnigen.taxonomy import Taxonomy, recorded_taxonomy


JOB = "export yolo"
LABEL_FORMAT = "%d" + " %.6f" * 4 + " %.6f %.6f %d" * NUM_KEYPOINTS + "\n"


def label_rows(ds: Dataset, class_ids: np.ndarray) -> np.ndarray:
    """(N, 29) label values of every object at once: class, box, then x y v per corner.

    Coordinates are shifted by half a pixel (our pixel centres are integers, Ultralytics measures
    from the corner), normalised and clipped to [0, 1]; corners with v = 0 are 0 0 0. The values
    are checked finite before the clip (NonFiniteError): clipped, an overflowed box would pass
    as one reaching the image's edge.
    """
    t = ds.objects
    w = ds.table.width[t.frame].astype(np.float64)[:, None]
    h = ds.table.height[t.frame].astype(np.float64)[:, None]
    x1, y1, x2, y2 = (t.bbox[:, k:k + 1] for k in range(4))
    v = coco_visibility(t.in_image, t.behind_camera, t.occluded)
    on = v != V_OUTSIDE
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is what the check below reports
        box = np.hstack([((x1 + x2) / 2 + 0.5) / w, ((y1 + y2) / 2 + 0.5) / h, (x2 - x1) / w, (y2 - y1) / h])
        xy = np.where(on[..., None], (t.keypoints + 0.5) / np.stack([w, h], axis=-1), 0.0)
    check_object_columns(ds, {"bbox": ("YOLO box", box), "keypoints": ("YOLO keypoints", xy)},
                         keep=class_ids[t.category] >= 0)
    kp = np.zeros((len(t), NUM_KEYPOINTS, 3))
    kp[..., :2] = np.clip(xy, 0, 1)
    kp[..., 2] = v
    return np.hstack([class_ids[t.category][:, None].astype(np.float64), np.clip(box, 0, 1), kp.reshape(len(t), -1)])


def data_yaml(out: Path, names: list[str], splits: list[str]) -> str:
    """The dataset YAML. Written as flow-style YAML (valid JSON inside), readable by any YAML parser."""
    train = "train" if "train" in splits else splits[0]
    val = "test" if "test" in splits else ("val" if "val" in splits else train)
    lines = [
        f"path: {json.dumps(str(out.resolve()))}",
        f"train: images/{train}",
        f"val: images/{val}",
    ]
    lines += [f"{s}: images/{s}" for s in splits if s not in ("train", "val")]
    lines += [
        f"kpt_shape: [{NUM_KEYPOINTS}, 3]",
        f"flip_idx: {json.dumps(list(FLIP_IDX))}",
        "names:",
        *(f"  {i}: {json.dumps(n)}" for i, n in enumerate(names)),
    ]
    return "\n".join(lines) + "\n"


def _exported_by_us(folder: Path) -> bool:
    """A YOLO export from before the .omnigen-job marker: a data.yaml with our keypoint layout."""
    try:
        text = (folder / "data.yaml").read_text()
    except (OSError, UnicodeDecodeError):
        return False
    return f"kpt_shape: [{NUM_KEYPOINTS}, 3]" in text and f"flip_idx: {json.dumps(list(FLIP_IDX))}" in text


def export_yolo(ds: Dataset, out: str | Path, taxonomy: Taxonomy | None = None, link: str = "hardlink") -> dict[str, int]:
    """Write the layout; returns counts for the summary. Frames in no split go to `train`.

    A re-export into the same folder starts from nothing: a frame an earlier export put in another
    split (the splits changed) would otherwise sit in both, a test frame among the training ones.
    data.yaml goes first and comes back last, so an interrupted export is no dataset to a reader.
    Everything that can refuse the export (the folder, the values) is checked before that.
    """
    out = Path(out)
    refuse_inputs(out, [ds.root], JOB)
    claim_output(out, JOB, _exported_by_us, mark=False)
    taxonomy = taxonomy or recorded_taxonomy(ds.manifest)
    class_ids = taxonomy.fine_class_ids()
    assignment = read_assignments(ds.root)
    rows = label_rows(ds, class_ids)
    claim_output(out, JOB, _exported_by_us)
    (out / "data.yaml").unlink(missing_ok=True)
    for folder in ("images", "labels"):
        shutil.rmtree(out / folder, ignore_errors=True)
    kept = rows[:, 0] >= 0
    counts = {"images": 0, "objects": 0}
    splits: set[str] = set()
    for i, frame_id in enumerate(progress(ds.table.frame_id, desc="export yolo", unit="frame")):
        split = assignment.get(frame_id, "train")
        splits.add(split)
        image = ds.table.image[i]
        link_file(ds.path(image), out / "images" / split / f"{frame_id}{Path(image).suffix}", link)
        lo, hi = int(ds.offsets[i]), int(ds.offsets[i + 1])
        frame_rows = rows[lo:hi][kept[lo:hi]]
        text = "".join(LABEL_FORMAT % tuple(r) for r in frame_rows.tolist())
        atomic_write_bytes(out / "labels" / split / f"{frame_id}.txt", text.encode(), durable=False)
        counts["images"] += 1
        counts["objects"] += len(frame_rows)
    atomic_write_text(out / "data.yaml", data_yaml(out, taxonomy.classes, sorted(splits)))
    counts["classes"] = len(taxonomy.classes)
    return counts
