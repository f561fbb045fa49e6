"""A dataset that says which process read each item, for the loader tests. A module of its own:
a DataLoader worker imports it to unpickle the dataset, and it imports nothing but torch."""

from __future__ import annotations

import os

import torch
from torch.utils.data import Dataset


class PidItems(Dataset):
    """``length`` items (the id of the process that read it, the index): who loads what."""

    def __init__(self, length: int) -> None:
        self.length = length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.tensor(os.getpid()), torch.tensor(index)
