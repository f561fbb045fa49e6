"""The value system watched at run time (docs/definitions.md §22): one parameter per constraint,
moved by each frame's loss once its labels arrive, and the matrix of §20's Lagrangian space at
those parameters.

The update (Lekeufack et al. 2023, *Conformal Decision Theory*; Angelopoulos et al. 2023,
*Conformal PID control*), for constraint i with level α_i and step η_i, when frame t's labels
arrive::

    θ_{i,t+1} = min(θ_max, max(0, θ_{i,t} + η_i (L_{i,t} − α_i)))       (frames with L undefined:
                                                                          no step)

θ is the multiplier μ itself (scale ``mu``) or ``log(1 + μ)`` (scale ``log``); the matrix is
``C(μ) = C₀ + Σ_i μ_i A_i`` (:func:`~costseg.rules.design_spaces.lagrangian_cost`; by region,
:class:`~costseg.rules.design_spaces.RegionalLagrangianSpace`). Summing the
steps gives, for any sequence of losses, over the n frames with a defined loss whose labels
arrived::

    mean L_i ≤ α_i + (θ_{i,now} − θ_{i,1} + c_i) / (η_i n)

where c_i is what the cap θ_max cut off (0 while it was never reached). A long-run average over
this stream, not §20's probability over a draw of images.

>>> ctl = Controller(alphas=(0.2,), eta=(1.0,))
>>> for loss in (1.0, 0.0, 0.5):
...     _ = ctl.observe([loss])
>>> ctl.theta.round(6).tolist(), ctl.bound().round(6).tolist()   # mean 0.5 ≤ 0.2 + 0.9 / 3
([0.9], [0.5])
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Scale = Literal["mu", "log"]


def to_mu(theta: np.ndarray, scale: Scale) -> np.ndarray:
    """The multipliers μ of parameters θ on ``scale``.

    >>> to_mu(np.array([0.0, math.log(2)]), "log").tolist()
    [0.0, 1.0]
    """
    theta = np.asarray(theta, dtype=np.float64)
    return np.expm1(theta) if scale == "log" else theta.copy()


def to_theta(mu: np.ndarray, scale: Scale) -> np.ndarray:
    """The parameters θ of multipliers μ ≥ 0 on ``scale`` (the inverse of :func:`to_mu`)."""
    mu = np.asarray(mu, dtype=np.float64)
    return np.log1p(mu) if scale == "log" else mu.copy()


@dataclass
class Controller:
    """The §22 controller: θ per constraint, its steps, and what its bound needs.

    Attributes:
        alphas: (K,) levels α_i; ``eta``: (K,) steps η_i > 0.
        theta: (K,) the current parameters (default 0); ``start`` θ_1, set from it.
        theta_max: the cap of every θ_i (inf: none).
        cut: (K,) what the cap cut off, summed; ``capped``: (K,) steps the cap changed.
        seen: (K,) frames with a defined loss observed; ``excess``: (K,) their Σ (L − α).
    """

    alphas: Sequence[float]
    eta: Sequence[float]
    theta: np.ndarray | None = None
    theta_max: float = math.inf
    start: np.ndarray = field(init=False)
    cut: np.ndarray = field(init=False)
    capped: np.ndarray = field(init=False)
    seen: np.ndarray = field(init=False)
    excess: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        k = len(self.alphas)
        self.alphas = np.asarray(self.alphas, dtype=np.float64)
        self.eta = np.broadcast_to(np.asarray(self.eta, dtype=np.float64), (k,)).copy()
        theta = np.zeros(k) if self.theta is None else np.asarray(self.theta, dtype=np.float64)
        if theta.shape != (k,) or (theta < 0).any() or (theta > self.theta_max).any():
            raise ValueError(f"θ must hold {k} values in [0, {self.theta_max}], got {theta}")
        if not (self.eta > 0).all():
            raise ValueError(f"every step η must be > 0, got {self.eta.tolist()}")
        self.theta, self.start = theta.copy(), theta.copy()
        self.cut, self.excess = np.zeros(k), np.zeros(k)
        self.capped, self.seen = np.zeros(k, dtype=np.int64), np.zeros(k, dtype=np.int64)

    def observe(self, losses: Sequence[float]) -> np.ndarray:
        """One frame's (K,) losses (NaN: undefined, no step) → the new θ."""
        losses = np.asarray(losses, dtype=np.float64)
        defined = ~np.isnan(losses)
        step = np.where(defined, self.eta * (np.nan_to_num(losses) - self.alphas), 0.0)
        moved = np.maximum(0.0, self.theta + step)
        kept = np.minimum(moved, self.theta_max)
        self.cut += moved - kept
        self.capped += moved > kept
        self.seen += defined
        self.excess += np.where(defined, np.nan_to_num(losses) - self.alphas, 0.0)
        self.theta = kept
        return self.theta.copy()

    def bound(self, pending: np.ndarray | None = None) -> np.ndarray:
        """(K,) the bound on the mean loss over the observed frames with a defined loss,
        ``α + (θ − θ_1 + cut) / (η n)``; with ``pending`` (K,) frames decided whose labels
        have not arrived, over those too: ``+ pending (1 − α) / (n + pending)`` with every
        mean over ``n + pending`` frames (each loss ≤ 1). NaN where there is no frame."""
        pending = np.zeros(len(self.alphas)) if pending is None else np.asarray(pending)
        frames = self.seen + pending
        with np.errstate(invalid="ignore", divide="ignore"):
            slack = (self.theta - self.start + self.cut) / self.eta
            out = self.alphas + (slack + pending * (1 - self.alphas)) / frames
        return np.where(frames > 0, out, np.nan)


@dataclass
class StreamTrace:
    """What :func:`run_stream` records, frame by frame (T frames, K constraints).

    Attributes:
        theta: (T + 1, K) θ_t before each frame, and after the last labels arrived.
        losses: (T, K) each frame's losses under its θ_t (NaN: undefined).
        labelled: (T,) whether the frame's labels arrive at all.
        bounds: (T, K) after each frame, :meth:`Controller.bound` over the labelled frames
            decided so far (the pending ones too).
        final_bound: (K,) the bound once every label has arrived.
        capped, cut: (K,) the cap's steps and what it cut off.
    """

    theta: np.ndarray
    losses: np.ndarray
    labelled: np.ndarray
    bounds: np.ndarray
    final_bound: np.ndarray
    capped: np.ndarray
    cut: np.ndarray


def labelled_frames(count: int, share: float, seed: int) -> np.ndarray:
    """(count,) bool: the frames whose labels arrive, each with probability ``share`` (all
    when 1), drawn with ``seed``.

    >>> labelled_frames(4, 1.0, 0).tolist()
    [True, True, True, True]
    """
    if share >= 1:
        return np.ones(count, dtype=bool)
    return np.random.default_rng(seed).random(count) < share


def run_stream(
    frame_losses: Callable[[int, np.ndarray], np.ndarray],
    count: int,
    controller: Controller,
    delay: int = 0,
    labelled: np.ndarray | None = None,
) -> StreamTrace:
    """Walk ``count`` frames in order: frame t decided at the current θ (its losses
    ``frame_losses(t, θ)``, (K,) with NaN where undefined), its labels arriving ``delay``
    frames later (before frame t + delay + 1 is decided) where ``labelled[t]``; at the end
    every label still on its way arrives.

    >>> ctl = Controller(alphas=(0.5,), eta=(1.0,))
    >>> trace = run_stream(lambda t, theta: np.array([1.0]), 3, ctl, delay=1)
    >>> trace.theta[:, 0].tolist()       # frame 0's label moves θ before frame 2
    [0.0, 0.0, 0.5, 1.5]
    """
    labelled = np.ones(count, dtype=bool) if labelled is None else np.asarray(labelled)
    k = len(controller.alphas)
    theta, losses = np.zeros((count + 1, k)), np.full((count, k), np.nan)
    bounds = np.full((count, k), np.nan)
    for t in range(count):
        arrived = t - 1 - delay
        if arrived >= 0 and labelled[arrived]:
            controller.observe(losses[arrived])
        theta[t] = controller.theta
        losses[t] = frame_losses(t, controller.theta.copy())
        waiting = [s for s in range(max(0, t - delay), t + 1) if labelled[s]]
        pending = (~np.isnan(losses[waiting])).sum(0) if waiting else np.zeros(k)
        bounds[t] = controller.bound(pending)
    for s in range(max(0, count - 1 - delay), count):
        if labelled[s]:
            controller.observe(losses[s])
    theta[count] = controller.theta
    return StreamTrace(theta, losses, labelled, bounds, controller.bound(),
                       controller.capped.copy(), controller.cut.copy())  # fmt: skip


def running_mean(losses: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
    """(T, K) the mean of each column's defined values among frames ``≤ t`` (and ``where``,
    (T,) bool), NaN before the first.

    >>> running_mean(np.array([[1.0], [np.nan], [0.0]]))[:, 0].tolist()
    [1.0, 1.0, 0.5]
    """
    kept = ~np.isnan(losses)
    if where is not None:
        kept &= np.asarray(where)[:, None]
    sums = np.cumsum(np.where(kept, losses, 0.0), 0)
    counts = np.cumsum(kept, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


def window_violations(losses: np.ndarray, alphas: Sequence[float], window: int) -> np.ndarray:
    """(K,) the share of the windows of ``window`` consecutive frames whose mean defined loss
    exceeds α (windows with no defined loss left out; NaN when none is left).

    >>> window_violations(np.array([[1.0], [0.0], [0.0]]), [0.4], 2).tolist()
    [0.5]
    """
    out = []
    for i, alpha in enumerate(alphas):
        column = losses[:, i]
        means = [
            np.nanmean(part)
            for part in (column[s : s + window] for s in range(max(1, len(column) - window + 1)))
            if (~np.isnan(part)).any()
        ]
        out.append(float(np.mean(np.array(means) > alpha)) if means else math.nan)
    return np.array(out)
