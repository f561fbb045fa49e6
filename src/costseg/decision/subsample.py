"""A fixed, seeded share of each image's labelled pixels, for a search that scores many matrices
(:func:`~.counts.count_decisions`) and can afford fewer pixels per matrix; a certificate always
tests on every pixel."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from costseg.classes import IGNORE_INDEX


class Subsample(NamedTuple):
    """S pixels of each image, as (B, ·, 1, S) images: the share of its labelled pixels, then
    padding labelled ``ignore_index`` (counted nowhere) up to the longest image's.

    Attributes:
        probs: (B, N, 1, S); labels: (B, 1, S); roi: None or (B, 1, S); priors: None, (N,), or
            (B, N, 1, S) (each image's own, from pixel-wise priors).
    """

    probs: torch.Tensor
    labels: torch.Tensor
    roi: torch.Tensor | None
    priors: torch.Tensor | None


def subsample(
    probs: torch.Tensor,
    labels: torch.Tensor,
    roi: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    share: float = 0.1,
    seed: int | Sequence[int] = 0,
    ignore_index: int = IGNORE_INDEX,
) -> Subsample:
    """``ceil(share · L)`` of the L labelled pixels of each image, drawn at random without
    replacement (the same for the same seed and labels), kept in their image order.

    Args:
        probs: (B, N, H, W); labels: (B, H, W); roi: None, (H, W) or (B, H, W);
        priors: None, (N,) or (N, H, W) (as in :func:`~.counts.prepare_counts`).
        share: the share of each image's labelled pixels kept, in (0, 1].
        seed: the draw's seed (the images drawn in turn), or one seed per image (each image's
            draw then does not depend on the batch it comes in).
        ignore_index: the label of unlabelled pixels.

    Returns:
        :class:`Subsample`, ready for :func:`~.counts.prepare_counts`.

    >>> labels = torch.tensor([[[0, 1, 255, 2]]])
    >>> part = subsample(torch.rand(1, 3, 1, 4), labels, share=0.5)
    >>> part.labels.shape, sorted(part.labels.flatten().tolist()) in ([0, 1], [0, 2], [1, 2])
    (torch.Size([1, 1, 2]), True)
    """
    if not 0 < share <= 1:
        raise ValueError(f"share must lie in (0, 1], got {share}")
    b, _, h, w = probs.shape
    if labels.shape != (b, h, w):
        raise ValueError(f"labels must be ({b}, {h}, {w}), got {tuple(labels.shape)}")
    seeds = [seed] * b if isinstance(seed, int) else list(seed)
    if len(seeds) != b:
        raise ValueError(f"seed must be one number or one per image ({b}), got {len(seeds)}")
    gen = torch.Generator().manual_seed(seeds[0])
    picks = []
    for i, image in enumerate(labels.reshape(b, -1).cpu()):
        if not isinstance(seed, int):
            gen.manual_seed(seeds[i])
        labelled = (image != ignore_index).nonzero()[:, 0]
        keep = math.ceil(share * len(labelled))
        picks.append(labelled[torch.randperm(len(labelled), generator=gen)[:keep]].sort().values)
    size = max(len(p) for p in picks)
    index = torch.zeros(b, size, dtype=torch.long)
    padded = torch.ones(b, size, dtype=torch.bool)
    for i, p in enumerate(picks):
        index[i, : len(p)], padded[i, : len(p)] = p, False

    def take(values: torch.Tensor) -> torch.Tensor:  # (B, C, H, W) → (B, C, 1, S)
        where = index.to(values.device).view(b, 1, size).expand(-1, values.shape[1], -1)
        return values.reshape(*values.shape[:2], -1).gather(2, where).unsqueeze(2)

    kept = take(labels.view(b, 1, h, w))[:, 0]
    kept.masked_fill_(padded.to(labels.device)[:, None], ignore_index)
    region = None if roi is None else take(roi.expand(b, h, w).reshape(b, 1, h, w))[:, 0]
    if priors is not None and torch.as_tensor(priors).ndim > 1:
        priors = take(torch.as_tensor(priors).to(probs.device).expand(b, -1, -1, -1))
    return Subsample(take(probs), kept, region, priors)
