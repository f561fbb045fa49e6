"""Precomputed probabilities (docs/definitions.md §8), so that networks of any framework can be
evaluated.

One file per image, named after the image (``<city>_<seq>_<frame>.npz`` or ``.pt``, directly in
the folder or in a ``<city>/`` subfolder), holding ``probs`` or ``logits`` of shape (N, H, W) at
the label resolution, in any floating dtype (float16 halves the size). A ``.npz`` file is
written by ``numpy.savez(path, probs=array)``, a ``.pt`` file by
``torch.save({"probs": tensor}, path)``. The files ``--save-probs`` writes also hold the
uncertainty maps (``entropy``, and ``mutual_information`` with several runs; (H, W) float16,
docs/definitions.md §13), which loading leaves aside.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from costseg.atomic import AtomicFile
from costseg.checkpoints import read_torch_file
from costseg.classes import CLASS_NAMES, NUM_CLASSES

__all__ = [
    "DATA_RECORD",
    "PROBS_SUFFIXES",
    "find_probs_file",
    "load_probs",
    "read_data_record",
    "records_its_data",
    "save_data_record",
    "save_probs",
]

DATA_RECORD = "dataset.json"
"""The file of a ``--save-probs`` folder that names the data its images came from."""
_PRIORS = "priors.pt"

PROBS_SUFFIXES = (".npz", ".pt")
_KEYS = ("probs", "logits")
_SUM_TOLERANCE = 1e-2  # float16 rounding moves a sum of probabilities by < 1e-3


def save_probs(
    path: str | Path,
    probs: Tensor,
    compress: bool = False,
    maps: Mapping[str, Tensor] | None = None,
) -> Path:
    """Write (N, H, W) probabilities as float16 ``probs``, atomically (temp file + rename).

    Args:
        path: the file to write, ending in ``.npz`` or ``.pt``.
        probs: (N, H, W) floating probabilities, on any device.
        compress: zip-compress a ``.npz`` file (smaller, several times slower to write).
        maps: (H, W) maps saved beside them as float16 under their names (the uncertainty maps
            ``entropy`` and ``mutual_information``, docs/definitions.md §13); reading a file
            reads ``probs`` only.

    Returns:
        ``path``.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     path = save_probs(f"{tmp}/lindau_000000_000019.npz", torch.full((19, 4, 6), 1 / 19))
        ...     load_probs(path, size=(4, 6)).shape
        torch.Size([19, 4, 6])
    """
    path = Path(path)
    if path.suffix not in PROBS_SUFFIXES:
        raise ValueError(f"probability files end in .npz or .pt; got {path}")
    if probs.ndim != 3 or not probs.is_floating_point():
        dtype = str(probs.dtype).removeprefix("torch.")
        raise ValueError(
            f"expected (N, H, W) floating probabilities; got {tuple(probs.shape)} {dtype}"
        )
    arrays = {"probs": probs, **(maps or {})}
    if "logits" in arrays:
        raise ValueError("'logits' cannot be saved beside 'probs'")
    half = {k: v.detach().to("cpu", torch.float16) for k, v in arrays.items()}
    with AtomicFile(path) as tmp, open(tmp, "wb") as f:
        if path.suffix == ".pt":
            torch.save(half, f)
        else:  # a file object: numpy would add ".npz" to a name
            save = np.savez_compressed if compress else np.savez
            save(f, **{k: v.numpy() for k, v in half.items()})
    return path


def find_probs_file(folder: str | Path, stem: str) -> Path:
    """The file holding image ``stem``'s probabilities: ``folder/[city/]stem.{npz,pt}``.

    Raises:
        FileNotFoundError: no such file (names the image).
        ValueError: more than one candidate.

    >>> find_probs_file(".", "aachen_000000_000019")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    FileNotFoundError: no probabilities for image aachen_000000_000019 in . (expected ...)
    """
    folder = Path(folder)
    city = stem.split("_")[0]
    found = [
        d / f"{stem}{suffix}"
        for d in (folder, folder / city)
        for suffix in PROBS_SUFFIXES
        if (d / f"{stem}{suffix}").is_file()
    ]
    if not found:
        raise FileNotFoundError(
            f"no probabilities for image {stem} in {folder} (expected {stem}.npz or .pt)"
        )
    if len(found) > 1:
        raise ValueError(
            f"image {stem} has several probability files: {', '.join(map(str, found))}"
        )
    return found[0]


def load_probs(
    path: str | Path, num_classes: int = NUM_CLASSES, size: tuple[int, int] | None = None
) -> Tensor:
    """(N, H, W) float32 probabilities from a file (softmax over N when it holds logits).

    Args:
        path: a ``.npz`` or ``.pt`` file holding ``probs`` or ``logits``.
        num_classes: the expected N.
        size: the expected (H, W) (the label size), or None for any.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a probability file, or a wrong key, dtype, shape, class count or size,
            or ``probs`` that do not sum to 1 (one line naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"probability file not found: {path}")
    key, scores = _read(path)
    if not scores.is_floating_point():
        dtype = str(scores.dtype).removeprefix("torch.")
        raise ValueError(f"{path}: {key} has dtype {dtype}; expected floating point (e.g. float16)")
    if scores.ndim != 3:
        raise ValueError(f"{path}: {key} has shape {tuple(scores.shape)}; expected (N, H, W)")
    if scores.shape[0] != num_classes:
        raise ValueError(f"{path}: {key} holds {scores.shape[0]} classes; expected {num_classes}")
    if size is not None and tuple(scores.shape[1:]) != tuple(size):
        raise ValueError(
            f"{path}: {key} is {scores.shape[1]}x{scores.shape[2]}; the image's labels are "
            f"{size[0]}x{size[1]}"
        )
    scores = scores.float()
    if key == "logits":
        return scores.softmax(0)
    deviation = (scores.sum(0) - 1).abs().max().item()
    if not deviation <= _SUM_TOLERANCE:  # written this way round so NaN fails too
        raise ValueError(
            f"{path}: probs do not sum to 1 over classes (off by up to {deviation:.3g}); "
            "store unnormalised scores as 'logits'"
        )
    return scores


def _read(path: Path) -> tuple[str, Tensor]:
    """The (key, tensor) a probability file holds; ValueError naming the file otherwise."""
    if path.suffix not in PROBS_SUFFIXES:
        raise ValueError(f"{path}: probability files end in .npz or .pt")
    if path.suffix == ".pt":
        content = read_torch_file(path)
    elif not zipfile.is_zipfile(path):  # np.load would try to unpickle it
        raise ValueError(f"{path} is not a .npz file (not a zip archive)")
    else:
        try:
            with np.load(path, allow_pickle=False) as data:
                content = {k: torch.from_numpy(data[k]) for k in data.files if k in _KEYS}
        except Exception as err:  # numpy raises many types for a foreign or truncated file
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise ValueError(f"{path} is not a readable .npz file: {first}") from None
    keys = [k for k in _KEYS if isinstance(content, dict) and isinstance(content.get(k), Tensor)]
    if len(keys) != 1:
        raise ValueError(f"{path} should hold exactly one tensor named 'probs' or 'logits'")
    return keys[0], content[keys[0]]


def save_data_record(folder: str | Path, data: dict[str, Any], priors: Tensor | None) -> None:
    """Say beside saved probabilities which data their images are (a data configuration, see
    :func:`costseg.data.from_config.evaluated_data`) and keep the priors used with them, so
    that ``--probs`` needs no ``--data_root`` and decides as the run that saved them."""
    from costseg.data.priors import save_priors

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with AtomicFile(folder / DATA_RECORD) as tmp:
        tmp.write_text(json.dumps({"data": data}, indent=1))
    if priors is not None:
        save_priors(folder / _PRIORS, priors)


def records_its_data(folder: str | Path) -> bool:
    """Whether a probabilities folder names its data (:func:`save_data_record`)."""
    return (Path(folder) / DATA_RECORD).is_file()


def read_data_record(folder: str | Path) -> tuple[dict[str, Any] | None, Tensor | None]:
    """(data configuration, priors) recorded beside saved probabilities; (None, None) for a
    folder without a record (another framework's files)."""
    from costseg.data.priors import read_priors_file

    folder = Path(folder)
    if not records_its_data(folder):
        return None, None
    try:
        data = json.loads((folder / DATA_RECORD).read_text())["data"]
    except (ValueError, KeyError, TypeError):
        raise ValueError(
            f"{folder / DATA_RECORD} is not a record of saved probabilities' data"
        ) from None
    priors_file = folder / _PRIORS
    priors = read_priors_file(priors_file, CLASS_NAMES)["priors"] if priors_file.is_file() else None
    return data, priors
