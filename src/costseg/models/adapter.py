"""Any segmentation network as ``model.net``: what train.py requires of a network, and the
adapter for one that does not meet it as it is.

``model.net`` is an ``nn.Module`` class that takes ``num_classes`` and maps (B, 3, H, W)
ImageNet-normalised images to (B, num_classes, h, w) logits; logits smaller than the input are
resized bilinearly to it, in training as in evaluation. :class:`NetworkAdapter` meets this for
a network built by a function (torchvision's ``deeplabv3_mobilenet_v3_large``) or one that
returns a dict (torchvision's ``{"out": ..., "aux": ...}``): it builds the network and returns
one entry of its output.
"""

from __future__ import annotations

import inspect
from typing import Any

import torch
from torch import nn

from costseg.models.entries import initial_weights_argument, module_builder

__all__ = ["NetworkAdapter", "NetworkOutputError", "network_output_error"]

ADAPTER = f"{__name__}.NetworkAdapter"
"""The adapter's ``class_path``, as error messages name it."""


class NetworkOutputError(ValueError):
    """The adapted network's output has no entry ``output``."""


class NetworkAdapter(nn.Module):
    """A network built by ``builder(num_classes=num_classes, **builder_args)``, whose forward
    returns the entry ``output`` of the built network's output (or the output itself where it
    is a tensor).

    Args:
        builder: import path of an ``nn.Module`` class or of a function annotated to return
            one, e.g. ``torchvision.models.segmentation.deeplabv3_mobilenet_v3_large``.
        num_classes: output classes (train.py links it to ``model.num_classes``).
        builder_args: further keyword arguments of ``builder``, e.g. ``{weights: null,
            weights_backbone: null}`` (torchvision's builders download ImageNet weights by
            default). A checkpoint rebuilds the network with every ``weights``, ``weights_*``
            and ``*_weights`` argument of the builder set to None, given or not: its own
            weights replace them.
        output: the key of the logits in the network's output (``out`` for torchvision's
            segmentation models; any key of a dict-like output).

    Raises:
        ValueError: ``builder`` is no module class or function returning one, or
            ``builder_args`` hold another ``num_classes`` (the same one is taken once).

    Example:
        >>> net = NetworkAdapter("torchvision.models.segmentation.lraspp_mobilenet_v3_large", 3,
        ...                      {"weights": None, "weights_backbone": None})
        >>> net.eval()(torch.zeros(1, 3, 32, 48)).shape
        torch.Size([1, 3, 32, 48])
    """

    def __init__(
        self,
        builder: str,
        num_classes: int,
        builder_args: dict[str, Any] | None = None,
        output: str = "out",
    ) -> None:
        super().__init__()
        builder_args = dict(builder_args or {})
        given = builder_args.pop("num_classes", num_classes)  # torchvision's habit: the same
        if given != num_classes:
            raise ValueError(
                f"--model.net.init_args.builder_args holds num_classes: {given}, and the network "
                f"is built with model.num_classes = {num_classes}: remove num_classes from "
                "builder_args (train.py passes model.num_classes)"
            )
        self.init_args = {  # what rebuilds this network (a checkpoint's model.net entry)
            "builder": builder,
            "num_classes": num_classes,
            "builder_args": builder_args,
            "output": output,
        }
        self.net = module_builder(builder)(num_classes=num_classes, **builder_args)
        self.output = output

    @classmethod
    def without_initial_weights(cls, init_args: dict[str, Any]) -> dict[str, Any]:
        """``init_args`` with every initial-weights argument of the builder set to None, given
        or not (torchvision's builders download ImageNet weights by default); a checkpoint
        rebuilds the network this way (:func:`costseg.models.entries.network_from_entry`)."""
        names = inspect.signature(module_builder(init_args["builder"])).parameters
        builder_args = dict(init_args.get("builder_args") or {})
        builder_args.update({n: None for n in names if initial_weights_argument(n)})
        return {**init_args, "builder_args": builder_args}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) normalised images → the network's logits."""
        out = self.net(x)
        if isinstance(out, torch.Tensor):
            return out
        try:
            return out[self.output]
        except (KeyError, IndexError, TypeError):
            raise NetworkOutputError(
                f"{self.init_args['builder']} returned {_described(out)}, without "
                f"{self.output!r}: set --model.net.init_args.output to the key of its logits"
            ) from None


def network_output_error(net: nn.Module, out: Any, num_classes: int, batch: int) -> str | None:
    """What is wrong with the output ``out`` of ``net`` for a batch of ``batch`` images, or
    None where it is (batch, num_classes, h, w) logits; the text ends with how to fix it.

    >>> net = nn.Conv2d(3, 2, 1)
    >>> network_output_error(net, {"out": torch.zeros(1, 19, 8, 8)}, 19, 1)[:48]
    "model.net returned a dict with keys ['out'], not"
    >>> network_output_error(net, torch.zeros(1, 19, 8, 8), 19, 1) is None
    True
    """
    if isinstance(out, torch.Tensor) and out.ndim == 4 and out.shape[0] == batch:
        if out.shape[1] == num_classes:
            return None
        return (
            f"model.net returned logits of {out.shape[1]} classes, and model.num_classes is "
            f"{num_classes}: model.net must take num_classes and return that many (train.py "
            "sets model.net.init_args.num_classes)"
        )
    kind = type(net)
    return (
        f"model.net returned {_described(out)}, not (B, {num_classes}, H, W) logits: pass "
        f"--model.net {ADAPTER} --model.net.init_args.builder {kind.__module__}."
        f"{kind.__qualname__} and, where the logits' key is not 'out', "
        '--model.net.init_args.output KEY (docs/usage.md, "Your own network")'
    )


def _described(out: Any) -> str:
    if isinstance(out, torch.Tensor):
        return f"a tensor of shape {tuple(out.shape)}"
    if isinstance(out, dict):
        return f"a dict with keys {list(out)}"
    return f"a {type(out).__name__}"
