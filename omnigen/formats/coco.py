"""The COCO keypoints view of an UrbanOmniView dataset.

pycocotools and most pose tools read it unchanged: images, annotations with 24 keypoint numbers
(x, y, v per corner; v = 0 corners written as 0 0 0), categories with keypoint names and a 1-based
skeleton. omnigen adds fields COCO tools ignore: per image K, frame_id, source and view; per
annotation the 3D box, truncation, occlusion level, instance id and the source's own 2D boxes.
Where a frame has them, its image also carries sequence, timestamp, pair and camera_to_world, and
its annotations track_id and velocity; a dataset without them exports as it did before schema 2.

The file's first key is `"omnigen": "export coco"`: a rerun recognises its own file by its first
bytes and replaces it; any other file at --out is refused (omnigen.outputs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import orjson

from omnigen.conventions import CORNER_NAMES, FINE_CLASSES, SKELETON, V_OUTSIDE, coco_visibility
from omnigen.dataset import Dataset
from omnigen.splits import read_split
from omnigen.files import atomic_write_bytes
from omnigen.formats.checks import check_frame_values, check_object_columns
from omnigen.outputs import MARK_KEY, check_output_file, json_made_by, read_prefix
from omnigen.taxonomy import Taxonomy, recorded_taxonomy

JOB = "export coco"
DESCRIPTION = "UrbanOmniView (COCO keypoints view)"


def xyxy_to_xywh(b: np.ndarray) -> list[float]:
    return [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]


def coco_categories(taxonomy: Taxonomy) -> list[dict[str, Any]]:
    return [
        {"id": i + 1, "name": name, "supercategory": "object", "keypoints": list(CORNER_NAMES),
         "skeleton": [[a + 1, b + 1] for a, b in SKELETON]}
        for i, name in enumerate(taxonomy.classes)
    ]


def keypoints_with_visibility(keypoints: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 24) x, y, v rows; corners with v = 0 become 0 0 0 as COCO expects."""
    out = np.zeros((*v.shape, 3))
    on = v != V_OUTSIDE
    out[..., :2] = np.where(on[..., None], keypoints, 0.0)
    out[..., 2] = v
    return out.reshape(*v.shape[:-1], 3 * v.shape[-1])


def _xywh(boxes: np.ndarray) -> np.ndarray:
    return np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)


def to_coco(ds: Dataset, split: str | None = None, taxonomy: Taxonomy | None = None) -> dict[str, Any]:
    """Build the COCO dict. Image ids follow the dataset's frame order (1-based).

    Per-object values are prepared for all objects at once (numpy, then one tolist per column),
    so that 300,000 annotations cost seconds, not minutes.
    """
    taxonomy = taxonomy or recorded_taxonomy(ds.manifest)
    keep = None if split is None else set(read_split(ds.root, split))
    t = ds.objects
    vis = coco_visibility(t.in_image, t.behind_camera, t.occluded)
    class_ids = taxonomy.fine_class_ids()
    cid = class_ids[t.category] if len(t) else np.zeros(0, int)
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is what check_object_columns reports
        xywh = _xywh(t.bbox)
        area = (np.diff(t.bbox[:, [0, 2]], axis=1) * np.diff(t.bbox[:, [1, 3]], axis=1)).ravel()
        src_xywh, vis_xywh = _xywh(t.bbox_source), _xywh(t.bbox_visible)
    kps = keypoints_with_visibility(t.keypoints, vis)
    has_src = ~np.isnan(t.bbox_source).any(axis=1)
    has_vis = ~np.isnan(t.bbox_visible).any(axis=1)
    check_object_columns(ds, {
        "bbox": ("COCO bbox and area", np.hstack([xywh, area[:, None]])), "keypoints": ("COCO keypoints", kps),
        "box3d.center": ("box3d center", t.center), "box3d.dims": ("box3d dims", t.dims),
        "box3d.rotation": ("box3d rotation", t.rotation), "truncation": ("truncation", t.truncation),
        "bbox_source": ("COCO bbox_source", np.where(has_src[:, None], src_xywh, 0.0)),
        "bbox_visible": ("COCO bbox_visible", np.where(has_vis[:, None], vis_xywh, 0.0)),
    }, keep=(cid >= 0) & _kept_frames(ds, keep)[t.frame])
    bbox, area, kps = xywh.tolist(), area.tolist(), kps.tolist()
    num_kp = (vis > 0).sum(axis=1).tolist()
    bbox_src, bbox_vis = src_xywh.tolist(), vis_xywh.tolist()
    centers, dims, rotations = t.center.tolist(), t.dims.tolist(), t.rotation.tolist()
    trunc, occ_level, inst = t.truncation.tolist(), t.occlusion_level.tolist(), t.instance_id.tolist()
    fine = [FINE_CLASSES[c] for c in t.category.tolist()]
    tracks, velocities = t.track_id.tolist(), t.velocity.tolist()
    has_velocity = ~np.isnan(t.velocity).any(axis=1)
    images, annotations = [], []
    ft = ds.table
    for i, frame_id in enumerate(ft.frame_id):
        if keep is not None and frame_id not in keep:
            continue
        extras = ft.extras[i]
        with np.errstate(over="ignore", invalid="ignore"):  # checked below
            regions = [xyxy_to_xywh(np.asarray(r["bbox"], dtype=np.float64)) for r in extras["ignore_regions"]]
        check_frame_values(ds, i, "K", "COCO K", ft.K[i])
        for k, region in enumerate(regions):
            check_frame_values(ds, i, f"ignore_regions[{k}].bbox", "COCO ignore region", region)
        image = {"id": i + 1, "file_name": ft.image[i], "width": int(ft.width[i]), "height": int(ft.height[i]),
                 "frame_id": frame_id, "source": ft.source[i], "view": ft.view[i], "K": ft.K[i].tolist(),
                 "ignore_regions": regions}
        if extras["synthetic"] is not None:
            image["depth_file"] = extras["synthetic"]["depth"]
            image["instance_file"] = extras["synthetic"]["instance"]
        image.update(_sequence_fields(ft, i))
        images.append(image)
        for j in range(int(ds.offsets[i]), int(ds.offsets[i + 1])):
            if cid[j] < 0:
                continue
            kp = kps[j]
            kp[2::3] = [int(v) for v in kp[2::3]]
            ann = {
                "id": len(annotations) + 1, "image_id": i + 1, "category_id": int(cid[j]) + 1,
                "fine_category": fine[j], "bbox": bbox[j], "area": area[j], "iscrowd": 0,
                "keypoints": kp, "num_keypoints": num_kp[j], "instance_id": inst[j],
                "box3d": {"center": centers[j], "dims": dims[j], "rotation": rotations[j]},
                "truncation": trunc[j], "occlusion_level": occ_level[j],
            }
            if has_src[j]:
                ann["bbox_source"] = bbox_src[j]
            if has_vis[j]:
                ann["bbox_visible"] = bbox_vis[j]
            if tracks[j] >= 1:
                ann["track_id"] = tracks[j]
            if has_velocity[j]:
                ann["velocity"] = velocities[j]
            annotations.append(ann)
    return {
        "info": {"description": DESCRIPTION, "taxonomy": taxonomy.name,
                 "split": split or "all", "dataset": ds.manifest.get("name", ds.root.name)},
        "images": images, "annotations": annotations, "categories": coco_categories(taxonomy),
    }


def _sequence_fields(ft, i: int) -> dict[str, Any]:
    """The frame's schema-2 fields that are set (absent ones are left out, not written null, so
    that older datasets export byte for byte as before)."""
    out: dict[str, Any] = {}
    if ft.sequence[i] is not None:
        out["sequence"] = ft.sequence[i]
    if not np.isnan(ft.timestamp[i]):
        out["timestamp"] = float(ft.timestamp[i])
    if ft.pair[i] is not None:
        out["pair"] = ft.pair[i]
    if not np.isnan(ft.camera_to_world[i]).any():
        out["camera_to_world"] = ft.camera_to_world[i].tolist()
    return out


def _kept_frames(ds: Dataset, keep: set[str] | None) -> np.ndarray:
    """(F,) which frames the export writes."""
    return np.array([keep is None or f in keep for f in ds.table.frame_id], dtype=bool)


_EARLIER_EXPORT = b'{"info":{"description":"%s"' % DESCRIPTION.encode()


def made_by_export_coco(path: Path) -> bool:
    """A file this job wrote: marked as its first key, or an export from before the mark (its
    first bytes are the info block only to_coco writes first)."""
    return json_made_by(JOB)(path) or read_prefix(path, len(_EARLIER_EXPORT)) == _EARLIER_EXPORT


def export_coco(ds: Dataset, out: str | Path, split: str | None = None, taxonomy: Taxonomy | None = None) -> dict[str, int]:
    """Write the COCO file atomically; returns counts for the summary.

    Refused before anything is built: an --out that is (or lies in) the dataset, and an existing
    file this job did not write."""
    out = check_output_file(out, JOB, made_by_export_coco, inputs=[ds.root])
    coco = {MARK_KEY: JOB, **to_coco(ds, split, taxonomy)}
    # orjson encodes the 300,000 annotations of a large dataset several times faster than json;
    # insertion order is deterministic, so reruns are byte-identical without sorting keys.
    atomic_write_bytes(out, orjson.dumps(coco) + b"\n")
    return {"images": len(coco["images"]), "annotations": len(coco["annotations"]), "categories": len(coco["categories"])}
