"""Test-time augmentation (``docs/definitions.md §13``): the mean softmax over views of an image.

A view scales the image by s (bilinear, ``align_corners=False``, rounded back to 8 bits as an
image file would be; the size ``round(H s) x round(W s)``, halves up as mmcv rounds) and/or flips
it horizontally; its logits are flipped back and resized to (H, W) (bilinear). The views'
probabilities (softmax of each) are averaged with equal weights; flip + scales is every scale with
and without the flip. With Monte-Carlo dropout each view's probabilities are its mean over the
passes (``docs/definitions.md §12``), each view seeded apart; pass t of the image is the mean over
the views of their pass t (the runs of the uncertainty maps, ``docs/definitions.md §13``).

>>> from costseg.networks.base import ImageNetwork
>>> logits = ImageNetwork(torch.nn.Conv2d(3, 4, 1))
>>> net = TestTimeAugmentation(logits, flip=True, scales=(0.5, 1.0))
>>> [v.tag for v in net.views]
['scale 0.5', 'scale 0.5 flip', '', 'flip']
>>> probs = net(torch.randint(0, 256, (2, 3, 6, 8), dtype=torch.uint8))
>>> tuple(probs.shape), bool(torch.allclose(probs.sum(1), torch.ones(2, 6, 8)))
((2, 4, 6, 8), True)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from costseg.networks.mc_dropout import MCDropout, mc_dropout_runs
from costseg.networks.uncertainty import RunAverage


def scaled_size(size: Sequence[int], scale: float) -> tuple[int, int]:
    """(H, W) times ``scale``, each rounded half up, at least 1 pixel.

    >>> scaled_size((1024, 2048), 0.75), scaled_size((5, 3), 0.5)
    ((768, 1536), (3, 2))
    """
    return tuple(max(1, int(n * scale + 0.5)) for n in size)  # type: ignore[return-value]


def resize_images(images: Tensor, size: Sequence[int]) -> Tensor:
    """(B, 3, H, W) uint8 images resized bilinearly to ``size`` (``align_corners=False``, no
    antialiasing), rounded to uint8."""
    resized = F.interpolate(images.float(), size=tuple(size), mode="bilinear", align_corners=False)
    return resized.round_().clamp_(0, 255).to(torch.uint8)


class View(nn.Module):
    """One view: the image scaled and/or flipped, the logits mapped back to the image's pixels.

    Args:
        network: uint8 images → logits at the input's size.
        scale: s > 0 (1: the image's own size).
        flip: flip horizontally.
    """

    def __init__(self, network: nn.Module, scale: float = 1.0, flip: bool = False) -> None:
        super().__init__()
        self.network, self.scale, self.flip = network, float(scale), bool(flip)

    @property
    def tag(self) -> str:
        """The view's name in seeds and outputs ('' for the image as it is)."""
        return " ".join(
            ([f"scale {self.scale:g}"] if self.scale != 1 else []) + ["flip"] * self.flip
        )

    def forward(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) uint8 → (B, N, H, W) float logits of the view, at the image's pixels."""
        size = tuple(images.shape[-2:])
        x = resize_images(images, scaled_size(size, self.scale)) if self.scale != 1 else images
        logits = self.network(x.flip(-1) if self.flip else x).float()
        if self.flip:
            logits = logits.flip(-1)
        if tuple(logits.shape[-2:]) != size:
            logits = F.interpolate(logits, size=size, mode="bilinear", align_corners=False)
        return logits


class TestTimeAugmentation(nn.Module):
    """A network whose output is the mean softmax over its views.

    Args:
        network: uint8 images → logits (a network, or its :class:`SlidingWindow`).
        flip: every scale with and without the horizontal flip.
        scales: the scales s, each once.
        passes: Monte-Carlo dropout passes per view (None: the plain softmax of each view).
        seed: the Monte-Carlo dropout seed.

    Raises:
        ValueError: Monte-Carlo dropout on a network without dropout layers.
    """

    __test__ = False  # not a pytest class

    def __init__(
        self,
        network: nn.Module,
        flip: bool,
        scales: Sequence[float] = (1.0,),
        passes: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__()
        flips = (False, True) if flip else (False,)
        self.views = nn.ModuleList([View(network, s, f) for s in scales for f in flips])
        self.mc_dropout = (
            nn.ModuleList([MCDropout(v, passes, seed) for v in self.views]) if passes else None
        )

    def forward(self, images: Tensor, names: Sequence[str] = ()) -> Tensor:
        """(B, 3, H, W) uint8 images (named ``names``, which key Monte-Carlo dropout's seed
        together with each view's tag) → (B, N, H, W) float32 probabilities."""
        if self.mc_dropout is None:
            total = None
            for view in self.views:
                probs = view(images).softmax(1)
                total = probs if total is None else total + probs
            return total / len(self.views)
        return self.average(images, names, keep_entropy=False).mean

    def average(
        self, images: Tensor, names: Sequence[str] = (), keep_entropy: bool = True
    ) -> RunAverage:
        """The mean probabilities and, with Monte-Carlo dropout, the passes' mean entropy: pass
        t's map is the mean over the views of each view's pass t (the views are one run)."""
        if self.mc_dropout is None:
            runs = RunAverage(keep_entropy=False)  # one run: no expected entropy
            runs.add(self(images))
            return runs
        keys = ["\n".join(f"{n} {v.tag}" if v.tag else n for n in names) for v in self.views]
        passes, seed = self.mc_dropout[0].passes, self.mc_dropout[0].seed
        return mc_dropout_runs(list(self.views), images, passes, seed, keys, keep_entropy)

    def describe(self) -> str:
        """What the probabilities are, for every output."""
        views = ", ".join(v.tag or "the image" for v in self.views)
        text = f"mean softmax of {len(self.views)} views ({views})"
        if self.mc_dropout is not None:
            text += f"; each view's softmax: {self.mc_dropout[0].describe()}"
        return text
