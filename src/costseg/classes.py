"""The 19 Cityscapes train classes, their colours and the label-id ↔ train-id tables.

Everything is read from torchvision's ``Cityscapes.classes`` so that nothing is retyped.

>>> NUM_CLASSES, CLASS_NAMES[11], class_index("person")
(19, 'person', 11)
>>> int(LABEL_ID_TO_TRAIN_ID[7]), int(LABEL_ID_TO_TRAIN_ID[0])   # road, unlabeled
(0, 255)
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from torchvision.datasets import Cityscapes

IGNORE_INDEX = 255

_TRAIN = sorted(
    (c for c in Cityscapes.classes if 0 <= c.train_id < IGNORE_INDEX), key=lambda c: c.train_id
)
CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in _TRAIN)
NUM_CLASSES = len(CLASS_NAMES)
PALETTE = np.array([c.color for c in _TRAIN], dtype=np.uint8)
"""(19, 3) uint8 RGB colour of each train id (Cityscapes' palette)."""


def _label_to_train_table() -> np.ndarray:
    # Label ids are stored as uint8 in the PNGs; license plate's id -1 reads as 255.
    table = np.full(256, IGNORE_INDEX, dtype=np.uint8)
    for c in Cityscapes.classes:
        if 0 <= c.train_id < IGNORE_INDEX:
            table[c.id % 256] = c.train_id
    return table


LABEL_ID_TO_TRAIN_ID = _label_to_train_table()
"""(256,) uint8 lookup: Cityscapes label id → train id (255 for void and ignored classes)."""

VALID_LABEL_IDS = frozenset(c.id % 256 for c in Cityscapes.classes)
"""Label ids that may occur in a ``*_gtFine_labelIds.png`` (license plate's -1 as 255)."""

TRAIN_ID_TO_LABEL_ID = np.array([c.id for c in _TRAIN], dtype=np.uint8)
"""(19,) uint8: train id → Cityscapes label id, for files the official evaluator reads."""

ROI_NAMES: tuple[str, ...] = ("image", "street", "sidewalk", "building", "sky")
"""Names of the RoI ids 0 (whole image) … 4 (SPEC §3)."""


def class_index(name: str, names: Sequence[str] = CLASS_NAMES) -> int:
    """Index of a class name, or a ValueError that lists the valid names.

    >>> class_index("traffic sign")
    7
    """
    try:
        return list(names).index(name)
    except ValueError:
        raise ValueError(f"unknown class {name!r}; expected one of: {', '.join(names)}") from None


def class_indices(names: Iterable[str], classes: Sequence[str] = CLASS_NAMES) -> list[int]:
    """Indices of several class names (see :func:`class_index`)."""
    return [class_index(n, classes) for n in names]


def colorize(labels: np.ndarray) -> np.ndarray:
    """(H, W) train ids → (H, W, 3) uint8 RGB in Cityscapes' palette; 255 is black.

    >>> colorize(np.array([[0, 255]])).tolist()
    [[[128, 64, 128], [0, 0, 0]]]
    """
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[:NUM_CLASSES] = PALETTE
    return lut[np.asarray(labels, dtype=np.int64).clip(0, 255)]
