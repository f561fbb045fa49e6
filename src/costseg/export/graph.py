"""The exported graph (``docs/definitions.md §19``): a network, its softmax and the decision of
§1 with the cost matrix, the priors and the temperature as inputs, as one ``nn.Module``. A
regional graph (§21) takes a stack of matrices and the RoI map instead of one matrix.

>>> from costseg.networks.base import ImageNetwork
>>> graph = DecisionGraph(ImageNetwork(nn.Conv2d(3, 4, 1)))
>>> image = torch.zeros(1, 3, 2, 2, dtype=torch.uint8)
>>> labels, margin = graph(image, 1 - torch.eye(4), torch.ones(4, 1, 1), torch.tensor(1.0))
>>> labels.dtype, tuple(margin.shape)
(torch.uint8, (1, 2, 2))
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from costseg.decision.label_maps import DEFERRED

__all__ = ["INPUTS", "OUTPUTS", "REGIONAL_INPUTS", "DecisionGraph", "graph_decision", "graph_roi"]

INPUTS = ("image", "cost", "priors", "temperature")
REGIONAL_INPUTS = (*INPUTS, "roi")
"""A regional graph's inputs: ``cost`` is a (K, N, N) or (K, N + 1, N) stack, ``roi`` an
(h, w) uint8 RoI map (docs/definitions.md §21)."""
OUTPUTS = ("labels", "margin", "probabilities")


def graph_roi(roi: Tensor, size: tuple[int, int]) -> Tensor:
    """An (h, w) uint8 RoI map as the graph resizes it to the labels' ``size``: nearest
    neighbour (ONNX Resize, nearest, asymmetric, floor), (H·W,) int64.

    >>> graph_roi(torch.tensor([[1, 2]], dtype=torch.uint8), (2, 4)).tolist()
    [1, 1, 2, 2, 1, 1, 2, 2]
    """
    resized = nn.functional.interpolate(roi[None, None].float(), size=size, mode="nearest")
    return resized.reshape(-1).long()


def graph_decision(
    probs: Tensor, cost: Tensor, priors: Tensor, roi: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """The decision of §1 in float32 as the graph computes it: the column-shifted matrix
    ``S = C − min_j C[j, ·]``, ``q = p / π``, the expected costs ``S q``, the argmin (ties to
    the lowest row; the defer row N gives 255) and the margin.

    A column constant changes every row's cost alike, so any shift decides as the reference
    (which subtracts the largest entry); the smallest keeps every term >= 0, so each cost errs
    by at most a relative float32 bound of itself, and the small costs of the rows that win
    keep their precision (the reference's shift puts the egoistic rule's costs near −1000).

    A regional value system (docs/definitions.md §21): a stack of K matrices, each shifted by its
    own columns' minima; every pixel's costs under all K, then those of its RoI's matrix.

    Args:
        probs: (B, H·W, N) float32 probabilities, classes last.
        cost: (N, N) or (N + 1, N) float32 matrix (rows: decisions, columns: true classes); with
            ``roi``, a (K, N, N) or (K, N + 1, N) stack.
        priors: (N, H, W) pixel-wise or (N, 1, 1) global priors (ones: no priors).
        roi: (H·W,) int64 each pixel's matrix in the stack (:func:`graph_roi`), or None.

    Returns:
        (B, H·W) uint8 labels (255: deferred) and (B, H·W) float32 margins: the second
        smallest minus the smallest expected cost.
    """
    n = probs.shape[-1]
    shifted = cost - cost.amin(dim=-2, keepdim=True)
    q = probs / priors.permute(1, 2, 0).reshape(-1, n)  # (H·W or 1, N): broadcast over B
    if roi is None:
        costs = torch.matmul(q, shifted.t())  # (B, H·W, M): classes last, as onnxruntime likes
    else:  # (B, H·W, K, M), then each pixel's matrix
        k, m = shifted.shape[0], shifted.shape[1]  # traced as the input's shape: dynamic
        every = torch.matmul(q, shifted.reshape(k * m, n).t())
        every = every.reshape(every.shape[0], every.shape[1], k, m)
        index = roi.view(1, -1, 1, 1).expand(every.shape[0], -1, 1, m)
        costs = every.gather(2, index).squeeze(2)
    best = costs.topk(2, dim=-1, largest=False).values
    rows = costs.argmin(dim=-1)  # the first minimum: ties to the lowest row
    labels = torch.where(rows >= n, torch.full_like(rows, DEFERRED), rows).to(torch.uint8)
    return labels, best[..., 1] - best[..., 0]


class DecisionGraph(nn.Module):
    """uint8 images, a cost matrix, priors and a temperature → labels, margins (and the
    probabilities with ``probabilities``).

    Args:
        network: maps (B, 3, H, W) uint8 RGB to (B, N, H, W) logits (its normalisation inside).
        probabilities: also return the (B, N, H, W) float32 probabilities.
        regional: take a regional value system (docs/definitions.md §21): ``cost`` a (K, M, N)
            stack and ``roi`` an (h, w) uint8 RoI map (:data:`REGIONAL_INPUTS`), resized to the
            labels' size (:func:`graph_roi`).
    """

    def __init__(
        self, network: nn.Module, probabilities: bool = False, regional: bool = False
    ) -> None:
        super().__init__()
        self.network, self.probabilities, self.regional = network, probabilities, regional
        self.eval()  # the exporter restores the mode it found: eval, for every layer

    def forward(
        self,
        image: Tensor,
        cost: Tensor,
        priors: Tensor,
        temperature: Tensor,
        roi: Tensor | None = None,
    ) -> tuple[Tensor, ...]:
        """See :func:`graph_decision`; the probabilities are ``softmax(logits / temperature)``."""
        logits = self.network(image) / temperature
        b, n, h, w = logits.shape
        probs = torch.softmax(logits.permute(0, 2, 3, 1).reshape(b, h * w, n), dim=-1)
        ids = graph_roi(roi, (h, w)) if self.regional else None
        labels, margin = graph_decision(probs, cost, priors, ids)
        labels, margin = labels.reshape(b, h, w), margin.reshape(b, h, w)
        if not self.probabilities:
            return labels, margin
        return labels, margin, probs.reshape(b, h, w, n).permute(0, 3, 1, 2)
