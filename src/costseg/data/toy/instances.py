"""Instance ids of the procedural street scenes, in Cityscapes' ``gtFine_instanceIds`` encoding.

Every object of an instance class (person, rider, car, truck, bus, train, motorcycle, bicycle)
gets ``label_id · 1000 + k``, k counting that class's objects of the scene from 0; every other
pixel holds its plain label id (< 1000: stuff, or an instance class drawn outside an object, as
Cityscapes' crowd regions), and ignored pixels 0 ("unlabeled"). Definitions:
``docs/definitions.md §9``.

The layer is drawn alongside the label canvas with the same shapes, so ``label_id(id // 1000)``
(or the id itself below 1000) is the pixel's label wherever both are drawn.

>>> from PIL import Image
>>> layer = InstanceLayer(Image.new("I", (4, 2), 0))
>>> layer.begin_object(); layer.value(11), layer.value(18), layer.value(0)   # person, bicycle
(24000, 33000, 7)
>>> layer.begin_object(); layer.value(11), layer.value(255)
(24001, 0)
"""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from costseg.classes import IGNORE_INDEX, INSTANCE_CLASSES, INSTANCE_OFFSET, TRAIN_ID_TO_LABEL_ID


class InstanceLayer:
    """A 32-bit instance-id canvas and the counter of each class's objects.

    Args:
        image: a mode ``"I"`` image of the scene's size, drawn in place.
    """

    def __init__(self, image: Image.Image) -> None:
        self.image, self.draw = image, ImageDraw.Draw(image)
        self.object = 0  # serial of the object being drawn; 0 = none (stuff)
        self._ids: dict[tuple[int, int], int] = {}
        self._count = dict.fromkeys(INSTANCE_CLASSES, 0)

    def begin_object(self) -> None:
        """Start a new object: its pixels of each instance class form one new instance."""
        self.object += 1

    def value(self, cls: int) -> int:
        """The id to paint for train id ``cls`` in the current object."""
        if cls == IGNORE_INDEX:
            return 0
        label_id = int(TRAIN_ID_TO_LABEL_ID[cls])
        if cls not in self._count or self.object == 0:
            return label_id
        key = (self.object, cls)
        if key not in self._ids:
            self._ids[key] = label_id * INSTANCE_OFFSET + self._count[cls]
            self._count[cls] += 1
        return self._ids[key]

    def array(self) -> np.ndarray:
        """(H, W) int32 instance ids."""
        return np.asarray(self.image, dtype=np.int32)
