"""The processes of one evaluation under ``torchrun``: which one this is, and the only
collectives the analyses use to bring their shares together (docs/design.md, Reliability).

Each process sees its share of the reported images (every ``world_size``-th, from its rank) and
all held-out images. torchmetrics states sum themselves across processes; what an analysis keeps
per image it hands to :func:`in_image_order`, and other counts to :func:`summed`, in its
:meth:`~costseg.evaluation.analyses.Analysis.gather`. One process: both return their input.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from typing import TypeVar

import torch
import torch.distributed as dist

T = TypeVar("T")


def distributed() -> bool:
    """Whether this process is one of several (a process group is up)."""
    return dist.is_available() and dist.is_initialized()


def rank() -> int:
    return dist.get_rank() if distributed() else 0


def world_size() -> int:
    if distributed():
        return dist.get_world_size()
    return int(os.environ.get("WORLD_SIZE", "1"))


def on_rank0(make: Callable[[], T]) -> T:
    """``make()`` on rank 0, its value shared with every process (e.g. the output folder)."""
    value = [make() if rank() == 0 else None]
    if distributed():
        dist.broadcast_object_list(value, src=0)
    return value[0]


@contextlib.contextmanager
def rank0_prints() -> Iterator[None]:
    """What is printed inside, printed once: by rank 0 (the others' stdout goes nowhere)."""
    if rank() == 0:
        yield
        return
    with open(os.devnull, "w") as nowhere, contextlib.redirect_stdout(nowhere):
        yield


def share(count: int) -> list[int]:
    """The positions among ``count`` reported images that this process sees.

    >>> share(5)
    [0, 1, 2, 3, 4]
    """
    return list(range(count))[rank() :: world_size()]


def in_image_order(records: list[tuple[int, T]]) -> list[T]:
    """Every process's ``(position, record)`` pairs, as the records in the order of the
    positions: what one process, seeing every image, would have kept.

    >>> in_image_order([(2, "c"), (0, "a")])
    ['a', 'c']
    """
    if distributed():
        parts: list = [None] * dist.get_world_size()
        dist.all_gather_object(parts, records)
        records = [r for part in parts for r in part]
    return [record for _, record in sorted(records, key=lambda r: r[0])]


def barrier() -> None:
    """Wait until every process comes here (one process: return)."""
    if distributed():
        dist.barrier()


def summed(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` summed over every process (a new tensor; an integer sum is exact)."""
    total = tensor.clone()
    if distributed():
        dist.all_reduce(total)
    return total
