"""The checks of the decision layer's inputs, and what the dispatcher sees of them."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from costseg.costs import cost_or_symmetric, has_defer_row
from costseg.decision.label_maps import DEFERRED
from costseg.decision.regions import distinct


@dataclass(frozen=True)
class Inputs:
    """What decides which fast path fits (:mod:`costseg.decision.dispatch`).

    Attributes:
        shape: (B, N, H, W) of the probabilities; device, dtype: theirs.
        pixel_priors: whether priors are pixel-wise (N, H, W).
        vertices: V matrices (1 for ``decide``); mixtures: K (None for ``decide``).
        defer: whether the matrices carry a defer row ((N + 1, N), docs/definitions.md §14).
        regions: the distinct matrices of a regional value system decided with a RoI map
            (docs/definitions.md §21); 0: one matrix.
    """

    shape: tuple[int, ...]
    device: torch.device
    dtype: torch.dtype
    pixel_priors: bool = False
    vertices: int = 1
    mixtures: int | None = None
    defer: bool = False
    regions: int = 0

    @classmethod
    def of(
        cls,
        probs: torch.Tensor,
        priors,
        matrices: torch.Tensor,
        mixtures: int | None = None,
        regions: int = 0,
    ):
        """What the dispatcher sees of ``probs``, ``priors``, (V, R, N) ``matrices`` (V = 1 for
        ``decide``, even with a regional value system of ``regions`` distinct matrices)."""
        pixel_priors = priors is not None and priors.ndim > 1
        shape, defer, vertices = tuple(probs.shape), has_defer_row(matrices), len(matrices)
        vertices = 1 if regions else vertices
        return cls(
            shape, probs.device, probs.dtype, pixel_priors, vertices, mixtures, defer, regions
        )

    @property
    def pixels(self) -> int:
        """Pixels per image."""
        return self.shape[2] * self.shape[3]

    def describe(self) -> str:
        rule = "decide" if self.mixtures is None else f"decide_mixtures ({self.mixtures} mixtures"
        rule += "" if self.mixtures is None else f" of {self.vertices} vertices)"
        rule += f" with a RoI map and {self.regions} distinct matrices" if self.regions else ""
        priors = "pixel-wise priors" if self.pixel_priors else "no or global priors"
        priors += ", a defer row" if self.defer else ""
        return f"{rule} on {self.shape} {self.dtype} probabilities on {self.device}, {priors}"


def check_probs(probs: torch.Tensor) -> int:
    """N, the number of classes of (B, N, H, W) float probabilities."""
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(
            f"probs must be a float (B, N, H, W) tensor, got {probs.dtype} {tuple(probs.shape)}"
        )
    return probs.shape[1]


def check_cost(cost: torch.Tensor | None, n: int) -> torch.Tensor:
    """(1, N, N) float64 on the CPU (small: prepared there), (1, N + 1, N) with a defer row; None:
    the symmetric matrix. A regional value system's (K, N, N) or (K, N + 1, N) stack: as it is
    (docs/definitions.md §21)."""
    cost = cost_or_symmetric(cost, n)
    if cost.shape[-2:] not in ((n, n), (n + 1, n)) or cost.ndim not in (2, 3) or not cost.numel():
        raise ValueError(
            f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}; with a defer "
            f"row it is {n + 1}x{n}; a regional value system stacks such matrices (K, {n}, {n})"
        )
    check_defer(cost, n)
    cost = cost.detach().to(torch.float64).cpu()
    return cost if cost.ndim == 3 else cost[None]


def check_regions(cost: torch.Tensor, roi, probs: torch.Tensor) -> tuple:
    """``check_cost``'s (K, M, N) matrices with their RoI map: (matrices, checked RoI map or None,
    the number of distinct matrices of a regional value system, 0 for one matrix). A stack
    whose matrices are all equal is one plain matrix (the same labels, docs/definitions.md §21);
    with one matrix, ``roi`` is unused."""
    if len(cost) == 1:
        return cost, None, 0
    roi = check_roi(roi, probs, cost)
    regions = len(distinct(cost)[0])
    return (cost[:1], None, 0) if regions == 1 else (cost, roi, regions)


def check_roi(roi: torch.Tensor | None, probs: torch.Tensor, stack: torch.Tensor) -> torch.Tensor:
    """(B' , H, W) integer RoI ids on the probabilities' device (B' = 1 or B), each < K, the
    matrices of the (K, M, N) ``stack`` of a regional value system (docs/definitions.md §21).

    Raises:
        ValueError: no map, a float map, a map of another size, an id without a matrix.
    """
    b, _, h, w = probs.shape
    if len(stack) > 256:
        raise ValueError(f"a regional value system has at most 256 matrices, got {len(stack)}")
    if roi is None:
        raise ValueError(
            f"a regional value system ({len(stack)} matrices) decides with a RoI map: give roi, "
            f"({h}, {w}) or (1 or {b}, {h}, {w}) integer RoI ids"
        )
    roi = torch.as_tensor(roi)
    roi = roi[None] if roi.ndim == 2 else roi
    if roi.is_floating_point() or roi.is_complex() or roi.dtype == torch.bool:
        raise ValueError(f"the RoI map must hold integer RoI ids, got {roi.dtype}")
    if roi.ndim != 3 or roi.shape[1:] != (h, w) or len(roi) not in (1, b):
        raise ValueError(
            f"the RoI map must be ({h}, {w}) or (1 or {b}, {h}, {w}) for these probabilities, "
            f"got {tuple(roi.shape)}"
        )
    low, high = _extremes(roi)
    if low < 0 or high >= len(stack):
        bad = low if low < 0 else high
        raise ValueError(
            f"the RoI map holds id {bad}; the regional value system has matrices for ids 0 … "
            f"{len(stack) - 1}"
        )
    return roi.to(probs.device)


def check_mixtures(vertices: torch.Tensor, weights: torch.Tensor, n: int) -> None:
    """(V, N, N) or, with defer rows, (V, N + 1, N) vertex matrices and (K, V) weights >= 0,
    each row with a positive entry."""
    shapes = ((n, n), (n + 1, n))
    if vertices.shape[1:] not in shapes or weights.ndim != 2 or weights.shape[1] != len(vertices):
        raise ValueError(
            f"expected vertices ({n} x {n} matrices, or {n + 1} x {n} with defer rows) and "
            f"weights (K, V), got {tuple(vertices.shape)} and {tuple(weights.shape)}"
        )
    check_defer(vertices, n)
    if not bool((weights >= 0).all() and (weights > 0).any(1).all()):
        raise ValueError("mixture weights must be >= 0 with a positive entry in each row")


def check_defer(matrices: torch.Tensor, n: int) -> None:
    """A defer row needs N <= 255 classes: a deferred pixel's label, 255, is then no class."""
    if has_defer_row(matrices) and n > DEFERRED:
        raise ValueError(
            f"a defer row needs at most {DEFERRED} classes (a deferred pixel is labelled "
            f"{DEFERRED}), got {n}"
        )


def check_priors(priors, n: int, probs: torch.Tensor) -> torch.Tensor | None:
    """None, (N,) or (N, H, W) priors > 0 on the probabilities' device."""
    if priors is None:
        return None
    h, w = probs.shape[2:]
    priors = torch.as_tensor(priors).to(probs.device)
    priors = priors if priors.is_floating_point() else priors.double()
    if priors.shape not in ((n,), (n, h, w)):
        raise ValueError(
            f"priors must be ({n},) or ({n}, {h}, {w}) for these probabilities, "
            f"got {tuple(priors.shape)}"
        )
    if not bool((priors > 0).all()):
        raise ValueError("priors must be > 0 everywhere (floor them, e.g. at 1e-5)")
    return priors


def _extremes(ids: torch.Tensor) -> tuple[int, int]:
    """The smallest and largest of integer ``ids`` (0, 0 when empty); numpy's on the CPU (torch's
    integer reductions take ten times longer there)."""
    if not ids.numel():
        return 0, 0
    if ids.device.type == "cpu":
        values = ids.numpy()
        low = 0 if ids.dtype == torch.uint8 else int(values.min())  # a uint8 map: one pass
        return low, int(values.max())
    return tuple(int(v) for v in ids.aminmax())
