"""Side outputs of training as Lightning callbacks; the LightningModule only trains and validates.

>>> ValidationMasks(num_images=2).num_images
2
"""

from __future__ import annotations

from typing import Any

import lightning as L
from torch import Tensor

from costseg.report.tensorboard import log_masks


class ValidationMasks(L.Callback):
    """Log the first validation batch's images, ground truth and each rule's mask to TensorBoard.

    Args:
        num_images: images of the first validation batch to log (0 = none).
    """

    def __init__(self, num_images: int = 2) -> None:
        if num_images < 0:
            raise ValueError(f"num_images must be >= 0, got {num_images}")
        self.num_images = num_images

    def on_validation_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: tuple[Tensor, Tensor],
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        writer = getattr(trainer.logger, "experiment", None)
        if batch_idx != 0 or not self.num_images or not hasattr(writer, "add_image"):
            return
        if not trainer.is_global_zero or not isinstance(outputs, dict) or "preds" not in outputs:
            return
        images, labels = batch
        names = outputs["names"]
        for i in range(min(self.num_images, len(images))):
            log_masks(
                writer,
                f"val/masks/{i}",
                images[i].permute(1, 2, 0).cpu().numpy(),
                labels[i].cpu().numpy(),
                {n: outputs["preds"][i, k].cpu().numpy() for k, n in enumerate(names)},
                step=trainer.global_step,
            )
