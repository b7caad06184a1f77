"""The options of a training run (:func:`.train.train`), apart from PyTorch: the command line reads
their defaults without importing it."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    epochs: int = 40
    steps_per_epoch: int = 100
    batch: int = 12
    crop: int = 256
    lr: float = 3e-3
    widths: tuple[int, ...] = (16, 32, 64, 96)
    head: int = 12
    patience: int = 8
    seed: int = 0
    val_slices: int = 48
    threads: int = 0  # 0: torch's default
    max_minutes: float = 0.0  # a time budget (0: none): the schedule runs on the clock and ends with it
