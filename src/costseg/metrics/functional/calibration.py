"""Expected calibration error over pixels, top-label or class-wise (docs/definitions.md §6), and
the negative log-likelihood and Brier score (§13).

Bins: ``n_bins`` equal-width bins over [0, 1]; bin b holds ``b / n_bins <= p < (b + 1) / n_bins``
and a probability of exactly 1 goes into the last bin. (torchmetrics' calibration error gives
p = 1 an extra bin of its own; here the 15 bins of the definitions are kept, so on data with
confidences of exactly 1 the two differ slightly.) Pixels whose target is ``ignore_index`` count
nowhere. :func:`calibration_bins` gives the per-bin sums of a batch (the states of
:class:`~costseg.metrics.CalibrationError`), :func:`calibration_error` the ECE from them;
:func:`score_sums` the sums of the NLL and the Brier score.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX

Norm = Literal["top", "class"]
BIN_DTYPES = (torch.long, torch.float64, torch.long)  # count, confidence, hits: ints stay exact
NLL_FLOOR = 1e-12  # p_y is clamped here before the log: a confidently wrong pixel costs 27.6


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

    Top-label: each labelled pixel falls in the bin of ``max_k p_k`` in the row of its predicted
    class ``argmax p`` (ties: lowest class); a hit is ``argmax p == target``. The rows sum to the
    top-label bins; each row alone gives that class's ECE (docs/definitions.md §13). Class-wise:
    for each class k, each labelled pixel falls in the bin of ``p_k``; a hit is ``target == k``.

    Args:
        probs: (B, N, H, W) probabilities (or (P, N)).
        target: (B, H, W) labels in ``[0, N)`` or ``ignore_index`` (or (P,)).
        n_bins: Number of equal-width bins.
        norm: ``"top"`` or ``"class"``.
        ignore_index: Label of pixels that count nowhere.

    Returns:
        count (N, n_bins) int64 pixels, confidence (N, n_bins) float64 sums of the binned
        probability, hits (N, n_bins) int64; row k: the pixels predicted as k (``"top"``), or
        class k's probability (``"class"``).

    >>> count, conf, hits = calibration_bins(torch.tensor([[0.9, 0.1], [0.6, 0.4]]),
    ...                                      torch.tensor([0, 1]), n_bins=2)
    >>> count.tolist(), conf.tolist(), hits.tolist()
    ([[0, 2], [0, 0]], [[0.0, 1.5], [0.0, 0.0]], [[0, 1], [0, 0]])
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
        bins = _bin(confidence, n_bins) + predicted * n_bins  # (class, bin) as one index
        size, shape = n * n_bins, (n, n_bins)
        hits = torch.bincount(bins[predicted == y], minlength=size).view(shape)
        sums = torch.bincount(bins, weights=confidence.double(), minlength=size).view(shape)
        return torch.bincount(bins, minlength=size).view(shape), sums, hits
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
    """ECE and per-bin numbers from the (N, n_bins) sums of :func:`calibration_bins`.

    Returns:
        "ece" () float64, NaN when no pixel was counted; "per_class" (N,) the ECE of each
        class (``"top"``: of the pixels predicted as the class, docs/definitions.md §13; NaN
        for a class never predicted); "classwise_ece" () their mean over the classes that
        have one; "count", "confidence" (mean probability per bin) and "accuracy" (fraction of
        hits per bin; NaN for an empty bin), (n_bins,) for ``"top"`` and (N, n_bins) for
        ``"class"``; "edges" (n_bins + 1,).

    >>> out = calibration_error(*calibration_bins(torch.tensor([[0.9, 0.1], [0.6, 0.4]]),
    ...                                           torch.tensor([0, 1]), n_bins=2), norm="top")
    >>> out["ece"].item(), out["accuracy"].tolist(), out["per_class"].tolist()
    (0.25, [nan, 0.5], [0.25, nan])
    """
    n_bins = count.shape[-1]
    per_class = (hits - confidence).abs().sum(dim=1) / count.sum(dim=1)
    if norm == "top":
        count, confidence, hits = count.sum(0), confidence.sum(0), hits.sum(0)
        ece = (hits - confidence).abs().sum() / count.sum()
    else:
        ece = per_class.mean()
    total = count.double()
    return {
        "ece": ece,
        "per_class": per_class,
        "classwise_ece": per_class.nanmean(),
        "count": count,
        "confidence": confidence / total,
        "accuracy": hits / total,
        "edges": torch.arange(n_bins + 1, dtype=torch.float64, device=count.device) / n_bins,
    }


def score_sums(
    probs: Tensor, target: Tensor, ignore_index: int = IGNORE_INDEX
) -> tuple[Tensor, Tensor, Tensor]:
    """The labelled pixels' count and float64 sums of ``−log max(p_y, 1e-12)`` (NLL) and
    ``Σ_k (p_k − 1[k = y])²`` (Brier score) of one batch (docs/definitions.md §13).

    Args:
        probs, target, ignore_index: as in :func:`calibration_bins` (target checked there).

    >>> pixels, nll, brier = score_sums(torch.tensor([[[[0.5]], [[0.5]]]]), torch.tensor([[[1]]]))
    >>> pixels.item(), round(nll.item(), 4), brier.item()
    (1, 0.6931, 0.5)
    """
    keep = target != ignore_index
    p = probs.movedim(1, -1)[keep].float()  # per pixel in float32, summed in float64
    p_true = p.gather(1, target[keep].long()[:, None])[:, 0]
    nll = -p_true.clamp(min=NLL_FLOOR).log().sum(dtype=torch.float64)
    brier = ((p * p).sum(1) - 2 * p_true + 1).sum(dtype=torch.float64)
    return keep.sum(), nll, brier
