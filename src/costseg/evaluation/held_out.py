"""The held-out images of an evaluation, through the network once, kept for every analysis
that fits on them (the scaling, the meta models, the guarantee, conformal sets).

Their batches are kept on the CPU as the source gave them (float32 scores, labels, instance ids,
expected entropy) up to :data:`MEMORY_BYTES`; the scores beyond that go, rounded to float16, to
a temporary folder inside the output folder, removed when the evaluation ends (docs/design.md).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from costseg.networks.sources import Batch, batches
from costseg.progress import progress

MEMORY_BYTES = 4 * 2**30
"""Scores of held-out images kept in memory (float32); those beyond go to disk as float16."""


class HeldOut:
    """The batches of ``indices`` of ``dataset``, scored at the first :meth:`batches` call and
    replayed from memory (or disk) at every later one.

    Args:
        plan: the evaluation plan (source, device, batch size, loader workers, output folder).
        dataset, indices: the held-out images.
        entropy: whether each batch needs the expected entropy of a source of several runs
            (the segments' features; costs a pass per run).
    """

    def __init__(self, plan, dataset: Dataset, indices: list[int], entropy: bool) -> None:
        self.plan, self.dataset, self.indices, self.entropy = plan, dataset, indices, entropy
        self.kept: list[Batch] | None = None
        self.spilled: Path | None = None

    def __len__(self) -> int:
        return len(self.indices)

    def batches(self, what: str) -> Iterator[Batch]:
        """The held-out batches on the plan's device (a progress bar named ``what``)."""
        desc = f"{what} ({len(self.indices)} held-out images)" if self.plan.progress else None
        if self.kept is None:
            yield from self._score(desc)
            return
        device = self.plan.device
        for batch in progress(self.kept, desc):
            yield _moved(self._scores_of(batch), device)

    def close(self) -> None:
        """Remove the scores kept on disk, if any."""
        if self.spilled is not None:
            shutil.rmtree(self.spilled, ignore_errors=True)
            self.spilled = None

    def _score(self, desc: str | None) -> Iterator[Batch]:
        plan, kept, used = self.plan, [], 0
        entropy = None if self.entropy else 0
        with torch.inference_mode():
            for batch in batches(
                plan.source, self.dataset, self.indices, plan.batch_size, plan.device,
                plan.num_workers, desc, entropy,
            ):  # fmt: skip
                yield batch
                stored = _moved(batch, torch.device("cpu"))
                size = stored.scores.numel() * stored.scores.element_size()
                if used + size > MEMORY_BYTES:
                    stored.scores = self._spill(stored.scores, len(kept))
                else:
                    used += size
                kept.append(stored)
        self.kept = kept

    def _spill(self, scores: torch.Tensor, index: int) -> Path:
        if self.spilled is None:
            self.spilled = Path(tempfile.mkdtemp(prefix=".held_out-", dir=self.plan.output_dir))
            print(
                f"held-out images beyond {MEMORY_BYTES / 2**30:.0f} GiB of scores: kept as float16 "
                f"in {self.spilled} until the evaluation ends"
            )
        path = self.spilled / f"{index}.npy"
        np.save(path, scores.half().numpy())
        return path

    @staticmethod
    def _scores_of(batch: Batch) -> Batch:
        if isinstance(batch.scores, Path):
            return replace(batch, scores=torch.from_numpy(np.load(batch.scores)).float())
        return batch


def held_out_images(plan) -> tuple[HeldOut | None, HeldOut | None]:
    """The calibration images and the meta models' images of ``plan`` (the same object when
    they are the same images), each scored at its first use and kept for every shift."""
    calibration = None
    if plan.calibration is not None:
        shared = plan.meta_images is plan.calibration
        calibration = HeldOut(plan, *plan.calibration, entropy=shared)
    meta = calibration if plan.meta_images is plan.calibration else None
    if plan.meta_images is not None and meta is None:
        meta = HeldOut(plan, *plan.meta_images, entropy=True)
    return calibration, meta


def _moved(batch: Batch, device: torch.device) -> Batch:
    """``batch`` with every tensor on ``device``."""

    def move(t):
        return t.to(device) if isinstance(t, torch.Tensor) else t

    return Batch(
        move(batch.images), move(batch.labels), batch.stems, move(batch.scores),
        move(batch.instances), move(batch.expected_entropy), move(batch.anomalies),
    )  # fmt: skip
