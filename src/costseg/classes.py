"""The 19 Cityscapes train classes, their colours and the label-id ↔ train-id tables.

The table is cityscapesScripts' ``labels.py`` (also torchvision's ``Cityscapes.classes``; a test
checks that they agree), kept here so that the classes load without importing torchvision.

>>> NUM_CLASSES, CLASS_NAMES[11], class_index("person")
(19, 'person', 11)
>>> ROI_NAMES[1], ROI_CLASSES[0], ROI_IDS["roi2"], NUM_ROIS
('street', 'road', 2, 4)
>>> int(LABEL_ID_TO_TRAIN_ID[7]), int(LABEL_ID_TO_TRAIN_ID[0])   # road, unlabeled
(0, 255)
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

IGNORE_INDEX = 255

# (name, label id, RGB colour) of each train class, in train-id order.
_TRAIN: tuple[tuple[str, int, tuple[int, int, int]], ...] = (
    ("road", 7, (128, 64, 128)),
    ("sidewalk", 8, (244, 35, 232)),
    ("building", 11, (70, 70, 70)),
    ("wall", 12, (102, 102, 156)),
    ("fence", 13, (190, 153, 153)),
    ("pole", 17, (153, 153, 153)),
    ("traffic light", 19, (250, 170, 30)),
    ("traffic sign", 20, (220, 220, 0)),
    ("vegetation", 21, (107, 142, 35)),
    ("terrain", 22, (152, 251, 152)),
    ("sky", 23, (70, 130, 180)),
    ("person", 24, (220, 20, 60)),
    ("rider", 25, (255, 0, 0)),
    ("car", 26, (0, 0, 142)),
    ("truck", 27, (0, 0, 70)),
    ("bus", 28, (0, 60, 100)),
    ("train", 31, (0, 80, 100)),
    ("motorcycle", 32, (0, 0, 230)),
    ("bicycle", 33, (119, 11, 32)),
)
CLASS_NAMES: tuple[str, ...] = tuple(name for name, _, _ in _TRAIN)
NUM_CLASSES = len(CLASS_NAMES)
PALETTE = np.array([color for _, _, color in _TRAIN], dtype=np.uint8)
"""(19, 3) uint8 RGB colour of each train id (Cityscapes' palette)."""

VALID_LABEL_IDS = frozenset(range(34)) | {255}
"""Label ids that may occur in a ``*_gtFine_labelIds.png``: 0 (unlabeled) … 33 (bicycle), and
license plate's id -1, which reads as 255 from the uint8 PNGs."""

TRAIN_ID_TO_LABEL_ID = np.array([label_id for _, label_id, _ in _TRAIN], dtype=np.uint8)
"""(19,) uint8: train id → Cityscapes label id, for files the official evaluator reads."""

LABEL_ID_TO_TRAIN_ID = np.full(256, IGNORE_INDEX, dtype=np.uint8)
"""(256,) uint8 lookup: Cityscapes label id → train id (255 for void and ignored classes)."""
LABEL_ID_TO_TRAIN_ID[TRAIN_ID_TO_LABEL_ID] = np.arange(NUM_CLASSES)

# (name, class whose pixel-wise prior decides the region) of each RoI id (docs/definitions.md §3).
_ROIS: tuple[tuple[str, str | None], ...] = (
    ("image", None),  # id 0: the whole image
    ("street", "road"),
    ("sidewalk", "sidewalk"),
    ("building", "building"),
    ("sky", "sky"),
)
ROI_NAMES: tuple[str, ...] = tuple(name for name, _ in _ROIS)
"""Names of the RoI ids 0 (whole image) … 4."""
NUM_ROIS = len(ROI_NAMES) - 1
"""R, the number of regions of interest (id 0, the whole image, is none of them)."""
ROI_CLASSES: tuple[str, ...] = tuple(cls for _, cls in _ROIS[1:] if cls)
"""The class of each RoI id 1 … R: a location belongs to the RoI whose class has the highest
prior there."""


def roi_label(roi: int) -> str:
    """How figures and tables name RoI id ``roi``.

    >>> roi_label(1), roi_label(0)
    ('RoI 1 (street)', 'RoI 0 (image)')
    """
    return f"RoI {roi} ({ROI_NAMES[roi]})"


ROI_IDS: dict[str, int] = {f"roi{i}": i for i in range(len(ROI_NAMES))}
ROI_IDS |= {name: i for i, name in enumerate(ROI_NAMES)}
"""How a RoI may be written (``roi1`` or ``street``) → its id."""

INSTANCE_CLASS_NAMES = ("person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle")
"""Classes whose objects are instances (Cityscapes' ``hasInstances``; definitions.md §9)."""
INSTANCE_CLASSES = tuple(CLASS_NAMES.index(n) for n in INSTANCE_CLASS_NAMES)
"""Train ids of :data:`INSTANCE_CLASS_NAMES`."""
INSTANCE_OFFSET = 1000
"""Instance ids are ``label_id · INSTANCE_OFFSET + k``; smaller values hold no instance."""


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


DEFERRED_COLOUR = (255, 255, 255)
"""RGB of a deferred pixel in a decision's colour map (white: no class of the palette is)."""


def colorize(labels: np.ndarray, deferred: bool = False) -> np.ndarray:
    """(H, W) train ids → (H, W, 3) uint8 RGB in Cityscapes' palette; 255 is black (ignored),
    or :data:`DEFERRED_COLOUR` when ``deferred`` (a decision's 255 is a deferred pixel).

    >>> colorize(np.array([[0, 255]])).tolist()
    [[[128, 64, 128], [0, 0, 0]]]
    >>> colorize(np.array([[255]]), deferred=True).tolist()
    [[[255, 255, 255]]]
    """
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[:NUM_CLASSES] = PALETTE
    if deferred:
        lut[255] = DEFERRED_COLOUR
    return lut[np.asarray(labels, dtype=np.int64).clip(0, 255)]


def label_ids(train_ids: np.ndarray) -> np.ndarray:
    """Train ids → uint8 Cityscapes label ids, for files the official evaluator reads; 255 (an
    ignored pixel, or a decision's deferred pixel) stays 255.

    >>> label_ids(np.array([[0, 11, 255]])).tolist()
    [[7, 24, 255]]
    """
    lut = np.full(256, 255, dtype=np.uint8)
    lut[:NUM_CLASSES] = TRAIN_ID_TO_LABEL_ID
    return lut[np.asarray(train_ids, dtype=np.int64).clip(0, 255)]
