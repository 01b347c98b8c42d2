"""Predicted cuboids drawn on their image, in the colours `omnigen show` uses for annotations.

Predictions are 2D keypoints only (no 3D box, no intrinsics), so the edges are straight segments
between predicted corners: top edges orange, ground-contact edges cyan, verticals green, the 2D box
yellow with the class and score.
"""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from omnigen.conventions import SKELETON
from omnigen.draw import BOX2D_COLOR, EDGE_COLORS, font


def draw_detections(image: np.ndarray, det: dict[str, np.ndarray], classes: list[str]) -> Image.Image:
    """RGB image (H, W, 3) and detections in its pixels (omnigen.detector.prediction.predict.to_image_coords) -> PIL image."""
    out = Image.fromarray(image).convert("RGB")
    draw = ImageDraw.Draw(out)
    lw = max(1, round(max(out.size) / 400))
    label_font = font(max(10, round(max(out.size) / 70)))
    for b, s, c, k in zip(det["boxes"], det["scores"], det["classes"], det["keypoints"]):
        draw.rectangle([float(v) for v in b], outline=BOX2D_COLOR, width=1)
        for edge in (8, 9, 10, 11, 4, 5, 6, 7, 0, 1, 2, 3):  # verticals, bottom, then top on top
            i, j = SKELETON[edge]
            draw.line([tuple(map(float, k[i, :2])), tuple(map(float, k[j, :2]))], fill=EDGE_COLORS[edge], width=lw)
        draw.text((float(b[0]), float(b[1]) - 2), f"{classes[int(c)]} {float(s):.2f}", fill=BOX2D_COLOR,
                  font=label_font, stroke_width=1, stroke_fill=(0, 0, 0), anchor="ld")
    return out
