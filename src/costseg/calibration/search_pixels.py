"""The pixels a design's search scores on D1 (docs/definitions.md §20): every pixel that can
change a constraint's per-image loss, and a seeded share of the labelled pixels for the objective.

A constraint on class c in RoI r counts, in each image, the labelled pixels of c in r (recall and
the rates of deferral) and, for precision and Dice, the labelled pixels of r decided c whatever
their label. The first are all kept. Of the others, a pixel whose label is not c is left out only
when no candidate of the space can decide it c. With a :class:`~costseg.rules.design_spaces.Hull`
holding every candidate's class rows and ``E_k(C) = Σ_j C[k, j] p_j``, that holds where

    min_{C ∈ hull} (E_c(C) − E_k(C)) > 0   for some class k ≠ c

(E is linear in C: the smallest value over the hull is the smallest over its vertices plus the
negative part of each generator), since then k always costs less than c. A space without a hull
keeps every labelled pixel of r. So each image's constraint losses on the kept pixels equal those
on every pixel, for every candidate, and no image leaves a constraint's mean because of sampling.

>>> import torch
>>> from costseg.costs import symmetric_cost
>>> from costseg.rules.design_spaces import LagrangianSpace, lagrangian_directions
>>> space = LagrangianSpace(symmetric_cost(3), lagrangian_directions([(2, "recall")], 3))
>>> probs = torch.tensor([[0.9, 0.4], [0.1, 0.4], [0.0, 0.2]])   # (N, P): two pixels
>>> could_decide(probs, 2, space.hull()).tolist()   # μ ≤ 100 lifts p_2 = 0.2, never p_2 = 0
[False, True]
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from costseg.classes import IGNORE_INDEX
from costseg.rules.design_spaces import Hull

CHUNK = 1 << 16
"""Pixels whose expected costs are bounded at once (every vertex and generator)."""

MARGIN = 2 * 2**-24
"""The rounding margin of :func:`could_decide`: twice float32's unit roundoff u, per term.
Each expected cost errs by at most ``(N + 1) u`` times its sum of sizes ``A`` (N products,
the cost's own rounding), the gap's subtraction and the sum over the hull's M matrices by
``(M + 1) u`` more: ``(N + M + 2) u (A_c + A_k) ≤ 2u (N + M) (A_c + A_k)``."""

PixelNeed = tuple[int | None, int, bool]
"""What a constraint counts: its class (None: every class), its RoI id (0: the whole image), and
whether it counts pixels of other classes decided as its class (precision, Dice:
:meth:`costseg.metrics.requirements.Requirements.pixel_needs`)."""


def could_decide(probs: torch.Tensor, cls: int, hull: Hull) -> torch.Tensor:
    """Where some matrix of ``hull`` may decide ``cls`` (the module docstring's bound).

    Computed in float32, one matrix product per block of pixels, each matrix's gap
    ``E_c − E_k`` lowered by a bound on its rounding error (:data:`MARGIN` ``· (N + M)`` times
    the sums of sizes ``Σ_j |C[c, j]| p_j + Σ_j |C[k, j]| p_j``) before the least over the hull
    is taken: a pixel left out is one the float64 rule cannot decide as c.

    Args:
        probs: (N, P) probabilities of P pixels.
        cls: the class c.
        hull: a set holding every candidate's class rows (M matrices in all).

    Returns:
        (P,) bool: False only where some class k costs less than c under every matrix of the
        hull, beyond rounding.
    """
    vertices, generators = hull.vertices, hull.generators
    m, n, v = len(vertices) + len(generators), vertices.shape[-1], len(vertices)
    rows = torch.cat([vertices, generators]).reshape(m * n, n)
    both = torch.cat([rows, rows.abs()]).to(probs.device, torch.float32)
    out = []
    for start in range(0, probs.shape[1], CHUNK):
        costs, sizes = (both @ probs[:, start : start + CHUNK].float()).view(2, m, n, -1)
        error = MARGIN * (n + m) * (sizes[:, cls : cls + 1] + sizes)
        gap = costs[:, cls : cls + 1] - costs  # E_c − E_k of each matrix: (M, N, P)
        low = (gap[:v] - error[:v]).amin(0) + (gap[v:].clamp(max=0) - error[v:]).sum(0)
        out.append(~(low > 0).any(0))  # no k beats c under every matrix of the hull
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool, device=probs.device)


def constraint_pixels(
    probs: torch.Tensor,
    labels: torch.Tensor,
    roi: torch.Tensor | None,
    constraints: Sequence[PixelNeed],
    hull: Hull | None,
    ignore_index: int = IGNORE_INDEX,
) -> torch.Tensor:
    """The pixels that can change a constraint's per-image loss under some candidate.

    Args:
        probs: (B, N, H, W); labels: (B, H, W); roi: None or (B, H, W) RoI ids (None: RoI 0 only).
        constraints: what each constraint counts (:data:`PixelNeed`); a class of None
            (``coverage`` over every class) keeps every labelled pixel of its RoI.
        hull: the space's bound, or None: every labelled pixel of a precision or Dice
            constraint's RoI.
        ignore_index: the label of unlabelled pixels (never kept: they count nowhere).

    Returns:
        (B, H, W) bool.

    >>> labels = torch.tensor([[[11, 0, 255]]])
    >>> probs = torch.full((1, 19, 1, 3), 1 / 19)
    >>> constraint_pixels(probs, labels, None, [(11, 0, False)], None).tolist()   # a recall
    [[[True, False, False]]]
    """
    labelled = labels != ignore_index
    keep = torch.zeros_like(labelled)
    for cls, roi_id, other_labels in constraints:
        region = labelled if roi_id == 0 else labelled & (roi == roi_id)
        if cls is None:
            keep |= region
            continue
        keep |= region & (labels == cls)
        if not other_labels:
            continue
        if hull is None:
            keep |= region
            continue
        open_ = region & ~keep  # only these may still be left out
        where = open_.nonzero(as_tuple=True)
        pixels = probs.permute(1, 0, 2, 3)[:, where[0], where[1], where[2]]  # (N, P)
        keep[where] = could_decide(pixels, cls, hull)
    return keep


def gather_pixels(
    probs: torch.Tensor,
    labels: torch.Tensor,
    roi: torch.Tensor | None,
    keep: torch.Tensor,
    ignore_index: int = IGNORE_INDEX,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The ``keep`` pixels of each image side by side, in image order: (B, N, 1, S) probabilities,
    (B, 1, S) labels (padded with ``ignore_index``) and RoIs, S the most any image keeps.

    >>> probs = torch.arange(8.0).view(1, 2, 2, 2)
    >>> kept = gather_pixels(probs, torch.zeros(1, 2, 2, dtype=torch.long), None,
    ...                      torch.tensor([[[True, False], [False, True]]]))
    >>> kept[0][0, :, 0].tolist(), kept[1].tolist()
    ([[0.0, 3.0], [4.0, 7.0]], [[[0, 0]]])
    """
    b, n = probs.shape[:2]
    picks = [k.flatten().nonzero()[:, 0] for k in keep]
    size = max((len(p) for p in picks), default=0)
    out_probs = probs.new_zeros(b, n, 1, size)
    out_labels = labels.new_full((b, 1, size), ignore_index)
    out_roi = None if roi is None else roi.new_zeros(b, 1, size)
    for i, p in enumerate(picks):
        out_probs[i, :, 0, : len(p)] = probs[i].flatten(1)[:, p]
        out_labels[i, 0, : len(p)] = labels[i].flatten()[p]
        if out_roi is not None:
            out_roi[i, 0, : len(p)] = roi[i].flatten()[p]
    return out_probs, out_labels, out_roi
