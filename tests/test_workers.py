"""costseg.workers: worker processes come from the forkserver, and every wait on a worker ends."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from costseg import workers
from costseg.workers import Stalled, loader_errors, loader_options, within


class SlowItems(Dataset):
    """Items that take ``seconds`` each, and say which process made them and its parent."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def __len__(self) -> int:
        return 2

    def __getitem__(self, i: int):
        time.sleep(self.seconds)
        return torch.tensor([os.getpid(), os.getppid()])


def test_data_loader_workers_are_forked_by_the_forkserver_not_by_this_process():
    pid, parent = next(iter(DataLoader(SlowItems(0), batch_size=None, **loader_options(1))))
    assert pid != os.getpid() and parent != os.getpid()
    command = Path(f"/proc/{int(parent)}/cmdline").read_bytes().replace(b"\0", b" ")
    assert b"forkserver" in command


def test_a_batch_that_never_comes_is_one_stalled_error(monkeypatch):
    monkeypatch.setattr(workers, "STALL_SECONDS", 1.0)
    loader = DataLoader(SlowItems(60), batch_size=None, **loader_options(1))
    start = time.monotonic()
    timed_out = r"^DataLoader timed out after 1.0 seconds while loading x$"
    with pytest.raises(Stalled, match=timed_out), loader_errors("x"):
        next(iter(loader))
    assert time.monotonic() - start < 30


def test_other_errors_pass_through_loader_errors():
    with pytest.raises(RuntimeError, match=r"^other$"), loader_errors("x"):
        raise RuntimeError("other")


def test_within_returns_raises_or_gives_up(monkeypatch):
    assert within(lambda: 3, "three") == 3
    with pytest.raises(KeyError):
        within(lambda: {}["k"], "a lookup")
    monkeypatch.setattr(workers, "STALL_SECONDS", 0.2)
    with pytest.raises(Stalled, match=r"^a sleep did not finish within 0 s$"):
        within(lambda: time.sleep(5), "a sleep")
