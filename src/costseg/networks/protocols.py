"""How a network's probability map is made (``docs/definitions.md §13``): the inference protocol.

``--inference whole`` (one forward at the image's own size) or ``slide`` (:mod:`sliding`), and
test-time augmentation, ``--tta flip`` and ``--scales`` (:mod:`tta`). They compose in one order:
each view of the test-time augmentation runs the sliding windows on its image, and Monte-Carlo
dropout's passes (``--mc_dropout``) run inside each view. Only logits leave the sliding windows;
with test-time augmentation or Monte-Carlo dropout the source gives probabilities. The rules
still run once, on the final map.

>>> p = Protocol(crop=(64, 64), stride=(48, 48), flip=True, scales=(0.75, 1.0, 1.25))
>>> p.describe()
{'inference': 'slide crop 64x64 stride 48x48', 'tta': 'flip, scales 0.75/1/1.25'}
>>> Protocol().describe()
{'inference': 'whole image', 'tta': 'none'}
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from costseg.networks.sources import Source, with_mc_dropout

OPTIONS = "--inference slide, --tta or --scales"


@dataclass(frozen=True)
class Protocol:
    """An inference protocol.

    Attributes:
        crop: the sliding windows' (height, width), or None for the whole image.
        stride: the steps (height, width) between windows (with ``crop``).
        flip: average with the horizontally flipped image.
        scales: the image scales averaged over (``(1.0,)``: the image's own size only).
    """

    crop: tuple[int, int] | None = None
    stride: tuple[int, int] | None = None
    flip: bool = False
    scales: tuple[float, ...] = (1.0,)

    @classmethod
    def from_options(cls, opts: Any) -> Protocol:
        """The protocol of a job's options (``inference``, ``crop``, ``stride``, ``tta`` and
        ``scales``, as :class:`costseg.options.NetworkOptions` holds them); ValueError (one line)
        for a malformed one, before any network loads.

        >>> from costseg.options import PredictOptions
        >>> Protocol.from_options(PredictOptions(inference="slide", crop=[8, 8], stride=[9, 4]))
        Traceback (most recent call last):
        ...
        ValueError: --stride 9 4 exceeds --crop 8 8: the windows would leave pixels uncovered
        """
        crop, stride = opts.crop, opts.stride
        if opts.inference not in ("whole", "slide"):
            raise ValueError(f"--inference must be whole or slide, got {opts.inference!r}")
        if opts.inference == "whole" and (crop is not None or stride is not None):
            raise ValueError("--crop and --stride go with --inference slide")
        if opts.inference == "slide":
            if crop is None or stride is None:
                raise ValueError("--inference slide needs --crop H W and --stride H W")
            for name, value in (("--crop", crop), ("--stride", stride)):
                if len(value) != 2 or min(value) < 1:
                    raise ValueError(f"{name} takes two whole numbers >= 1 (H W), got {value}")
            if stride[0] > crop[0] or stride[1] > crop[1]:
                raise ValueError(
                    f"--stride {stride[0]} {stride[1]} exceeds --crop {crop[0]} {crop[1]}: "
                    "the windows would leave pixels uncovered"
                )
        if opts.tta not in (None, "flip"):
            raise ValueError(f"--tta must be flip, got {opts.tta!r}")
        scales = tuple(float(s) for s in opts.scales or (1.0,))
        if not all(0 < s < float("inf") for s in scales):
            raise ValueError(f"--scales must be positive numbers, got {opts.scales}")
        if len(set(scales)) < len(scales):
            raise ValueError(f"--scales repeats a scale: {' '.join(f'{s:g}' for s in scales)}")
        shape = tuple(crop) if crop else None
        return cls(shape, tuple(stride) if stride else None, opts.tta == "flip", scales)

    @property
    def augments(self) -> bool:
        """Whether there is more than one view (flip, or a scale other than 1 alone)."""
        return self.flip or self.scales != (1.0,)

    def describe(self) -> dict[str, str]:
        """The protocol as every output that records the source states it."""
        inference = "whole image"
        if self.crop is not None and self.stride is not None:
            (ch, cw), (sh, sw) = self.crop, self.stride
            inference = f"slide crop {ch}x{cw} stride {sh}x{sw}"
        tta = ["flip"] * self.flip
        if self.scales != (1.0,):
            tta.append("scales " + "/".join(f"{s:g}" for s in self.scales))
        return {"inference": inference, "tta": ", ".join(tta) or "none"}


def with_protocol(source: Source, protocol: Protocol, passes: int | None, seed: int) -> Source:
    """``source`` run as ``protocol`` says, with ``passes`` of Monte-Carlo dropout (or None).

    Raises:
        ValueError: a protocol for saved probabilities, Monte-Carlo dropout without dropout
            layers (or for saved probabilities).
    """
    if source.network is None:
        if protocol != Protocol():
            raise ValueError(f"{OPTIONS} need a network: saved probabilities cannot be rerun")
        return with_mc_dropout(source, passes, seed)
    from costseg.networks.sliding import SlidingWindow
    from costseg.networks.tta import TestTimeAugmentation

    source.description.update(protocol.describe())
    windows = ""
    if protocol.crop is not None and protocol.stride is not None:
        source.network = SlidingWindow(source.network, protocol.crop, protocol.stride)
        windows = f"logits averaged over sliding windows ({source.network.describe()})"
        source.probabilities = f"softmax of the {windows}"
    if not protocol.augments:
        source = with_mc_dropout(source, passes, seed)
        if passes is not None and windows:
            source.probabilities = f"{source.probabilities}; each pass's {windows}"
        return source
    net = TestTimeAugmentation(source.network, protocol.flip, protocol.scales, passes, seed)
    source.kind, source.network = "probs", net
    source.probabilities = net.describe() + (f"; each view's {windows}" if windows else "")
    if passes is not None:
        source.description["mc_dropout"] = {"passes": passes, "seed": seed}
    return source
