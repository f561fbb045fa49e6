"""SumMetric: the base of costseg's metrics, whose states are sums.

Every state is a tensor that batches and processes add up, so a metric is the same in one
batch, many batches or across processes. This is the part of ``torchmetrics.Metric`` that these
metrics use (``add_state(..., dist_reduce_fx="sum")``, ``update`` / ``compute`` / ``reset``,
``merge_state``, calling the metric on a batch), kept here because importing torchmetrics takes
seconds: it imports all its metrics, and with them transformers, torchvision and matplotlib.

>>> class Count(SumMetric):
...     def __init__(self):
...         super().__init__()
...         self.add_state("n", torch.zeros((), dtype=torch.long))
...     def update(self, x):
...         self.n += len(x)
...     def _compute(self):
...         return self.n
>>> m = Count()
>>> m.update([1, 2]); m(torch.zeros(3)).item(), m.compute().item()   # batch value, then total
(3, 5)
"""

from __future__ import annotations

from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn


class SumMetric(nn.Module):
    """A metric whose states are summed over batches and over the processes of a group.

    Subclasses register their states with :meth:`add_state` and implement ``update(...)``
    (add a batch to the states) and ``_compute()`` (the result from the states). The states are
    non-persistent buffers: they follow ``.to(device)`` and stay out of checkpoints.
    """

    def __init__(self) -> None:
        super().__init__()
        self._defaults: dict[str, Tensor] = {}

    def add_state(self, name: str, default: Tensor) -> None:
        """Register the state ``name``, starting at (and reset to) ``default``."""
        self._defaults[name] = default.detach().clone()
        self.register_buffer(name, default.detach().clone(), persistent=False)

    @property
    def device(self) -> torch.device:
        """Where the states are."""
        return getattr(self, next(iter(self._defaults))).device

    def update(self, *args: Any, **kwargs: Any) -> None:
        raise NotImplementedError

    def _compute(self) -> Any:
        raise NotImplementedError

    def compute(self) -> Any:
        """The result of everything seen so far: with an initialised process group, of every
        process's batches (the states are summed for this; each process keeps its own)."""
        if not (dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return self._compute()
        local = self._states()
        for name, value in local.items():
            total = value.clone()
            dist.all_reduce(total)
            setattr(self, name, total)
        try:
            return self._compute()
        finally:
            for name, value in local.items():
                setattr(self, name, value)

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        """Add a batch (as ``update``) and return the result of that batch alone."""
        totals = self._states()
        self.reset()
        self.update(*args, **kwargs)
        batch = self._compute()
        for name, total in totals.items():
            setattr(self, name, total + getattr(self, name))
        return batch

    def reset(self) -> None:
        """Back to the default states."""
        device = self.device
        for name, default in self._defaults.items():
            setattr(self, name, default.to(device, copy=True))

    def merge_state(self, other: SumMetric) -> None:
        """Add the states of ``other`` (a metric of the same settings) to these."""
        for name in self._defaults:
            setattr(self, name, getattr(self, name) + getattr(other, name).to(self.device))

    def _states(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in self._defaults}
