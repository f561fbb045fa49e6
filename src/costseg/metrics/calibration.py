"""CalibrationError: top-label and class-wise expected calibration error (docs/definitions.md §6).

The states are per-bin sums (pixel counts, sums of probabilities, counts of hits), so batches and
processes merge exactly; the core is :mod:`costseg.metrics.functional.calibration`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from costseg.classes import IGNORE_INDEX, NUM_CLASSES
from costseg.metrics.functional.calibration import (
    BIN_DTYPES,
    Norm,
    calibration_bins,
    calibration_error,
)
from costseg.metrics.shapes import KeepShapes


class CalibrationError(KeepShapes, Metric):
    """Expected calibration error over pixels, top-label or class-wise.

    Top-label: ``ECE = Σ_b (n_b / n) |acc_b − conf_b|`` over the bins of ``max_k p_k``.
    Class-wise: for each class k the same binned gap between ``p_k`` and the frequency of k
    among the pixels of the bin, then the mean over the N classes.

    States (all summed across batches and processes): ``count``, ``confidence`` and ``hits``,
    each (R, n_bins), R = 1 for ``"top"`` and N for ``"class"`` (see
    :func:`~costseg.metrics.functional.calibration_bins`). ``compute()`` returns everything a
    reliability diagram needs (keys and shapes:
    :func:`~costseg.metrics.functional.calibration_error`).

    Args:
        num_classes: N.
        n_bins: Number of equal-width bins over [0, 1].
        norm: ``"top"`` (top-label ECE) or ``"class"`` (class-wise ECE).
        ignore_index: Target value that counts nowhere.
        kwargs: torchmetrics' options of every ``Metric`` (e.g. ``sync_on_compute``).

    >>> m = CalibrationError(num_classes=2, n_bins=2)
    >>> m.update(torch.tensor([[[[0.9]], [[0.1]]]]), torch.tensor([[[0]]]))
    >>> m.update(torch.tensor([[[[0.6, 0.2]], [[0.4, 0.8]]]]), torch.tensor([[[1, 255]]]))
    >>> out = m.compute()      # bin 1 holds 0.9 (hit) and 0.6 (miss): |1/2 - 3/4|
    >>> round(out["ece"].item(), 6), out["count"].tolist(), out["accuracy"].tolist()
    (0.25, [0, 2], [nan, 0.5])
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        n_bins: int = 15,
        norm: Norm = "top",
        ignore_index: int = IGNORE_INDEX,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if not isinstance(num_classes, int) or not isinstance(n_bins, int):
            raise ValueError(
                f"num_classes and n_bins must be integers; got {num_classes!r}, {n_bins!r}"
            )
        if num_classes < 1 or n_bins < 1 or norm not in ("top", "class"):
            raise ValueError(
                "expected num_classes >= 1, n_bins >= 1 and norm 'top' or 'class'; got "
                f"{num_classes}, {n_bins}, {norm!r}"
            )
        self.num_classes, self.n_bins, self.norm = num_classes, n_bins, norm
        self.ignore_index = ignore_index
        shape = (1 if norm == "top" else num_classes, n_bins)
        for name, dtype in zip(("count", "confidence", "hits"), BIN_DTYPES, strict=True):
            self.add_state(name, torch.zeros(shape, dtype=dtype), dist_reduce_fx="sum")

    def update(self, probs: Tensor, target: Tensor) -> None:
        """Add a batch: probs (B, N, H, W) probabilities, target (B, H, W) labels."""
        if probs.ndim < 2 or probs.shape[1] != self.num_classes:
            raise ValueError(
                f"expected probs with {self.num_classes} classes in dimension 1; got "
                f"{tuple(probs.shape)}"
            )
        count, confidence, hits = calibration_bins(
            probs, target, self.n_bins, self.norm, self.ignore_index
        )
        self.count += count
        self.confidence += confidence
        self.hits += hits

    def compute(self) -> dict[str, Tensor]:
        """ECE and per-bin numbers of everything seen so far."""
        return calibration_error(self.count, self.confidence, self.hits, self.norm)
