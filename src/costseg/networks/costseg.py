"""costseg's own checkpoints (written by ``train.py``), read without importing Lightning.

A Lightning checkpoint of `costseg.training.module.SegmentationModule` holds only tensors and
plain data (hyper-parameters are a dict of strings and numbers), so
:func:`costseg.checkpoints.read_checkpoint` reads it with ``weights_only=True``, and the network
is rebuilt from ``hyper_parameters`` and the ``net.*`` weights.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torch import Tensor

from costseg.checkpoints import CHECKPOINT_KEY, read_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.networks.base import ImageNetwork, check_state_keys

__all__ = ["CostsegCheckpoint", "load_costseg_checkpoint"]


@dataclass(frozen=True)
class CostsegCheckpoint:
    """What evaluation needs from a costseg checkpoint.

    Attributes:
        network: the trained network behind costseg's ImageNet normalisation.
        priors: (N, H, W) pixel-wise priors from the training labels, or None.
        data_config: ``{"class_path": ..., "init_args": {...}}`` of the training data, or None.
        class_names: the N classes, in output order.
        hparams: the LightningModule's hyper-parameters.
        extra: everything the module stored under the checkpoint's ``CHECKPOINT_KEY``
            (``priors_info``, ...), priors included.
    """

    network: ImageNetwork
    priors: Tensor | None
    data_config: dict[str, Any] | None
    class_names: tuple[str, ...]
    hparams: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)


_NET_ARGS = ("num_classes", "backbone", "output_stride", "decoder_channels")


def load_costseg_checkpoint(
    path: str | Path, class_names: Sequence[str] = CLASS_NAMES
) -> CostsegCheckpoint:
    """Read a ``train.py`` checkpoint trained on ``class_names`` into a plain `DeepLabV3Plus`,
    without Lightning.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable costseg checkpoint, trained on other classes, or its weights
            do not fit its settings.

    >>> load_costseg_checkpoint("runs/none/last.ckpt")
    Traceback (most recent call last):
    ...
    FileNotFoundError: file not found: runs/none/last.ckpt
    """
    path = Path(path)
    checkpoint = read_checkpoint(path, class_names)
    extra = checkpoint[CHECKPOINT_KEY]
    hparams = dict(checkpoint.get("hyper_parameters") or {})
    net = DeepLabV3Plus(**{k: hparams[k] for k in _NET_ARGS if k in hparams})
    state = {k[4:]: v for k, v in checkpoint["state_dict"].items() if k.startswith("net.")}
    check_state_keys(net.state_dict(), state, f"{path} does not fit its own settings")
    net.load_state_dict(state)
    # The file is memory-mapped, and train.py may rewrite it while evaluation runs.
    priors = extra.get("priors")
    priors = None if priors is None else priors.clone()
    return CostsegCheckpoint(
        network=ImageNetwork(net, channels_last=bool(hparams.get("channels_last", False))),
        priors=priors,
        data_config=extra.get("data"),
        class_names=tuple(extra.get("class_names") or ()),
        hparams=hparams,
        extra={**extra, "priors": priors},
    )
