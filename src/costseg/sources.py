"""Where the probabilities come from: a network (costseg, VainF, transformers) or saved files.

Every source maps a batch of (B, 3, H, W) uint8 images, with their image names, to (B, N, H, W)
scores: logits from a network, probabilities from files. The evaluation loop turns them into
the probabilities the rules see (softmax, calibration, float16 rounding for ``--save-probs``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from costseg.checkpoints import check_classes, find_checkpoint
from costseg.classes import CLASS_NAMES


@dataclass
class Source:
    """A probability source.

    Attributes:
        kind: "network" (``scores`` are logits) or "probs" (``scores`` are probabilities).
        description: what it is, for every output (spec, path).
        network: for kind "network", the module mapping uint8 images to logits.
        probs_dir: for kind "probs", the folder of per-image files.
        priors: (N, H, W) pixel-wise priors stored with a costseg checkpoint, else None.
        data_config: the dataset a costseg checkpoint was trained on, else None.
        run_dir: the training run's folder of a costseg checkpoint (default output place).
    """

    kind: str
    description: dict[str, Any]
    network: torch.nn.Module | None = None
    probs_dir: Path | None = None
    priors: Tensor | None = None
    data_config: dict[str, Any] | None = None
    run_dir: Path | None = None
    hparams: dict[str, Any] = field(default_factory=dict)

    def scores(self, images: Tensor, stems: list[str]) -> Tensor:
        """(B, N, H, W) float logits (network) or probabilities (files) for a batch."""
        if self.network is not None:
            return self.network(images).float()
        from costseg.probs_files import find_probs_file, load_probs

        assert self.probs_dir is not None
        size = tuple(images.shape[-2:])
        files = [find_probs_file(self.probs_dir, stem) for stem in stems]
        probs = [load_probs(f, len(CLASS_NAMES), size=size) for f in files]
        return torch.stack(probs).to(images.device)


def open_source(
    ckpt_path: str | None, network: str | None, probs: str | None, device: torch.device
) -> Source:
    """The source the options name: ``--network SPEC``, ``--probs DIR`` or a costseg checkpoint
    (``--ckpt_path``, default the newest ``runs/**/last.ckpt``)."""
    if probs is not None:
        folder = Path(probs)
        if not folder.is_dir():
            raise FileNotFoundError(f"--probs folder not found: {probs}")
        return Source("probs", {"probs": str(folder)}, probs_dir=folder)
    if network is not None and not network.startswith("costseg:"):
        from costseg.networks import load_network

        net = load_network(network, device=str(device))
        return Source("network", {"network": network}, network=net)
    path = find_checkpoint(network.removeprefix("costseg:") if network else ckpt_path)
    return _costseg_source(path, device)


def _costseg_source(path: Path, device: torch.device) -> Source:
    from costseg.networks import load_network

    print(f"checkpoint: {path}")
    checkpoint = check_classes(path, CLASS_NAMES)
    extra = checkpoint.get("costseg", {})
    net = load_network(f"costseg:{path}", device=str(device))
    return Source(
        "network",
        {"network": f"costseg:{path}", "hparams": dict(checkpoint.get("hyper_parameters", {}))},
        network=net,
        priors=extra.get("priors"),
        data_config=extra.get("data"),
        run_dir=path.parent.parent,
    )


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA when present), ``cpu``, ``cuda``, ``cuda:1``, ...; ValueError if unusable.

    >>> resolve_device("cpu")
    device(type='cpu')
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}: expected auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"device {name!r} is not available: this machine has no CUDA GPU")
        if device.index is not None and device.index >= count:
            raise ValueError(f"device {name!r} is not available: this machine has {count} GPU(s)")
    elif device.type != "cpu":
        raise ValueError(f"device {name!r} is not supported: expected auto, cpu, cuda or cuda:N")
    return device
