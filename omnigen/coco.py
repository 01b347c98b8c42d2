"""The COCO keypoints view of an UrbanOmniView dataset.

pycocotools and most pose tools read it unchanged: images, annotations with 24 keypoint numbers
(x, y, v per corner; v = 0 corners written as 0 0 0), categories with keypoint names and a 1-based
skeleton. omnigen adds fields COCO tools ignore: per image K, frame_id, source and view; per
annotation the 3D box, truncation, occlusion level, instance id and the source's own 2D boxes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from omnigen.conventions import CORNER_NAMES, FINE_CLASSES, SKELETON, V_OUTSIDE, coco_visibility
from omnigen.dataset import Dataset, read_split
from omnigen.files import atomic_write_json
from omnigen.taxonomy import Taxonomy, load_taxonomy


def xyxy_to_xywh(b: np.ndarray) -> list[float]:
    return [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]


def coco_categories(taxonomy: Taxonomy) -> list[dict[str, Any]]:
    return [
        {"id": i + 1, "name": name, "supercategory": "object", "keypoints": list(CORNER_NAMES),
         "skeleton": [[a + 1, b + 1] for a, b in SKELETON]}
        for i, name in enumerate(taxonomy.classes)
    ]


def keypoints_with_visibility(keypoints: np.ndarray, v: np.ndarray) -> list[float]:
    """24 numbers x, y, v; corners with v = 0 become 0 0 0 as COCO expects."""
    out: list[float] = []
    for (x, y), vis in zip(keypoints, v):
        out.extend((0.0, 0.0, 0) if vis == V_OUTSIDE else (float(x), float(y), int(vis)))
    return out


def to_coco(ds: Dataset, split: str | None = None, taxonomy: Taxonomy | None = None) -> dict[str, Any]:
    """Build the COCO dict. Image ids follow the dataset's frame order (1-based)."""
    taxonomy = taxonomy or load_taxonomy("fine")
    keep = None if split is None else set(read_split(ds.root, split))
    t = ds.objects
    vis = coco_visibility(t.in_image, t.behind_camera, t.occluded)
    class_ids = np.array([(taxonomy.class_id(c) if taxonomy.class_id(c) is not None else -1) for c in FINE_CLASSES])
    images, annotations = [], []
    ft = ds.table
    for i, frame_id in enumerate(ft.frame_id):
        if keep is not None and frame_id not in keep:
            continue
        extras = ft.extras[i]
        image = {"id": i + 1, "file_name": ft.image[i], "width": int(ft.width[i]), "height": int(ft.height[i]),
                 "frame_id": frame_id, "source": ft.source[i], "view": ft.view[i], "K": ft.K[i].tolist(),
                 "ignore_regions": [xyxy_to_xywh(np.asarray(r["bbox"])) for r in extras["ignore_regions"]]}
        if extras["synthetic"] is not None:
            image["depth_file"] = extras["synthetic"]["depth"]
            image["instance_file"] = extras["synthetic"]["instance"]
        images.append(image)
        for j in range(int(ds.offsets[i]), int(ds.offsets[i + 1])):
            cid = class_ids[t.category[j]]
            if cid < 0:
                continue
            bbox = xyxy_to_xywh(t.bbox[j])
            ann = {
                "id": len(annotations) + 1, "image_id": i + 1, "category_id": int(cid) + 1,
                "fine_category": FINE_CLASSES[t.category[j]],
                "bbox": bbox, "area": bbox[2] * bbox[3], "iscrowd": 0,
                "keypoints": keypoints_with_visibility(t.keypoints[j], vis[j]),
                "num_keypoints": int((vis[j] > 0).sum()), "instance_id": int(t.instance_id[j]),
                "box3d": {"center": t.center[j].tolist(), "dims": t.dims[j].tolist(), "rotation": t.rotation[j].tolist()},
                "truncation": float(t.truncation[j]), "occlusion_level": int(t.occlusion_level[j]),
            }
            if not np.isnan(t.bbox_source[j]).any():
                ann["bbox_source"] = xyxy_to_xywh(t.bbox_source[j])
            if not np.isnan(t.bbox_visible[j]).any():
                ann["bbox_visible"] = xyxy_to_xywh(t.bbox_visible[j])
            annotations.append(ann)
    return {
        "info": {"description": "UrbanOmniView (COCO keypoints view)", "taxonomy": taxonomy.name,
                 "split": split or "all", "dataset": ds.manifest.get("name", ds.root.name)},
        "images": images, "annotations": annotations, "categories": coco_categories(taxonomy),
    }


def export_coco(ds: Dataset, out: str | Path, split: str | None = None, taxonomy: Taxonomy | None = None) -> dict[str, int]:
    """Write the COCO file atomically; returns counts for the summary."""
    coco = to_coco(ds, split, taxonomy)
    atomic_write_json(out, coco)
    return {"images": len(coco["images"]), "annotations": len(coco["annotations"]), "categories": len(coco["categories"])}
