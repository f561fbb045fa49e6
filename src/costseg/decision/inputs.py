"""The checks of the decision layer's inputs, and what the dispatcher sees of them."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from costseg.costs import symmetric_cost


@dataclass(frozen=True)
class Inputs:
    """What decides which fast path fits (:mod:`costseg.decision.dispatch`).

    Attributes:
        shape: (B, N, H, W) of the probabilities; device, dtype: theirs.
        pixel_priors: whether priors are pixel-wise (N, H, W).
        vertices: V matrices (1 for ``decide``); mixtures: K (None for ``decide``).
    """

    shape: tuple[int, ...]
    device: torch.device
    dtype: torch.dtype
    pixel_priors: bool = False
    vertices: int = 1
    mixtures: int | None = None

    @classmethod
    def of(cls, probs: torch.Tensor, priors, vertices: int = 1, mixtures: int | None = None):
        pixel_priors = priors is not None and priors.ndim > 1
        return cls(tuple(probs.shape), probs.device, probs.dtype, pixel_priors, vertices, mixtures)

    @property
    def pixels(self) -> int:
        """Pixels per image."""
        return self.shape[2] * self.shape[3]

    def describe(self) -> str:
        rule = "decide" if self.mixtures is None else f"decide_mixtures ({self.mixtures} mixtures"
        rule += "" if self.mixtures is None else f" of {self.vertices} vertices)"
        priors = "pixel-wise priors" if self.pixel_priors else "no or global priors"
        return f"{rule} on {self.shape} {self.dtype} probabilities on {self.device}, {priors}"


def check_probs(probs: torch.Tensor) -> int:
    """N, the number of classes of (B, N, H, W) float probabilities."""
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(
            f"probs must be a float (B, N, H, W) tensor, got {probs.dtype} {tuple(probs.shape)}"
        )
    return probs.shape[1]


def check_cost(cost: torch.Tensor | None, n: int) -> torch.Tensor:
    """(1, N, N) float64 on the CPU (small: prepared there); None: the symmetric matrix."""
    cost = symmetric_cost(n) if cost is None else cost
    if cost.shape != (n, n):
        raise ValueError(f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}")
    return cost.detach().to(torch.float64).cpu()[None]


def check_mixtures(vertices: torch.Tensor, weights: torch.Tensor, n: int) -> None:
    """(V, N, N) vertex matrices and (K, V) weights >= 0, each row with a positive entry."""
    if vertices.shape[1:] != (n, n) or weights.ndim != 2 or weights.shape[1] != len(vertices):
        raise ValueError(
            f"expected vertices ({n} x {n} matrices) and weights (K, V), got "
            f"{tuple(vertices.shape)} and {tuple(weights.shape)}"
        )
    if not bool((weights >= 0).all() and (weights > 0).any(1).all()):
        raise ValueError("mixture weights must be >= 0 with a positive entry in each row")


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
