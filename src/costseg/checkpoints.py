"""Finding, checking and loading checkpoints.

>>> find_checkpoint("no/such/file.ckpt")
Traceback (most recent call last):
...
FileNotFoundError: checkpoint not found: no/such/file.ckpt
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

RUNS_DIR = Path("runs")


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


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint's dictionary (memory-mapped, on the CPU); a clear error if unreadable."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    except Exception as err:  # torch raises several types for a truncated or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {err.__class__.__name__}") from err


def check_classes(path: str | Path, class_names: Sequence[str]) -> dict[str, Any]:
    """Raise ValueError unless the checkpoint was trained on exactly ``class_names``.

    Returns:
        the checkpoint's dictionary.
    """
    checkpoint = read_checkpoint(path)
    trained = checkpoint.get("costseg", {}).get("class_names")
    if trained is None:
        raise ValueError(f"{path} is not a costseg checkpoint (no class list in it)")
    if list(trained) != list(class_names):
        raise ValueError(
            f"checkpoint {path} was trained on {len(trained)} classes "
            f"({', '.join(trained[:3])}, ...), but {len(class_names)} classes are expected "
            f"({', '.join(class_names[:3])}, ...)"
        )
    return checkpoint
