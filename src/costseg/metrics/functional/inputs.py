"""Checks of the label maps every metric takes: integer (B, [K,] H, W) maps and RoI ids."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


def is_integer(t: Tensor) -> bool:
    """Whether ``t`` holds integers (not floats, complex numbers or bools)."""
    return not (t.is_floating_point() or t.is_complex() or t.dtype == torch.bool)


def describe(x: Any) -> str:
    """``dtype tensor of shape (…)`` for a tensor, ``repr`` for anything else (error messages)."""
    return f"{x.dtype} tensor of shape {tuple(x.shape)}" if isinstance(x, Tensor) else repr(x)


def check_batch(preds: Tensor, target: Tensor, roi: Tensor | None, num_rois: int) -> None:
    """Raise ValueError unless preds (B, [K,] H, W), target (B, H, W), roi (H, W)/(B, H, W) fit.

    >>> check_batch(torch.zeros(1, 2, 2).long(), torch.zeros(1, 2, 2).long(), None, 4)
    >>> check_batch(torch.zeros(1, 2, 2), torch.zeros(1, 2, 2).long(), None, 4)
    Traceback (most recent call last):
    ...
    ValueError: expected preds as an integer (B, H, W) or (B, K, H, W) tensor, got torch.float32 tensor of shape (1, 2, 2)
    """  # noqa: E501
    if not isinstance(preds, Tensor) or not is_integer(preds) or preds.ndim not in (3, 4):
        raise ValueError(
            f"expected preds as an integer (B, H, W) or (B, K, H, W) tensor, got {describe(preds)}"
        )
    expected = (preds.shape[0], *preds.shape[-2:])
    if not isinstance(target, Tensor) or not is_integer(target) or tuple(target.shape) != expected:
        raise ValueError(f"expected target as an integer {expected} tensor, got {describe(target)}")
    if roi is None:
        return
    if (
        not isinstance(roi, Tensor)
        or not is_integer(roi)
        or roi.shape not in (expected, expected[1:])
    ):
        raise ValueError(
            f"expected roi as an integer {expected} or {expected[1:]} tensor, got {describe(roi)}"
        )
    lo, hi = (int(v) for v in torch.aminmax(roi)) if roi.numel() else (0, 0)
    if lo < 0 or hi > num_rois:
        raise ValueError(f"expected roi ids in 0..{num_rois}, got values in {lo}..{hi}")


def as_rules(preds: Tensor, num_rules: int) -> Tensor:
    """(B, K, H, W) view of preds; (B, H, W) is accepted when ``num_rules == 1``.

    >>> as_rules(torch.zeros(2, 3, 4).long(), 1).shape
    torch.Size([2, 1, 3, 4])
    """
    if isinstance(preds, Tensor) and preds.ndim == 3 and num_rules == 1:
        return preds.unsqueeze(1)
    if isinstance(preds, Tensor) and preds.ndim == 4 and preds.shape[1] == num_rules:
        return preds
    alternative = " or (B, H, W)" if num_rules == 1 else ""
    raise ValueError(
        f"expected preds of shape (B, {num_rules}, H, W){alternative}, got {describe(preds)}"
    )
