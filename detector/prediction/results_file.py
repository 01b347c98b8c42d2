"""Reading a COCO-results file: the one format every detector command takes its predictions in.

`omnigen eval`, `omnigen bev` and `omnigen calib-sensitivity` all read the list pycocotools'
`loadRes` reads (image_id, category_id, bbox, keypoints, score); a dict holding that list under
"annotations" or "predictions" (a COCO file, a wrapped export) is accepted too. Field checks stay
with each command, which knows what it needs; this module only gets the list, or says why not.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import orjson


def read_results(path: str | Path) -> list[dict[str, Any]]:
    """The list of detections in `path`; a missing, unreadable or non-list file is a ValueError
    naming the file."""
    path = Path(path)
    try:
        data = orjson.loads(path.read_bytes())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such predictions file") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read predictions: {exc}") from None
    except orjson.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from None
    if isinstance(data, dict):
        data = data.get("annotations", data.get("predictions"))
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list of detections (COCO results form)")
    return data
