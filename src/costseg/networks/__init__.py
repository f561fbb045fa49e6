"""Networks that map uint8 images to Cityscapes logits, whoever trained them.

Specs understood by `load_network`:

* ``costseg:PATH`` — a checkpoint written by ``train.py`` (read without importing Lightning);
* ``vainf:PATH`` — a VainF/DeepLabV3Plus-Pytorch checkpoint (ResNet-50/101), rebuilt as
  costseg's own `DeepLabV3Plus`. The backbone is read from the weights; the output stride
  (invisible in the weights) from ``?os=8`` / ``?os=16`` after the path, else from ``os8`` /
  ``os16`` in the file name, else 16; ``?backbone=resnet50`` overrides the detected backbone
  (options join with ``&``). Example: ``vainf:best_deeplabv3plus_resnet101_cityscapes_os16.pth``;
* ``hf:DIR`` (alias ``segformer:DIR``) — a ``transformers`` semantic-segmentation model saved
  with ``save_pretrained`` (SegFormer, ...), normalised as its ``preprocessor_config.json`` says
  (no resizing). Needs the ``hf`` extra;
* ``onnx:FILE`` — any framework's ONNX network: one (B, 3, H, W) image input, 19-class logits
  out at the input size or a fraction of it (``docs/definitions.md §19``); ``?mean=a,b,c&std=d,e,f``
  (on ``image / 255``, default ImageNet's) and ``?output=probs`` for probabilities. A decision
  graph of ``scripts/export.py`` gives its probabilities. Needs the ``onnx`` extra.

Every loader returns an `ImageNetwork` in eval mode: (B, 3, H, W) uint8 RGB → (B, 19, H, W)
float logits at the input resolution. Nothing is ever downloaded.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, ImageNetwork
from costseg.networks.costseg import CostsegCheckpoint, load_costseg_checkpoint
from costseg.networks.hf import load_hf
from costseg.networks.onnx import load_onnx, onnx_options
from costseg.networks.vainf import VAINF_DEPTHS, export_vainf_state, load_vainf
from costseg.values import NETWORK_SPECS, NETWORK_USAGE

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "LOADERS",
    "CostsegCheckpoint",
    "ImageNetwork",
    "export_vainf_state",
    "load_costseg_checkpoint",
    "load_hf",
    "load_network",
    "load_onnx",
    "load_vainf",
]

LOADERS: dict[str, Callable[[str, dict[str, Any]], ImageNetwork]] = {
    "costseg": lambda location, _: load_costseg_checkpoint(location).network,
    "vainf": lambda location, options: load_vainf(location, **options),
    "hf": lambda location, _: load_hf(location),
    "segformer": lambda location, _: load_hf(location),
    "onnx": lambda location, options: load_onnx(location, **options),
}
"""The loader of each ``--network`` prefix of :data:`costseg.values.NETWORK_SPECS`: a new
source is an entry in both (``tests/test_networks.py`` checks that they agree)."""
_OPTIONS = re.compile(r"\?(\w+=[^&?=]+(?:&\w+=[^&?=]+)*)$")


def load_network(spec: str, device: str | torch.device = "cpu") -> ImageNetwork:
    """The network a spec names (see the module docstring), on ``device``, in eval mode.

    Args:
        spec: ``costseg:PATH``, ``vainf:PATH[?os=8]``, ``hf:DIR``, ``segformer:DIR`` or
            ``onnx:FILE[?mean=...&std=...]``.
        device: where the network runs.

    Returns:
        a module mapping (B, 3, H, W) uint8 RGB to (B, 19, H, W) float logits.

    Raises:
        ValueError: unknown prefix or option, a file of the wrong kind or class count.
        FileNotFoundError: the file or folder does not exist.

    Example:
        >>> load_network("tflite:model.tflite")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: unknown network spec 'tflite:model.tflite': expected one of costseg:PATH, ...
    """
    prefix, location, options = _parse_spec(spec)
    return LOADERS[prefix](location, options).to(torch.device(device)).eval()


def check_spec(spec: str) -> None:
    """Raise as :func:`load_network` would for a malformed spec or a missing file or folder,
    without loading anything (so an ensemble can check every member first).

    >>> check_spec("vainf:no/such.pth")
    Traceback (most recent call last):
    ...
    FileNotFoundError: not found: no/such.pth (vainf:no/such.pth)
    """
    _, location, _ = _parse_spec(spec)
    if not Path(location).exists():
        raise FileNotFoundError(f"not found: {location} ({spec})")


def _parse_spec(spec: str) -> tuple[str, str, dict[str, Any]]:
    prefix, sep, location = spec.partition(":")
    if not sep or prefix not in LOADERS or not location:
        raise ValueError(f"unknown network spec {spec!r}: expected one of {NETWORK_USAGE}")
    match = _OPTIONS.search(location) if prefix in ("vainf", "onnx") else None
    if match is None:
        return prefix, location, {}
    items = [tuple(item.split("=")) for item in match.group(1).split("&")]
    if prefix == "onnx":
        return prefix, location[: match.start()], onnx_options(items, spec)
    options: dict[str, Any] = {}
    for key, value in items:
        item = f"{key}={value}"
        if key == "os" and value in ("8", "16"):
            options["output_stride"] = int(value)
        elif key == "backbone" and value in VAINF_DEPTHS.values():
            options["backbone"] = value
        else:
            raise ValueError(f"bad option {item!r} in {spec!r}: expected {NETWORK_SPECS['vainf']}")
    return prefix, location[: match.start()], options
