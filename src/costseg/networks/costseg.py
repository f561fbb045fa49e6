"""costseg's own checkpoints (written by ``train.py``), read without importing Lightning.

A Lightning checkpoint of `costseg.training.module.SegmentationModule` holds only tensors and
plain data (hyper-parameters are a dict of strings and numbers), so
:func:`costseg.checkpoints.read_checkpoint` reads it with ``weights_only=True``. The network is
rebuilt from the config entry the checkpoint records (``hyper_parameters["net"]``: the class
named by ``class_path`` called with ``init_args``) and the ``net.*`` weights. Initial weights
named in ``init_args`` (``backbone_weights``) are not read again: the checkpoint's weights
replace them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torch import Tensor

from costseg.checkpoints import CHECKPOINT_KEY, read_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.models.entries import network_from_entry
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


def load_costseg_checkpoint(
    path: str | Path, class_names: Sequence[str] = CLASS_NAMES
) -> CostsegCheckpoint:
    """Read a ``train.py`` checkpoint trained on ``class_names`` into its network, without
    Lightning.

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
    if "net" not in hparams:
        raise ValueError(f"{path} records no network (model.net): train it again with train.py")
    try:
        net = network_from_entry(hparams["net"], initial_weights=False)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from None
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
