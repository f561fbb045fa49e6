"""The decision rule itself, in plain float64 torch: the definition every fast path equals.

See docs/definitions.md §1, §14 (a defer row) and §21 (a regional value system: the matrix of
each pixel's RoI). :func:`decide_reference` is slow and simple on purpose; the fast paths behind
:func:`costseg.decision.decide` give its decision on every pixel, bit for bit.
"""

from __future__ import annotations

import torch

from costseg.costs import cost_or_symmetric, mix_costs
from costseg.decision.inputs import check_defer, check_roi
from costseg.decision.label_maps import labels_of


def decide_reference(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    roi: torch.Tensor | None = None,
) -> torch.Tensor:
    """The cost-based decision of every pixel, by definition (docs/definitions.md §1).

    ``d(x) = argmin_k' Σ_k S[k', k] · q_k`` with ``S = C - max_j C[j, ·]`` (each column shifted
    by its largest entry: the same decisions, and the symmetric matrix becomes ``-λI``, so the
    robotistic rule is argmax, ties included) and ``q = p / π``. In float64: S, q (one division),
    the sum over k in ascending order (one rounded product and one rounded sum at a time), the
    argmin with ties to the lowest class index.

    A defer row (an (N + 1, N) matrix, docs/definitions.md §14) is one more candidate, last: the
    same shift (over all N + 1 rows), q and sums; the argmin over the N + 1 rows, so a class wins
    a tie with deferring; a deferred pixel gets the label 255.

    A regional value system (docs/definitions.md §21) is a stack of K matrices and a RoI map:
    pixel x is decided as above with the matrix ``C_{r(x)}`` of its RoI id r(x).

    Args:
        probs: (B, N, H, W) class probabilities >= 0, any float type and device.
        cost: (N, N) cost matrix (rows: predicted class, columns: true class), or (N + 1, N) with
            a defer row (N <= 255); None: symmetric. A regional value system: (K, N, N) or
            (K, N + 1, N), matrix r that of RoI id r (0: the default).
        priors: None, (N,) global or (N, H, W) pixel-wise priors π > 0.
        roi: with a regional ``cost``, (H, W), (1, H, W) or (B, H, W) integer RoI ids < K (one
            map for every image, or one per image); unused with one matrix.

    Returns:
        (B, H, W) int64 class indices, 255 where deferring costs least.

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])
    >>> decide_reference(p).item(), decide_reference(p, C).item()
    (0, 1)
    >>> decide_reference(p, torch.cat([C, torch.full((1, 3), 0.4)])).item()  # 0.4 < 0.7
    255
    >>> stack = torch.stack([1 - torch.eye(3), C])  # RoI 0: argmax; RoI 1: C
    >>> decide_reference(p.expand(1, 3, 1, 2), stack, roi=torch.tensor([[0, 1]])).tolist()
    [[[0, 1]]]
    """
    cost = cost_or_symmetric(cost, probs.shape[1])
    check_defer(cost, probs.shape[1])
    if cost.ndim == 3:
        return labels_of(regional_rows(probs, cost, priors, check_roi(roi, probs, cost)), cost)
    return labels_of(reference_rows(probs, cost, priors), cost)


def reference_rows(probs: torch.Tensor, cost: torch.Tensor, priors) -> torch.Tensor:
    """(B, H, W) int64 rows of :func:`decide_reference`'s argmin (a defer row: N), before they
    become labels (the ``reference`` path of :mod:`.dispatch`)."""
    b, _, h, w = probs.shape
    shifted = shift(cost.detach().to(probs.device, torch.float64))
    return reference_labels(_q(probs, priors), shifted[None]).view(b, h, w)


REGIONAL_STEP = 1 << 14  # pixels at once: their (step, M, N) float64 matrices


def regional_rows(probs: torch.Tensor, stack: torch.Tensor, priors, roi: torch.Tensor):
    """(B, H, W) int64 rows of the argmin of a regional value system, by definition: each pixel's
    sums with the shifted matrix of its RoI id, ``S_{r(x)}``, as :func:`reference_labels` sums
    (``stack``: (K, M, N); ``roi``: checked (B' , H, W) ids, B' = 1 or B)."""
    b, _, h, w = probs.shape
    shifted = shift(stack.detach().to(probs.device, torch.float64))  # each matrix's own shift
    ids = roi.to(probs.device).long().expand(b, h, w).reshape(-1)
    q, rows = _q(probs, priors), torch.empty(b * h * w, dtype=torch.long, device=probs.device)
    for s in range(0, len(q), REGIONAL_STEP):
        part = slice(s, s + REGIONAL_STEP)
        rows[part] = reference_labels(q[part], shifted[ids[part]])  # (P, M, N): one per pixel
    return rows.view(b, h, w)


def decide_mixtures_reference(
    probs: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, K, H, W) int64: :func:`decide_reference` on each mixed matrix ``mix_costs(vertices,
    weights)[k]`` (:func:`costseg.costs.mix_costs`), what ``decide_mixtures`` equals. Vertices
    (V, N + 1, N) carry defer rows: 255 marks the deferred pixels."""
    check_defer(vertices, probs.shape[1])
    return labels_of(reference_mixture_rows(probs, vertices, weights, priors), vertices)


def reference_mixture_rows(probs, vertices, weights, priors) -> torch.Tensor:
    """(B, K, H, W) int64 rows of :func:`decide_mixtures_reference`'s argmins (a defer row: N),
    before they become labels (the ``reference`` path of :mod:`.dispatch`)."""
    b, _, h, w = probs.shape
    matrices = mix_costs(vertices.detach(), weights.detach())
    shifted = shift(matrices.to(probs.device, torch.float64))[:, None]  # (K, 1, M, N)
    q = _q(probs, priors)
    step = max(1, (1 << 24) // q.numel())  # mixtures at once: (step, B·H·W, N) float64 costs
    labels = torch.cat(
        [reference_labels(q, shifted[k : k + step]) for k in range(0, len(shifted), step)]
    )
    return labels.view(-1, b, h, w).transpose(0, 1)


def _q(probs: torch.Tensor, priors) -> torch.Tensor:
    """(B·H·W, N) float64 ``p / π``."""
    n = probs.shape[1]
    return over_priors(probs.detach(), priors).permute(0, 2, 3, 1).reshape(-1, n)


def over_priors(probs: torch.Tensor, priors: torch.Tensor | None) -> torch.Tensor:
    """(B, N, H, W) float64 ``q = p / π``, one division per entry, with ``priors`` None, (N,)
    (the same for every pixel) or (N, H, W).

    >>> p = torch.tensor([0.5, 0.5]).view(1, 2, 1, 1)
    >>> over_priors(p, torch.tensor([0.25, 0.5])).flatten().tolist()
    [2.0, 1.0]
    """
    q = probs.double()
    if priors is None:
        return q
    priors = torch.as_tensor(priors).to(q.device, torch.float64)
    return q / (priors.view(-1, 1, 1) if priors.ndim == 1 else priors)


def shift(costs: torch.Tensor) -> torch.Tensor:
    """(..., R, N) matrices minus their columns' largest entries, over all R rows (a column
    constant changes every row's cost alike, hence no decision)."""
    return costs - costs.amax(dim=-2, keepdim=True)


def reference_labels(q: torch.Tensor, shifted: torch.Tensor) -> torch.Tensor:
    """The reference's sums and argmin: (R, N) float64 q and (..., R or 1, M, N) shifted matrices
    (M = N, or N + 1 with a defer row; R: one per pixel) → (..., R) int64 rows of the argmin."""
    costs = torch.zeros((), dtype=torch.float64, device=q.device)
    for k in range(q.shape[1]):  # ascending k, product and sum each rounded once
        costs = costs + shifted[..., k] * q[:, k, None]  # broadcasts to (..., R, M)
    return costs.min(-1).indices  # the first minimum: ties to the lowest index


def expected_costs(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    roi: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, K, H, W) float64 expected cost ``Σ_k C[k', k] q_k`` of each decision k' (the rows of
    ``cost``, a defer row last; None: symmetric), with ``q = p / π`` (``priors``: None, (N,) or
    (N, H, W)). The rule decides the row of least expected cost (docs/definitions.md §1). A
    regional stack (R + 1, K, N) with its ``roi`` map: each pixel's costs with its RoI's matrix
    (docs/definitions.md §21).

    >>> p = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
    >>> expected_costs(p).flatten().tolist()
    [0.5, 0.75, 0.75]
    """
    q = over_priors(probs, priors)
    cost = cost_or_symmetric(cost, probs.shape[1]).to(q)
    if cost.ndim == 2:
        return torch.einsum("jk,bkhw->bjhw", cost, q)
    b, n, h, w = q.shape
    ids = check_roi(roi, probs, cost).expand(b, h, w).reshape(-1)
    q = q.permute(0, 2, 3, 1).reshape(-1, n)
    out = q.new_empty(len(q), cost.shape[1])
    for r, matrix in enumerate(cost):  # each RoI's pixels with its matrix
        mine = (ids == r).nonzero()[:, 0]
        out[mine] = q[mine] @ matrix.t()
    return out.view(b, h, w, -1).permute(0, 3, 1, 2)
