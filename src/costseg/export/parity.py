"""The exported graph's labels against the reference decision (``docs/definitions.md §19``).

The graph decides in float32 on its own probabilities, with the matrix shifted to entries >= 0
(:func:`~costseg.export.graph.graph_decision`); :func:`decide_reference` decides in float64 on
PyTorch's. A pixel may differ only where the reference's costs of the two labels lie within the
sum of the graph's cost errors: float32 rounding (the bound of
:func:`costseg.decision.certificate.costs_gamma` times the cost itself, the matrix rounded twice:
cast and shift), the difference of the two probability maps weighed by the matrix, and the
reference's own rounding. A regional value system (docs/definitions.md §21): each pixel with
the matrix of its RoI, as the graph resized the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from costseg.decision import decide_reference
from costseg.decision.certificate import TEST_MARGIN, costs_gamma, gamma, reference_eps
from costseg.decision.label_maps import DEFERRED
from costseg.decision.reference import shift

__all__ = ["Parity", "parity"]


@dataclass(frozen=True)
class Parity:
    """How the graph's labels compare with the reference's.

    Attributes:
        pixels: pixels compared.
        differing: pixels whose labels differ.
        outside: differing pixels beyond the bound (0 when the graph is right).
    """

    pixels: int
    differing: int
    outside: int


def parity(
    reference_probs: Tensor,
    graph_probs: Tensor,
    labels: Tensor,
    cost: Tensor,
    priors: Tensor | None = None,
    roi: Tensor | None = None,
) -> Parity:
    """Compare the graph's ``labels`` with :func:`decide_reference` on ``reference_probs``.

    Args:
        reference_probs: (B, N, H, W) probabilities of the PyTorch network.
        graph_probs: (B, N, H, W) the graph's own probabilities (its ``probabilities`` output).
        labels: (B, H, W) the graph's labels (255: deferred).
        cost: (N, N) or (N + 1, N) matrix given to both; a regional stack (K, M, N) with ``roi``.
        priors: None, (N,) or (N, H, W) priors given to both.
        roi: (H, W) each pixel's matrix, the RoI map as the graph resized it (regional graphs).

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> parity(p, p, torch.tensor([[[1]]]), 1 - torch.eye(3))  # argmax is 0
    Parity(pixels=1, differing=1, outside=1)
    """
    reference = decide_reference(reference_probs, cost, priors, roi)
    where = (labels.long() != reference).nonzero(as_tuple=True)  # (b, y, x) of differing pixels
    n, count = reference_probs.shape[1], len(where[0])
    if count == 0:
        return Parity(labels.numel(), 0, 0)
    pi = torch.ones(n, 1, 1) if priors is None else priors.double().cpu()
    pi = (pi.view(n, 1, 1) if pi.ndim == 1 else pi).expand(n, *labels.shape[1:])
    pi = pi[:, where[1], where[2]].T  # (count, N)
    q_ref = reference_probs.double().permute(0, 2, 3, 1)[where].cpu() / pi
    q_graph = graph_probs.double().permute(0, 2, 3, 1)[where].cpu() / pi
    matrices = cost.double().cpu()
    matrices = matrices[roi.cpu().long()[where[1], where[2]]] if cost.ndim == 3 else matrices[None]
    shifted = shift(matrices)  # (count or 1, M, N): each pixel's matrix
    costs = _apply(shifted, q_ref)  # (count, M): the reference's costs
    scale = _apply(shifted.abs(), q_ref).amax(1, keepdim=True)  # the reference's T
    graph = matrices - matrices.amin(-2, keepdim=True)  # the graph's matrix, >= 0
    bound = (
        costs_gamma(gamma(2), 0.0, n) * _apply(graph, q_graph)
        + _apply(graph, (q_graph - q_ref).abs())
        + reference_eps(n, False) * scale
    )
    graph_rows = _rows(labels.long()[where].cpu(), n)
    reference_rows = _rows(reference[where].cpu(), n)
    pick = torch.arange(count)
    gap = costs[pick, graph_rows] - costs[pick, reference_rows]
    allowed = TEST_MARGIN * (bound[pick, graph_rows] + bound[pick, reference_rows])
    return Parity(labels.numel(), count, int((gap > allowed).sum()))


def _apply(matrices: Tensor, q: Tensor) -> Tensor:
    """(count, M): each pixel's (1 or count, M, N) matrix times its (count, N) q."""
    return torch.einsum("pmn,pn->pm", matrices.expand(len(q), -1, -1), q)


def _rows(labels: Tensor, n: int) -> Tensor:
    """The matrix rows of labels (255: the defer row N)."""
    return torch.where(labels == DEFERRED, n, labels)
