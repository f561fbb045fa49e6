"""The TensorBoard logger of a training run: only cards that say something.

Lightning's ``TensorBoardLogger`` adds an ``hp_metric`` card (a placeholder value) and, with every
logged value, an ``epoch`` card (a constant when a run trains by steps); this one writes neither.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from lightning.pytorch.loggers import TensorBoardLogger


class RunLogger(TensorBoardLogger):
    """``TensorBoardLogger`` without the ``hp_metric`` and ``epoch`` cards (same arguments)."""

    def __init__(
        self,
        save_dir: str,
        name: str | None = "lightning_logs",
        default_hp_metric: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(save_dir, name, default_hp_metric=default_hp_metric, **kwargs)

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        super().log_metrics({k: v for k, v in metrics.items() if k != "epoch"}, step)
