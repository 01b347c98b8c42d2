"""The training data loader: one for the whole run, whose batches flow from epoch to epoch.

Why: the loader used to be built again every epoch, forking its 14 worker processes anew, and
every epoch began with the GPU waiting while fresh workers decoded their first batches. Now the
run iterates one loader whose batch sampler never ends: it yields the batches of epoch after
epoch, and the trainer takes an epoch's worth of them at a time. The workers keep decoding across
the epoch boundary and through validation, with `prefetch_factor` batches each in flight.

A worker holds the copy of the dataset it started with, so `KeypointDataset.set_epoch` in the
main process would not reach it: each index carries its epoch, (epoch, frame), and `EpochData`
sets the epoch before it draws the sample (repeat-factor sampling adds the frame's copy number). Each sample's augmentation thus stays seeded by
(seed, epoch, frame) and the shuffling by (seed, epoch) exactly as before, so a resumed run still
equals an uninterrupted one.

Batches leave the workers as uint8 images (a quarter of the bytes of float32): the copy into
pinned memory and to the GPU is what limits a fast accelerator, and the division by 255 is one
cheap kernel on the device (train_step.to_device).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from typing import Iterator

import numpy as np
import torch

from omnigen.detector.data.balance import epoch_frames
from omnigen.detector.data.samples import KeypointDataset, Sample, collate


class EpochBatches(torch.utils.data.Sampler):
    """Batches of (epoch, index) pairs, epoch after epoch from `start`, without end.

    An epoch's order is a permutation seeded by (seed, epoch), the one DataLoader(shuffle=True)
    drew with such a generator, or this process's shard of a DistributedSampler; its last batch
    may be short (batches never mix two epochs).

    With `repeat` (each frame's repeat factor, balance.repeat_factors) an epoch draws each frame
    floor(r) times plus, without replacement and weighted by the fractional parts, as many extra
    frames as those parts add up to: the same number of frames every epoch, all from (seed, epoch).
    Under several processes each takes every world-th of that order, padded from its start as
    DistributedSampler pads."""

    def __init__(self, n: int, batch: int, seed: int, start: int = 0,
                 shard: torch.utils.data.distributed.DistributedSampler | None = None,
                 repeat: np.ndarray | None = None):
        if repeat is not None:
            repeat = np.asarray(repeat, dtype=np.float64)
            if len(repeat) != n or not (np.isfinite(repeat) & (repeat >= 1)).all():
                raise ValueError(f"EpochBatches.repeat: expected {n} finite factors >= 1, got {len(repeat)} "
                                 f"(smallest {np.min(repeat) if len(repeat) else 'none'}, largest "
                                 f"{np.max(repeat) if len(repeat) else 'none'})")
        self.n, self.batch, self.seed, self.start, self.shard = n, batch, seed, start, shard
        self.repeat = repeat

    def order(self, epoch: int) -> list[int]:
        """This process's frames of the epoch, in order."""
        if self.repeat is not None:
            return [i for _, i, _ in self.keys(epoch)]
        if self.shard is not None:
            self.shard.set_epoch(epoch)
            return list(self.shard)
        gen = torch.Generator().manual_seed(self.seed * 100_003 + epoch)
        return torch.randperm(self.n, generator=gen).tolist()

    def keys(self, epoch: int) -> list[tuple[int, ...]]:
        """This process's loader keys of the epoch: (epoch, frame), or (epoch, frame, copy) under
        repeat factors, the copies numbered over all processes' draws before the order is split
        (two processes never draw one copy)."""
        if self.repeat is None:
            return [(epoch, i) for i in self.order(epoch)]
        keys = with_copies(epoch, self._repeated(epoch))
        if self.shard is None:
            return keys
        world, rank = self.shard.num_replicas, self.shard.rank
        total = math.ceil(len(keys) / world) * world
        keys = (keys * math.ceil(total / len(keys)))[:total]  # padded from the start, as DistributedSampler pads
        return keys[rank::world]

    def _repeated(self, epoch: int) -> list[int]:
        """The whole epoch's frames under repeat factors (every process's), shuffled by (seed, epoch)."""
        gen = torch.Generator().manual_seed(self.seed * 100_003 + epoch)
        whole = np.floor(self.repeat)
        frames = np.repeat(np.arange(self.n), whole.astype(np.int64))
        frac = self.repeat - whole
        extra = epoch_frames(self.repeat) - len(frames)
        if extra > 0:
            drawn = torch.multinomial(torch.from_numpy(frac), extra, replacement=False, generator=gen).numpy()
            frames = np.concatenate([frames, drawn])
        return frames[torch.randperm(len(frames), generator=gen).numpy()].tolist()

    def frames_per_epoch(self) -> int:
        """Frames this process draws an epoch."""
        if self.repeat is not None:
            total = epoch_frames(self.repeat)
            return math.ceil(total / self.shard.num_replicas) if self.shard is not None else total
        return len(self.shard) if self.shard is not None else self.n

    def per_epoch(self) -> int:
        """Batches an epoch."""
        return math.ceil(self.frames_per_epoch() / self.batch)

    def __iter__(self) -> Iterator[list[tuple[int, ...]]]:
        epoch = self.start
        while True:
            keys = self.keys(epoch)
            for k in range(0, len(keys), self.batch):
                yield keys[k:k + self.batch]
            epoch += 1


def with_copies(epoch: int, order: list[int]) -> list[tuple[int, int, int]]:
    """(epoch, frame, copy) keys: a frame drawn twice in an epoch is augmented twice, differently
    (its copy number enters the sample's seed, KeypointDataset.item)."""
    seen: dict[int, int] = {}
    keys = []
    for i in order:
        keys.append((epoch, i, seen.get(i, 0)))
        seen[i] = seen.get(i, 0) + 1
    return keys


class EpochData(torch.utils.data.Dataset):
    """A KeypointDataset indexed by (epoch, index): the epoch travels with the index into the
    loader's worker processes."""

    def __init__(self, data: KeypointDataset):
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, key: tuple[int, ...]) -> Sample:
        epoch, i, *copy = key
        self.data.set_epoch(epoch)
        return self.data.item(i, copy[0] if copy else 0)


def collate_uint8(samples: list[Sample]) -> tuple[torch.Tensor, dict[str, torch.Tensor], list[Sample]]:
    """data.collate's batch with the images left as uint8 (B, 3, S, S) (channels-last in memory).

    The targets come from data.collate itself, given 1x1 views of the images so that it does not
    convert the pixels the device will convert.
    """
    images = torch.from_numpy(np.stack([s.image for s in samples])).permute(0, 3, 1, 2)
    _, targets, _ = collate([replace(s, image=s.image[:1, :1]) for s in samples])
    return images, targets, samples


def quiet_worker(worker_id: int) -> None:
    """Loader processes run one thread each: 16 workers with OpenCV's and torch's default thread
    pools would put hundreds of threads on 16 cores and slow the step's own threads."""
    import cv2

    cv2.setNumThreads(0)
    torch.set_num_threads(1)


PREFETCH = 4
"""Batches each loader worker keeps in flight (DataLoader's prefetch_factor)."""

FEW_CORES = 2
"""A CPU with at most this many usable cores trains with the loader in the step's own process."""

GPU_WORKERS = 2
"""Loader processes of a run on a GPU, or on a CPU with more cores, unless --workers says."""


def usable_cores() -> int:
    """The cores this process may run on (its affinity, which a cluster's job sets), not the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        return os.cpu_count() or 1


def loader_workers(setting: int | None, device: torch.device) -> int:
    """The loader processes of a run: `setting` when given; otherwise none on a CPU of FEW_CORES
    or fewer, GPU_WORKERS elsewhere.

    Why none there: the step's threads use every core, and a loader process that takes one of them
    in turn stalls all of the step's threads until it yields. On 2 cores the recipe's step on make
    validate's data ran 11.2 images a second with the loader in the step's process against 7.7
    with one loader process (benchmarks/bench_train_speed.py throughput --recipe --compare-workers
    0,1; detector-training.md): loading in turn costs less than the stalls. Each sample is seeded
    by (seed, epoch, frame) either way, so the same run is trained."""
    if setting is not None:
        return setting
    return 0 if device.type == "cpu" and usable_cores() <= FEW_CORES else GPU_WORKERS


def make_loader(data: KeypointDataset, batches: EpochBatches, workers: int, pin: bool,
                collate_fn=collate_uint8) -> torch.utils.data.DataLoader:
    """The run's one loader (iterate it once: its batches do not end); each worker keeps
    PREFETCH batches in flight, queued as soon as the loader is iterated."""
    return torch.utils.data.DataLoader(
        EpochData(data), batch_sampler=batches, num_workers=workers, collate_fn=collate_fn, pin_memory=pin,
        prefetch_factor=PREFETCH if workers > 0 else None, worker_init_fn=quiet_worker if workers > 0 else None)
