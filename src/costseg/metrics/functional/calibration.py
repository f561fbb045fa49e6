"""Expected calibration error over pixels, top-label or class-wise (docs/definitions.md §6).

Bins: ``n_bins`` equal-width bins over [0, 1]; bin b holds ``b / n_bins <= p < (b + 1) / n_bins``
and a probability of exactly 1 goes into the last bin. (torchmetrics' calibration error gives
p = 1 an extra bin of its own; here the 15 bins of the definitions are kept, so on data with
confidences of exactly 1 the two differ slightly.) Pixels whose target is ``ignore_index`` count
nowhere. :func:`calibration_bins` gives the per-bin sums of a batch (the states of
:class:`~costseg.metrics.CalibrationError`), :func:`calibration_error` the ECE from them.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX

Norm = Literal["top", "class"]
BIN_DTYPES = (torch.long, torch.float64, torch.long)  # count, confidence, hits: ints stay exact


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
    out = [torch.zeros(n, n_bins, dtype=dtype, device=p.device) for dtype in BIN_DTYPES]
    for k in range(n):
        bins = _bin(p[:, k], n_bins)
        out[0][k] = torch.bincount(bins, minlength=n_bins)
        out[1][k] = torch.bincount(bins, weights=p[:, k].double(), minlength=n_bins)
        out[2][k] = torch.bincount(bins[y == k], minlength=n_bins)
    return out[0], out[1], out[2]


def calibration_error(
    count: Tensor, confidence: Tensor, hits: Tensor, norm: Norm
) -> dict[str, Tensor]:
    """ECE and per-bin numbers from the (R, n_bins) sums of :func:`calibration_bins`.

    Returns:
        "ece" () float64, NaN when no pixel was counted; "count", "confidence" (mean probability
        per bin) and "accuracy" (fraction of hits per bin; NaN for an empty bin), (n_bins,) for
        ``"top"`` and (N, n_bins) for ``"class"``; "edges" (n_bins + 1,); for ``"class"`` also
        "per_class" (N,), the ECE of each class.

    >>> out = calibration_error(*calibration_bins(torch.tensor([[0.9, 0.1], [0.6, 0.4]]),
    ...                                           torch.tensor([0, 1]), n_bins=2), norm="top")
    >>> out["ece"].item(), out["accuracy"].tolist()
    (0.25, [nan, 0.5])
    """
    n_bins = count.shape[-1]
    total = count.double()
    pixels = total.sum(dim=1)  # (R,): every row counts every labelled pixel once
    gap = (hits - confidence).abs().sum(dim=1) / pixels
    out = {
        "ece": gap.mean() if norm == "class" else gap[0],
        "count": count,
        "confidence": confidence / total,
        "accuracy": hits / total,
        "edges": torch.arange(n_bins + 1, dtype=torch.float64, device=count.device) / n_bins,
    }
    if norm == "class":
        out["per_class"] = gap
    else:
        out |= {key: out[key][0] for key in ("count", "confidence", "accuracy")}
    return out
