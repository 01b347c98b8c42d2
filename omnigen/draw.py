"""Drawing one frame: its cuboids, 2D boxes and ignore regions, and its bird's-eye view.

Shared by `omnigen show` and the statistics report's gallery, so what a person checks by hand is
what the report shows. PIL draws at the image's own pixel grid (upscaled by a whole factor for
small images), so a drawn corner sits exactly where its keypoint says: the viewer shows the
record's keypoints, not a re-projection, and a label error is visible rather than hidden.

Colours: top edges orange, bottom (ground-contact) edges cyan, verticals green; corner markers
take their face's colour and carry the corner index (0-3 top, 4-7 bottom, docs/conventions.md);
2D boxes are yellow, ignore regions red and hatched. `omnigen show --instant` passes an
`object_color` (track_color) that paints a tracked object's whole cuboid and footprint in its
track's colour, the same in every view of the instant. In the BEV the camera sits at the bottom
looking up, footprints are the bottom corners 4-7 on the ground plane (filled in the class's
colour, front edge white), and the grey wedge is the part of the ground the image sees.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from omnigen.conventions import BOTTOM_CORNERS, FINE_CLASSES, NEAR_PLANE, SKELETON, TOP_CORNERS
from omnigen.images import MAX_IMAGE_PIXELS, load_rgb
from omnigen.record import FrameRecord, ObjectRecord

TOP_COLOR = (255, 150, 0)
BOTTOM_COLOR = (0, 210, 255)
VERTICAL_COLOR = (60, 230, 60)
BOX2D_COLOR = (255, 235, 0)
IGNORE_COLOR = (255, 40, 60)
BACKGROUND = (24, 24, 28)
PLACEHOLDER = (90, 90, 96)
CLASS_COLORS = {  # tab20-like, one per fine class, in FINE_CLASSES order
    name: color for name, color in zip(FINE_CLASSES, [
        (31, 119, 180), (174, 199, 232), (255, 127, 14), (255, 187, 120), (44, 160, 44), (214, 39, 40),
        (148, 103, 189), (197, 176, 213), (140, 86, 75), (227, 119, 194), (255, 152, 150), (127, 127, 127)])
}
EDGE_COLORS = tuple(TOP_COLOR if i < 4 else BOTTOM_COLOR if i < 8 else VERTICAL_COLOR for i in range(len(SKELETON)))
"""Colour of each SKELETON edge: 0-3 the top face, 4-7 the bottom face, 8-11 the verticals."""
TITLE_HEIGHT = 22
PANEL_GAP = 6
"""Background pixels between the panels of an instant, so that two images never read as one."""

Color = tuple[int, int, int]
ObjectColor = Callable[[ObjectRecord], "Color | None"]
"""One colour for an object's whole cuboid (edges, corner markers, BEV footprint), or None for the
default colours by face and class."""

GOLDEN = (math.sqrt(5) - 1) / 2
"""Hue step between consecutive track ids: the golden ratio spreads any run of ids over the hue
circle, so neighbouring ids (often neighbouring objects) never get near-identical colours."""


def track_color(obj: ObjectRecord) -> Color | None:
    """The object's track colour: a function of track_id alone, so one track is one colour in every
    view and at every instant; None (default colours) for an untracked object."""
    if obj.track_id is None:
        return None
    r, g, b = colorsys.hsv_to_rgb((obj.track_id * GOLDEN) % 1.0, 0.8, 1.0)
    return int(round(r * 255)), int(round(g * 255)), int(round(b * 255))


def font(size: int) -> ImageFont.ImageFont:
    return ImageFont.load_default(size=size)


def display_scale(width: int, height: int, target: int = 900, most: int = 8) -> int:
    """Whole-number upscale that brings a small image near `target` pixels wide (1 for large ones).

    A whole factor keeps the mapping exact: pixel centre x is drawn at (x + 0.5) * s - 0.5.
    """
    return int(max(1, min(most, target // max(width, 1))))


MAX_CANVAS_PIXELS = 4 * MAX_IMAGE_PIXELS
"""Largest picture drawn (width x height, title strip and BEV included). An image at
omnigen.images.MAX_IMAGE_PIXELS with a 0.2 margin and its BEV beside it stays under it; a record
claiming 65535 x 65535 pixels, or a --scale or --margin that would blow a frame up to gigabytes,
is refused before anything is allocated."""

MAX_BEV_SIDE = 4096
"""Largest BEV panel side: the panel is as tall as the image panel, but a square of a tall image's
height would hold more pixels than the image itself."""


def load_image(path: str | Path) -> tuple[Image.Image | None, str | None]:
    """The frame's image as RGB, or None and the reason it failed (draw_frame then draws on grey)."""
    try:
        return load_rgb(path), None  # the header's size is capped before any pixel is decoded
    except Exception as exc:  # noqa: BLE001 - the viewer must draw the labels whatever the pixels do
        return None, f"{type(exc).__name__}: {exc}".splitlines()[0]


def bev_side(panel_height: int) -> int:
    """The BEV panel's side beside an image panel `panel_height` tall."""
    return min(max(panel_height, 360), MAX_BEV_SIDE)


def panel_size(width: int, height: int, scale: float, margin: float) -> tuple[int, int, int, int]:
    """(w, h, mx, my): a `width` x `height` image at `scale` and the margin on each side, in pixels."""
    w, h = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    return w, h, int(round(margin * w)), int(round(margin * h))


def check_canvas(width: int, height: int, what: str, hint: str = "use a smaller --scale or --margin") -> None:
    """Refuse a picture larger than MAX_CANVAS_PIXELS before it is allocated, naming what it is of."""
    if width * height > MAX_CANVAS_PIXELS:
        raise ValueError(f"{what}: the picture would be {width}x{height} pixels, more than the {MAX_CANVAS_PIXELS} "
                         f"allowed (omnigen.draw.MAX_CANVAS_PIXELS); {hint}")


# ---------------------------------------------------------------------------------------------
# Segments: near-plane clipping (3D) and image-rectangle clipping (2D)
# ---------------------------------------------------------------------------------------------


def edge_segment(p: np.ndarray, q: np.ndarray, kp_p: np.ndarray, kp_q: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """The drawable 2D segment of a cuboid edge with 3D ends p, q and stored keypoints kp_p, kp_q.

    Both ends in front: the stored keypoints. One behind: that end is replaced by the projection
    of the edge's crossing of the near plane. Both behind: None.
    """
    front_p, front_q = p[2] >= NEAR_PLANE, q[2] >= NEAR_PLANE
    if front_p and front_q:
        return np.array([kp_p, kp_q])
    if not front_p and not front_q:
        return None
    t = (NEAR_PLANE - p[2]) / (q[2] - p[2])
    x = p + t * (q - p)
    uvw = K @ x
    cut = uvw[:2] / uvw[2]
    return np.array([cut, kp_q]) if front_q else np.array([kp_p, cut])


def clip_segment(seg: np.ndarray, lo: tuple[float, float], hi: tuple[float, float]) -> np.ndarray | None:
    """Liang-Barsky: the part of a 2D segment inside [lo, hi], or None (keeps PIL off huge coordinates)."""
    (x0, y0), (x1, y1) = seg
    if not np.isfinite(seg).all():
        return None
    dx, dy = x1 - x0, y1 - y0
    t0, t1 = 0.0, 1.0
    for p, q in ((-dx, x0 - lo[0]), (dx, hi[0] - x0), (-dy, y0 - lo[1]), (dy, hi[1] - y0)):
        if p == 0:
            if q < 0:
                return None
            continue
        r = q / p
        if p < 0:
            t0 = max(t0, r)
        else:
            t1 = min(t1, r)
        if t0 > t1:
            return None
    return np.array([[x0 + t0 * dx, y0 + t0 * dy], [x0 + t1 * dx, y0 + t1 * dy]])


# ---------------------------------------------------------------------------------------------
# The image panel
# ---------------------------------------------------------------------------------------------


@dataclass
class Panel:
    """A drawn panel and how record pixel coordinates map onto it."""

    image: Image.Image
    scale: float
    offset: tuple[int, int] = (0, 0)  # where the image's top-left corner sits in the panel (the margin)

    def to_display(self, xy: np.ndarray) -> np.ndarray:
        """Record pixel coordinates (pixel centres at integers) to this panel's pixel coordinates."""
        return (np.asarray(xy, dtype=np.float64) + 0.5) * self.scale - 0.5 + np.asarray(self.offset, dtype=np.float64)


def draw_frame(rec: FrameRecord, image: Image.Image | None = None, scale: float = 1.0,
               corner_labels: bool = True, margin: float = 0.0, object_color: ObjectColor | None = None) -> Panel:
    """The image with every object's cuboid, corner indices and 2D box, and the ignore regions.

    `margin` (a fraction of the image size on each side) shows what lies just outside the image:
    the contract keeps the raw projection of corners outside the image, and a truncated object's
    cuboid is easier to judge whole. Corners outside the image are drawn as hollow markers.
    `object_color` (see ObjectColor) overrides the colours by face per object.
    """
    w, h, mx, my = panel_size(rec.width, rec.height, scale, margin)
    if image is None:  # made at the panel's size: a record may claim far more pixels than it has
        image = Image.new("RGB", (w, h), PLACEHOLDER)
    image = image.convert("RGB")
    if image.size != (w, h):  # an image not of the record's size is stretched onto the record's grid
        whole = image.size == (rec.width, rec.height) and scale >= 1
        image = image.resize((w, h), Image.NEAREST if whole else Image.BILINEAR)
    if mx or my:
        canvas = Image.new("RGB", (w + 2 * mx, h + 2 * my), BACKGROUND)
        canvas.paste(image, (mx, my))
        ImageDraw.Draw(canvas).rectangle([mx - 1, my - 1, mx + w, my + h], outline=(200, 200, 200))
        image = canvas
    W, H = image.size
    panel = Panel(image, scale, (mx, my))
    lw = max(2, int(round(scale / 3)))

    overlay = Image.new("RGBA", (W, H), (0, 0, 0, 0))
    od = ImageDraw.Draw(overlay)
    for region in rec.ignore_regions:  # translucent fill, hatching, outline
        (x1, y1), (x2, y2) = panel.to_display(np.reshape(region.bbox, (2, 2)))
        od.rectangle([x1, y1, x2, y2], fill=IGNORE_COLOR + (60,), outline=IGNORE_COLOR + (255,), width=lw)
        step = max(6, int(8 * scale))
        for c in np.arange(x1 - (y2 - y1), x2, step):
            seg = clip_segment(np.array([[c, y2], [c + (y2 - y1), y1]]), (x1, y1), (x2, y2))
            if seg is not None:
                od.line([tuple(seg[0]), tuple(seg[1])], fill=IGNORE_COLOR + (150,), width=1)
    image = Image.alpha_composite(image.convert("RGBA"), overlay).convert("RGB")
    panel.image = image
    draw = ImageDraw.Draw(image)

    lo, hi = (-2.0 * W, -2.0 * H), (3.0 * W, 3.0 * H)
    label_font = font(max(10, int(7 + 2 * min(scale, 3))))
    r = max(2, int(round(1.5 * min(scale, 3))))
    order = sorted(rec.objects, key=lambda o: -float(np.linalg.norm(o.box.center)))  # far first, near on top
    for obj in order:
        (x1, y1), (x2, y2) = panel.to_display(np.reshape(obj.bbox, (2, 2)))
        draw.rectangle([x1, y1, x2, y2], outline=BOX2D_COLOR, width=1)
        corners = obj.box.corners()
        kp = panel.to_display(obj.keypoints)
        one = object_color(obj) if object_color else None
        for edge in (8, 9, 10, 11, 4, 5, 6, 7, 0, 1, 2, 3):  # verticals, bottom, then top on top
            a, b = SKELETON[edge]
            seg = edge_segment(corners[a], corners[b], obj.keypoints[a], obj.keypoints[b], rec.K)
            seg = None if seg is None else clip_segment(panel.to_display(seg), lo, hi)
            if seg is not None:
                draw.line([tuple(seg[0]), tuple(seg[1])], fill=one or EDGE_COLORS[edge], width=lw)
        for j in range(len(kp)):
            x, y = kp[j]
            if obj.behind_camera[j] or not (-r <= x <= W + r and -r <= y <= H + r):
                continue
            color = one or (TOP_COLOR if j in TOP_CORNERS else BOTTOM_COLOR)
            inside = bool(obj.in_image[j])
            draw.ellipse([x - r, y - r, x + r, y + r], fill=color if inside else None,
                         outline=(0, 0, 0) if inside else color, width=1 if inside else 2)
            if corner_labels:
                draw.text((x + r + 1, y - r - 1), str(j), fill=(255, 255, 255), font=label_font,
                          stroke_width=1, stroke_fill=(0, 0, 0), anchor="ld")
    return panel


# ---------------------------------------------------------------------------------------------
# The bird's-eye view
# ---------------------------------------------------------------------------------------------


def ground_axes(rec: FrameRecord) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """(origin, right, forward, on_ground) of the BEV: the ground plane's frame when the record has
    one, else the camera's own x-z plane (a top view that ignores the camera's pitch)."""
    if rec.ground_plane is not None:
        from omnigen.stats.compute import ground_frames

        plane = np.array([[*rec.ground_plane.normal, rec.ground_plane.offset]])
        origin, right, forward = (a[0] for a in ground_frames(plane))
        return origin, right, forward, True
    return np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), False


def footprints(rec: FrameRecord) -> np.ndarray:
    """(objects, 4, 2) bottom corners 4-7 of each object as (right, forward) metres in the BEV frame."""
    origin, right, forward, _ = ground_axes(rec)
    if not rec.objects:
        return np.zeros((0, 4, 2))
    pts = np.stack([o.box.corners()[list(BOTTOM_CORNERS)] for o in rec.objects]) - origin
    return np.stack([pts @ right, pts @ forward], axis=-1)


def _nice_step(span: float) -> float:
    raw = span / 5
    p = 10 ** math.floor(math.log10(raw))
    return next(m * p for m in (1, 2, 2.5, 5, 10) if m * p >= raw)


@dataclass
class BevPanel:
    """A drawn BEV and its mapping from (right, forward) metres to panel pixels."""

    image: Image.Image
    center_x: float  # panel x of right = 0
    base_y: float  # panel y of forward = 0
    px_per_m: float

    def to_display(self, rf: np.ndarray) -> np.ndarray:
        rf = np.asarray(rf, dtype=np.float64)
        return np.stack([self.center_x + rf[..., 0] * self.px_per_m, self.base_y - rf[..., 1] * self.px_per_m], axis=-1)


def draw_bev(rec: FrameRecord, size: int = 480, object_color: ObjectColor | None = None) -> BevPanel:
    """Footprints of the frame's objects on the ground, the camera at the bottom looking up."""
    fp = footprints(rec)
    origin, right, forward, on_ground = ground_axes(rec)
    reach = max(10.0, float(np.nanmax(fp[..., 1])) if len(fp) else 10.0,
                2 * float(np.nanmax(np.abs(fp[..., 0]))) if len(fp) else 10.0)
    span = reach / 0.85
    px_per_m = size / span
    bev = BevPanel(Image.new("RGB", (size, size), BACKGROUND), size / 2, size * 0.95, px_per_m)
    img = bev.image
    draw = ImageDraw.Draw(img, "RGBA")
    small = font(11)

    wedge = _visible_ground(rec, origin, right, forward, on_ground, span * 1.5)
    if wedge is not None:
        draw.polygon([tuple(p) for p in bev.to_display(wedge)], fill=(255, 255, 255, 28), outline=(150, 150, 150, 255))
    step = _nice_step(span)
    for k in range(1, int(span / step) + 1):  # range rings around the camera's foot
        rad = k * step * px_per_m
        draw.arc([bev.center_x - rad, bev.base_y - rad, bev.center_x + rad, bev.base_y + rad], 180, 360,
                 fill=(70, 70, 80, 255))
        draw.text((bev.center_x + 3, bev.base_y - rad + 1), f"{k * step:g} m", fill=(150, 150, 160), font=small)
    for i, obj in enumerate(rec.objects):
        poly = bev.to_display(fp[i])
        if not np.isfinite(poly).all():
            continue
        color = (object_color(obj) if object_color else None) or CLASS_COLORS[obj.category]
        draw.polygon([tuple(p) for p in poly], fill=color + (150,), outline=color + (255,))
        draw.line([tuple(poly[0]), tuple(poly[1])], fill=(255, 255, 255, 255), width=2)  # front edge: 4-5
    cx, cy = bev.center_x, bev.base_y
    draw.polygon([(cx, cy - 7), (cx - 5, cy + 4), (cx + 5, cy + 4)], fill=(255, 255, 255, 255))
    caption = "BEV: ground plane, camera at the bottom" if on_ground else "BEV: camera x-z plane (no ground plane)"
    draw.rectangle([0, 0, int(draw.textlength(caption, font=small)) + 8, 17], fill=BACKGROUND + (255,))
    draw.text((4, 3), caption, fill=(220, 220, 220), font=small)
    return bev


def _visible_ground(rec: FrameRecord, origin, right, forward, on_ground: bool, far: float) -> np.ndarray | None:
    """The image border back-projected onto the ground, as a (right, forward) polygon.

    Rays above the horizon (or hitting beyond `far`) are cut at `far` metres in their heading.
    """
    if not on_ground:
        return None
    W, H = rec.width, rec.height
    border = np.concatenate([
        np.stack([np.linspace(-0.5, W - 0.5, 24), np.full(24, H - 0.5)], 1),
        np.stack([np.full(12, W - 0.5), np.linspace(H - 0.5, -0.5, 12)], 1),
        np.stack([np.linspace(W - 0.5, -0.5, 24), np.full(24, -0.5)], 1),
        np.stack([np.full(12, -0.5), np.linspace(-0.5, H - 0.5, 12)], 1)])
    rays = np.linalg.solve(rec.K, np.concatenate([border, np.ones((len(border), 1))], 1).T).T
    n, d = rec.ground_plane.normal, rec.ground_plane.offset
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -d / denom
    pts = []
    for ray, tt in zip(rays, t):
        hit = tt * ray if np.isfinite(tt) and tt > 0 else None
        rel = None if hit is None else hit - origin
        if rel is None or np.hypot(rel @ right, rel @ forward) > far:
            flat = np.array([ray @ right, ray @ forward])
            norm = np.linalg.norm(flat)
            if norm < 1e-9:
                continue
            pts.append(flat / norm * far)
        else:
            pts.append(np.array([rel @ right, rel @ forward]))
    return np.array(pts) if len(pts) >= 3 else None


# ---------------------------------------------------------------------------------------------
# One frame, composed
# ---------------------------------------------------------------------------------------------


@dataclass
class FrameView:
    """The composed picture: a title strip, the image panel at (0, strip), the BEV beside it."""

    image: Image.Image
    frame: Panel
    bev: BevPanel | None
    image_error: str | None
    strip: int = TITLE_HEIGHT  # the title strip's height: two rows where the key does not fit beside the title

    @property
    def frame_origin(self) -> tuple[int, int]:
        return 0, self.strip

    @property
    def bev_origin(self) -> tuple[int, int]:
        return self.frame.image.width, self.strip


LEGEND = (("top", TOP_COLOR), ("bottom", BOTTOM_COLOR), ("verticals", VERTICAL_COLOR), ("2D box", BOX2D_COLOR),
          ("ignore", IGNORE_COLOR))


TRACK_LEGEND = (("cuboid: its track's colour", (235, 235, 235)),) + LEGEND
"""The key where cuboids are coloured by track (untracked objects keep the colours by face)."""


def _legend_width(d: ImageDraw.ImageDraw, f, legend=LEGEND) -> int:
    return sum(int(d.textlength(label, font=f)) + 12 for label, _ in legend)


def render_frame(rec: FrameRecord, image_path: str | Path | None, bev: bool = True, scale: float | None = None,
                 bev_size: int | None = None, margin: float = 0.0, object_color: ObjectColor | None = None) -> FrameView:
    """The frame drawn (and its BEV beside it), with a title strip naming it and a colour key.

    The key is whole or not at all: where it does not fit beside the title (a 640 px frame without
    its BEV), the strip takes a second row for it rather than drop entries."""
    if scale is None:
        scale = display_scale(rec.width, rec.height)
    w, h, mx, my = panel_size(rec.width, rec.height, scale, margin)
    side = (bev_size or bev_side(h + 2 * my)) if bev else 0
    check_canvas(w + 2 * mx + side, 2 * TITLE_HEIGHT + max(h + 2 * my, side), f"frame {rec.frame_id}")
    if image_path is None:
        image, error = None, "no image"
    else:
        image, error = load_image(image_path)
    panel = draw_frame(rec, image, scale, margin=margin, object_color=object_color)
    bev_panel = draw_bev(rec, side, object_color) if bev else None
    legend = TRACK_LEGEND if object_color else LEGEND
    width = panel.image.width + (bev_panel.image.width if bev_panel else 0)
    f = font(12)
    title = f"{rec.frame_id}  {rec.source} / {rec.view}  {rec.width}x{rec.height}  {len(rec.objects)} objects"
    if error:
        title += f"  [image: {error}]"
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    one_row = probe.textlength(title, font=f) + 12 + _legend_width(probe, f, legend) <= width
    strip = TITLE_HEIGHT if one_row else 2 * TITLE_HEIGHT
    height = strip + max(panel.image.height, bev_panel.image.height if bev_panel else 0)
    out = Image.new("RGB", (width, height), BACKGROUND)
    out.paste(panel.image, (0, strip))
    if bev_panel:
        out.paste(bev_panel.image, (panel.image.width, strip))
    d = ImageDraw.Draw(out)
    d.text((4, 4), title, fill=(235, 235, 235), font=f)
    x = width - _legend_width(d, f, legend) + 8 if one_row else 4
    y = 4 if one_row else 4 + TITLE_HEIGHT
    for label, color in legend:
        d.text((x, y), label, fill=color, font=f)
        x += int(d.textlength(label, font=f)) + 12
    return FrameView(out, panel, bev_panel, error, strip)



def render_instant(recs: list[FrameRecord], image_paths: list[str | Path | None], bev: bool = False,
                   scale: float | None = None, margin: float = 0.0) -> tuple[Image.Image, list[FrameView]]:
    """The frames of one instant in one row, in the order given, each drawn as render_frame draws it
    with cuboids in their track's colour (track_color), so one object is one colour in every view.

    Each frame gets its own scale so that the images share one height (the tallest at `scale`, or
    at its default display scale): drawn at that scale rather than resized afterwards, every line
    stays as sharp and its colour as exact as in a single frame's picture."""
    height = max(r.height * (scale or display_scale(r.width, r.height)) for r in recs)
    scales = [height / r.height for r in recs]
    sizes = [panel_size(r.width, r.height, s, margin) for r, s in zip(recs, scales)]
    width = sum(w + 2 * mx + (bev_side(h + 2 * my) if bev else 0) for w, h, mx, my in sizes)
    tallest = max(max(h + 2 * my, bev_side(h + 2 * my) if bev else 0) for w, h, mx, my in sizes)
    check_canvas(width + PANEL_GAP * (len(recs) - 1), 2 * TITLE_HEIGHT + tallest, f"the instant of {recs[0].frame_id}")
    views = [render_frame(r, path, bev=bev, scale=s, margin=margin, object_color=track_color)
             for r, path, s in zip(recs, image_paths, scales)]
    return side_by_side([v.image for v in views]), views


def side_by_side(pictures: list[Image.Image]) -> Image.Image:
    """The pictures in one row, top-aligned, PANEL_GAP apart on the background colour."""
    out = Image.new("RGB", (sum(p.width for p in pictures) + PANEL_GAP * (len(pictures) - 1),
                            max(p.height for p in pictures)), BACKGROUND)
    x = 0
    for p in pictures:
        out.paste(p, (x, 0))
        x += p.width + PANEL_GAP
    return out
