"""CalibrationError: top-label and class-wise expected calibration error (docs/definitions.md §6),
the negative log-likelihood and the Brier score (§13).

The states are sums (per-bin pixel counts, sums of probabilities, counts of hits; the NLL's and
the Brier score's sums), so batches and processes merge exactly; the core is
:mod:`costseg.metrics.functional.calibration`.
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
    score_sums,
)
from costseg.metrics.shapes import KeepShapes


class CalibrationError(KeepShapes, Metric):
    """Expected calibration error over pixels, top-label or class-wise; NLL and Brier score.

    Top-label: ``ECE = Σ_b (n_b / n) |acc_b − conf_b|`` over the bins of ``max_k p_k``, and the
    same over the pixels predicted as each class (its "per_class" ECE, docs/definitions.md
    §13). Class-wise (``norm="class"``, §6): for each class k the same binned gap between
    ``p_k`` and the frequency of k among the pixels of the bin, then the mean over the N
    classes. NLL: the mean of ``−log p_y`` (p clamped at 1e-12); Brier: the mean of
    ``Σ_k (p_k − 1[k = y])²``, over the labelled pixels.

    States (all summed across batches and processes): ``count``, ``confidence`` and ``hits``,
    each (N, n_bins) (see :func:`~costseg.metrics.functional.calibration_bins`), ``pixels``,
    ``nll`` and ``brier``. ``compute()`` returns everything a reliability diagram needs (keys
    and shapes: :func:`~costseg.metrics.functional.calibration_error`) and "nll", "brier".

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
    >>> round(out["nll"].item(), 4), round(out["brier"].item(), 4)  # -log .9, -log .4; .02, .72
    (0.5108, 0.37)
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
        for name, dtype in zip(("count", "confidence", "hits"), BIN_DTYPES, strict=True):
            self.add_state(name, torch.zeros(num_classes, n_bins, dtype=dtype), "sum")
        self.add_state("pixels", torch.zeros((), dtype=torch.long), "sum")
        for name in ("nll", "brier"):
            self.add_state(name, torch.zeros((), dtype=torch.float64), "sum")

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
        pixels, nll, brier = score_sums(probs, target, self.ignore_index)
        self.pixels += pixels
        self.nll += nll
        self.brier += brier

    def compute(self) -> dict[str, Tensor]:
        """ECE, per-bin numbers, NLL and Brier score of everything seen so far (NaN without
        pixels)."""
        out = calibration_error(self.count, self.confidence, self.hits, self.norm)
        return out | {"nll": self.nll / self.pixels, "brier": self.brier / self.pixels}
