"""Training samples from an UrbanOmniView dataset: images letterboxed to the network input, and
each object's class, 2D box and eight corners as loss targets.

The loader reads the canonical records (not a COCO export) because the record keeps what COCO
drops: corners outside the image but in front of the camera. Those are real targets for truncated
objects (a car cut by the image border still has a rear corner somewhere to the left of it), so by
default the model learns them (`out_of_image="learn"`); `out_of_image="drop"` masks them as COCO's
v = 0 does. Corners behind the camera are never targets: they have no image position.

Randomness: every sample draws from its own `numpy.random.Generator`, seeded from (seed, epoch,
frame index), so an epoch is the same whatever the number of workers or processes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from omnigen.conventions import FLIP_IDX, NUM_KEYPOINTS
from omnigen.detector.data.balance import check_crop_focus, focus_weights, focused_range, instance_counts, pick_focus
from omnigen.detector.recipe import RECIPE
from omnigen.dataset import Dataset
from omnigen.splits import TRAIN, read_split, split_names
from omnigen.taxonomy import Taxonomy

PAD_VALUE = 114
"""Grey of the letterbox padding, as YOLO detectors use (a neutral value for the normalised input)."""

MIN_BOX_PX = 2.0
"""Objects whose box, after augmentation and clipping to the canvas, is narrower or lower than this
are dropped: the assigner cannot place an anchor inside them."""

OutOfImage = Literal["learn", "drop"]


_AUGMENT = RECIPE.augment
"""The recipe's augmentation (detector/recipe.py): Augment's defaults, declared there only."""


@dataclass(frozen=True)
class Augment:
    """Training augmentation; all off gives the validation transform (letterbox only). What
    validation and the tests build without a recipe is the recipe's (`Augment()`)."""

    flip: float = _AUGMENT.flip  # probability of a horizontal flip (corners permuted by FLIP_IDX)
    scale: float = _AUGMENT.scale  # random zoom in [1 - scale, 1 + scale] of the letterboxed image
    translate: float = _AUGMENT.translate  # random shift, fraction of the input size
    hsv: tuple[float, float, float] = _AUGMENT.hsv  # hue, saturation, value jitter gains

    @classmethod
    def off(cls) -> "Augment":
        return cls(flip=0.0, scale=0.0, translate=0.0, hsv=(0.0, 0.0, 0.0))


@dataclass
class Letterbox:
    """How an image maps into the square input, in the contract's pixel convention (pixel centres
    at integers, so an image of width w spans -0.5 .. w - 0.5, as cv2.resize samples it):
    x_in = (x + 0.5) * gain - 0.5 + pad."""

    gain: float
    pad: tuple[float, float]
    # the resized image's (width, height) inside the input, from pad on: the far side's padding
    # can be a pixel wider than the near side's (None where unknown: assume symmetric padding)
    content: tuple[int, int] | None = None

    def content_box(self, width: int, height: int) -> tuple[int, int, int, int]:
        """x0, y0, x1, y1 (exclusive) of the image's own pixels in an input `width` x `height`."""
        px, py = int(self.pad[0]), int(self.pad[1])
        cw, ch = self.content or (width - 2 * px, height - 2 * py)
        return px, py, px + cw, py + ch

    def to_input(self, xy: np.ndarray) -> np.ndarray:
        return (xy + 0.5) * self.gain - 0.5 + np.asarray(self.pad)

    def to_image(self, xy: np.ndarray) -> np.ndarray:
        return (xy - np.asarray(self.pad) + 0.5) / self.gain - 0.5


def letterbox(image: np.ndarray, size: int) -> tuple[np.ndarray, Letterbox]:
    """Resize keeping the aspect ratio and pad to size x size (centred)."""
    h, w = image.shape[:2]
    gain = size / max(h, w)
    nw, nh = max(1, round(w * gain)), max(1, round(h * gain))
    resized = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if gain < 1 else cv2.INTER_LINEAR)
    px, py = (size - nw) // 2, (size - nh) // 2
    out = np.full((size, size, 3), PAD_VALUE, np.uint8)
    out[py:py + nh, px:px + nw] = resized
    # The pixel grid is continuous-coordinate exact when gain is the per-axis ratio; the rounding of
    # nw, nh moves edges by under half a pixel, which is below annotation noise.
    return out, Letterbox(gain, (float(px), float(py)), (nw, nh))


def read_image(path: Path) -> np.ndarray:
    """RGB uint8; a missing or unreadable file is an error naming it."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"{path}: image missing or unreadable")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def available_memory() -> int | None:
    """Bytes of memory the kernel says can be had now (Linux MemAvailable); None where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def hsv_jitter(image: np.ndarray, gains: tuple[float, float, float], rng: np.random.Generator) -> np.ndarray:
    """Colour jitter in HSV with lookup tables (cheap on large images)."""
    if not any(gains):
        return image
    r = rng.uniform(-1, 1, 3) * np.asarray(gains) + 1
    hue, sat, val = cv2.split(cv2.cvtColor(image, cv2.COLOR_RGB2HSV))
    x = np.arange(256, dtype=np.float32)
    lut_h = ((x * r[0]) % 180).astype(np.uint8)
    lut_s = np.clip(x * r[1], 0, 255).astype(np.uint8)
    lut_v = np.clip(x * r[2], 0, 255).astype(np.uint8)
    hsv = cv2.merge((cv2.LUT(hue, lut_h), cv2.LUT(sat, lut_s), cv2.LUT(val, lut_v)))
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


@dataclass
class Sample:
    """One training example: the input image and its targets in input pixels."""

    image: np.ndarray  # (size, size, 3) uint8 RGB
    cls: np.ndarray  # (M,) int64
    bboxes: np.ndarray  # (M, 4) xyxy
    keypoints: np.ndarray  # (M, 8, 2)
    kpt_mask: np.ndarray  # (M, 8) bool
    kpt_visible: np.ndarray  # (M, 8) float32
    frame_index: int
    letterbox: Letterbox


def flip_horizontal(sample: Sample) -> Sample:
    """Mirror the image and swap left and right corners. Pixel column c goes to w - 1 - c, so with
    pixel centres at integers a coordinate x goes to w - 1 - x (boxes and corners alike)."""
    w = sample.image.shape[1]
    b = sample.bboxes.copy()
    b[:, [0, 2]] = (w - 1) - sample.bboxes[:, [2, 0]]
    k = sample.keypoints[:, FLIP_IDX].copy()
    k[..., 0] = (w - 1) - k[..., 0]
    return Sample(np.ascontiguousarray(sample.image[:, ::-1]), sample.cls, b, k,
                  sample.kpt_mask[:, FLIP_IDX], sample.kpt_visible[:, FLIP_IDX], sample.frame_index,
                  sample.letterbox)


def random_affine(sample: Sample, scale: float, translate: float, rng: np.random.Generator) -> Sample:
    """Zoom about the centre and shift; corners keep their (possibly outside) positions. cv2's
    warpAffine maps pixel centres (integers) by M, so M maps the contract's coordinates exactly."""
    if scale == 0 and translate == 0:
        return sample
    size = sample.image.shape[0]
    s = rng.uniform(1 - scale, 1 + scale)
    tx, ty = rng.uniform(-translate, translate, 2) * size
    c = (size - 1) / 2  # the canvas centre in pixel-centre coordinates
    M = np.array([[s, 0, c - s * c + tx], [0, s, c - s * c + ty]], np.float32)
    image = cv2.warpAffine(sample.image, M, (size, size), flags=cv2.INTER_LINEAR, borderValue=(PAD_VALUE,) * 3)
    A, t = M[:, :2].astype(np.float64), M[:, 2].astype(np.float64)
    kp = sample.keypoints @ A.T + t
    b = sample.bboxes.reshape(-1, 2, 2) @ A.T + t
    return Sample(image, sample.cls, b.reshape(-1, 4), kp, sample.kpt_mask, sample.kpt_visible,
                  sample.frame_index, sample.letterbox)


def random_crop(sample: Sample, window: int, rng: np.random.Generator, focus: int | None = None) -> Sample:
    """A random window x window part of the letterboxed canvas, at the canvas's scale.

    Why: a small network input (what a CPU can afford) normally means shrinking the whole image,
    and a car of 20 pixels becomes one of 10, whose corners OKS then asks for within a pixel or
    two. Training on windows of the image at its full input size keeps every object at the scale
    the model will see it at when it predicts on the whole image (detectors are fully
    convolutional), for a quarter of the pixels per step when the window is half the size.
    The window is drawn inside the image's content (the letterbox padding only where the content
    is narrower than the window); corners and boxes shift with it and `clip_to_canvas` then treats
    objects cut by the window as truncated ones. With `focus` (an object's index) the window is
    drawn among those that put that object's box centre in their middle half (balance.focused_range).
    """
    size = sample.image.shape[0]
    if window >= size:
        return sample
    lb = sample.letterbox
    h, w = sample.image.shape[:2]
    origin = []
    for axis, extent in ((0, w), (1, h)):
        pad = lb.pad[axis]
        content = size - 2 * pad  # the letterbox centres the content
        lo, hi = (pad, pad + content - window) if content >= window else (pad + content - window, pad)
        lo, hi = max(0, lo), min(extent - window, hi)
        if focus is not None:
            b = sample.bboxes[focus]
            lo, hi = focused_range(lo, hi, (b[axis] + b[axis + 2]) / 2, window)
        origin.append(int(round(rng.uniform(lo, max(lo, hi)))))
    x0, y0 = origin
    shift = np.array([x0, y0], dtype=np.float64)
    image = np.ascontiguousarray(sample.image[y0:y0 + window, x0:x0 + window])
    b = (sample.bboxes.reshape(-1, 2, 2) - shift).reshape(-1, 4)
    return Sample(image, sample.cls, b, sample.keypoints - shift, sample.kpt_mask, sample.kpt_visible,
                  sample.frame_index, sample.letterbox)


def clip_to_canvas(sample: Sample, out_of_image: OutOfImage) -> Sample:
    """Clip boxes to the canvas, drop objects left too small, update corner masks and visibility."""
    size = sample.image.shape[0]
    lo, hi = -0.5, size - 0.5  # the canvas's extent with pixel centres at integers
    b = np.clip(sample.bboxes, lo, hi)
    keep = ((b[:, 2] - b[:, 0]) >= MIN_BOX_PX) & ((b[:, 3] - b[:, 1]) >= MIN_BOX_PX)
    kp = sample.keypoints[keep]
    inside = (kp >= lo).all(-1) & (kp <= hi).all(-1)
    mask = sample.kpt_mask[keep] & (inside if out_of_image == "drop" else True)
    visible = sample.kpt_visible[keep] * inside
    return Sample(sample.image, sample.cls[keep], b[keep], kp, mask, visible.astype(np.float32),
                  sample.frame_index, sample.letterbox)


class KeypointDataset(torch.utils.data.Dataset):
    """Frames of one split as training samples for a taxonomy (classes it drops are not targets).

    Each image is letterboxed to `size`; with `crop`, a sample is a random crop x crop window of
    it (see random_crop), drawn before the other augmentations; with `crop_focus` that share of the
    windows is centred on an object drawn class-balanced (detector/data/balance.py).

    Ignore regions (KITTI DontCare) are not used in training: objects inside them are simply
    unlabelled, which costs a little recall signal and never teaches a wrong box.
    """

    def __init__(self, root: str | Path, taxonomy: Taxonomy, size: int, frame_ids: list[str] | None = None,
                 augment: Augment | None = None, out_of_image: OutOfImage = "learn", seed: int = 0,
                 crop: int | None = None, crop_focus: float = 0.0):
        if out_of_image not in ("learn", "drop"):
            raise ValueError(f"out_of_image must be 'learn' or 'drop', got {out_of_image!r}")
        if crop is not None and not 0 < crop <= size:
            raise ValueError(f"crop must be between 1 and the input size {size}, got {crop}")
        self.crop = crop  # training window (random_crop); None: the whole letterboxed image
        check_crop_focus(crop_focus, crop)
        self.crop_focus = crop_focus
        self.ds = Dataset.open(root, show_progress=False)
        self.taxonomy = taxonomy
        self.size = size
        self.augment = augment or Augment.off()
        self.out_of_image = out_of_image
        self.seed = seed
        self.epoch = 0
        if frame_ids is None:
            self.indices = np.arange(len(self.ds))
        else:
            self.indices = np.array([self.ds.index_of(f) for f in frame_ids], dtype=np.int64)
        self.class_of_fine = taxonomy.fine_class_ids()
        self._frame_classes: list[np.ndarray] | None = None  # frame_classes(), counted once
        self._focus_weights = focus_weights(instance_counts(self.frame_classes(), len(taxonomy.classes))) \
            if crop_focus > 0 else None
        self._cache: list[tuple[np.ndarray, Letterbox]] | None = None  # cache_images()

    def __len__(self) -> int:
        return len(self.indices)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def cache_images(self, show_progress: bool = False) -> int:
        """Decode and letterbox every image once and keep it in memory; returns the bytes held.

        Why: every epoch decodes every image again, and on a machine with few cores the loader's
        work takes CPU from the training step (benchmarks/bench_train_speed.py cache measures it). Call it before the loader starts its worker
        processes, which then share the cache (fork, copy-on-write). The arrays are read-only,
        so an augmentation that wrote into its input would fail instead of corrupting the cache.
        Refuses, naming the sizes, when the cache would not fit in the memory now available.
        """
        from omnigen.progress import progress

        need = len(self) * self.size * self.size * 3
        free = available_memory()
        if free is not None and need > 0.8 * free:
            raise MemoryError(f"{self.ds.root}: caching {len(self)} images at {self.size} px needs "
                              f"{need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB is available; train without the cache")
        cache = []
        for i in progress(range(len(self)), "cache images", total=len(self), disable=not show_progress):
            boxed, lb = letterbox(read_image(self._image_path(i)), self.size)
            boxed.setflags(write=False)
            cache.append((boxed, lb))
        self._cache = cache
        return need

    def frame_classes(self) -> list[np.ndarray]:
        """Each frame's target classes (taxonomy ids, one per object), without reading images:
        what class-balanced sampling counts (detector/data/balance.py)."""
        if self._frame_classes is None:
            cat = self.ds.objects.category
            self._frame_classes = [self.class_of_fine[cat[self._target_rows(int(f))]].astype(np.int64)
                                   for f in self.indices]
        return self._frame_classes

    def _target_rows(self, f: int) -> np.ndarray:
        """Object-table rows of frame f whose class the taxonomy keeps."""
        ds = self.ds
        rows = np.arange(int(ds.offsets[f]), int(ds.offsets[f + 1]))
        return rows[self.class_of_fine[ds.objects.category[rows]] >= 0] if len(rows) else rows

    def _image_path(self, i: int) -> Path:
        return self.ds.path(self.ds.table.image[int(self.indices[i])])

    def raw(self, i: int) -> tuple[np.ndarray, Sample]:
        """The original image and the letterboxed sample, before augmentation."""
        image = read_image(self._image_path(i))
        return image, self._targets(i, *letterbox(image, self.size))

    def sample(self, i: int) -> Sample:
        """The letterboxed sample before augmentation, from the cache when there is one."""
        return self._targets(i, *self._cache[i]) if self._cache is not None else self.raw(i)[1]

    def _targets(self, i: int, boxed: np.ndarray, lb: Letterbox) -> Sample:
        f = int(self.indices[i])
        t = self.ds.objects
        rows = self._target_rows(f)
        kp = lb.to_input(t.keypoints[rows]) if len(rows) else np.zeros((0, NUM_KEYPOINTS, 2))
        bb = lb.to_input(t.bbox[rows].reshape(-1, 2, 2)).reshape(-1, 4) if len(rows) else np.zeros((0, 4))
        front = ~t.behind_camera[rows] & np.isfinite(kp).all(-1)
        visible = (t.in_image[rows] & ~t.occluded[rows] & front).astype(np.float32)
        # 'drop' masks corners outside the original image, not only outside the (padded) canvas
        mask = front & t.in_image[rows] if self.out_of_image == "drop" else front
        return Sample(boxed, self.class_of_fine[t.category[rows]], bb, np.nan_to_num(kp), mask, visible, f, lb)

    def __getitem__(self, i: int) -> Sample:
        return self.item(i)

    def item(self, i: int, copy: int = 0) -> Sample:
        """Frame i augmented for this epoch; `copy` numbers a frame's repeats within an epoch
        (repeat-factor sampling), each its own draw (copy 0 is the draw without repeats)."""
        sample = self.sample(i)
        seed = [self.seed, self.epoch, int(self.indices[i])] + ([copy] if copy else [])
        rng = np.random.default_rng(seed)
        a = self.augment
        if self.crop is not None:
            focus = None
            if self.crop_focus > 0 and rng.random() < self.crop_focus:  # no draw when off: same samples as before
                focus = pick_focus(sample.cls, self._focus_weights, rng)
            sample = random_crop(sample, self.crop, rng, focus)
        sample = random_affine(sample, a.scale, a.translate, rng)
        if rng.random() < a.flip:
            sample = flip_horizontal(sample)
        sample.image = hsv_jitter(sample.image, a.hsv, rng)
        return clip_to_canvas(sample, self.out_of_image)


def collate(samples: list[Sample]) -> tuple[torch.Tensor, dict[str, torch.Tensor], list[Sample]]:
    """Images (B, 3, S, S) float in 0..1 and the loss's targets (detector/model/outputs.py layout)."""
    images = torch.from_numpy(np.stack([s.image for s in samples])).permute(0, 3, 1, 2).float().div_(255)
    n = [len(s.cls) for s in samples]
    targets = {
        "batch_idx": torch.from_numpy(np.repeat(np.arange(len(samples)), n)).long(),
        "cls": torch.from_numpy(np.concatenate([s.cls for s in samples])).long(),
        "bboxes": torch.from_numpy(np.concatenate([s.bboxes for s in samples])).float(),
        "keypoints": torch.from_numpy(np.concatenate([s.keypoints for s in samples])).float(),
        "kpt_mask": torch.from_numpy(np.concatenate([s.kpt_mask for s in samples])).bool(),
        "kpt_visible": torch.from_numpy(np.concatenate([s.kpt_visible for s in samples])).float(),
    }
    return images, targets, samples


def split_frames(root: str | Path, name: str | None) -> list[str] | None:
    """Frame ids of a split; None (all frames) when the name is None or 'all'. A dataset without
    split files (a raw render) trains on all frames when the train split is asked for."""
    if name is None or name == "all":
        return None
    if name == TRAIN and not split_names(root):
        return None
    return read_split(root, name)
