"""CalibrationError: top-label and class-wise expected calibration error (SPEC §6).

Bins: ``n_bins`` equal-width bins over [0, 1]; bin b holds ``b / n_bins <= p < (b + 1) / n_bins``
and a probability of exactly 1 goes into the last bin. (torchmetrics' calibration error gives
p = 1 an extra bin of its own; here the 15 bins of the SPEC are kept, so on data with confidences
of exactly 1 the two differ slightly.) Pixels whose target is ``ignore_index`` count nowhere.

The states are per-bin sums (pixel counts, sums of probabilities, counts of hits), so batches and
processes merge exactly; the ECE and the reliability-diagram numbers are derived in ``compute``.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES
from costseg.metrics.base import SumMetric

Norm = Literal["top", "class"]
_DTYPES = (torch.long, torch.float64, torch.long)  # count, confidence, hits: ints stay exact


def _bin(values: Tensor, n_bins: int) -> Tensor:
    """Bin index of each probability; edges b / n_bins computed in float64 (1.0 → last bin)."""
    edges = torch.arange(n_bins + 1, dtype=torch.float64, device=values.device) / n_bins
    index = torch.bucketize(values.double(), edges, right=True) - 1
    return index.clamp(0, n_bins - 1)


def calibration_bins(
    probs: Tensor,
    target: Tensor,
    n_bins: int = 15,
    norm: Norm = "top",
    ignore_index: int = IGNORE_INDEX,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-bin sums of one batch, the state of :class:`CalibrationError`.

    Top-label: each labelled pixel falls in the bin of ``max_k p_k``; a hit is ``argmax p ==
    target`` (ties: lowest class). Class-wise: for each class k, each labelled pixel falls in the
    bin of ``p_k``; a hit is ``target == k``.

    Args:
        probs: (B, N, H, W) probabilities (or (P, N)).
        target: (B, H, W) labels in ``[0, N)`` or ``ignore_index`` (or (P,)).
        n_bins: Number of equal-width bins.
        norm: ``"top"`` or ``"class"``.
        ignore_index: Label of pixels that count nowhere.

    Returns:
        count (R, n_bins) int64 pixels, confidence (R, n_bins) float64 sums of the binned
        probability, hits (R, n_bins) int64; R = 1 for ``"top"``, N for ``"class"``.

    >>> count, conf, hits = calibration_bins(torch.tensor([[0.9, 0.1], [0.6, 0.4]]),
    ...                                      torch.tensor([0, 1]), n_bins=2)
    >>> count.tolist(), conf.tolist(), hits.tolist()
    ([[0, 2]], [[0.0, 1.5]], [[0, 1]])
    """
    if probs.ndim != target.ndim + 1 or (probs.shape[0], *probs.shape[2:]) != target.shape:
        raise ValueError(
            "expected probs (B, N, H, W) with target (B, H, W), or probs (P, N) with target "
            f"(P,); got {tuple(probs.shape)} and {tuple(target.shape)}"
        )
    n = probs.shape[1]
    keep = target != ignore_index
    p, y = probs.movedim(1, -1)[keep], target[keep].long()
    if bool(((y < 0) | (y >= n)).any()):
        bad = sorted(set(y[(y < 0) | (y >= n)].unique().tolist()))
        raise ValueError(f"target holds {bad}; expected 0..{n - 1} or {ignore_index}")
    if norm == "top":
        confidence, predicted = p.max(dim=1)
        bins = _bin(confidence, n_bins)
        hits = torch.bincount(bins[predicted == y], minlength=n_bins)
        sums = torch.bincount(bins, weights=confidence.double(), minlength=n_bins)
        return torch.bincount(bins, minlength=n_bins)[None], sums[None], hits[None]
    # One class at a time: memory stays at a few (P,) tensors even at full resolution.
    out = [torch.zeros(n, n_bins, dtype=dtype, device=p.device) for dtype in _DTYPES]
    for k in range(n):
        bins = _bin(p[:, k], n_bins)
        out[0][k] = torch.bincount(bins, minlength=n_bins)
        out[1][k] = torch.bincount(bins, weights=p[:, k].double(), minlength=n_bins)
        out[2][k] = torch.bincount(bins[y == k], minlength=n_bins)
    return out[0], out[1], out[2]


class CalibrationError(SumMetric):
    """Expected calibration error over pixels, top-label or class-wise (SPEC §6).

    Top-label: ``ECE = Σ_b (n_b / n) |acc_b − conf_b|`` over the bins of ``max_k p_k``.
    Class-wise: for each class k the same binned gap between ``p_k`` and the frequency of k
    among the pixels of the bin, then the mean over the N classes.

    States (all summed across batches and processes): ``count``, ``confidence`` and ``hits``,
    each (R, n_bins), R = 1 for ``"top"`` and N for ``"class"`` (see :func:`calibration_bins`).

    ``compute()`` returns a dict, everything a reliability diagram needs:

    * ``"ece"``: () float64, NaN when no pixel was counted;
    * ``"per_class"``: (N,) float64 ECE of each class (``"class"`` only);
    * ``"count"``: (n_bins,) int64 pixels per bin (``"class"``: (N, n_bins));
    * ``"confidence"``: mean probability per bin, NaN for an empty bin (same shape);
    * ``"accuracy"``: per bin, the fraction of hits (top-label: argmax correct; class-wise:
      target is k), NaN for an empty bin (same shape);
    * ``"edges"``: (n_bins + 1,) float64 bin edges.

    Args:
        num_classes: N.
        n_bins: Number of equal-width bins over [0, 1].
        norm: ``"top"`` (top-label ECE) or ``"class"`` (class-wise ECE).
        ignore_index: Target value that counts nowhere.

    >>> m = CalibrationError(num_classes=2, n_bins=2)
    >>> m.update(torch.tensor([[[[0.9]], [[0.1]]]]), torch.tensor([[[0]]]))
    >>> m.update(torch.tensor([[[[0.6, 0.2]], [[0.4, 0.8]]]]), torch.tensor([[[1, 255]]]))
    >>> out = m.compute()      # bin 1 holds 0.9 (hit) and 0.6 (miss): |1/2 - 3/4|
    >>> round(out["ece"].item(), 6), out["count"].tolist(), out["accuracy"].tolist()
    (0.25, [0, 2], [nan, 0.5])
    """

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        n_bins: int = 15,
        norm: Norm = "top",
        ignore_index: int = IGNORE_INDEX,
    ) -> None:
        super().__init__()
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
        for name, dtype in zip(("count", "confidence", "hits"), _DTYPES, strict=True):
            self.add_state(name, torch.zeros(shape, dtype=dtype))

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

    def _compute(self) -> dict[str, Tensor]:
        """ECE and per-bin numbers (keys and shapes in the class docstring)."""
        count = self.count.double()
        pixels = count.sum(dim=1)  # (R,): every row counts every labelled pixel once
        gap = (self.hits - self.confidence).abs().sum(dim=1) / pixels
        out = {
            "ece": gap.mean() if self.norm == "class" else gap[0],
            "count": self.count,
            "confidence": self.confidence / count,
            "accuracy": self.hits / count,
            "edges": torch.arange(self.n_bins + 1, dtype=torch.float64, device=count.device)
            / self.n_bins,
        }
        if self.norm == "class":
            out["per_class"] = gap
        else:
            out |= {key: out[key][0] for key in ("count", "confidence", "accuracy")}
        return out
