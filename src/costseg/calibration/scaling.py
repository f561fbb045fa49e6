"""Calibration of the network's probabilities: temperature and vector scaling (docs/definitions.md
§6).

Argmax does not change when the probabilities are sharpened or flattened; a cost rule does. So
the probabilities a rule sees are ``softmax(z / T)`` (temperature scaling) or
``softmax(a ⊙ z + b)`` (vector scaling), fitted by minimising the mean negative log-likelihood
(NLL) of the non-ignored pixels of a calibration set. Fitting streams:
:class:`~costseg.calibration.sample.PixelSampler` keeps a fixed number of pixels per image, so a
full-resolution split is never held in memory.
:class:`Scaling` records what was fitted and applies it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX

TEMPERATURE_RANGE = (1e-2, 1e2)
"""Bounds of the fitted T: beyond them the optimum is an endpoint (e.g. separable data)."""

ScalingKind = Literal["none", "temperature", "vector"]


def _pixels(logits: Tensor, target: Tensor, ignore_index: int) -> tuple[Tensor, Tensor]:
    """Validate and flatten to float64 (P, N) logits and int64 (P,) labels, ignored dropped."""
    if logits.ndim == 4 and target.ndim == 3:
        if (logits.shape[0], *logits.shape[2:]) != tuple(target.shape):
            raise ValueError(
                f"logits (B, N, H, W) and target (B, H, W) must agree in B, H, W; got "
                f"{tuple(logits.shape)} and {tuple(target.shape)}"
            )
        logits = logits.movedim(1, -1).reshape(-1, logits.shape[1])
        target = target.reshape(-1)
    elif not (logits.ndim == 2 and target.ndim == 1 and len(logits) == len(target)):
        raise ValueError(
            "expected logits (P, N) with target (P,), or logits (B, N, H, W) with target "
            f"(B, H, W); got {tuple(logits.shape)} and {tuple(target.shape)}"
        )
    if not logits.is_floating_point() or target.is_floating_point():
        raise ValueError(
            f"expected float logits and integer target; got {logits.dtype}, {target.dtype}"
        )
    keep = target != ignore_index
    z, y = logits[keep].double(), target[keep].long()
    n = logits.shape[1]
    if len(y) == 0:
        raise ValueError(f"no pixel to fit on: every target is the ignore index {ignore_index}")
    if bool(((y < 0) | (y >= n)).any()):
        bad = sorted(set(y[(y < 0) | (y >= n)].unique().tolist()))
        raise ValueError(f"target holds {bad}; expected 0..{n - 1} or {ignore_index}")
    if not bool(torch.isfinite(z).all()):
        raise ValueError("logits of non-ignored pixels must be finite")
    return z, y


def _nll_slope(z: Tensor, y: Tensor, beta: float) -> float:
    """d/dβ of the mean NLL of softmax(β z): mean over pixels of E_p[z] - z_y (increasing in β)."""
    p = torch.softmax(beta * z, dim=1)
    return float(((p * z).sum(1) - z.gather(1, y[:, None])[:, 0]).mean())


def fit_temperature(logits: Tensor, target: Tensor, ignore_index: int = IGNORE_INDEX) -> float:
    """The temperature T > 0 minimising the mean NLL of ``softmax(z / T)`` over labelled pixels.

    The NLL is convex in β = 1/T, so its slope is increasing and the optimum is the root of the
    slope; it is found in float64 by Brent's method on log T (to about 1e-10 relative), within
    :data:`TEMPERATURE_RANGE` (an optimum outside returns the nearer endpoint).

    Args:
        logits: (P, N) or (B, N, H, W) float logits.
        target: (P,) or (B, H, W) integer labels in ``[0, N)`` or ``ignore_index``.
        ignore_index: Label of pixels left out.

    Returns:
        The NLL-optimal temperature.

    >>> z = torch.tensor([[2.0, 0.0], [2.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    >>> round(fit_temperature(z, torch.tensor([0, 0, 1, 1])), 4)   # p = 3/4 is optimal: 2/log 3
    1.8205
    """
    z, y = _pixels(logits, target, ignore_index)
    low, high = (math.log(1 / t) for t in reversed(TEMPERATURE_RANGE))

    def slope(log_beta: float) -> float:
        return _nll_slope(z, y, math.exp(log_beta))

    if slope(low) >= 0:
        return TEMPERATURE_RANGE[1]
    if slope(high) <= 0:
        return TEMPERATURE_RANGE[0]
    from scipy.optimize import brentq  # ~0.4 s to import: only when a temperature is fitted

    return math.exp(-brentq(slope, low, high, xtol=1e-12, rtol=1e-12))


def fit_vector_scaling(
    logits: Tensor, target: Tensor, ignore_index: int = IGNORE_INDEX, max_iter: int = 500
) -> tuple[Tensor, Tensor]:
    """Per-class scale a and offset b minimising the mean NLL of ``softmax(a ⊙ z + b)``.

    The NLL is convex in (a, b); L-BFGS (float64, strong Wolfe line search) starts from the
    fitted temperature (a = 1/T, b = 0), so the result is never worse than temperature scaling.
    A class absent from the labelled pixels keeps a = 1/T, b = 0: otherwise its b would run to
    -inf. b is returned centred (mean 0), which leaves the softmax unchanged.

    Args:
        logits: (P, N) or (B, N, H, W) float logits.
        target: (P,) or (B, H, W) integer labels in ``[0, N)`` or ``ignore_index``.
        ignore_index: Label of pixels left out.
        max_iter: L-BFGS iterations at most.

    Returns:
        a, b: two (N,) float64 tensors on the CPU.

    >>> z = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    >>> a, b = fit_vector_scaling(z, torch.tensor([0, 0, 0, 1]))
    >>> p = torch.softmax(a * z + b, dim=1)     # optimum: class 0 has 1 and 1/2 in each group
    >>> [round(v, 3) for v in p[:, 0].tolist()]
    [1.0, 1.0, 0.5, 0.5]
    """
    z, y = _pixels(logits, target, ignore_index)
    n = z.shape[1]
    inverse_t = 1 / fit_temperature(z, y, ignore_index)
    present = torch.bincount(y, minlength=n) > 0
    a = torch.full((n,), inverse_t, dtype=torch.float64, device=z.device)
    b = torch.zeros(n, dtype=torch.float64, device=z.device)
    free_a, free_b = a[present].clone().requires_grad_(), b[present].clone().requires_grad_()
    optimizer = torch.optim.LBFGS(
        [free_a, free_b],
        lr=1,
        max_iter=max_iter,
        tolerance_grad=1e-10,
        tolerance_change=1e-14,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Tensor:
        optimizer.zero_grad()
        scores = (a.index_put((present,), free_a)) * z + b.index_put((present,), free_b)
        loss = torch.nn.functional.cross_entropy(scores, y)
        loss.backward()
        return loss

    optimizer.step(closure)
    a[present], b[present] = free_a.detach(), free_b.detach()
    return a.cpu(), (b - b.mean()).cpu()


@dataclass(frozen=True)
class Scaling:
    """How the logits become the probabilities every rule sees (docs/definitions.md §6).

    Attributes:
        kind: ``"none"`` (plain softmax), ``"temperature"`` (``softmax(z / T)``) or
            ``"vector"`` (``softmax(a ⊙ z + b)``).
        temperature: T, used when ``kind == "temperature"``.
        scale: a, N floats, when ``kind == "vector"`` (else empty).
        offset: b, N floats, when ``kind == "vector"`` (else empty).
        fitted_on: Where the parameters come from, e.g. ``"50 images, 204800 pixels"``
            (empty: set by hand).

    >>> s = Scaling("temperature", temperature=2.0, fitted_on="4 images")
    >>> s.describe()
    'temperature scaling, T = 2.000 (fitted on 4 images)'
    >>> [round(p, 6) for p in s.apply(torch.tensor([[2 * math.log(9.0), 0.0]]))[0].tolist()]
    [0.9, 0.1]
    """

    kind: ScalingKind = "none"
    temperature: float = 1.0
    scale: tuple[float, ...] = ()
    offset: tuple[float, ...] = ()
    fitted_on: str = ""

    def __post_init__(self) -> None:
        if self.kind not in ("none", "temperature", "vector"):
            raise ValueError(f"kind must be 'none', 'temperature' or 'vector'; got {self.kind!r}")
        if not (math.isfinite(self.temperature) and self.temperature > 0):
            raise ValueError(f"temperature must be finite and > 0; got {self.temperature}")
        # Tensors, arrays and lists become tuples of floats, so the dataclass stays hashable.
        object.__setattr__(self, "scale", tuple(float(v) for v in self.scale))
        object.__setattr__(self, "offset", tuple(float(v) for v in self.offset))
        lengths = (len(self.scale), len(self.offset))
        if (self.kind == "vector") != (lengths[0] > 0) or lengths[0] != lengths[1]:
            raise ValueError(
                "scale and offset must both have one entry per class for vector scaling and be "
                f"empty otherwise; got kind {self.kind!r} with lengths {lengths}"
            )

    def apply(self, logits: Tensor) -> Tensor:
        """Probabilities from logits (class dimension 1): (P, N) or (B, N, H, W) → float32."""
        z = logits.float()
        if self.kind == "temperature":
            z = z / self.temperature
        elif self.kind == "vector":
            if z.ndim < 2 or z.shape[1] != len(self.scale):
                raise ValueError(
                    f"expected logits with {len(self.scale)} classes in dimension 1; got "
                    f"{tuple(z.shape)}"
                )
            view = (1, -1) + (1,) * (z.ndim - 2)
            a = torch.tensor(self.scale, dtype=z.dtype, device=z.device).view(view)
            b = torch.tensor(self.offset, dtype=z.dtype, device=z.device).view(view)
            z = a * z + b
        return z.softmax(dim=1)

    def describe(self) -> str:
        """One line for every output: which probabilities were used and their parameters."""
        source = f" (fitted on {self.fitted_on})" if self.fitted_on else ""
        if self.kind == "none":
            return "raw probabilities (softmax of the logits, no scaling)"
        if self.kind == "temperature":
            return f"temperature scaling, T = {self.temperature:.3f}{source}"
        a, b = self.scale, self.offset
        return (
            f"vector scaling softmax(a ⊙ z + b), a in [{min(a):.3f}, {max(a):.3f}], "
            f"b in [{min(b):.3f}, {max(b):.3f}]{source}"
        )

    def to_dict(self) -> dict[str, object]:
        """JSON-ready parameters; ``Scaling(**d)`` rebuilds the same object."""
        return {
            "kind": self.kind,
            "temperature": self.temperature,
            "scale": list(self.scale),
            "offset": list(self.offset),
            "fitted_on": self.fitted_on,
        }
