"""Pixel-wise class priors from training labels and the regions of interest (RoI) they define.

docs/definitions.md §3: per image location, the fraction of training labels holding each class
(label 255 is
counted in neither numerator nor denominator), Gaussian-smoothed, floored at ``eps`` and
renormalised to sum 1. As in the paper's authors' code, the per-class *counts* are smoothed
(σ = 80 px at Cityscapes' 1024 rows, so ``80 · H / 1024`` by default) and then divided by the
smoothed total, so locations that are often ignored weigh less; a location with no labelled
pixel within reach of the kernel gets the uniform distribution. The RoI map gives each location
the class among road, sidewalk, building and sky with the highest prior there.

:func:`costseg.data.priors_cache.cached_priors` computes priors once (for a network costseg
did not train) and reuses the file while its settings stay the same.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable, Mapping, Sequence, Sized
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter
from torch import Tensor

from costseg.atomic import AtomicFile
from costseg.checkpoints import read_torch_file
from costseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, ROI_CLASSES, class_indices
from costseg.progress import progress as progress_of

_FORMAT = "costseg-pixel-priors-v1"
_HANDFUL = 10  # no progress bar for a few labels (doctests, tests)

FEW_LABELS = 50
"""Priors counted on fewer labels than this get a note: the smoothed frequencies of a handful of
scenes are one street's layout, not a camera's (an ``ml`` mIoU of a few % follows)."""


def default_sigma(height: int) -> float:
    """The default smoothing in pixels for labels of ``height`` rows: ``80 · height / 1024``.

    >>> default_sigma(1024), default_sigma(128)
    (80.0, 10.0)
    """
    return 80.0 * height / 1024


def pixel_priors(
    labels: Iterable[Tensor],
    num_classes: int = NUM_CLASSES,
    sigma: float | None = None,
    eps: float = 1e-5,
    progress: bool = True,
    max_labels: int | None = None,
) -> Tensor:
    """Per-location class frequencies of a set of label maps (docs/definitions.md §3).

    Args:
        labels: Iterable of (H, W) integer label maps of one size; values in
            ``[0, num_classes)`` or 255 (ignored). Read one at a time (streamed).
        num_classes: Number of classes N.
        sigma: Standard deviation in pixels of the Gaussian smoothing of each class's counts;
            None means :func:`default_sigma` of H, 0 means no smoothing. Borders repeat the
            nearest value.
        eps: Floor applied before the final renormalisation, ``0 < eps < 1 / N``.
        progress: Show a tqdm bar when there are more than a handful of labels.
        max_labels: Use only the first ``max_labels`` labels (None = all).

    Returns:
        (N, H, W) float32 on the CPU; every location sums to 1 and is at least about ``eps``.

    >>> labels = [torch.tensor([[0, 255]]), torch.tensor([[1, 255]])]
    >>> pi = pixel_priors(labels, num_classes=2, sigma=0)
    >>> pi[:, 0, 0].tolist(), pi[:, 0, 1].tolist()
    ([0.5, 0.5], [0.5, 0.5])
    """
    return count_pixel_priors(labels, num_classes, sigma, eps, progress, max_labels)[0]


def normalise_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """A JSON round trip: tuples become lists and paths strings, so equal settings compare equal."""
    return json.loads(json.dumps(dict(settings), default=str, sort_keys=True))


def count_pixel_priors(
    labels: Iterable[Tensor],
    num_classes: int,
    sigma: float | None,
    eps: float,
    progress: bool,
    max_labels: int | None,
) -> tuple[Tensor, int, float]:
    """Priors, the number of labels counted and the σ used."""
    if num_classes < 1 or (sigma is not None and sigma < 0) or not 0 < eps < 1 / num_classes:
        raise ValueError(
            f"expected num_classes >= 1, sigma None or >= 0 and 0 < eps < 1/num_classes; got "
            f"num_classes={num_classes}, sigma={sigma}, eps={eps}"
        )
    if max_labels is not None and (not isinstance(max_labels, int) or max_labels < 1):
        raise ValueError(f"max_labels must be None or an integer >= 1; got {max_labels!r}")
    counts, count = _count(labels, num_classes, progress, max_labels)
    sigma = default_sigma(counts.shape[1]) if sigma is None else float(sigma)
    if sigma > 0:
        counts = torch.from_numpy(
            gaussian_filter(counts.numpy(), sigma=(0.0, sigma, sigma), mode="nearest")
        )
    total = counts.sum(dim=0, keepdim=True)  # exactly 0 beyond the kernel's reach (truncate 4σ)
    freq = torch.where(total > 0, counts / total.clamp(min=1e-300), 1.0 / num_classes)
    freq = freq.clamp(min=eps)
    return (freq / freq.sum(dim=0, keepdim=True)).float(), count, sigma


def _count(
    labels: Iterable[Tensor], num_classes: int, progress: bool, max_labels: int | None
) -> tuple[Tensor, int]:
    """(N, H, W) float64 count of each class per location (255 excluded), labels counted."""
    total = len(labels) if isinstance(labels, Sized) else None
    if max_labels is not None:
        total = max_labels if total is None else min(total, max_labels)
        labels = itertools.islice(labels, max_labels)
    show = progress and (total is None or total > _HANDFUL)
    bins = num_classes + 1  # the extra bin collects 255, so no masking is needed
    counts = position = ones = None
    size: tuple[int, ...] = ()
    for i, label in enumerate(progress_of(labels, "pixel priors" if show else None, total)):
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
    return per_location.permute(2, 0, 1).double().contiguous(), i + 1


def roi_map(pi: Tensor, class_names: Sequence[str] = CLASS_NAMES) -> Tensor:
    """Region of interest per location: the RoI class with the highest prior (docs/definitions.md
    §3).

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


GEOMETRIC_HORIZON = 0.45
"""Row of the geometric RoI map's horizon, as a fraction of the height (docs/definitions.md §3)."""


def geometric_roi_map(size: tuple[int, int]) -> Tensor:
    """The fixed RoI map of a forward-facing street camera, for data without training labels
    (docs/definitions.md §3): with u, v the pixel centre's column and row as fractions of the
    width and height and d = |u − 1/2|, below the horizon (v ≥ 0.45) the street is the wedge
    d ≤ 0.15 + 0.6 (v − 0.45) and the sidewalk the rest; above it the sky is v < 0.2 with
    d < 0.2, and the building is everything else.

    Args:
        size: (H, W) of the map.

    Returns:
        (H, W) int64 RoI ids as :func:`roi_map`'s.

    >>> for row in geometric_roi_map((5, 8)).tolist():
    ...     print(*row)
    3 3 4 4 4 4 3 3
    3 3 3 3 3 3 3 3
    2 2 2 1 1 2 2 2
    2 2 1 1 1 1 2 2
    2 1 1 1 1 1 1 2
    """
    h, w = size
    v = ((torch.arange(h, dtype=torch.float64) + 0.5) / h)[:, None]
    d = ((torch.arange(w, dtype=torch.float64) + 0.5) / w - 0.5).abs()[None, :]
    below = (v >= GEOMETRIC_HORIZON).expand(h, w)
    roi = torch.full((h, w), 3, dtype=torch.int64)
    roi[below] = 2
    roi[below & (d <= 0.15 + 0.6 * (v - GEOMETRIC_HORIZON))] = 1
    roi[(v < 0.2) & (d < 0.2)] = 4
    return roi


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


def save_priors(
    path: str | Path,
    pi: Tensor,
    class_names: Sequence[str] = CLASS_NAMES,
    settings: Mapping[str, Any] | None = None,
) -> None:
    """Write priors, their class names and optional settings to a ``.pt`` file atomically.

    ``settings`` (JSON-like: how the priors were made) are stored for :func:`cached_priors`.
    """
    payload = {
        "format": _FORMAT,
        "class_names": list(class_names),
        "priors": pi.float().cpu(),
        "settings": None if settings is None else normalise_settings(settings),
    }
    with AtomicFile(path) as tmp:
        torch.save(payload, tmp)


def check_priors(
    priors: Tensor, class_names: Sequence[str] = CLASS_NAMES, what: str = "priors"
) -> Tensor:
    """``priors`` if they are (N, H, W) priors of ``class_names``, finite and > 0 everywhere:
    rules divide by them (``ml``, the α sweep) and the RoI map compares them, so a NaN or a 0
    would decide pixels silently (docs/definitions.md §3).

    Args:
        priors: the tensor to check.
        class_names: the classes of its N channels.
        what: names the priors in the message (a file, ``the priors given to evaluate``).

    Raises:
        ValueError: one line naming ``what``, the shape expected, or how many values are not
            finite and > 0 and where the first is.

    >>> check_priors(torch.full((2, 1, 3), 0.5), ["a", "b"]).shape
    torch.Size([2, 1, 3])
    >>> check_priors(torch.tensor([[[0.5, float("nan")]], [[0.5, 0.5]]]), ["a", "b"])
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: priors hold 1 value that is not finite and > 0 (nan for class 'a' at row 0, ...
    """
    n = len(class_names)
    if not isinstance(priors, Tensor):
        raise ValueError(f"{what} must be a torch tensor ({n}, H, W), got {type(priors).__name__}")
    if priors.ndim != 3 or priors.shape[0] != n:
        raise ValueError(
            f"{what} must be ({n}, H, W) for the {n} classes, got shape {tuple(priors.shape)}"
        )
    bad = ~(torch.isfinite(priors) & (priors > 0))
    count = int(bad.sum())
    if count:
        k, y, x = (int(v) for v in bad.nonzero()[0])
        values = "value that is" if count == 1 else "values that are"
        raise ValueError(
            f"{what} hold {count} {values} not finite and > 0 ({priors[k, y, x].item()} for class "
            f"{class_names[k]!r} at row {y}, column {x}): rules divide by them and the RoI map "
            "compares them; count them again"
        )
    return priors


def check_priors_file(priors: str | None, class_names: Sequence[str] = CLASS_NAMES) -> None:
    """A ``--priors`` file, when given, that holds priors of ``class_names`` that
    :func:`check_priors` accepts (checked before anything heavy: one read of a small file).

    >>> check_priors_file(None)
    """
    if priors is not None:
        if not Path(priors).is_file():
            raise ValueError(f"--priors file not found: {priors}")
        read_priors_file(priors, class_names)


def read_priors_file(path: str | Path, class_names: Sequence[str]) -> dict[str, Any]:
    """The checked payload of a file written by :func:`save_priors`: ``"priors"`` (N, H, W)
    float32 (finite, > 0: :func:`check_priors`), ``"class_names"``, ``"settings"``.

    Raises:
        FileNotFoundError: No file at ``path``.
        ValueError: The file is not a priors file, its classes differ from ``class_names``, or
            its priors are not valid (one line naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"priors file '{path}' does not exist; create it with save_priors")
    expected = (
        "expected a pixel-priors .pt file (a run's priors.pt, scripts/count_priors.py's or "
        "scripts/export.py's)"
    )
    try:
        payload = read_torch_file(path)
    except ValueError as err:
        raise ValueError(f"{err}; {expected}") from None
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(f"'{path}' is not a pixel-priors file written by save_priors: {expected}")
    if list(payload["class_names"]) != list(class_names):
        raise ValueError(
            f"priors in '{path}' are for classes {payload['class_names']}; "
            f"expected {list(class_names)}"
        )
    check_priors(payload["priors"], class_names, f"the priors in '{path}'")
    return payload


def priors_note(
    num_labels: int | None, folder: str | Path | None = None, evaluated_labels: Iterable = ()
) -> str | None:
    """The one line that warns about priors counted on fewer than :data:`FEW_LABELS` labels, or
    on the labels of the evaluated images themselves; None when neither is known to hold.

    Args:
        num_labels: how many labels the priors were counted on (None: unknown).
        folder: the folder they were counted from (``scripts/count_priors.py`` records it).
        evaluated_labels: the label files of the evaluated images.

    >>> print(priors_note(6, "cs/gtFine/val", ["cs/gtFine/val/a/x_gtFine_labelIds.png"]))
    ... # doctest: +ELLIPSIS
    note: the priors were counted on 6 labels (fewer than 50) and on the evaluated images' ...
    >>> priors_note(2975, "cs/gtFine/train", ["cs/gtFine/val/a/x_gtFine_labelIds.png"]) is None
    True
    """
    reasons = []
    if isinstance(num_labels, int) and num_labels < FEW_LABELS:
        reasons.append(f"on {num_labels} labels (fewer than {FEW_LABELS})")
    if folder is not None:
        root = Path(folder).resolve()
        if any(root in Path(label).resolve().parents for label in evaluated_labels):
            reasons.append(f"on the evaluated images' own labels ({folder})")
    if not reasons:
        return None
    return (
        f"note: the priors were counted {' and '.join(reasons)}: their RoIs and the rules that "
        "divide by them (ml) follow those labels, not the scene; count them on a training "
        "split of 50 labels or more (scripts/count_priors.py)"
    )


def note_priors(description: dict[str, Any], priors_file: str | None, evaluated: object) -> None:
    """Print :func:`priors_note` of an evaluation's priors and add it to their record
    ``description["priors"]``: a ``--priors`` file's settings (its label count and folder), or
    the record of priors counted on the train split (its ``labels`` count); ``evaluated`` is the
    dataset of the evaluated images (its label files, ``files``, where it has them)."""
    record = description.get("priors")
    if priors_file is not None:
        settings = read_torch_file(priors_file, mmap=True).get("settings") or {}
        folder = settings.get("labels") if isinstance(settings.get("labels"), str) else None
        note = priors_note(settings.get("num_labels"), folder, _label_files(evaluated))
    elif isinstance(record, dict):
        note = priors_note(record.get("labels"))
    else:
        return
    if note is not None:
        print(note)
        if isinstance(record, dict):
            record["note"] = note


def _label_files(dataset: object) -> list[Path]:
    """The label files of a dataset that lists (image, label) paths as ``files``."""
    return [pair[1] for pair in getattr(dataset, "files", ())]
