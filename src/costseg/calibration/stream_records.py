"""A frame of a stream kept so that its decision counts can be recomputed under any matrix of a
box (docs/definitions.md §22): the monitor's θ_t depends on the frames before t, so an evaluation
keeps each frame's record while the images pass (in any order, on any process) and walks the
stream afterwards.

Within §20's Lagrangian space with every μ_i in ``[0, μ_max]`` most labelled pixels are decided
alike by every matrix: a pixel where no constrained class can be decided, or where one beats
every other class under every matrix (:func:`settled`). Every class outside the constrained set
moves by the same μ-terms, so the best of them (least ``E⁰``) is the only one to compare with;
each expected cost is affine in μ, so its least gap over the box is the gap at μ = 0 plus
``μ_max`` times each negative slope. Computed in float64, a pixel counts as settled only by a
margin far above the rounding. Those pixels are counted once, under C₀; the others are kept
with their probabilities, labels and RoIs. In §21's regional space a pixel of RoI r is decided by
``C_r``, which only the constraints on r and on RoI 0 move: it is settled within
:meth:`~costseg.rules.design_spaces.RegionalLagrangianSpace.region` r's box (as
:mod:`~costseg.calibration.search_pixels` bounds it by its own RoI's hull).
So a record's counts under a matrix of the space equal those of every pixel
(:func:`~costseg.decision.count_decisions` on the whole frame).

>>> import torch
>>> from costseg.costs import symmetric_cost
>>> from costseg.rules.design_spaces import LagrangianSpace, lagrangian_directions
>>> space = LagrangianSpace(symmetric_cost(3), lagrangian_directions([(2, "recall")], 3), high=3)
>>> probs = torch.tensor([[0.9, 0.5, 0.1], [0.1, 0.3, 0.1], [0.0, 0.2, 0.8]]).view(1, 3, 1, 3)
>>> frame = record_frame(probs[0], torch.tensor([[0, 2, 2]]), None, space, [2])
>>> frame.kept_pixels      # only the middle pixel may change
1
>>> frame.counts(space.matrix([3.0])).confusion[0, 0, 2].tolist()   # both 2s decided 2
[0, 0, 2, 0]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from costseg.calibration.search_pixels import CHUNK
from costseg.classes import IGNORE_INDEX, NUM_ROIS
from costseg.decision import DecisionCounts, decide_counts
from costseg.rules.design_spaces import LagrangianSpace, RegionalLagrangianSpace


@dataclass(frozen=True)
class FrameRecord:
    """One frame's exact record.

    Attributes:
        settled: the counts of the pixels every matrix of the space decides alike:
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

    def save(self, path: Path) -> None:
        """Write the record to ``path`` (a file of tensors: :meth:`load` reads it back)."""
        torch.save({"confusion": self.settled.confusion, "agree": self.settled.agree,
                    "probs": self.probs, "labels": self.labels, "roi": self.roi}, path)  # fmt: skip

    @classmethod
    def load(cls, path: Path) -> FrameRecord:
        """The record :meth:`save` wrote to ``path``."""
        parts = torch.load(path, weights_only=True)
        settled = DecisionCounts(parts["confusion"], parts["agree"])
        return cls(settled, parts["probs"], parts["labels"], parts["roi"])

    def counts(self, matrix: torch.Tensor) -> DecisionCounts:
        """The frame's decision counts under ``matrix`` (of the space the record was made for)."""
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
    space: LagrangianSpace,
    classes: Sequence[int],
    num_rois: int = NUM_ROIS,
) -> FrameRecord:
    """The record of one frame.

    Args:
        probs: (N, H, W) probabilities; labels: (H, W) train ids (``IGNORE_INDEX``: counted
            nowhere); roi: None or (H, W) RoI ids.
        space: every matrix the record must serve: C₀ (``base``) plus Σ μ_i A_i, μ_i in
            ``[0, space.high]`` (a regional space: each RoI's own, roi then required).
        classes: the constrained classes (those whose μ-terms differ from the rest).
        num_rois: R.
    """
    labelled = labels != IGNORE_INDEX
    where = labelled.nonzero(as_tuple=True)
    pixels = probs[:, where[0], where[1]].float()  # (N, P) the labelled pixels
    if isinstance(space, RegionalLagrangianSpace):
        if roi is None:
            raise ValueError("a regional space decides each pixel with its RoI's matrix: "
                             "give the frame's RoI map")  # fmt: skip
        ids = roi.expand_as(labels)[where]
        changing = torch.zeros(len(ids), dtype=torch.bool, device=ids.device)
        for r in ids.unique().tolist():  # each RoI's pixels within its own matrix's box
            own = ids == r
            changing[own] = ~settled(pixels[:, own], space.region(r), classes)
        base = space.bases()
    else:
        changing = ~settled(pixels, space, classes)
        base = torch.as_tensor(space.base, dtype=torch.float64)
    kept = torch.zeros_like(labelled)
    kept[where[0][changing], where[1][changing]] = True
    settled_labels = labels.masked_fill(kept, IGNORE_INDEX)
    counts = decide_counts(probs[None].float(), base, settled_labels[None], roi, num_rois=num_rois)
    return FrameRecord(
        DecisionCounts(counts.confusion.cpu(), counts.agree.cpu()),
        pixels[:, changing].cpu().contiguous(),
        labels[kept].to(torch.uint8).cpu(),
        None if roi is None else roi.expand_as(labels)[kept].to(torch.uint8).cpu(),
    )


def settled(probs: torch.Tensor, space: LagrangianSpace, classes: Sequence[int]) -> torch.Tensor:
    """Where every matrix of ``space`` decides alike (the module docstring's bound).

    Args:
        probs: (N, P) probabilities of P pixels.
        space: C₀ + Σ μ_i A_i with μ_i in [0, ``space.high``]; ``classes``: the constrained ones.

    Returns:
        (P,) bool.

    Raises:
        ValueError: directions that move the classes outside ``classes`` differently (not
            :func:`~costseg.rules.design_spaces.lagrangian_directions`').

    >>> from costseg.costs import symmetric_cost
    >>> from costseg.rules.design_spaces import lagrangian_directions
    >>> space = LagrangianSpace(symmetric_cost(2), lagrangian_directions([(1, "recall")], 2),
    ...                         high=1.0)
    >>> settled(torch.tensor([[0.9, 0.6, 0.2], [0.1, 0.4, 0.8]]), space, [1]).tolist()
    [True, False, True]
    """
    base = torch.as_tensor(space.base, dtype=torch.float64)[: probs.shape[0]].to(probs.device)
    directions = torch.as_tensor(space.directions, dtype=torch.float64).to(probs.device)
    k, n = len(directions), base.shape[-1]
    own = torch.as_tensor(sorted(set(classes)), dtype=torch.long, device=probs.device)
    others = torch.ones(n, dtype=torch.bool, device=probs.device)
    others[own] = False
    other = int(others.nonzero()[0])  # any class outside: they all move alike
    if not (directions[:, others] == directions[:, other : other + 1]).all():
        raise ValueError("the classes outside the constrained ones must move alike")
    moved = directions[:, torch.cat([own, own.new_tensor([other])])].reshape(-1, n)
    outside = base[others]
    # every quantity is at most max|C₀| + K μ_max; float64 errs by ~1e-15 of that
    margin = 1e-9 * (base.abs().max().item() + k * space.high)
    itself = torch.eye(len(own), len(own) + 1, dtype=torch.bool, device=probs.device)[..., None]
    out = []
    for start in range(0, probs.shape[1], CHUNK):
        p = probs[:, start : start + CHUNK].double()
        best = (outside @ p).min(0).values  # E⁰ of the best class outside
        e = torch.cat([base[own] @ p, best[None]])  # (C + 1, P) E⁰ of the candidates
        t = (moved @ p).view(k, len(own) + 1, -1)  # (K, C + 1, P) ∂E/∂μ_i
        gap = e[:-1, None] - e[None]  # (C, C + 1, P) E⁰_c − E⁰_q
        down = (t[:, :-1, None] - t[:, None]).clamp_(max=0).sum(0)  # Σ_i min(0, slope_i)
        total = t.sum(0)
        up = (total[:-1, None] - total[None]).sub_(down)  # Σ_i max(0, slope_i)
        beaten = gap.add(down, alpha=space.high)  # least E_c − E_q over the box
        beats = gap.neg_().sub_(up, alpha=space.high)  # least E_q − E_c
        may = ~((beaten > margin) & ~itself).any(1)  # (C, P) no q beats c under every matrix
        always = ((beats > margin) | itself).all(1)  # c beats every q under every matrix
        out.append(~may.any(0) | always.any(0))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool, device=probs.device)
