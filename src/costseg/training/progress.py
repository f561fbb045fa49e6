"""Training progress counted in steps, visible on a terminal and in a log file alike.

Lightning's bars count epochs ("Epoch 0/-2" when only ``max_steps`` is set) and print nothing
useful when the output is not a terminal; :class:`StepProgress` counts optimiser steps towards
``max_steps`` with :class:`costseg.progress.Progress` (a bar, or a line every few percent).
"""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.callbacks import ProgressBar

from costseg.progress import Progress


class StepProgress(ProgressBar):
    """Steps of training towards ``max_steps``; validation says when it runs.

    Args:
        every: percent between two lines when the output is not a terminal.
    """

    def __init__(self, every: float = 5) -> None:
        super().__init__()
        self.every, self.enabled, self.bar = every, True, None

    def disable(self) -> None:
        self.enabled = False

    def enable(self) -> None:
        self.enabled = True

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.enabled and trainer.is_global_zero:
            total = trainer.max_steps if trainer.max_steps > 0 else None
            self.bar = Progress(total, "train", trainer.global_step, self.every)

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        if self.bar is not None:
            self.bar.update_to(trainer.global_step, self._metrics(trainer, pl_module))

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None and not trainer.sanity_checking and self.bar.bar is None:
            print(f"validation at step {trainer.global_step}", file=self.bar.file, flush=True)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None and not trainer.sanity_checking:
            metrics = self._metrics(trainer, pl_module)
            if self.bar.bar is not None:
                self.bar.bar.set_postfix(metrics)
            else:
                shown = ", ".join(f"{k} {v:.4g}" for k, v in metrics.items() if "val" in k)
                print(f"validation: {shown}", file=self.bar.file, flush=True)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def _metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, Any]:
        metrics = self.get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)
        return {k: float(v) for k, v in metrics.items() if isinstance(v, int | float)}
