"""Per-image losses of a guarantee's target (docs/definitions.md §7): 1 − recall, 1 − precision
and the segment error rates, from counts, NaN where undefined (what
:func:`~costseg.calibration.guarantee.learn_then_test` certifies).
"""

from __future__ import annotations

import torch
from numpy.typing import ArrayLike
from torch import Tensor


def _ratio(part: ArrayLike | Tensor, whole: ArrayLike | Tensor, names: str) -> Tensor:
    """part / whole in float64, NaN where whole = 0, after checking 0 ≤ part ≤ whole."""
    part, whole = torch.as_tensor(part).double(), torch.as_tensor(whole).double()
    if part.shape != whole.shape:
        raise ValueError(f"{names}: expected equal shapes; got {part.shape} and {whole.shape}")
    if bool((part < 0).any() | (part > whole).any()):
        raise ValueError(f"{names}: expected 0 <= numerator <= denominator counts")
    return torch.where(whole > 0, part / whole.clamp(min=1e-300), torch.nan)


def recall_loss(tp: ArrayLike | Tensor, fn: ArrayLike | Tensor) -> Tensor:
    """Per-image ``1 − recall = FN / (TP + FN)``; NaN where the image has no such pixel.

    Args:
        tp, fn: Pixel counts of one shape, e.g. (n_images, L) for one class in one RoI.

    Returns:
        float64 losses, the same shape.

    >>> recall_loss(torch.tensor([[3, 0], [0, 0]]), torch.tensor([[1, 2], [0, 4]])).tolist()
    [[0.25, 1.0], [nan, 1.0]]
    """
    tp, fn = torch.as_tensor(tp), torch.as_tensor(fn)
    return _ratio(fn, tp + fn, "recall_loss(tp, fn)")


def precision_loss(tp: ArrayLike | Tensor, fp: ArrayLike | Tensor) -> Tensor:
    """Per-image ``1 − precision = FP / (TP + FP)``; NaN where nothing was predicted.

    >>> precision_loss(torch.tensor([1, 0]), torch.tensor([3, 0])).tolist()
    [0.75, nan]
    """
    tp, fp = torch.as_tensor(tp), torch.as_tensor(fp)
    return _ratio(fp, tp + fp, "precision_loss(tp, fp)")


def fn_segment_rate(fn: ArrayLike | Tensor, n_gt: ArrayLike | Tensor) -> Tensor:
    """Per-image rate of false-negative segments ``fn / n_gt``; NaN where ``n_gt = 0``.

    >>> fn_segment_rate(torch.tensor([1, 0]), torch.tensor([4, 0])).tolist()
    [0.25, nan]
    """
    return _ratio(fn, n_gt, "fn_segment_rate(fn, n_gt)")


def fp_segment_rate(fp: ArrayLike | Tensor, n_pred: ArrayLike | Tensor) -> Tensor:
    """Per-image rate of false-positive segments ``fp / n_pred``; NaN where ``n_pred = 0``.

    >>> fp_segment_rate(torch.tensor([[2, 0]]), torch.tensor([[2, 0]])).tolist()
    [[1.0, nan]]
    """
    return _ratio(fp, n_pred, "fp_segment_rate(fp, n_pred)")
