"""Finding and reading checkpoints: the one reader of torch files (weights and plain data only,
``weights_only=True``) and the one check of a costseg checkpoint's classes.

>>> find_checkpoint("no/such/file.ckpt")
Traceback (most recent call last):
...
FileNotFoundError: checkpoint not found: no/such/file.ckpt
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

RUNS_DIR = Path("runs")
CHECKPOINT_KEY = "costseg"
"""The key of a costseg checkpoint's own entries: class names, priors, data configuration."""


def find_checkpoint(path: str | Path | None, runs_dir: Path = RUNS_DIR) -> Path:
    """The checkpoint at ``path``; ``None`` or ``"last"``: the newest ``last.ckpt`` under runs/.

    Raises:
        FileNotFoundError: no such file, or no checkpoint under ``runs_dir`` (says how to train).
    """
    if path is not None and str(path) != "last":
        if Path(path).is_dir():
            raise FileNotFoundError(f"checkpoint {path} is a directory; expected a .ckpt file")
        if not Path(path).is_file():
            raise FileNotFoundError(f"checkpoint not found: {path}")
        return Path(path)
    found = sorted(runs_dir.glob("**/last.ckpt"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise FileNotFoundError(
            f"no last.ckpt found under {runs_dir}/: train a model first with `python train.py` "
            "(or `make demo`), or pass --ckpt_path"
        )
    return found[-1]


def numpy_scalar_globals() -> list[Any]:
    """What a pickled numpy scalar needs (VainF stores ``best_score`` as one), under the module
    names of numpy 2 and of numpy 1 (which wrote most published checkpoints)."""
    core = getattr(np, "_core", None) or np.core
    scalar = core.multiarray.scalar
    dtypes = {type(np.dtype(code)) for code in "?bhilqBHILQefdg"}
    return [
        np.dtype,
        *dtypes,
        (scalar, "numpy.core.multiarray.scalar"),
        (scalar, "numpy._core.multiarray.scalar"),
    ]


def read_torch_file(path: str | Path, mmap: bool = False) -> Any:
    """``torch.load`` of weights and plain data only (``weights_only=True``), on the CPU: a file
    from someone else cannot run code. Numpy scalars are allowed too; ``mmap`` suits large
    zip-format files (a legacy file is read without it).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable, or holds other objects (one line naming the file).

    >>> read_torch_file("no/such.pth")
    Traceback (most recent call last):
    ...
    FileNotFoundError: file not found: no/such.pth
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"file not found: {path}")
    allow = getattr(torch.serialization, "safe_globals", None)  # torch >= 2.5
    try:
        if allow is None:
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
        with allow(numpy_scalar_globals()):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:
        # torch's message spans many lines and suggests weights_only=False: keep the cause.
        lines = str(err).partition("WeightsUnpickler error:")[2].strip().splitlines()
        cause = (lines or ["unreadable pickle"])[0].split(" was not an allowed global")[0]
        if "global" not in cause.lower() and "got <class" not in cause:
            raise ValueError(f"{path} is not a readable torch file: {cause}") from None
        raise ValueError(
            f"{path} holds objects other than weights and plain data ({cause})"
        ) from None
    except Exception as err:  # torch raises several types for a truncated or foreign file
        if mmap and "mmap can only be used" in str(err):  # a legacy or non-torch file
            return read_torch_file(path, mmap=False)
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"{path} is not a readable torch file: {first}") from None


def read_checkpoint(path: str | Path, class_names: Sequence[str]) -> dict[str, Any]:
    """A costseg checkpoint's dictionary (memory-mapped, on the CPU), trained on ``class_names``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable, not a costseg checkpoint, or trained on other classes.

    >>> read_checkpoint("runs/none/last.ckpt", ["road"])
    Traceback (most recent call last):
    ...
    FileNotFoundError: file not found: runs/none/last.ckpt
    """
    checkpoint = read_torch_file(path, mmap=True)
    extra = checkpoint.get(CHECKPOINT_KEY) if isinstance(checkpoint, dict) else None
    if not isinstance(extra, dict) or "state_dict" not in checkpoint:
        raise ValueError(f"{path} is not a costseg checkpoint (no {CHECKPOINT_KEY!r} and weights)")
    trained = extra.get("class_names")
    if trained is None:
        raise ValueError(f"{path} is not a costseg checkpoint (no class list in it)")
    if list(trained) != list(class_names):
        raise ValueError(
            f"checkpoint {path} was trained on {len(trained)} classes "
            f"({', '.join(trained[:3])}, ...), but {len(class_names)} classes are expected "
            f"({', '.join(class_names[:3])}, ...)"
        )
    return checkpoint
