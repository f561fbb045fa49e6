"""A network and its config entry (``class_path`` / ``init_args``, as ``model.net`` in
``configs/*.yaml``): one builds the other. A loss (``model.loss``) is recorded the same way.

>>> entry = {"class_path": "costseg.models.deeplabv3plus.DeepLabV3Plus",
...          "init_args": {"backbone": "resnet18", "decoder_channels": 8}}
>>> net = network_from_entry(entry, num_classes=3)
>>> module_entry(net)["init_args"]["num_classes"], type(net).__name__
(3, 'DeepLabV3Plus')
"""

from __future__ import annotations

import importlib
from typing import Any

from torch import nn

__all__ = ["module_entry", "network_from_entry"]


def network_from_entry(
    entry: Any, num_classes: int | None = None, initial_weights: bool = True
) -> nn.Module:
    """The network named by a config entry: ``class_path`` called with ``init_args``.

    Args:
        entry: ``{"class_path": "package.module.Class", "init_args": {...}}``.
        num_classes: sets ``init_args["num_classes"]`` (a config links it to the model's).
        initial_weights: False sets every ``*_weights`` argument (initial weights read from a
            file, e.g. ``backbone_weights``) to None: weights loaded next replace them.

    Raises:
        ValueError: not such an entry, or its class cannot be imported or is no ``nn.Module``
            (only a module class is called: a checkpoint cannot name any other callable).
    """
    if not (isinstance(entry, dict) and isinstance(entry.get("class_path"), str)):
        raise ValueError(f"not a network entry (class_path / init_args): {entry!r}")
    module, _, name = entry["class_path"].rpartition(".")
    try:
        kind = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as err:
        raise ValueError(f"cannot import the network {entry['class_path']}: {err}") from None
    if not (isinstance(kind, type) and issubclass(kind, nn.Module)):  # a file names no callable
        raise ValueError(f"the network {entry['class_path']} is not a torch.nn.Module class")
    init_args = dict(entry.get("init_args") or {})
    if num_classes is not None:
        init_args["num_classes"] = num_classes
    if not initial_weights:
        init_args = {k: None if k.endswith("_weights") else v for k, v in init_args.items()}
    return kind(**init_args)


def module_entry(module: nn.Module) -> dict[str, Any] | None:
    """The entry that rebuilds ``module`` (a network, a loss), from the ``init_args`` it records
    (costseg's networks and losses do), or None."""
    init_args = getattr(module, "init_args", None)
    if not isinstance(init_args, dict):
        return None
    kind = type(module)
    return {"class_path": f"{kind.__module__}.{kind.__qualname__}", "init_args": dict(init_args)}
