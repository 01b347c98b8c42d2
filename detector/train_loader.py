"""The training data loader: built once per run, its worker processes kept across epochs.

Why it is built once: forking 14 loader processes every epoch cost seconds an epoch on a GPU
machine, and each fresh process decoded its first images while the GPU waited. Persistent workers
hold a copy of the dataset made when they started, so `KeypointDataset.set_epoch` in the main
process would no longer reach them; instead the sampler hands every worker (epoch, index) pairs
and `EpochData` sets the epoch before it draws the sample. Each sample's augmentation thus stays
seeded by (seed, epoch, frame) and the shuffling by (seed, epoch) exactly as before, so a resumed
run still equals an uninterrupted one.

Batches leave the workers as uint8 images (a quarter of the bytes of float32): the copy into
pinned memory and to the GPU is what limits a fast accelerator, and the division by 255 is one
cheap kernel on the device (train_step.to_device).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterator

import numpy as np
import torch

from detector.data import KeypointDataset, Sample, collate


class EpochSampler(torch.utils.data.Sampler):
    """(epoch, index) pairs of one epoch: a permutation seeded by (seed, epoch), or the shard of a
    DistributedSampler (which shuffles by its own seed and the epoch)."""

    def __init__(self, n: int, seed: int, shard: torch.utils.data.distributed.DistributedSampler | None = None):
        self.n, self.seed, self.shard, self.epoch = n, seed, shard, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        if self.shard is not None:
            self.shard.set_epoch(epoch)

    def order(self) -> list[int]:
        if self.shard is not None:
            return list(self.shard)
        # the same permutation as DataLoader(shuffle=True, generator=Generator().manual_seed(...))
        gen = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        return torch.randperm(self.n, generator=gen).tolist()

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch = self.epoch
        return iter([(epoch, i) for i in self.order()])

    def __len__(self) -> int:
        return len(self.shard) if self.shard is not None else self.n


class EpochData(torch.utils.data.Dataset):
    """A KeypointDataset indexed by (epoch, index): the epoch travels with the index into the
    loader's worker processes."""

    def __init__(self, data: KeypointDataset):
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, key: tuple[int, int]) -> Sample:
        epoch, i = key
        self.data.set_epoch(epoch)
        return self.data[i]


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


def make_loader(data: KeypointDataset, batch: int, workers: int, sampler: EpochSampler, pin: bool,
                collate_fn=collate_uint8) -> torch.utils.data.DataLoader:
    """The run's one loader; workers (when any) persist across epochs, prefetching 4 batches each."""
    return torch.utils.data.DataLoader(
        EpochData(data), batch_size=batch, sampler=sampler, num_workers=workers, collate_fn=collate_fn,
        drop_last=False, pin_memory=pin, persistent_workers=workers > 0,
        prefetch_factor=4 if workers > 0 else None, worker_init_fn=quiet_worker if workers > 0 else None)
