"""The BEV picture of one image, in the style of the design's Figure 4: the image with its detected
footprints on the left, the rectified bird's-eye view with the oriented footprints on the right.

Drawn with PIL and omnigen.draw's colours and fonts, so it reads like `omnigen show`: ground-contact
edges cyan with the front edge (corners 4-5) white, footprints in the BEV filled in their class
colour, 2D-only boxes (placed by the ridge map) yellow. The BEV has no camera position (nothing
calibrates it), so instead of range rings it carries a metre grid in the head's approximate metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw

from omnigen.detector.bev.homography import BevResult
from omnigen.draw import (BACKGROUND, BOTTOM_COLOR, BOX2D_COLOR, CLASS_COLORS, PLACEHOLDER, TITLE_HEIGHT, bev_side,
                          check_canvas, display_scale, font)
from omnigen.images import MAX_IMAGE_PIXELS

FRONT_COLOR = (255, 255, 255)
GRID_COLOR = (60, 60, 70)
FALLBACK_COLOR = (200, 200, 200)


@dataclass
class BevScene:
    """What one image's picture shows: ground corners (N, 4, 2) in pixels with their class names,
    the head's result, and 2D-only boxes (M, 4) COCO xywh with their placed BEV centres (M, 2)."""

    ground_xy: np.ndarray
    classes: list[str]
    result: BevResult | None
    boxes_2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    placed: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    title: str = ""


def _color(name: str) -> tuple[int, int, int]:
    return CLASS_COLORS.get(name, FALLBACK_COLOR)


def image_scale(width: int, height: int) -> int:
    """The image panel's whole-number upscale: display_scale's, lowered so that the panel holds at
    most MAX_IMAGE_PIXELS (a narrow image, 20 x 5000, would otherwise be blown up 8 times)."""
    s = display_scale(width, height, target=720)
    while s > 1 and width * height * s * s > MAX_IMAGE_PIXELS:
        s -= 1
    return s


def draw_image_panel(scene: BevScene, image: Image.Image | None, width: int, height: int) -> Image.Image:
    """The image (or a grey placeholder) with each footprint's four ground edges and the 2D-only boxes."""
    s = image_scale(width, height)
    if image is None:
        image = Image.new("RGB", (width, height), PLACEHOLDER)
    image = image.convert("RGB")
    if s != 1 or image.size != (width, height):
        image = image.resize((width * s, height * s), Image.BILINEAR)
    draw = ImageDraw.Draw(image)
    to = lambda p: (np.asarray(p, dtype=np.float64) + 0.5) * s - 0.5  # noqa: E731 - pixel centres stay put
    lw = max(2, s)
    for quad, name in zip(scene.ground_xy, scene.classes):
        q = to(quad)
        for k in range(4):
            a, b = q[k], q[(k + 1) % 4]
            draw.line([tuple(a), tuple(b)], fill=FRONT_COLOR if k == 0 else BOTTOM_COLOR, width=lw)
        draw.ellipse([*(q.mean(0) - 3), *(q.mean(0) + 3)], fill=_color(name))
    for box in scene.boxes_2d:
        (x1, y1), (x2, y2) = to([box[:2], box[:2] + box[2:]])
        draw.rectangle([x1, y1, x2, y2], outline=BOX2D_COLOR, width=max(1, lw - 1))
    return image


def _nice_step(span: float) -> float:
    raw = max(span, 1e-9) / 6
    p = 10 ** math.floor(math.log10(raw))
    return next(m * p for m in (1, 2, 2.5, 5, 10) if m * p >= raw)


def draw_bev_panel(scene: BevScene, size: int) -> Image.Image:
    """The rectified ground: a metre grid, oriented footprints (front edge white, an arrow along the
    heading), 2D-only boxes as yellow rings at their ridge-placed centres; forward points up."""
    img = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(img, "RGBA")
    small = font(11)
    res = scene.result
    if res is None:
        draw.text((8, size // 2), "no footprints: no homography", fill=(220, 220, 220), font=small)
        return img
    pts = np.concatenate([res.footprints.reshape(-1, 2), scene.placed.reshape(-1, 2)])
    lo, hi = pts.min(0), pts.max(0)
    span = float(max(hi - lo)) * 1.15 + 1e-9
    centre = (lo + hi) / 2
    ppm = size / span
    to = lambda p: np.stack([size / 2 + (np.asarray(p)[..., 0] - centre[0]) * ppm,  # noqa: E731
                             size / 2 - (np.asarray(p)[..., 1] - centre[1]) * ppm], axis=-1)
    step = _nice_step(span)
    for k in range(int(math.floor((centre[0] - span / 2) / step)), int(math.ceil((centre[0] + span / 2) / step)) + 1):
        x = to(np.array([k * step, 0.0]))[0]
        draw.line([(x, 0), (x, size)], fill=GRID_COLOR + (255,))
    for k in range(int(math.floor((centre[1] - span / 2) / step)), int(math.ceil((centre[1] + span / 2) / step)) + 1):
        y = to(np.array([0.0, k * step]))[1]
        draw.line([(0, y), (size, y)], fill=GRID_COLOR + (255,))
    for quad, name, heading in zip(res.footprints, scene.classes, res.headings):
        poly = to(quad)
        color = _color(name)
        draw.polygon([tuple(p) for p in poly], fill=color + (150,), outline=color + (255,))
        draw.line([tuple(poly[0]), tuple(poly[1])], fill=FRONT_COLOR + (255,), width=2)
        c = poly.mean(0)
        tip = c + 0.6 * (0.5 * (poly[0] + poly[1]) - c)
        draw.line([tuple(c), tuple(tip)], fill=FRONT_COLOR + (200,), width=1)
    for p in to(scene.placed.reshape(-1, 2)):
        draw.ellipse([p[0] - 5, p[1] - 5, p[0] + 5, p[1] + 5], outline=BOX2D_COLOR + (255,), width=2)
    parts = ["BEV (no calibration),", f"grid {step:g} m", "(class-prior scale)"]
    if res.degenerate:
        parts[-1] += ","
        parts += ["one heading:", "aspect from prior"]
    lines = wrap_words(draw, parts, small, size - 8)
    tall = 3 + 14 * len(lines)
    draw.rectangle([0, 0, max(int(draw.textlength(line, font=small)) for line in lines) + 8, tall],
                   fill=BACKGROUND + (255,))
    for k, line in enumerate(lines):
        draw.text((4, 3 + 14 * k), line, fill=(220, 220, 220), font=small)
    return img


def wrap_words(draw: ImageDraw.ImageDraw, words: list[str], font_, width: float) -> list[str]:
    """Words joined into lines no wider than `width` (a word wider than that stands alone): the
    caption of a small BEV panel was cut mid-word ("aspec")."""
    lines: list[str] = []
    for word in words:
        if lines and draw.textlength(f"{lines[-1]} {word}", font=font_) <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines


def render_bev_figure(scene: BevScene, image: Image.Image | None, width: int, height: int,
                      what: str = "the BEV picture") -> Image.Image:
    """Image panel and BEV panel side by side under a title strip; a ValueError, before anything is
    drawn, when that would be more than omnigen.draw.MAX_CANVAS_PIXELS (an image of an extreme
    aspect ratio: its panel is as tall as the image)."""
    s = image_scale(width, height)
    side = bev_side(height * s)
    check_canvas(width * s + side, TITLE_HEIGHT + max(height * s, side), what, "too large to draw beside its BEV")
    left = draw_image_panel(scene, image, width, height)
    right = draw_bev_panel(scene, side)
    out = Image.new("RGB", (left.width + right.width, TITLE_HEIGHT + max(left.height, right.height)), BACKGROUND)
    out.paste(left, (0, TITLE_HEIGHT))
    out.paste(right, (left.width, TITLE_HEIGHT))
    d = ImageDraw.Draw(out)
    d.text((4, 4), scene.title, fill=(235, 235, 235), font=font(12))
    return out
