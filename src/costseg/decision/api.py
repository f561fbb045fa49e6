"""``decide`` and ``decide_mixtures``: the inputs checked, then the path the dispatcher picks."""

from __future__ import annotations

import functools

import torch

from costseg.decision import dispatch
from costseg.decision import inputs as checks
from costseg.decision.inputs import Inputs
from costseg.decision.label_maps import labels_of


def _exact_precision(fn):
    """Run ``fn`` outside autocast: mixed-precision validation must not lower the costs' float32
    / float64 precision (the certificates assume it)."""

    @functools.wraps(fn)
    def wrapper(probs: torch.Tensor, *args, **kwargs):
        with torch.autocast(probs.device.type, enabled=False):
            return fn(probs, *args, **kwargs)

    return wrapper


@_exact_precision
def decide(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
    roi: torch.Tensor | None = None,
    *,
    path: str | None = None,
) -> torch.Tensor:
    """Cost-based decision for every pixel, equal to :func:`~.reference.decide_reference` on
    every pixel (docs/definitions.md §1; deferring: §14; a regional value system: §21).

    Args:
        probs: (B, N, H, W) class probabilities >= 0 (float16/bfloat16/32/64, any device).
        cost: (N, N) cost matrix, rows = predicted class, columns = true class; ``None`` means the
            symmetric matrix (argmax, or maximum likelihood when priors are given). (N + 1, N)
            with a defer row (N <= 255): deferring is one more option, after the classes.
        priors: ``None``, (N,) global or (N, H, W) pixel-wise priors π > 0: the rule is applied to
            ``p / π`` (a per-pixel column scaling).
        roi: a regional value system's RoI map: (H, W), (1, H, W) or (B, H, W) integer ids, each
            pixel decided with the matrix ``cost[id]`` of a (K, N, N) or (K, N + 1, N) stack
            (:func:`costseg.costs.load_cost` of a file with ``regions:``); unused with one matrix.
        path: force a path (``triton``, ``numba``, ``torch``, ``reference``; see
            :mod:`~.dispatch`); default: ``$COSTSEG_DECISION_PATH``, else the fastest that fits.

    Returns:
        (B, H, W) int64 class indices; 255 where deferring costs least.

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])
    >>> decide(p, None).item(), decide(p, C).item(), decide(p, torch.cat([C, C[1:2]])).item()
    (0, 1, 1)
    >>> stack = torch.stack([1 - torch.eye(3), C])  # RoI 0: argmax; RoI 1: C
    >>> decide(p.expand(1, 3, 1, 2), stack, roi=torch.tensor([[0, 1]])).tolist()
    [[[0, 1]]]
    """
    n = checks.check_probs(probs)
    cost = checks.check_cost(cost, n)
    priors = checks.check_priors(priors, n, probs)
    cost, roi, regions = checks.check_regions(cost, roi, probs)
    chosen = dispatch.choose(Inputs.of(probs, priors, cost, regions=regions), path)
    if regions:
        return labels_of(chosen.decide_regional(probs, cost, priors, roi), cost)
    return labels_of(chosen.decide(probs, cost, priors), cost)


@_exact_precision
def decide_mixtures(
    probs: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    priors: torch.Tensor | None = None,
    *,
    path: str | None = None,
) -> torch.Tensor:
    """Decisions for K mixtures ``Σ_v w_kv C_v`` of V vertex matrices, in one pass.

    Equals ``decide(probs, mix_costs(vertices, weights)[k], priors)`` exactly for every k
    (:func:`~.reference.decide_mixtures_reference`), at the cost of V vertex cost maps plus a
    cheap mixing step, instead of K full evaluations: the cost is linear in C, and the vertices'
    shifts differ from the mixture's by a column constant.

    Args:
        probs: (B, N, H, W) class probabilities >= 0.
        vertices: (V, N, N) cost matrices, or (V, N + 1, N) with defer rows (N <= 255).
        weights: (K, V) mixture weights >= 0, each row with a positive entry
            (e.g. :func:`costseg.costs.barycentric_grid`).
        priors, path: as in :func:`decide`.

    Returns:
        (B, K, H, W) class indices, uint8 when N <= 256 (K label maps are large), else int64;
        255 where deferring costs least.

    >>> from costseg.costs import barycentric_grid, load_cost
    >>> V = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    >>> decide_mixtures(torch.rand(2, 19, 4, 5).softmax(1), V, barycentric_grid(0.1)).shape
    torch.Size([2, 66, 4, 5])
    """
    n = checks.check_probs(probs)
    checks.check_mixtures(vertices, weights, n)
    vertices, weights = vertices.detach(), weights.detach()  # decisions have no gradient
    priors = checks.check_priors(priors, n, probs)
    chosen = dispatch.choose(Inputs.of(probs, priors, vertices, len(weights)), path)
    return labels_of(chosen.decide_mixtures(probs, vertices, weights, priors), vertices)
