"""Pixel-wise class priors from training labels and the regions of interest (RoI) they define.

SPEC §3: per image location, the fraction of training labels holding each class (label 255 is
counted in neither numerator nor denominator; a location never labelled gets the uniform
distribution), optionally Gaussian-smoothed, floored at ``eps`` and renormalised to sum 1.
The RoI map gives each location the class among road, sidewalk, building and sky with the
highest prior there.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Sequence, Sized
from pathlib import Path

import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter
from torch import Tensor
from tqdm.auto import tqdm

from costseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, class_indices

ROI_CLASSES = ("road", "sidewalk", "building", "sky")
"""The class that defines RoI id 1, 2, 3, 4."""
_FORMAT = "costseg-pixel-priors-v1"
_HANDFUL = 10  # no progress bar for a few labels (doctests, tests)


def pixel_priors(
    labels: Iterable[Tensor],
    num_classes: int = NUM_CLASSES,
    sigma: float = 0.0,
    eps: float = 1e-5,
    progress: bool = True,
) -> Tensor:
    """Per-location class frequencies of a set of label maps (SPEC §3).

    Args:
        labels: Iterable of (H, W) integer label maps of one size; values in
            ``[0, num_classes)`` or 255 (ignored).
        num_classes: Number of classes N.
        sigma: Standard deviation in pixels of the Gaussian smoothing of each class map
            (0 = none); borders repeat the nearest value.
        eps: Floor applied before the final renormalisation, ``0 < eps < 1 / N``.
        progress: Show a tqdm bar when there are more than a handful of labels.

    Returns:
        (N, H, W) float32 on the CPU; every location sums to 1 and is at least about ``eps``.

    >>> pi = pixel_priors([torch.tensor([[0, 255]]), torch.tensor([[1, 255]])], num_classes=2)
    >>> pi[:, 0, 0].tolist(), pi[:, 0, 1].tolist()
    ([0.5, 0.5], [0.5, 0.5])
    """
    if num_classes < 1 or sigma < 0 or not 0 < eps < 1 / num_classes:
        raise ValueError(
            f"expected num_classes >= 1, sigma >= 0 and 0 < eps < 1/num_classes; got "
            f"num_classes={num_classes}, sigma={sigma}, eps={eps}"
        )
    counts = _count(labels, num_classes, progress)
    total = counts.sum(dim=0, keepdim=True)
    freq = torch.where(total > 0, counts / total.clamp(min=1), 1.0 / num_classes)
    if sigma > 0:
        smoothed = gaussian_filter(freq.numpy(), sigma=(0.0, sigma, sigma), mode="nearest")
        freq = torch.from_numpy(smoothed)
    freq = freq.clamp(min=eps)
    return (freq / freq.sum(dim=0, keepdim=True)).float()


def _count(labels: Iterable[Tensor], num_classes: int, progress: bool) -> Tensor:
    """(N, H, W) float32 count of each class per location, 255 excluded."""
    total = len(labels) if isinstance(labels, Sized) else None
    show = progress and (total is None or total > _HANDFUL)
    bins = num_classes + 1  # the extra bin collects 255, so no masking is needed
    counts = position = ones = None
    size: tuple[int, ...] = ()
    for i, label in enumerate(tqdm(labels, total=total, desc="pixel priors", disable=not show)):
        label = torch.as_tensor(label)
        if counts is None:
            size = tuple(label.shape)
            if label.ndim != 2 or label.dtype.is_floating_point or label.dtype == torch.bool:
                raise ValueError(f"labels must be (H, W) integer maps; got {label.dtype} {size}")
            counts = torch.zeros(size[0] * size[1] * bins, dtype=torch.int32)
            position = torch.arange(size[0] * size[1]) * bins
            ones = torch.ones(size[0] * size[1], dtype=torch.int32)
        if tuple(label.shape) != size:
            raise ValueError(
                f"all labels must share one size; label {i} is {tuple(label.shape)}, "
                f"label 0 is {size}"
            )
        flat = label.reshape(-1).long().cpu()
        if bool(((flat < 0) | ((flat >= num_classes) & (flat != IGNORE_INDEX))).any()):
            bad = sorted(set(flat.unique().tolist()) - {*range(num_classes), IGNORE_INDEX})
            raise ValueError(f"label {i} holds values {bad}; expected 0..{num_classes - 1} or 255")
        # (location, class) order keeps the scattered additions close together in memory.
        counts.index_add_(0, position + flat.clamp(max=num_classes), ones)
    if counts is None:
        raise ValueError("pixel_priors needs at least one label map; got none")
    per_location = counts.view(size[0], size[1], bins)[..., :num_classes]
    return per_location.permute(2, 0, 1).float().contiguous()


def roi_map(pi: Tensor, class_names: Sequence[str] = CLASS_NAMES) -> Tensor:
    """Region of interest per location: the RoI class with the highest prior (SPEC §3).

    Args:
        pi: (N, H, W) priors, N = ``len(class_names)``.
        class_names: Class name per channel; must include road, sidewalk, building and sky.

    Returns:
        (H, W) int64 RoI ids: 1 street (road), 2 sidewalk, 3 building, 4 sky (see
        ``costseg.classes.ROI_NAMES``); ties go to the lower id.

    >>> pi = torch.zeros(19, 1, 3)
    >>> pi[10, 0, 0], pi[0, 0, 1], pi[1, 0, 2] = 1, 1, 1    # sky, road, sidewalk
    >>> roi_map(pi).tolist()
    [[4, 1, 2]]
    """
    if pi.ndim != 3 or pi.shape[0] != len(class_names):
        raise ValueError(
            f"priors must be (N, H, W) with N = {len(class_names)} classes; got {tuple(pi.shape)}"
        )
    roi = pi[class_indices(ROI_CLASSES, class_names)]
    return roi.argmax(dim=0) + 1


def resize_priors(pi: Tensor, size: tuple[int, int]) -> Tensor:
    """Priors at another resolution: bilinear (antialiased) resize, renormalised per location.

    Args:
        pi: (N, H, W) priors.
        size: Target (h, w).

    Returns:
        (N, h, w) float32 priors that sum to 1 per location.

    >>> pi = torch.tensor([[[1.0, 0.0]], [[0.0, 1.0]]])
    >>> resize_priors(pi, (1, 4))[0].tolist()   # class 0; class 1 is 1 minus this
    [[1.0, 0.75, 0.25, 0.0]]
    """
    if tuple(pi.shape[-2:]) == tuple(size):
        return pi.float()
    resized = F.interpolate(
        pi[None].float(), size=tuple(size), mode="bilinear", align_corners=False, antialias=True
    )[0]
    return resized / resized.sum(dim=0, keepdim=True)


def save_priors(path: str | Path, pi: Tensor, class_names: Sequence[str] = CLASS_NAMES) -> None:
    """Write priors and their class names to a ``.pt`` file atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": _FORMAT, "class_names": list(class_names), "priors": pi.float().cpu()}
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as tmp:
        torch.save(payload, tmp)
    os.replace(tmp.name, path)


def load_priors(path: str | Path, class_names: Sequence[str] = CLASS_NAMES) -> Tensor:
    """Read priors written by :func:`save_priors`, checking they belong to ``class_names``.

    Returns:
        (N, H, W) float32 priors.

    Raises:
        FileNotFoundError: No file at ``path``.
        ValueError: The file is not a priors file, or its classes differ from ``class_names``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"priors file '{path}' does not exist; create it with save_priors")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load raises many types for a foreign or truncated file
        raise ValueError(f"cannot read priors file '{path}': {type(err).__name__}") from None
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(f"'{path}' is not a pixel-priors file written by save_priors")
    if list(payload["class_names"]) != list(class_names):
        raise ValueError(
            f"priors in '{path}' are for classes {payload['class_names']}; "
            f"expected {list(class_names)}"
        )
    return payload["priors"]
