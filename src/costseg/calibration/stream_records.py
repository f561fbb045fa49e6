"""A frame of a stream kept so that its decision counts can be recomputed under any matrix of a
box (docs/definitions.md §22): the monitor's θ_t depends on the frames before t, so an evaluation
keeps each frame's record while the images pass (in any order, on any process) and walks the
stream afterwards.

Within a :class:`~costseg.rules.design_spaces.Hull` (§20's Lagrangian space with every μ_i in
``[0, μ_max]``) most labelled pixels are decided alike by every matrix: a pixel where no
constrained class can be decided (every other class's expected cost moves by the same μ-terms,
so the best of them stays best), or where one constrained class beats every other class under
every matrix (:func:`~costseg.calibration.search_pixels.decidable`, with float32 rounding bounded).
Those are counted once, under C₀; the others are kept with their probabilities, labels and RoIs.
So a record's counts under a matrix of the hull equal those of every pixel
(:func:`~costseg.decision.count_decisions` on the whole frame).

>>> import torch
>>> from costseg.costs import symmetric_cost
>>> from costseg.rules.design_spaces import LagrangianSpace, lagrangian_directions
>>> space = LagrangianSpace(symmetric_cost(3), lagrangian_directions([(2, "recall")], 3), high=3)
>>> probs = torch.tensor([[0.9, 0.5, 0.1], [0.1, 0.3, 0.1], [0.0, 0.2, 0.8]]).view(1, 3, 1, 3)
>>> frame = record_frame(probs[0], torch.tensor([[0, 2, 2]]), None, space.hull(), [2])
>>> frame.kept_pixels      # only the middle pixel may change
1
>>> frame.counts(space.matrix([3.0])).confusion[0, 0, 2].tolist()   # both 2s decided 2
[0, 0, 2, 0]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from costseg.calibration.search_pixels import decidable
from costseg.classes import IGNORE_INDEX, NUM_ROIS
from costseg.decision import DecisionCounts, decide_counts
from costseg.rules.design_spaces import Hull


@dataclass(frozen=True)
class FrameRecord:
    """One frame's exact record.

    Attributes:
        settled: the counts of the pixels every matrix of the hull decides alike:
            (1, R + 1, N, N + 1) confusion and (1,) agreements (int64).
        probs: (N, S) float32 the kept pixels' probabilities; ``labels`` (S,) uint8 train ids;
            ``roi`` (S,) uint8 RoI ids or None.
    """

    settled: DecisionCounts
    probs: torch.Tensor
    labels: torch.Tensor
    roi: torch.Tensor | None

    @property
    def kept_pixels(self) -> int:
        return self.probs.shape[1]

    @property
    def nbytes(self) -> int:
        """The record's size in bytes."""
        parts = [*self.settled, self.probs, self.labels, *([] if self.roi is None else [self.roi])]
        return sum(p.numel() * p.element_size() for p in parts)

    def counts(self, matrix: torch.Tensor) -> DecisionCounts:
        """The frame's decision counts under ``matrix`` (of the hull the record was made for)."""
        if not self.kept_pixels:
            return self.settled
        n = self.probs.shape[0]
        roi = None if self.roi is None else self.roi.long().view(1, 1, -1)
        labels = self.labels.long().view(1, 1, -1)
        rois = self.settled.confusion.shape[1] - 1
        kept = decide_counts(self.probs.view(1, n, 1, -1), matrix, labels, roi, num_rois=rois)
        settled = self.settled
        return DecisionCounts(settled.confusion + kept.confusion, settled.agree + kept.agree)


def record_frame(
    probs: torch.Tensor,
    labels: torch.Tensor,
    roi: torch.Tensor | None,
    hull: Hull,
    classes: Sequence[int],
    num_rois: int = NUM_ROIS,
) -> FrameRecord:
    """The record of one frame.

    Args:
        probs: (N, H, W) probabilities; labels: (H, W) train ids (``IGNORE_INDEX``: counted
            nowhere); roi: None or (H, W) RoI ids.
        hull: every matrix the record must serve (its first vertex C₀ counts the settled pixels).
        classes: the constrained classes (those whose μ-terms differ from the rest).
        num_rois: R.
    """
    labelled = labels != IGNORE_INDEX
    where = labelled.nonzero(as_tuple=True)
    pixels = probs[:, where[0], where[1]].float()  # (N, P) the labelled pixels
    may, always = decidable(pixels, classes, hull)
    changing = may.any(0) & ~always.any(0)
    kept = torch.zeros_like(labelled)
    kept[where[0][changing], where[1][changing]] = True
    settled_labels = labels.masked_fill(kept, IGNORE_INDEX)
    base = hull.vertices[0]
    settled = decide_counts(probs[None].float(), base, settled_labels[None], roi, num_rois=num_rois)
    return FrameRecord(
        DecisionCounts(settled.confusion.cpu(), settled.agree.cpu()),
        pixels[:, changing].cpu().contiguous(),
        labels[kept].to(torch.uint8).cpu(),
        None if roi is None else roi.expand_as(labels)[kept].to(torch.uint8).cpu(),
    )
