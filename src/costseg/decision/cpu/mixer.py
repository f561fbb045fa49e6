"""Mixtures decided on the CPU's cores in compiled passes (numba).

The same method as :class:`costseg.decision.tensor_ops.Mixer`, which runs it as a sequence of
tensor operations over a chunk, each a pass over memory. Here :func:`.mixture_kernel.decide_chunk`
decides a chunk's K mixtures block by block of pixels, computing the vertex
costs in cache (a float32 image without pixel-wise priors is one chunk, read where it lies);
the pairs left open (and every pair of a pixel whose ``T`` is not finite) go to the float64
re-check (stage 2): in the kernel, while the pixel is in cache, where its q is exactly p; else
compiled here (``_settle_pairs``). What stays open goes to the reference. Compiled on first use
and cached beside the modules.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from costseg.decision import certificate as cert
from costseg.decision.certified import CertifiedCosts
from costseg.decision.cpu import VERTICES
from costseg.decision.cpu.block_steps import certify64
from costseg.decision.cpu.mixture_kernel import decide_chunk
from costseg.decision.reference import reference_labels
from costseg.workers import in_pieces


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _settle_pairs(costs, weights, grid, pixel, g, eps, labels, unsure, start, stop):
    """Stage 2 for (mixture, pixel) pairs ``start:stop`` (``certify64``).

    Args:
        costs: (U, V, N + 1) float64 vertex costs of the U pixels (T last); weights: (K, V).
        grid, pixel: (R,) each pair's mixture and row of ``costs``.
        g: ``γ / (1 - γ)``, γ the rounding of the mixed costs; eps: the reference's, per T.
        labels, unsure: (R,) outputs.
    """
    mixed = np.empty(costs.shape[2])
    for r in range(start, stop):
        labels[r], unsure[r] = certify64(costs[pixel[r]], weights, grid[r], g, eps, mixed)


CHUNK = 1 << 17  # pixels per chunk: fewer, longer kernel calls than CPU_CHUNK
PIECES = 16  # per thread: a pixel's mixing costs more the more classes contest it, so finer
# pieces keep the threads busy to the end (4: one thread idled 25-65 ms of ~270 at the end)


class NumbaMixer:
    """Decisions of K mixtures, chunk by chunk, on the CPU's cores (see the module docstring).

    Args:
        fast: the vertices' ``CertifiedCosts`` (matrices, rounding ``γ`` of their costs, ``eps``).
        weights: (K, V) mixture weights.
        mix_gamma: the rounding of the mixed costs (``Mixer.gamma``).
    """

    def __init__(
        self, fast: CertifiedCosts, weights: torch.Tensor, mix_gamma: float, shifted: torch.Tensor
    ) -> None:
        k, v = weights.shape
        self.fast, self.weights = fast, np.zeros((VERTICES, k), np.float32)  # zeros: padding
        self.weights[:v] = weights.t().float().numpy()
        self.weights64, self.shifted = weights.double().contiguous().numpy(), shifted
        rows, n = fast.weight.shape  # zero-padded for block_products
        self.weight = np.zeros((-(-rows // 4) * 4, -(-n // 4) * 4), np.float32)
        self.weight[:rows, :n] = fast.weight.cpu().numpy()
        self.step = fast.probs.shape[2] if fast.read_as_is else CHUNK
        # The float64 re-check, in the kernel where its q is p exactly (float32 probabilities
        # read as they are; global priors folded into the weights as for float32: one rounding
        # of the matrix, one of the division, as q's in CertifiedCosts.gamma64); else no
        # columns.
        self.exact64 = np.zeros((n, 0))  # transposed: (N, V (N + 1))
        if fast.read_as_is:
            weight64, priors = fast.weight64.cpu(), fast.priors
            weight64 = weight64 if priors is None else weight64 / priors.double().cpu()
            self.exact64 = weight64.t().contiguous().numpy()
        # block_products' depth of rounding; the float tests' (see the certificate)
        self.params = cert.mixture_kernel_params(
            fast.gamma, fast.gamma64, mix_gamma, fast.eps, n, v
        )

    def chunk(self, q: torch.Tensor, labels: torch.Tensor, column: int) -> torch.Tensor:
        """(N, P) float32 q of pixels ``column :`` → their labels, written into the image's
        (K, H·W) ``labels``; returns (2, R) the mixture and the chunk's pixel of each pair left
        open."""
        q = q.detach().contiguous().numpy()
        vertices = self.weights64.shape[1]
        weights = self.weights, self.weights64, self.params
        args = (q, self.weight, self.exact64, vertices, *weights, labels.numpy(), column)
        pairs = in_pieces(decide_chunk, args, q.shape[1], per_thread=PIECES)
        return torch.from_numpy(np.concatenate(pairs, 1))

    def settle(self, q: torch.Tensor, grid: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
        """Labels (R,) of the pairs left open: stage 2 here, stage 3 (the reference) in torch.

        Args:
            q: (U, N) float64 ``p / π`` of the pixels (``CertifiedCosts.exact_q``).
            grid, pixel: (R,) each pair's mixture and row of ``q``.
        """
        fast = self.fast
        costs = (q @ fast.weight64.t()).view(len(q), *fast.rows).numpy()
        labels, unsure = np.empty(len(grid), np.int64), np.empty(len(grid), np.bool_)
        args = (costs, self.weights64, grid.numpy(), pixel.numpy(), *self.params[7:])
        in_pieces(_settle_pairs, (*args, labels, unsure), len(grid))
        labels, unsure = torch.from_numpy(labels), torch.from_numpy(unsure).nonzero()[:, 0]
        if len(unsure):
            matrices = self.shifted[grid[unsure]]
            labels[unsure] = reference_labels(q[pixel[unsure]], matrices)
        return labels
