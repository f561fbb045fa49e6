"""The class table of costseg.classes agrees with torchvision's copy of cityscapesScripts'."""

import numpy as np
from torchvision.datasets import Cityscapes

from costseg import classes


def test_class_table_matches_torchvision() -> None:
    train = sorted(
        (c for c in Cityscapes.classes if 0 <= c.train_id < 255), key=lambda c: c.train_id
    )
    assert tuple(c.name for c in train) == classes.CLASS_NAMES
    assert classes.PALETTE.tolist() == [list(c.color) for c in train]
    assert classes.TRAIN_ID_TO_LABEL_ID.tolist() == [c.id for c in train]
    assert {c.id % 256 for c in Cityscapes.classes} == classes.VALID_LABEL_IDS
    expected = np.full(256, classes.IGNORE_INDEX, dtype=np.uint8)
    for c in train:
        expected[c.id] = c.train_id
    assert np.array_equal(classes.LABEL_ID_TO_TRAIN_ID, expected)
