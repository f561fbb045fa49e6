"""Results with the shapes their docstrings give: torchmetrics squeezes every one-element tensor
of ``compute()``'s result to 0-d (a (K,) mIoU of one rule would lose its rule axis); the
:class:`KeepShapes` mixin gives each tensor back the shape ``compute`` made.

>>> import torch
>>> from torchmetrics import Metric
>>> class Count(KeepShapes, Metric):
...     def __init__(self):
...         super().__init__()
...         self.add_state("n", torch.zeros(1, dtype=torch.long), dist_reduce_fx="sum")
...     def update(self, x):
...         self.n += len(x)
...     def compute(self):
...         return {"n": self.n}
>>> m = Count()
>>> m.update([1, 2]); m.compute()["n"].shape
torch.Size([1])
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from torch import Tensor


class KeepShapes:
    """Mixin before :class:`torchmetrics.Metric` for a metric whose ``compute`` returns a dict of
    tensors: the shapes of ``compute``'s own result are kept (also in ``forward``)."""

    def _wrap_compute(self, compute: Callable) -> Callable:
        shapes: dict[str, tuple[int, ...]] = {}

        @functools.wraps(compute)
        def recorded(*args: Any, **kwargs: Any) -> Any:
            out = compute(*args, **kwargs)
            shapes.clear()
            shapes.update({k: v.shape for k, v in out.items() if isinstance(v, Tensor)})
            return out

        wrapped = super()._wrap_compute(recorded)  # type: ignore[misc]

        @functools.wraps(compute)
        def restored(*args: Any, **kwargs: Any) -> Any:
            out = wrapped(*args, **kwargs)
            return {k: v.reshape(shapes[k]) if k in shapes else v for k, v in out.items()}

        return restored
