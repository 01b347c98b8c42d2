"""Issue 25: class-balanced training (detector/data/balance.py): repeat-factor sampling of frames and
crop windows centred on rare objects."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from omnigen.detector.data.balance import (epoch_frames, focus_weights, focused_range, instance_counts, pick_focus,
                                      repeat_factors)
from omnigen.detector.data.samples import Augment, KeypointDataset, Letterbox, Sample, random_crop, split_frames
from omnigen.detector.training.train import TrainConfig, check_sampling
from omnigen.detector.data.loader import EpochBatches, make_loader, with_copies
from omnigen.fakes import write_fake_dataset
from omnigen.taxonomy import load_taxonomy


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake")
    write_fake_dataset(root, 8, objects_per_frame=6, seed=4)
    return root


def test_repeat_factors_follow_lvis_by_the_rarest_class_of_a_frame():
    frames = [np.array([0, 0, 1]), np.array([0]), np.array([0, 2]), np.array([0]), np.array([], dtype=np.int64)]
    # class 0 in 4 of 5 frames, class 1 in 1/5, class 2 in 1/5, class 3 in none
    r = repeat_factors(frames, 4, thresh=0.8)
    assert r == pytest.approx([2.0, 1.0, 2.0, 1.0, 1.0])  # sqrt(0.8 / 0.2) = 2; sqrt(0.8 / 0.8) = 1
    assert repeat_factors(frames, 4, thresh=0.0) == pytest.approx([1.0] * 5)
    assert repeat_factors(frames, 4, thresh=0.45) == pytest.approx([1.5, 1.0, 1.5, 1.0, 1.0])
    for bad in (-1, float("nan")):
        with pytest.raises(ValueError, match="repeat_thresh: .* is not a finite number >= 0"):
            repeat_factors(frames, 4, thresh=bad)
    assert epoch_frames(np.array([1.5, 1.0, 1.5, 1.0, 1.0])) == 6  # 5 whole draws, halves add to one more


def test_an_epoch_under_repeat_factors_has_a_fixed_length_and_repeats_the_rare_frames():
    repeat = np.array([1.0, 1.0, 2.5, 1.0, 1.2])
    sampler = EpochBatches(5, 2, seed=3, repeat=repeat)
    assert sampler.frames_per_epoch() == epoch_frames(repeat) == 7 and sampler.per_epoch() == 4
    counts = Counter()
    for epoch in range(200):
        order = sampler.order(epoch)
        assert len(order) == 7 and set(order) == set(range(5))  # every frame at least once
        c = Counter(order)
        assert c[2] in (2, 3) and c[0] == c[1] == c[3] == 1 and c[4] in (1, 2)
        counts.update(order)
    # the fractions 0.5 and 0.2 add up to one extra draw an epoch, shared by them in proportion
    assert counts[2] / 200 == pytest.approx(2 + 5 / 7, abs=0.08) and counts[4] / 200 == pytest.approx(1 + 2 / 7, abs=0.08)
    assert sampler.order(7) == EpochBatches(5, 2, seed=3, repeat=repeat).order(7)  # (seed, epoch) alone
    assert sampler.order(7) != sampler.order(8)
    for bad in ([1.0, 0.5, 1, 1, 1], [1.0, np.nan, 1, 1, 1], [1.0, np.inf, 1, 1, 1], [1.0, 1.0]):
        with pytest.raises(ValueError, match="EpochBatches.repeat: expected 5 finite factors >= 1"):
            EpochBatches(5, 2, seed=3, repeat=np.array(bad))


def test_without_the_options_the_samples_and_the_order_are_those_of_before(fake):
    # the draw order before class balance: a (seed, epoch) permutation, then per sample
    # random_crop, random_affine, flip, hsv_jitter from one Generator seeded [seed, epoch, frame]
    from omnigen.detector.data.samples import clip_to_canvas, flip_horizontal, hsv_jitter, random_affine

    sampler = EpochBatches(6, 4, seed=9)
    gen = torch.Generator().manual_seed(9 * 100_003 + 2)
    assert sampler.keys(2) == [(2, i) for i in torch.randperm(6, generator=gen).tolist()]
    data = KeypointDataset(str(fake), load_taxonomy("fine"), 256, split_frames(str(fake), "train"), Augment(),
                           seed=4, crop=64)
    data.set_epoch(3)
    for i in range(len(data)):
        rng = np.random.default_rng([4, 3, int(data.indices[i])])
        a = Augment()
        want = random_affine(random_crop(data.sample(i), 64, rng), a.scale, a.translate, rng)
        if rng.random() < a.flip:
            want = flip_horizontal(want)
        want.image = hsv_jitter(want.image, a.hsv, rng)
        want = clip_to_canvas(want, "learn")
        got = data[i]
        assert np.array_equal(got.image, want.image) and np.array_equal(got.keypoints, want.keypoints), i


def test_processes_split_one_repeated_order_between_them_and_never_draw_one_copy_twice():
    repeat = np.array([1.0, 3.0, 1.0, 1.6])
    whole = EpochBatches(4, 2, seed=1, repeat=repeat)
    assert len(whole.order(4)) == 7  # 6 whole + 1 drawn
    padded = whole.keys(4) + whole.keys(4)[:1]  # padded from the start to a multiple of the processes
    shards = []
    for rank in range(2):
        ddp = torch.utils.data.distributed.DistributedSampler(range(4), num_replicas=2, rank=rank, shuffle=True, seed=1)
        s = EpochBatches(4, 1, seed=1, shard=ddp, repeat=repeat)
        shards.append(s.keys(4))
        assert s.frames_per_epoch() == 4 == len(shards[-1]) and s.order(4) == [i for _, i, _ in shards[-1]]
    assert shards[0] == padded[0::2] and shards[1] == padded[1::2]
    drawn = shards[0] + shards[1]
    assert len(set(drawn)) == 7  # the three copies of frame 1 are three different draws across the processes
    assert sorted(c for _, i, c in set(drawn) if i == 1) == [0, 1, 2]


def test_a_frame_repeated_in_an_epoch_is_augmented_anew_and_copy_zero_is_the_plain_draw(fake):
    assert with_copies(3, [4, 1, 4, 4]) == [(3, 4, 0), (3, 1, 0), (3, 4, 1), (3, 4, 2)]
    data = KeypointDataset(str(fake), load_taxonomy("fine"), 64, split_frames(str(fake), "train"), Augment(), seed=2)
    data.set_epoch(1)
    plain, again = data[0], data.item(0, 0)
    assert np.array_equal(plain.image, again.image) and np.array_equal(plain.keypoints, again.keypoints)
    assert any(not np.array_equal(data.item(i, 0).keypoints, data.item(i, 1).keypoints) for i in range(len(data)))


def test_the_loader_yields_each_copy_with_its_own_draw(fake):
    data = KeypointDataset(str(fake), load_taxonomy("fine"), 64, split_frames(str(fake), "train"), Augment(), seed=5)
    repeat = np.full(len(data), 1.0)
    repeat[0] = 3.0
    sampler = EpochBatches(len(data), 2, seed=5, repeat=repeat)
    keys, batches = iter(sampler), iter(make_loader(data, sampler, workers=0, pin=False, collate_fn=list))
    got = {}
    for _ in range(sampler.per_epoch()):
        for key, sample in zip(next(keys), next(batches), strict=True):
            got[key] = sample
    assert {k for k in got if k[1] == 0} == {(0, 0, 0), (0, 0, 1), (0, 0, 2)} and len(got) == len(data) + 2
    data.set_epoch(0)
    for (epoch, i, copy), sample in got.items():
        assert np.array_equal(sample.keypoints, data.item(i, copy).keypoints)


def test_a_focused_window_puts_the_object_centre_in_its_middle_half():
    size, window = 256, 64
    rng = np.random.default_rng(0)
    image = np.zeros((size, size, 3), np.uint8)
    boxes = np.array([[10.0, 200.0, 20.0, 230.0], [120.0, 30.0, 160.0, 50.0], [250.0, 5.0, 255.0, 9.0]])
    kp = np.repeat(((boxes[:, :2] + boxes[:, 2:]) / 2)[:, None], 8, 1)
    sample = Sample(image, np.arange(3), boxes, kp, np.ones((3, 8), bool), np.ones((3, 8), np.float32), 0,
                    Letterbox(1.0, (0.0, 0.0)))
    for _ in range(50):
        out = random_crop(sample, window, rng, 1)
        c = (out.bboxes[1, :2] + out.bboxes[1, 2:]) / 2
        assert (c >= 0.25 * window).all() and (c <= 0.75 * window).all(), c
    # near the canvas's edges no window centres them: the window nearest to it, inside the canvas
    out = random_crop(sample, window, rng, 0)  # x at 15: the left-most window; y at 215 can be centred
    c = (out.bboxes[0, :2] + out.bboxes[0, 2:]) / 2
    assert c[0] == 15.0 and 0.25 * window <= c[1] <= 0.75 * window
    out = random_crop(sample, window, rng, 2)  # the top-right corner: that corner's window
    assert out.image.shape[:2] == (window, window)
    assert (out.bboxes[2, :2] + out.bboxes[2, 2:]) / 2 == pytest.approx([252.5 - 192, 7.0])
    assert focused_range(0, 192, 252.5, 64) == (192, 192) and focused_range(0, 192, 100, 64) == (52, 84)
    assert focused_range(0, 192, 15, 64) == (0, 0)


def test_focus_weights_pick_objects_by_the_inverse_of_their_class_count():
    counts = instance_counts([np.array([0, 0, 0, 1]), np.array([0, 2])], 4)
    assert counts.tolist() == [4, 1, 1, 0]
    w = focus_weights(counts)
    assert w.tolist() == [0.25, 1.0, 1.0, 0.0]
    rng = np.random.default_rng(1)
    picks = Counter(pick_focus(np.array([0, 0, 0, 1]), w, rng) for _ in range(4000))
    assert picks[3] / 4000 == pytest.approx(1.0 / 1.75, abs=0.03)  # 1 against 3 x 0.25
    assert pick_focus(np.array([], dtype=np.int64), w, rng) is None and pick_focus(np.array([3]), w, rng) is None


def test_focused_crops_show_the_rarest_class_more_often(fake):
    taxonomy = load_taxonomy("fine")
    ids = split_frames(str(fake), "train")

    whole = KeypointDataset(str(fake), taxonomy, 256, ids, Augment.off())  # the targets a whole image keeps
    counts = instance_counts([whole[i].cls for i in range(len(whole))], len(taxonomy.classes))
    rare = int(np.argmin(np.where(counts > 0, counts, np.inf)))

    def seen(focus: float) -> Counter:
        data = KeypointDataset(str(fake), taxonomy, 256, ids, Augment.off(), seed=0, crop=64, crop_focus=focus)
        hits = Counter()
        for epoch in range(40):
            data.set_epoch(epoch)
            for i in range(len(data)):
                hits[epoch, i] = int((data[i].cls == rare).any())
        return hits

    plain, focused = seen(0.0), seen(1.0)
    assert sum(focused.values()) > 1.5 * sum(plain.values()) > 0


def test_a_focus_share_is_a_probability_and_centres_only_windows_there_are():
    # the recipe's focus with whole images (no window, or one as large as the input) centres nothing
    assert TrainConfig(dataset="x", out="y", crop=None, crop_focus=0.5).focus() == 0.0
    assert TrainConfig(dataset="x", out="y", imgsz=320, crop=320, crop_focus=0.5).focus() == 0.0
    check_sampling(TrainConfig(dataset="x", out="y", crop=None, crop_focus=0.5))
    with pytest.raises(ValueError, match="crop_focus: 1.5"):
        check_sampling(TrainConfig(dataset="x", out="y", crop=None, crop_focus=1.5))
    with pytest.raises(ValueError, match="crop_focus: 1.5"):
        check_sampling(TrainConfig(dataset="x", out="y", crop=320, crop_focus=1.5))
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="repeat_thresh: .* is not a finite number >= 0"):
            check_sampling(TrainConfig(dataset="x", out="y", repeat_thresh=bad))
    with pytest.raises(ValueError, match="crop_focus: nan"):
        check_sampling(TrainConfig(dataset="x", out="y", crop=320, crop_focus=float("nan")))
    check_sampling(TrainConfig(dataset="x", out="y", crop=320, crop_focus=0.5, repeat_thresh=0.3))


def test_the_train_command_carries_the_sampling_keys(fake, tmp_path, monkeypatch):
    from omnigen.cli import main
    from omnigen.detector.training import train as train_module

    seen = {}
    monkeypatch.setattr(train_module, "train", lambda cfg, **kw: seen.setdefault("cfg", cfg) and {})
    assert main(["train", str(fake), "data.window=256", "data.focus=0.25", "data.repeat_thresh=0.5",
                 "--out", str(tmp_path / "run")]) == 0
    assert (seen["cfg"].crop, seen["cfg"].crop_focus, seen["cfg"].repeat_thresh) == (256, 0.25, 0.5)


def test_a_dataset_refuses_a_focus_share_without_windows(fake):
    with pytest.raises(ValueError, match="crop_focus centres crop windows, but crop is not set"):
        KeypointDataset(str(fake), load_taxonomy("fine"), 64, None, crop_focus=0.5)
