"""The decision layer: per-pixel argmin of expected cost (SPEC §1).

``d(x; C) = argmin_k' Σ_k C[k', k] · p(k|x) / π(k)``, ties to the lowest class index.

Two details make it exact and fast:

* Expected costs are summed in float64 and, before that, each column of ``C`` is shifted by its
  largest entry (a column constant changes every row's cost equally, hence no decision). The
  symmetric matrix then becomes ``-λI``: its costs are ``-λ p`` bit for bit, so exact ties in
  ``p`` reach the argmin untouched and the robotistic rule *is* argmax.
* Work runs in chunks of pixels that stay in cache on the CPU; on a GPU in one piece.
  Mixtures mix the few vertex cost maps (the cost is linear in ``C``) and skip every pixel whose
  decision cannot change anywhere on the mixture simplex.
"""

from __future__ import annotations

import torch
from torch import nn

CPU_CHUNK = 16384  # pixels per chunk on the CPU: (N × chunk) float64 stays in L2
MIX_BLOCK = 1 << 21  # mixed costs held at once (K × pixels × candidates), 16 MB of float64


def decide(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Cost-based decision for every pixel.

    Args:
        probs: (B, N, H, W) class probabilities (any float dtype, any device).
        cost: (N, N) cost matrix, rows = predicted class, columns = true class; ``None`` means the
            symmetric matrix (argmax, or maximum likelihood when priors are given).
        priors: ``None``, (N,) global or (N, H, W) pixel-wise priors π: the rule is applied to
            ``p / π`` (a per-pixel column scaling).

    Returns:
        (B, H, W) int64 class indices.

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])
    >>> decide(p, None).item(), decide(p, C).item()
    (0, 1)
    """
    shifted = _shift(_costs(cost, probs))
    # min(dim).indices: first minimum like argmin, but much faster over a non-inner dim.
    return _run(probs, shifted, priors, lambda e, out: out[0].copy_(e.min(0).indices))[:, 0]


def decide_mixtures(
    probs: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Decisions for K mixtures ``Σ_v w_kv C_v`` of V vertex matrices, in one pass.

    Equals ``decide(probs, Σ_v w_kv C_v, priors)`` for every k (float64 rounding aside), at the
    cost of V vertex cost maps plus a cheap mixing step, instead of K full evaluations.

    Args:
        probs: (B, N, H, W) class probabilities.
        vertices: (V, N, N) cost matrices.
        weights: (K, V) mixture weights (e.g. :func:`costseg.costs.barycentric_grid`).
        priors: as in :func:`decide`.

    Returns:
        (B, K, H, W) class indices, uint8 when N <= 256 (K label maps are large), else int64.

    >>> from costseg.costs import barycentric_grid, load_cost
    >>> V = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    >>> decide_mixtures(torch.rand(2, 19, 4, 5).softmax(1), V, barycentric_grid(0.1)).shape
    torch.Size([2, 66, 4, 5])
    """
    if vertices.ndim != 3 or weights.ndim != 2 or weights.shape[1] != vertices.shape[0]:
        raise ValueError(
            f"expected vertices (V, N, N) and weights (K, V), got {tuple(vertices.shape)} "
            f"and {tuple(weights.shape)}"
        )
    shifted = _shift(torch.stack([_costs(c, probs) for c in vertices]))
    mix = weights.to(device=probs.device, dtype=torch.float64)
    dtype = torch.uint8 if probs.shape[1] <= 256 else torch.long  # K label maps add up
    return _run(probs, shifted, priors, lambda e, out: _mixed_argmin(e, mix, out), len(mix), dtype)


class DecisionLayer(nn.Module):
    """``nn.Module`` form of :func:`decide_mixtures` (of :func:`decide` when K = 1).

    The matrices are non-persistent buffers: they follow ``.to(device)`` but never enter a
    checkpoint, so a checkpoint cannot override the cost the user asked for.

    >>> from costseg.costs import load_cost
    >>> layer = DecisionLayer(torch.stack([load_cost("robotistic"), load_cost("egoistic")]))
    >>> layer(torch.rand(1, 19, 8, 8).softmax(1)).shape     # two rules, one pass
    torch.Size([1, 2, 8, 8])
    """

    def __init__(self, vertices: torch.Tensor, weights: torch.Tensor | None = None) -> None:
        super().__init__()
        vertices = torch.as_tensor(vertices, dtype=torch.float64)
        if weights is None:
            weights = torch.eye(len(vertices), dtype=torch.float64)
        self.register_buffer("vertices", vertices, persistent=False)
        self.register_buffer("weights", torch.as_tensor(weights, dtype=torch.float64), False)

    def forward(self, probs: torch.Tensor, priors: torch.Tensor | None = None) -> torch.Tensor:
        """(B, N, H, W) probabilities → (B, K, H, W) decisions."""
        return decide_mixtures(probs, self.vertices, self.weights, priors)


def _costs(cost: torch.Tensor | None, probs: torch.Tensor) -> torch.Tensor:
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(
            f"probs must be a float (B, N, H, W) tensor, got {probs.dtype} {tuple(probs.shape)}"
        )
    n = probs.shape[1]
    if cost is None:
        return 1 - torch.eye(n, dtype=torch.float64, device=probs.device)
    if cost.shape != (n, n):
        raise ValueError(f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}")
    return cost.to(device=probs.device, dtype=torch.float64)


def _shift(costs: torch.Tensor) -> torch.Tensor:
    # Subtracting a per-column constant leaves every decision unchanged (see module docstring).
    return costs - costs.amax(dim=-2, keepdim=True)


def _run(probs, shifted, priors, pick, k: int = 1, dtype=torch.long) -> torch.Tensor:
    """Expected costs (N, P) or (V, N, P) chunk by chunk; ``pick`` writes (K, P) labels."""
    b, n, h, w = probs.shape
    flat = probs.reshape(b, n, h * w)
    scale = _flat_priors(priors, n, h, w, probs.device)
    chunk = CPU_CHUNK if probs.device.type == "cpu" else h * w
    out = torch.empty(b, k, h * w, dtype=dtype, device=probs.device)
    for i in range(b):
        for s in range(0, h * w, chunk):
            q = flat[i, :, s : s + chunk].to(torch.float64)
            if scale is not None:
                q = q / (scale if scale.shape[1] == 1 else scale[:, s : s + chunk])
            pick(shifted @ q, out[i, :, s : s + chunk])
    return out.view(b, k, h, w)


def _flat_priors(priors, n: int, h: int, w: int, device) -> torch.Tensor | None:
    if priors is None:
        return None
    priors = torch.as_tensor(priors).to(device=device, dtype=torch.float64)
    if priors.shape not in ((n,), (n, h, w)):
        raise ValueError(
            f"priors must be ({n},) or ({n}, {h}, {w}) for these probabilities, "
            f"got {tuple(priors.shape)}"
        )
    if not bool((priors > 0).all()):
        raise ValueError("priors must be > 0 everywhere (floor them, e.g. at 1e-5)")
    return priors.reshape(n, -1)


def _mixed_argmin(costs: torch.Tensor, weights: torch.Tensor, labels: torch.Tensor) -> None:
    """Argmin over classes of ``Σ_v w_kv costs[v]``: (V, N, P), weights (K, V) → labels (K, P).

    Where every vertex picks the same class, so does every mixture. Elsewhere only classes
    that no vertex winner beats in every vertex can win; those few are mixed for each k.
    """
    k = weights.shape[0]
    winners = costs.min(1).indices  # (V, P)
    labels.copy_(winners[0].expand(k, -1))
    contested = (winners != winners[:1]).any(0).nonzero().squeeze(1)
    if contested.numel() == 0:
        return
    costs, winners = costs[:, :, contested], winners[:, contested]
    candidate = _undominated(costs, winners)
    count = candidate.sum(0)
    descending = torch.arange(costs.shape[1], 0, -1, device=costs.device).unsqueeze(1)
    for m in count.unique().tolist():  # pixels with m candidates each, in blocks
        same = (count == m).nonzero().squeeze(1)
        for part in same.split(max(1, MIX_BLOCK // (k * m))):
            # Candidates first, in ascending class order, so ties go to the lowest index.
            index = (candidate[:, part] * descending).topk(m, dim=0).indices  # (m, P')
            picked = costs[:, :, part].gather(1, index.expand(costs.shape[0], -1, -1))
            mixed = (weights @ picked.flatten(1)).view(k, m, -1)
            labels[:, contested[part]] = index.gather(0, mixed.min(1).indices).to(labels.dtype)


def _undominated(costs: torch.Tensor, winners: torch.Tensor) -> torch.Tensor:
    """(N, P) bool: classes that no vertex winner beats in every vertex by more than rounding.

    A class beaten in every vertex by the same class is beaten at every mixture, so it can
    never be the argmin; vertex winners themselves always remain.
    """
    margin = 1e-9 * costs.abs().amax((0, 1)) + 1e-300
    candidate = torch.ones(costs.shape[1:], dtype=torch.bool, device=costs.device)
    for winner in winners:
        beaten_by = costs.gather(1, winner.expand(costs.shape[0], 1, -1))  # (V, 1, P)
        candidate &= ~(beaten_by + margin < costs).all(0)
    return candidate
