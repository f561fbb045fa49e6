"""The checks of the decision layer's inputs, and what the dispatcher sees of them."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from costseg.costs import cost_or_symmetric, has_defer_row
from costseg.decision.label_maps import DEFERRED


@dataclass(frozen=True)
class Inputs:
    """What decides which fast path fits (:mod:`costseg.decision.dispatch`).

    Attributes:
        shape: (B, N, H, W) of the probabilities; device, dtype: theirs.
        pixel_priors: whether priors are pixel-wise (N, H, W).
        vertices: V matrices (1 for ``decide``); mixtures: K (None for ``decide``).
        defer: whether the matrices carry a defer row ((N + 1, N), docs/definitions.md §14).
    """

    shape: tuple[int, ...]
    device: torch.device
    dtype: torch.dtype
    pixel_priors: bool = False
    vertices: int = 1
    mixtures: int | None = None
    defer: bool = False

    @classmethod
    def of(cls, probs: torch.Tensor, priors, matrices: torch.Tensor, mixtures: int | None = None):
        """What the dispatcher sees of ``probs``, ``priors`` and (V, R, N) ``matrices``."""
        pixel_priors = priors is not None and priors.ndim > 1
        shape, defer = tuple(probs.shape), has_defer_row(matrices)
        return cls(shape, probs.device, probs.dtype, pixel_priors, len(matrices), mixtures, defer)

    @property
    def pixels(self) -> int:
        """Pixels per image."""
        return self.shape[2] * self.shape[3]

    def describe(self) -> str:
        rule = "decide" if self.mixtures is None else f"decide_mixtures ({self.mixtures} mixtures"
        rule += "" if self.mixtures is None else f" of {self.vertices} vertices)"
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
    the symmetric matrix."""
    cost = cost_or_symmetric(cost, n)
    if cost.shape not in ((n, n), (n + 1, n)):
        raise ValueError(
            f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}; with a defer "
            f"row it is {n + 1}x{n}"
        )
    check_defer(cost, n)
    return cost.detach().to(torch.float64).cpu()[None]


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
