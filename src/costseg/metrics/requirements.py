"""Requirements of a value system (docs/definitions.md §20): K constraints ``R_i ≤ α_i`` and one
objective, measured per image from decision counts (and label maps where a constraint counts
segments or instances).

A constraint is a target of §7 / §9 (``person:roi1:recall>=0.95``): its per-image loss is the
guarantee's (:func:`~costseg.metrics.per_image.per_image_loss`), its level α the target's risk
level. The objective is ``agreement`` (the share of labelled pixels decided as argmax: the
smallest change from the Bayes rule), ``miou``, or a pixel rate of a class in a RoI, pooled
over the images.

>>> req = Requirements.parse(["person:roi1:recall>=0.75", "rider:roi0:precision>=0.5"])
>>> req.alphas, req.objective, req.maximize
((0.25, 0.5), 'agreement', True)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from costseg.metrics.functional.roi import mean_iou
from costseg.metrics.names import (
    DEFER_RATES,
    INSTANCE_RATES,
    PIXEL_RATE_PARTS,
    PIXEL_RATES,
    SEGMENT_RATES,
)
from costseg.metrics.per_image import per_image_counts, per_image_loss, pixel_parts
from costseg.metrics.selection import (
    Metric,
    Target,
    certifiable_level,
    parse_metric,
    parse_target,
)

OBJECTIVES = ("agreement", "miou")
"""The objectives that are no class rate: the share of pixels that agree with argmax, mIoU."""


@dataclass(frozen=True)
class Requirements:
    """The constraints and the objective of a design.

    Attributes:
        texts: the constraints as given; ``constraints`` parsed; ``alphas`` their levels α_i.
        objective: ``agreement``, ``miou`` or a pixel rate (:class:`Metric`); ``objective_text``
            as given; ``maximize``: whether larger is better.
    """

    texts: tuple[str, ...]
    constraints: tuple[Target, ...]
    alphas: tuple[float, ...]
    objective: str | Metric
    objective_text: str
    maximize: bool

    @classmethod
    def parse(
        cls, targets: Sequence[str], maximize: str | None = None, minimize: str | None = None
    ) -> Requirements:
        """The requirements of ``--require`` and ``--design_maximize`` / ``--design_minimize``
        (default: maximise agreement); ValueError naming what is wrong."""
        constraints = []
        for text in targets:
            try:
                constraints.append(parse_target(text))
            except ValueError as err:
                raise ValueError(f"--require {text}: {err}") from None
        constraints = tuple(constraints)
        alphas = tuple(certifiable_level(t, "--require") for t in targets)
        if maximize and minimize:
            raise ValueError("--design_maximize and --design_minimize: give one objective")
        text = minimize or maximize or "agreement"
        objective = text if text in OBJECTIVES else parse_metric(text)
        if isinstance(objective, Metric) and objective.metric not in (*PIXEL_RATES, *DEFER_RATES):
            raise ValueError(
                f"the objective of --design is {', '.join(OBJECTIVES)} or a pixel rate, such as "
                f"person:roi1:precision; got {text}"
            )
        return cls(tuple(targets), constraints, alphas, objective, text, minimize is None)

    @property
    def label_maps(self) -> bool:
        """Whether a constraint counts segments or instances (label maps, whole images)."""
        return any(t.metric in (*SEGMENT_RATES, *INSTANCE_RATES) for t in self.constraints)

    def pixel_needs(self) -> list[tuple[int | None, int, bool]]:
        """Per constraint, what its per-image loss counts: its class (None: every class), its
        RoI, and whether pixels of other classes decided as the class count (its false
        positives: precision, Dice); recall and the rates of deferral count the class's own.

        >>> Requirements.parse(["person:roi1:recall>=0.5", "car:roi0:precision>=0.5"]).pixel_needs()
        [(11, 1, False), (13, 0, True)]
        """
        out = []
        for t in self.constraints:
            parts = PIXEL_RATE_PARTS.get(t.metric)
            out.append((t.cls, t.roi, parts is not None and any(v != 0 for v in parts(0, 1, 0))))
        return out

    def losses(
        self,
        confusion: Tensor,
        preds: Tensor | None = None,
        labels: Tensor | None = None,
        roi: Tensor | None = None,
        instances: Tensor | None = None,
    ) -> Tensor:
        """(B, K) float64 per-image losses of the constraints (NaN where undefined).

        Args:
            confusion: (B, R + 1, N, N + 1) per-image counts of one matrix's decisions
                (:func:`costseg.decision.count_decisions`).
            preds, labels, roi, instances: (B, H, W) its label maps, the labels, (H, W) or
                (B, H, W) RoIs and instance ids: needed where :attr:`label_maps`.
        """
        out = []
        for t in self.constraints:
            if t.metric in (*PIXEL_RATES, *DEFER_RATES):
                parts = pixel_parts(confusion[:, t.roi], t.cls, t.metric)
            else:
                parts = per_image_counts(
                    preds[:, None], labels, roi, t.cls, t.roi, t.metric, instances=instances
                )[:, 0]
            out.append(per_image_loss(parts[:, None].cpu(), t.metric)[:, 0])
        return torch.stack(out, 1)

    def value(self, confusion: Tensor, agree: Tensor) -> float:
        """The objective pooled over images: ``confusion`` (R + 1, N, N + 1) and ``agree`` the
        summed counts of :func:`costseg.decision.count_decisions` (NaN where undefined)."""
        whole = confusion[0].double()
        if self.objective == "agreement":
            labelled = whole.sum().item()
            return agree.item() / labelled if labelled else math.nan
        if self.objective == "miou":  # a deferred pixel (the last column) misses its class
            n = whole.shape[0]
            return mean_iou(whole[:, :n], whole[:, n]).item()
        m = self.objective
        part, whole_count = pixel_parts(confusion[m.roi], m.cls, m.metric).double().tolist()
        return part / whole_count if whole_count else math.nan
