"""VainF/DeepLabV3Plus-Pytorch checkpoints as costseg's own `DeepLabV3Plus`.

VainF's DeepLabV3+ (ResNet backbones) is costseg's network with a one-conv decoder
(``decoder_convs=1``) under other key names:

=====================================  ==========================================
VainF ``model_state`` key              costseg `DeepLabV3Plus` key
=====================================  ==========================================
``backbone.*`` (torchvision ResNet)    ``backbone.*`` (same names)
``classifier.aspp.*``                  ``aspp.*`` (torchvision's ASPP, same layout)
``classifier.project.0/1``             ``decoder.project.0/1`` (1x1 conv to 48 + BN)
``classifier.classifier.0/1``          ``decoder.fuse.0.0/1`` (3x3 conv 304→256 + BN)
``classifier.classifier.3``            ``classifier`` (1x1 conv to the classes)
=====================================  ==========================================

VainF concatenates ``[low-level, ASPP]`` before the 3x3 conv and costseg ``[ASPP, low-level]``,
so that conv's input channels are swapped on the way in and out. Everything else (dilation
scheme, ASPP pooling branch, bilinear upsampling with ``align_corners=False``) is identical, so
the mapped network gives VainF's logits.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from costseg.checkpoints import read_torch_file
from costseg.classes import NUM_CLASSES
from costseg.models.deeplabv3plus import LOW_LEVEL_CHANNELS, DeepLabV3Plus
from costseg.networks.base import ImageNetwork, check_state_keys

__all__ = [
    "VAINF_DEPTHS",
    "export_vainf_state",
    "load_vainf",
    "vainf_backbone",
    "vainf_deeplabv3plus",
    "vainf_to_costseg_state",
]

VAINF_DEPTHS: dict[int, str] = {6: "resnet50", 23: "resnet101"}
"""Number of ``backbone.layer3`` blocks → backbone name."""
_FUSE_CONV = ("classifier.classifier.0.weight", "decoder.fuse.0.0.weight")
# (VainF prefix, costseg prefix); the first match wins, so longer prefixes come first.
_PREFIXES: tuple[tuple[str, str], ...] = (
    ("classifier.classifier.0.", "decoder.fuse.0.0."),
    ("classifier.classifier.1.", "decoder.fuse.0.1."),
    ("classifier.classifier.3.", "classifier."),
    ("classifier.project.", "decoder.project."),
    ("classifier.aspp.", "aspp."),
    ("backbone.", "backbone."),
)


def _rename(key: str, to_costseg: bool) -> str | None:
    for vainf, costseg in _PREFIXES:
        old, new = (vainf, costseg) if to_costseg else (costseg, vainf)
        if key.startswith(old):
            return new + key[len(old) :]
    return None


def _swap_inputs(weight: torch.Tensor, first: int) -> torch.Tensor:
    """Move the first ``first`` input channels of a conv weight (O, I, k, k) to the end."""
    return torch.cat([weight[:, first:], weight[:, :first]], dim=1)


def vainf_to_costseg_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename (and reorder where needed) a VainF ``model_state`` for `DeepLabV3Plus`.

    Keys outside VainF's layout are dropped; compare key sets first to report them.

    Example:
        >>> net = DeepLabV3Plus(19, "resnet50", decoder_convs=1)
        >>> back = vainf_to_costseg_state(export_vainf_state(net))
        >>> all(torch.equal(back[k], v) for k, v in net.state_dict().items())
        True
    """
    out = {}
    for key, value in state.items():
        new = _rename(key, to_costseg=True)
        if new is not None:
            out[new] = value
    if _FUSE_CONV[1] in out:
        out[_FUSE_CONV[1]] = _swap_inputs(out[_FUSE_CONV[1]], LOW_LEVEL_CHANNELS)
    return out


def export_vainf_state(net: DeepLabV3Plus) -> dict[str, torch.Tensor]:
    """The state dict VainF's ``DeepLabV3`` would hold for ``net`` (one-conv decoder, 256 wide).

    Args:
        net: a ResNet `DeepLabV3Plus` built with ``decoder_convs=1``.

    Raises:
        ValueError: ``net`` has more than one decoder conv (VainF's layout has one).

    Example:
        >>> net = DeepLabV3Plus(19, "resnet50", decoder_convs=1)
        >>> state = export_vainf_state(net)
        >>> state["classifier.classifier.0.weight"].shape
        torch.Size([256, 304, 3, 3])
    """
    if len(net.decoder.fuse) != 1:
        raise ValueError(
            f"VainF's decoder has one 3x3 conv; this network has {len(net.decoder.fuse)}"
        )
    out = {}
    for key, value in net.state_dict().items():
        new = _rename(key, to_costseg=False)
        if new is not None:
            out[new] = value.detach().clone()
    aspp_channels = out[_FUSE_CONV[0]].shape[1] - LOW_LEVEL_CHANNELS
    out[_FUSE_CONV[0]] = _swap_inputs(out[_FUSE_CONV[0]], aspp_channels)
    return out


def vainf_backbone(state: dict[str, torch.Tensor]) -> str | None:
    """``resnet50`` / ``resnet101`` from the number of ``backbone.layer3`` blocks, else None.

    >>> vainf_backbone({f"backbone.layer3.{i}.conv1.weight": torch.zeros(1) for i in range(23)})
    'resnet101'
    """
    blocks = {k.split(".")[2] for k in state if k.startswith("backbone.layer3.")}
    return VAINF_DEPTHS.get(len(blocks))


def vainf_deeplabv3plus(num_classes: int, backbone: str, output_stride: int) -> DeepLabV3Plus:
    """An (untrained) `DeepLabV3Plus` with VainF's architecture, in eval mode.

    Example:
        >>> net = vainf_deeplabv3plus(19, "resnet50", 16)
        >>> len(net.decoder.fuse), net.aspp.convs[1][0].dilation
        (1, (6, 6))
    """
    net = DeepLabV3Plus(num_classes, backbone, output_stride, decoder_channels=256, decoder_convs=1)
    net.aspp.project[-1].p = 0.1  # VainF's ASPP drops 10 % (matters for --mc_dropout only)
    return net.eval()


def load_vainf(
    path: str | Path, output_stride: int | None = None, backbone: str | None = None
) -> ImageNetwork:
    """A VainF/DeepLabV3Plus-Pytorch ResNet checkpoint as costseg's `DeepLabV3Plus`.

    Args:
        path: a file whose ``model_state`` (or itself) is VainF's ``DeepLabV3`` state dict.
        output_stride: 8 or 16; default from ``os8`` / ``os16`` in the file name, else 16.
        backbone: ``resnet50`` or ``resnet101``; default from the number of layer3 blocks.

    Raises:
        FileNotFoundError: no such file.
        ValueError: other key names or shapes (the first few are named), a class count other
            than 19, or a backbone other than ResNet-50/101.

    Example:
        >>> import tempfile
        >>> state = export_vainf_state(vainf_deeplabv3plus(19, "resnet50", 16))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     torch.save({"model_state": state, "best_score": 0.5}, f"{tmp}/r50_os16.pth")
        ...     net = load_vainf(f"{tmp}/r50_os16.pth")
        >>> net(torch.zeros(1, 3, 40, 56, dtype=torch.uint8)).shape
        torch.Size([1, 19, 40, 56])
    """
    path = Path(path)
    state = _vainf_state(read_torch_file(path, mmap=False), path)
    if any(k.startswith("backbone.low_level_features.") for k in state):
        raise ValueError(f"{path}: VainF MobileNetV2 checkpoints are not supported (ResNets only)")
    head = state.get("classifier.classifier.3.weight")
    if isinstance(head, Tensor) and head.shape[0] != NUM_CLASSES:
        raise ValueError(
            f"{path} predicts {head.shape[0]} classes; expected the {NUM_CLASSES} Cityscapes "
            "train classes"
        )
    found = re.search(r"(?<![a-z])os(8|16)(?!\d)", path.name.lower())
    output_stride = output_stride or (int(found.group(1)) if found else 16)
    backbone = backbone or vainf_backbone(state) or "resnet101"
    net = vainf_deeplabv3plus(NUM_CLASSES, backbone, output_stride)
    expected = export_vainf_state(net)
    check_state_keys(expected, state, f"{path} is not a VainF DeepLabV3+ {backbone} checkpoint")
    # Checkpoints of very old PyTorch lack BN's num_batches_tracked (unused in eval): keep ours.
    net.load_state_dict({**net.state_dict(), **vainf_to_costseg_state(state)})
    return ImageNetwork(net)


def _vainf_state(checkpoint: Any, path: Path) -> dict[str, Tensor]:
    state = checkpoint.get("model_state", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"{path} is not a VainF checkpoint (expected a dict with 'model_state')")
    if state and all(k.startswith("module.") for k in state):  # saved from nn.DataParallel
        state = {k.removeprefix("module."): v for k, v in state.items()}
    return state
