"""``transformers`` semantic-segmentation models (SegFormer, ...) from a local folder.

``transformers`` is an optional extra (``pip install 'costseg[hf]'``), imported only here and only
when such a model is loaded.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from torch import Tensor, nn

from costseg.classes import NUM_CLASSES
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, ImageNetwork

__all__ = ["load_hf"]


class _HFLogits(nn.Module):
    """A transformers model as a plain ``pixel_values → logits`` module."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: Tensor) -> Tensor:
        return self.model(pixel_values=x).logits


def load_hf(folder: str | Path) -> ImageNetwork:
    """A ``transformers`` semantic-segmentation model from a local folder (no download).

    Normalisation follows the folder's ``preprocessor_config.json`` (``rescale_factor``,
    ``image_mean``, ``image_std``; ImageNet's when absent); images are not resized.

    Raises:
        FileNotFoundError: no such folder.
        ValueError: ``transformers`` is not installed, the folder holds no semantic-segmentation
            model, or the model does not predict 19 classes.

    >>> load_hf("no/such/folder")
    Traceback (most recent call last):
    ...
    FileNotFoundError: model folder not found: no/such/folder
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"model folder not found: {folder}")
    try:
        from transformers import AutoModelForSemanticSegmentation
    except ImportError:
        raise ValueError("hf: networks need transformers: pip install 'costseg[hf]'") from None
    if not (folder / "config.json").is_file():
        raise ValueError(f"{folder} is not a transformers model folder (no config.json)")
    try:
        model = AutoModelForSemanticSegmentation.from_pretrained(folder, local_files_only=True)
    except (OSError, ValueError, KeyError, TypeError) as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"{folder} is not a transformers segmentation model: {first}") from None
    if model.config.num_labels != NUM_CLASSES:
        raise ValueError(
            f"{folder} predicts {model.config.num_labels} classes; expected the {NUM_CLASSES} "
            "Cityscapes train classes"
        )
    return ImageNetwork(_HFLogits(model.float()), **_hf_normalisation(folder))


def _hf_normalisation(folder: Path) -> dict[str, Any]:
    path = folder / "preprocessor_config.json"
    if not path.is_file():
        return {}
    try:
        config = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path} is not readable JSON: {err}") from None

    def triple(value: Any, default: tuple[float, ...]) -> tuple[float, ...]:
        value = default if value is None else value
        return tuple(float(v) for v in value) if isinstance(value, list) else (float(value),) * 3

    normalise = config.get("do_normalize", True)
    rescale = float(config.get("rescale_factor", 1 / 255))
    return {
        "rescale": rescale if config.get("do_rescale", True) else 1.0,
        "mean": triple(config.get("image_mean"), IMAGENET_MEAN) if normalise else (0.0,) * 3,
        "std": triple(config.get("image_std"), IMAGENET_STD) if normalise else (1.0,) * 3,
    }
