"""Decide and count in one pass: the confusion counts of a cost matrix's decisions, per image
and RoI, without a label map (the score of a candidate matrix in a search).

The decisions are those of :func:`~.reference.decide_reference` on every pixel (docs/definitions.md
§1, a defer row §14); the counts are :func:`costseg.metrics.functional.roi_confusion`'s, per
image. A search scores many matrices on the same probabilities, so the pixels are prepared once
(:func:`prepare_counts`: the labelled pixels of every image, side by side, with the row of the
counts each one goes to) and each matrix is one pass over them (:func:`count_decisions`). On the
CPU the pass is compiled (:mod:`.cpu.count_kernel`): each block of pixels is decided by the
single-rule kernel, certified in float32, and counted while in cache; the few pixels whose gap
the certificate cannot settle are decided again exactly. Elsewhere, ``decide`` and a bincount.
A regional value system's stack (docs/definitions.md §21) counts the pixels of the RoIs that
share a matrix, prepared apart once (:meth:`CountInputs.of_rois`), under that matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch

from costseg.classes import IGNORE_INDEX, NUM_ROIS
from costseg.decision import certificate as cert
from costseg.decision import certified
from costseg.decision import inputs as checks
from costseg.decision.api import decide
from costseg.decision.label_maps import DEFERRED
from costseg.decision.reference import shift
from costseg.decision.regions import distinct

ALIGN = 1024  # pixels padded to a multiple of the compiled kernel's block
PATHS = ("numba", "torch")


class DecisionCounts(NamedTuple):
    """What one pass counts for one matrix.

    Attributes:
        confusion: (B, R + 1, N, N + 1) int64: ``confusion[b, r, t, d]`` = labelled pixels of
            image b with true class t and decision d in RoI r (r = 0: the whole image), the
            deferred ones in column N (``roi_confusion``'s layout with ``deferred``, per image).
        agree: (B,) int64 labelled pixels whose decision is ``argmax_k p_k`` (ties to the lowest
            index): the pixels that agree with the Bayes rule.
    """

    confusion: torch.Tensor
    agree: torch.Tensor


@dataclass(frozen=True)
class CountInputs:
    """The labelled pixels of B images side by side, prepared once for many matrices
    (:func:`prepare_counts`); P pixels in all, padded (a multiple of 1024).

    Attributes:
        probs: (1, N, 1, P) the pixels' probabilities, their own type and device.
        priors: None, (N,) or (N, 1, P) the pixels' priors.
        cell: (P,) int32 the row of the counts of each pixel, ``(image · (R + 1) + RoI id) · N +
            true class``; -1: padding.
        argmax: (P,) int32 each pixel's ``argmax_k p_k``.
        q: (N, P) float32 ``p / π`` of pixel-wise priors, else ``p`` (global priors are folded
            into the matrix), contiguous: what the compiled pass reads (on the CPU; else None).
        images, rois: B and R.
    """

    probs: torch.Tensor
    priors: torch.Tensor | None
    cell: torch.Tensor
    argmax: torch.Tensor
    q: np.ndarray | None
    images: int
    rois: int
    by_roi: dict = field(default_factory=dict, compare=False, repr=False)  # of_rois', kept

    @property
    def classes(self) -> int:
        """N."""
        return self.probs.shape[1]

    def of_rois(self, rois: tuple[int, ...]) -> CountInputs | None:
        """The pixels of the RoI ids ``rois`` alone (None: there are none), prepared once and
        kept: what one matrix of a regional value system decides (docs/definitions.md §21)."""
        if rois not in self.by_roi:
            n, valid = self.classes, self.cell >= 0
            ids = torch.div(self.cell, n, rounding_mode="floor") % (self.rois + 1)
            take = (valid & torch.isin(ids, torch.tensor(rois, dtype=ids.dtype))).nonzero()[:, 0]
            self.by_roi[rois] = _taken(self, take) if len(take) else None
        return self.by_roi[rois]


def prepare_counts(
    probs: torch.Tensor,
    labels: torch.Tensor,
    roi: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    num_rois: int = NUM_ROIS,
    ignore_index: int = IGNORE_INDEX,
) -> CountInputs:
    """The labelled pixels of a batch, prepared for :func:`count_decisions` (one copy of them).

    Args:
        probs: (B, N, H, W) class probabilities >= 0 (float, any device).
        labels: (B, H, W) integer true classes in [0, N), or ``ignore_index`` (counted nowhere).
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois (0: in no RoI).
        priors: None, (N,) global, (N, H, W) pixel-wise or (B, N, H, W) each image's own priors
            π > 0 (what :func:`~.subsample.subsample` gives for pixel-wise priors).
        num_rois: R.
        ignore_index: the label of a pixel that counts nowhere.

    Raises:
        ValueError: inputs of the wrong shape, type or range.

    >>> probs = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1).expand(2, 3, 2, 2)
    >>> inputs = prepare_counts(probs, torch.tensor([[[0, 1], [2, 255]]] * 2), num_rois=1)
    >>> inputs.images, inputs.classes, inputs.cell[:7].tolist()
    (2, 3, [0, 1, 2, 6, 7, 8, -1])
    """
    n = checks.check_probs(probs)
    b, _, h, w = probs.shape
    _check_labels(labels, roi, (b, h, w), n, num_rois, ignore_index)
    per_image = priors is not None and torch.as_tensor(priors).ndim == 4
    if per_image:
        priors = torch.as_tensor(priors).to(probs.device)
        if priors.shape != probs.shape or not bool((priors > 0).all()):
            raise ValueError(
                f"each image's priors must be > 0 and {tuple(probs.shape)}, got "
                f"{tuple(priors.shape)}"
            )
    else:
        priors = checks.check_priors(priors, n, probs)
    labelled = labels != ignore_index
    roi_ids = torch.zeros_like(labels) if roi is None else roi.expand(b, h, w)
    cell = (
        torch.arange(b, device=labels.device).view(b, 1, 1) * (num_rois + 1) + roi_ids
    ) * n + labels.long()
    take = [labelled[i].flatten().nonzero()[:, 0].to(probs.device) for i in range(b)]
    pad = -sum(len(t) for t in take) % ALIGN

    def gathered(values: torch.Tensor, fill: float) -> torch.Tensor:  # (B, C, H, W) → (C, P)
        parts = [values[i].flatten(1).index_select(1, t) for i, t in enumerate(take)]
        return torch.cat([*parts, values.new_full((values.shape[1], pad), fill)], 1)

    flat_probs = gathered(probs.detach(), 0.0)
    pixel_priors = None
    if priors is not None and priors.ndim > 1:
        pixel_priors = gathered(priors if per_image else priors.expand(b, -1, -1, -1), 1.0)
        priors = pixel_priors.view(n, 1, -1)
    cells = gathered(cell[:, None].to(probs.device), -1)[0].to(torch.int32)
    argmax = flat_probs.argmax(0).to(torch.int32)
    q = None
    if probs.device.type == "cpu":
        q = flat_probs.float()
        q = (q if pixel_priors is None else q / pixel_priors.float()).contiguous().numpy()
    return CountInputs(flat_probs.view(1, n, 1, -1), priors, cells, argmax, q, b, num_rois)


def count_decisions(
    inputs: CountInputs, cost: torch.Tensor | None = None, *, path: str | None = None
) -> DecisionCounts:
    """Decide every prepared pixel by ``cost`` and count, in one pass: equal to
    :func:`~.reference.decide_reference` on each image then a bincount.

    Args:
        inputs: the pixels (:func:`prepare_counts`), for any number of matrices.
        cost: (N, N) cost matrix or (N + 1, N) with a defer row; None: symmetric; a regional
            value system's (R + 1, N(+1), N) stack: each pixel decided by its RoI's matrix
            (docs/definitions.md §21).
        path: ``numba`` (the compiled pass: CPU, the default there) or ``torch`` (``decide``
            and a bincount: any device, the default elsewhere).

    Returns:
        :class:`DecisionCounts`: (B, R + 1, N, N + 1) confusion counts, (B,) agreements.

    >>> probs = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    >>> inputs = prepare_counts(probs, torch.tensor([[[0, 1], [2, 255]]]), num_rois=0)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])  # decides class 1
    >>> counts = count_decisions(inputs, C, path="torch")
    >>> counts.confusion[0, 0].tolist(), counts.agree.tolist()
    ([[0, 1, 0, 0], [0, 1, 0, 0], [0, 1, 0, 0]], [0])
    """
    n = inputs.classes
    cost = checks.check_cost(cost, n)
    if len(distinct(cost)[0]) > 1:
        return _by_roi(inputs, cost, path)
    cost = cost[:1]
    path = path or ("numba" if inputs.q is not None else "torch")
    if path not in PATHS or (path == "numba" and inputs.q is None):
        raise ValueError(f"count path must be one of {', '.join(PATHS)} (numba: on the CPU)")
    with torch.autocast(inputs.probs.device.type, enabled=False):  # the certificates' precision
        if path == "torch":
            rows = decide(inputs.probs, cost[0], inputs.priors).flatten().long()
            rows = rows.masked_fill_(rows == DEFERRED, n)
        else:
            return _compiled(inputs, cost)
    valid = inputs.cell >= 0
    cell, rows = inputs.cell[valid].long(), rows[valid]
    total = inputs.images * (inputs.rois + 1) * n
    counts = torch.bincount(cell * (n + 2) + rows, minlength=total * (n + 2)).view(total, n + 2)
    agree = rows == inputs.argmax[valid]
    counts[:, n + 1] = torch.bincount(cell[agree], minlength=total)
    return _per_roi(counts, inputs)


def decide_counts(
    probs: torch.Tensor,
    cost: torch.Tensor | None,
    labels: torch.Tensor,
    roi: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    num_rois: int = NUM_ROIS,
) -> DecisionCounts:
    """:func:`count_decisions` of :func:`prepare_counts` (for one matrix; for many, prepare the
    pixels once). Arguments as there.

    >>> probs = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> deferring = torch.tensor([[0.0, 1, 1], [1, 0, 1], [1, 1, 0], [0.4, 0.4, 0.4]])
    >>> counts = decide_counts(probs, deferring, torch.tensor([[[0]]]), num_rois=0)
    >>> counts.confusion[0, 0, 0].tolist(), counts.agree.tolist()  # deferred: the last column
    ([0, 0, 0, 1], [0])
    """
    return count_decisions(prepare_counts(probs, labels, roi, priors, num_rois), cost)


def _by_roi(inputs: CountInputs, stack: torch.Tensor, path: str | None) -> DecisionCounts:
    """The counts of a regional stack (R + 1, M, N): the pixels of the RoIs that share a matrix
    counted under it (:meth:`CountInputs.of_rois`), the counts summed (each pixel lies in one
    RoI)."""
    if len(stack) != inputs.rois + 1:
        raise ValueError(f"a regional value system for {inputs.rois} RoIs stacks "
                         f"{inputs.rois + 1} matrices, got {len(stack)}")  # fmt: skip
    b, n = inputs.images, inputs.classes
    confusion = torch.zeros(b, inputs.rois + 1, n, n + 1, dtype=torch.int64)
    agree = torch.zeros(b, dtype=torch.int64)
    matrices, index = distinct(stack)
    for d, matrix in enumerate(matrices):
        pixels = inputs.of_rois(tuple(r for r in range(len(stack)) if index[r] == d))
        if pixels is not None:
            counts = count_decisions(pixels, matrix, path=path)
            confusion, agree = confusion + counts.confusion.cpu(), agree + counts.agree.cpu()
    device = inputs.probs.device
    return DecisionCounts(confusion.to(device), agree.to(device))


def _taken(inputs: CountInputs, take: torch.Tensor) -> CountInputs:
    """The prepared pixels at positions ``take`` (P',), padded again to a multiple of
    :data:`ALIGN` (probabilities 0, priors 1, cell -1)."""
    pad = -len(take) % ALIGN

    def taken(values: torch.Tensor, fill: float) -> torch.Tensor:  # (..., P) → (..., P' + pad)
        part = values.index_select(-1, take.to(values.device))
        return torch.cat([part, part.new_full((*part.shape[:-1], pad), fill)], -1)

    priors = inputs.priors
    if priors is not None and priors.ndim > 1:
        priors = taken(priors, 1.0)
    q = None
    if inputs.q is not None:
        q = taken(torch.from_numpy(inputs.q), 0.0).contiguous().numpy()
    return CountInputs(taken(inputs.probs, 0.0), priors, taken(inputs.cell, -1),
                       taken(inputs.argmax, 0), q, inputs.images, inputs.rois)  # fmt: skip


def _compiled(inputs: CountInputs, cost: torch.Tensor) -> DecisionCounts:
    """The compiled pass (:func:`.cpu.count_kernel.count_blocks`) over every pixel, then the
    pixels it left open decided again exactly and counted."""
    from costseg.decision.cpu.count_kernel import count_blocks  # numba: loaded where used
    from costseg.decision.cpu.sparse_kernel import BLOCK, reference_pixels
    from costseg.decision.cpu.sparse_rule import SparseRule
    from costseg.workers import in_pieces

    n, m = inputs.classes, cost.shape[1]
    shifted = shift(cost)
    fast = certified.prepare(cost, inputs.probs, inputs.priors, cert.reference_eps(n, False))
    rule = SparseRule(fast, cost, shifted)
    args = (inputs.q, rule.program, rule.certificate, inputs.cell.numpy(), inputs.argmax.numpy())
    pieces = in_pieces(count_blocks, args, inputs.q.shape[1], BLOCK) if inputs.q.size else []
    total = inputs.images * (inputs.rois + 1) * n
    counts = np.zeros((total, n + 2), np.int64)  # decisions 0..N (deferred: N), agreements
    for first, part, _, _ in pieces:
        counts[first : first + len(part), :m] += part[:, :m]
        counts[first : first + len(part), n + 1] += part[:, m]
    opened = np.concatenate([np.empty(0, np.int64)] + [piece[2] for piece in pieces])
    if len(opened):
        rows = np.full(len(opened), -1, np.int64)
        if rule.reference64 is not None:  # q is p: the compiled reference
            values = np.concatenate([piece[3] for piece in pieces])
            which = np.zeros(len(opened), np.uint8)  # one matrix
            in_pieces(reference_pixels, (values, *rule.reference64, which, rows), len(opened))
        rest = np.flatnonzero(rows < 0)  # NaN costs, or q is not p: the float64 settling
        if len(rest):
            exact = fast.exact_q(0, torch.from_numpy(opened[rest]).to(inputs.probs.device))
            rows[rest] = fast.settle(exact, shifted.to(exact.device)).cpu().numpy()
        cell = inputs.cell.numpy()[opened]
        np.add.at(counts, (cell, rows), 1)
        np.add.at(counts[:, n + 1], cell, rows == inputs.argmax.numpy()[opened])
    return _per_roi(torch.from_numpy(counts), inputs)


def _per_roi(counts: torch.Tensor, inputs: CountInputs) -> DecisionCounts:
    """(B·(R + 1)·N, N + 2) counts per RoI id (decisions, then agreements) → the whole image
    and each RoI."""
    n, r1 = inputs.classes, inputs.rois + 1
    counts = counts.view(inputs.images, r1, n, n + 2).to(inputs.probs.device)
    whole = counts[:, :, :, : n + 1].sum(1, keepdim=True)
    confusion = torch.cat([whole, counts[:, 1:, :, : n + 1]], 1)
    return DecisionCounts(confusion, counts[..., n + 1].sum((1, 2)))


def _check_labels(labels, roi, shape: tuple, n: int, num_rois: int, ignore_index: int) -> None:
    """(B, H, W) integer labels in [0, N) or ``ignore_index``; None, (H, W) or (B, H, W) RoI
    ids in 0..num_rois."""
    if labels.shape != shape or labels.is_floating_point() or labels.is_complex():
        raise ValueError(
            f"labels must be an integer {shape} tensor, got {labels.dtype} {tuple(labels.shape)}"
        )
    bad = ((labels < 0) | (labels >= n)) & (labels != ignore_index)
    if bad.any():
        raise ValueError(f"labels must lie in [0, {n}) or be {ignore_index}, got {labels[bad][0]}")
    if roi is None:
        return
    if roi.shape not in (shape, shape[1:]) or roi.is_floating_point():
        raise ValueError(
            f"roi must be an integer {shape} or {shape[1:]} tensor, got "
            f"{roi.dtype} {tuple(roi.shape)}"
        )
    if roi.numel() and (int(roi.min()) < 0 or int(roi.max()) > num_rois):
        raise ValueError(f"roi ids must lie in 0..{num_rois}")
