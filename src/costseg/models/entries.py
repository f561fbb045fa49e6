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
import inspect
import typing
from collections.abc import Callable
from typing import Any

from torch import nn

__all__ = ["initial_weights_argument", "module_builder", "module_entry", "network_from_entry"]


def network_from_entry(
    entry: Any, num_classes: int | None = None, initial_weights: bool = True
) -> nn.Module:
    """The network named by a config entry: ``class_path`` called with ``init_args``.

    Args:
        entry: ``{"class_path": "package.module.Class", "init_args": {...}}``.
        num_classes: sets ``init_args["num_classes"]`` (a config links it to the model's).
        initial_weights: False sets every argument that names initial weights
            (:func:`initial_weights_argument`, e.g. ``backbone_weights``) to None, or calls
            the class's ``without_initial_weights(init_args)`` where it has one: weights loaded
            next replace them.

    Raises:
        ValueError: not such an entry, or its class cannot be imported or is no ``nn.Module``
            (only a module class is called: a checkpoint cannot name any other callable).
    """
    if not (isinstance(entry, dict) and isinstance(entry.get("class_path"), str)):
        raise ValueError(f"not a network entry (class_path / init_args): {entry!r}")
    kind = module_builder(entry["class_path"], functions=False)
    init_args = dict(entry.get("init_args") or {})
    if num_classes is not None:
        init_args["num_classes"] = num_classes
    if not initial_weights:  # a class may say where its initial weights are named
        hook = getattr(kind, "without_initial_weights", None)
        init_args = hook(init_args) if hook else _without_initial_weights(init_args)
    return kind(**init_args)


def module_builder(path: str, functions: bool = True) -> Callable[..., nn.Module]:
    """The ``nn.Module`` class that ``path`` names or, with ``functions``, a function annotated
    to return one (torchvision's ``deeplabv3_mobilenet_v3_large``); nothing else is returned,
    so that a checkpoint cannot name any other callable.

    Raises:
        ValueError: ``path`` cannot be imported, or names something else.

    >>> module_builder("torch.nn.Conv2d").__name__
    'Conv2d'
    >>> module_builder("os.system")
    Traceback (most recent call last):
    ...
    ValueError: the network os.system is not a torch.nn.Module class or a function returning one
    """
    module, _, name = path.rpartition(".")
    try:
        kind = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as err:
        raise ValueError(f"cannot import the network {path}: {err}") from None
    if isinstance(kind, type) and issubclass(kind, nn.Module):
        return kind
    if functions and inspect.isfunction(kind) and _returns_module(kind):
        return kind
    what = "class or a function returning one" if functions else "class"
    raise ValueError(f"the network {path} is not a torch.nn.Module {what}")


def _returns_module(function: Callable) -> bool:
    try:
        returned = typing.get_type_hints(function).get("return")
    except Exception:  # an annotation that does not resolve says nothing
        return False
    return isinstance(returned, type) and issubclass(returned, nn.Module)


def initial_weights_argument(name: str) -> bool:
    """Whether an argument called ``name`` names initial weights (``backbone_weights``,
    torchvision's ``weights`` and ``weights_backbone``).

    >>> [initial_weights_argument(n) for n in ("weights", "weights_backbone", "num_classes")]
    [True, True, False]
    """
    return name == "weights" or name.endswith("_weights") or name.startswith("weights_")


def _without_initial_weights(init_args: dict[str, Any]) -> dict[str, Any]:
    return {k: None if initial_weights_argument(k) else v for k, v in init_args.items()}


def module_entry(module: nn.Module) -> dict[str, Any] | None:
    """The entry that rebuilds ``module`` (a network, a loss), from the ``init_args`` it records
    (costseg's networks and losses do), or None."""
    init_args = getattr(module, "init_args", None)
    if not isinstance(init_args, dict):
        return None
    kind = type(module)
    return {"class_path": f"{kind.__module__}.{kind.__qualname__}", "init_args": dict(init_args)}
