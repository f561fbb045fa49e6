"""The run-time monitor of a value system (docs/definitions.md §22): requirements of §20 kept on a
stream of frames by the controller of :mod:`costseg.calibration.monitor`, each frame decided with
§20's Lagrangian matrix at the current multipliers (or §21's stack by region,
``space="regional"``). ``costseg.Monitor`` is the class a deployment loop drives;
``evaluate.py --monitor_require`` walks the reported images with it.

>>> import torch
>>> monitor = Monitor(["person:roi0:recall>=0.9"], eta=0.5, scale="mu")
>>> monitor.matrix()[0, 11].item()                # C₀ = robotistic, μ = 0
1.0
>>> probs = torch.full((19, 2, 2), 0.01); probs[0] = 0.82         # road everywhere
>>> labels = torch.full((2, 2), 11)                                # ... but it is a person
>>> monitor.update(probs, labels).tolist()        # recall 0: θ += 0.5 (1 − 0.1)
[0.45]
>>> monitor.matrix()[0, 11].item()                # missing a person now costs 1.45
1.45
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from costseg.calibration.monitor import Controller, Scale, to_mu, to_theta
from costseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_ROIS
from costseg.costs import cost_or_symmetric, load_cost
from costseg.decision import decide_counts
from costseg.metrics.functional.roi import roi_confusion
from costseg.metrics.names import PIXEL_RATES
from costseg.metrics.requirements import Requirements
from costseg.rules import parse_rules
from costseg.rules.design_spaces import (
    LagrangianSpace,
    RegionalLagrangianSpace,
    constraints_moving,
    lagrangian_directions,
    lagrangian_multipliers,
)

Space = Literal["whole", "regional"]

MONITORED = ("recall", "precision")
"""The rates the monitor keeps: pixel rates one multiplier steers (a class's column or row)."""


def monitored_requirements(texts: Sequence[str], flag: str = "--monitor_require") -> Requirements:
    """The requirements ``texts`` (``person:roi1:recall>=0.8``, the syntax of ``--require``);
    ValueError unless each is a recall or precision of one class."""
    req = Requirements.parse(texts)
    for text, t in zip(texts, req.constraints, strict=True):
        if t.metric not in MONITORED or t.metric not in PIXEL_RATES or t.cls is None:
            raise ValueError(
                f"{flag} {text}: the monitor keeps the recall or precision of one class "
                "(a pixel rate one multiplier steers)"
            )
    return req


def base_matrix(
    name: str | Path | torch.Tensor = "robotistic", regional: bool = False
) -> torch.Tensor:
    """C₀: a preset, a cost file or a matrix; (N, N) float64, or with ``regional`` a regional
    file's (R + 1, N, N) stack too. ValueError for ``ml`` (priors), a defer row, or a regional
    C₀ of a whole-image monitor."""
    n = len(CLASS_NAMES)
    if isinstance(name, torch.Tensor):
        base = name.to(torch.float64)
    else:
        rule = parse_rules([str(name)])[0]
        if rule.priors_alpha or rule.defers or (rule.regional and not regional):
            why = " (a regional one with --monitor_space regional)" if rule.regional else ""
            raise ValueError(f"{name}: C₀ of the monitor is one cost matrix without a defer "
                             f"row{why}")  # fmt: skip
        base = cost_or_symmetric(rule.cost, n).to(torch.float64)
    shapes = [(n, n), *([(NUM_ROIS + 1, n, n)] if regional else [])]
    if tuple(base.shape) not in shapes:
        raise ValueError(f"C₀ must be {' or '.join(map(str, shapes))}, got {tuple(base.shape)}")
    return base


class Monitor:
    """Requirements kept frame by frame (docs/definitions.md §22).

    Args:
        require: the constraints, e.g. ``["person:roi1:recall>=0.8"]`` (recall or precision).
        eta: the step η (one, or one per constraint).
        base: C₀ (a preset name, a cost file, or an (N, N) matrix; for a regional monitor a
            regional file or stack too: each RoI's own C₀).
        start: where θ starts: None (μ = 0), a cost file of the space (a designed one: its μ is
            read back from the matrix), or (K,) multipliers μ.
        scale: θ is ``mu`` itself or ``log`` (log(1 + μ)).
        mu_max: the cap of every μ (the box a stream's records serve).
        space: ``whole`` (§20's ``C₀ + Σ μ_i A_i`` on every pixel) or ``regional`` (§21's: each
            constraint's μ moves only its RoI's matrix, RoI 0 every one; :meth:`matrix` is the
            (R + 1, N, N) stack, decided with the frame's RoI map).

    Attributes:
        fixed: the start's matrix (or stack), the one a fixed value system would keep (a start
            file's own, else ``C(μ_start)``).
    """

    def __init__(
        self,
        require: Sequence[str],
        eta: float | Sequence[float] = 0.5,
        *,
        base: str | Path | torch.Tensor = "robotistic",
        start: str | Path | Sequence[float] | None = None,
        scale: Scale = "log",
        mu_max: float = 100.0,
        space: Space = "whole",
    ) -> None:
        if scale not in ("log", "mu"):
            raise ValueError(f"the monitor's scale is log or mu, got {scale!r}")
        if space not in ("whole", "regional"):
            raise ValueError(f"the monitor's space is whole or regional, got {space!r}")
        self.requirements = monitored_requirements(require)
        self.base = base_matrix(base, regional=space == "regional")
        pairs = [(t.cls, t.metric) for t in self.requirements.constraints]
        self.directions = lagrangian_directions(pairs, len(CLASS_NAMES))
        self.regions = tuple(t.roi for t in self.requirements.constraints)
        self.regional = space == "regional"
        self.scale, self.mu_max = scale, float(mu_max)
        mu = start_multipliers(start, self.space())
        if (mu > self.mu_max).any():
            raise ValueError(f"the start's multipliers {mu.tolist()} exceed μ_max {self.mu_max:g}")
        self.controller = Controller(
            self.requirements.alphas,
            np.broadcast_to(np.asarray(eta, dtype=np.float64), (len(pairs),)),
            to_theta(mu, scale),
            theta_max=float(to_theta(np.array(self.mu_max), scale)),
        )
        given = isinstance(start, (str, Path))
        self.fixed = start_matrix(start, self.space()) if given else self.matrix()

    @property
    def theta(self) -> np.ndarray:
        """(K,) the current parameters."""
        return self.controller.theta.copy()

    @property
    def mu(self) -> np.ndarray:
        """(K,) the current multipliers."""
        return to_mu(self.controller.theta, self.scale)

    def matrix(self, theta: np.ndarray | None = None) -> torch.Tensor:
        """float64 ``C(μ)`` at the current θ (or at ``theta``): (N, N), or the (R + 1, N, N)
        stack of a regional monitor (the exported regional graph's ``cost`` input)."""
        mu = self.mu if theta is None else to_mu(theta, self.scale)
        return self.space().matrix(torch.as_tensor(mu))

    def space(self) -> LagrangianSpace:
        """Every matrix the monitor can reach (μ_i in [0, μ_max]): §20's space, or §21's by
        region."""
        if self.regional:
            return RegionalLagrangianSpace(self.base, self.directions, high=self.mu_max,
                                           regions=self.regions)  # fmt: skip
        return LagrangianSpace(self.base, self.directions, high=self.mu_max)

    def losses(
        self,
        probs: torch.Tensor,
        labels: torch.Tensor,
        roi: torch.Tensor | None = None,
        matrix: torch.Tensor | None = None,
    ) -> np.ndarray:
        """(K,) one frame's losses (NaN: undefined) under ``matrix`` (default the current one).

        Args:
            probs: (N, H, W) probabilities; labels: (H, W) train ids (255 ignored); roi: None
                (RoI 0 only) or (H, W) RoI ids.
        """
        matrix = self.matrix() if matrix is None else matrix
        if matrix.dim() == 3 and roi is None:
            raise ValueError("a regional monitor decides each pixel with its RoI's matrix: "
                             "give the frame's RoI map")  # fmt: skip
        counts = decide_counts(probs[None].float(), matrix, labels[None], roi)
        return self.requirements.losses(counts.confusion)[0].numpy()

    def decided_losses(
        self, decided: torch.Tensor, labels: torch.Tensor, roi: torch.Tensor | None = None
    ) -> np.ndarray:
        """(K,) one frame's losses from the labels it was decided with (NaN: undefined).

        Args:
            decided: (H, W) the decision (the exported graph's ``labels``; 255: deferred);
                labels: (H, W) train ids (255 ignored); roi: None or (H, W) RoI ids.
        """
        confusion = roi_confusion(decided[None].long(), labels[None].long(), roi,
                                  deferred=IGNORE_INDEX)  # fmt: skip
        return self.requirements.losses(confusion[None])[0].numpy()

    def update(
        self,
        losses: Sequence[float] | np.ndarray | torch.Tensor,
        labels: torch.Tensor | None = None,
        roi: torch.Tensor | None = None,
        matrix: torch.Tensor | None = None,
    ) -> np.ndarray:
        """A frame's labels arrived: step θ with its (K,) ``losses``, or with those of its
        (N, H, W) probabilities given as ``losses`` with ``labels`` (and ``roi``) under
        ``matrix``, the matrix the frame was decided with (default the current one: no delay).
        Returns the new θ."""
        if labels is not None:
            losses = self.losses(torch.as_tensor(losses), labels, roi, matrix)
        return self.controller.observe(np.asarray(losses, dtype=np.float64))

    def bound(self) -> np.ndarray:
        """(K,) the bound on the mean loss of the frames observed (docs/definitions.md §22)."""
        return self.controller.bound()


def start_matrix(path: str | Path, space: LagrangianSpace) -> torch.Tensor:
    """The cost file ``path`` as a matrix of ``space``: float64, (N, N), or the (R + 1, N, N)
    stack of a regional space (a regional file whose RoIs are all equal may hold one matrix).
    ValueError for a defer row, or a regional file in the whole-image space."""
    matrix = load_cost(path).to(torch.float64)
    n = len(CLASS_NAMES)
    if isinstance(space, RegionalLagrangianSpace) and matrix.shape == (n, n):
        matrix = matrix.expand(len(space.bases()), n, n)
    shape = tuple(space.matrix(torch.zeros(len(space.directions))).shape)
    if tuple(matrix.shape) != shape:
        regional = isinstance(space, RegionalLagrangianSpace) or matrix.dim() == 2
        raise ValueError(
            f"{path}: the monitor's start is a {'' if regional else 'plain '}matrix of shape "
            f"{shape} without a defer row"
            + ("" if regional else " (a regional file needs --monitor_space regional)")
        )
    return matrix


def start_multipliers(
    start: str | Path | Sequence[float] | None, space: LagrangianSpace
) -> np.ndarray:
    """(K,) μ where a monitor of ``space`` starts: 0, those given, or those of a cost file of
    the space (a regional stack's μ_i read in the matrix of constraint i's own RoI, and the
    whole stack checked against the space's matrix at those μ)."""
    k = len(space.directions)
    if start is None:
        return np.zeros(k)
    if isinstance(start, (str, Path)):
        matrix = start_matrix(start, space)
        try:
            if not isinstance(space, RegionalLagrangianSpace):
                return lagrangian_multipliers(matrix, space.base, space.directions).numpy()
            mu = torch.zeros(k, dtype=torch.float64)
            for r in sorted(set(space.regions)):
                moves = constraints_moving(space.regions, r).bool()
                mu[moves] = lagrangian_multipliers(matrix[r], space.bases()[r],
                                                   space.directions[moves])  # fmt: skip
            scale = 1e-6 * matrix.abs().max().item()
            if not torch.allclose(space.matrix(mu), matrix, rtol=0, atol=scale):
                raise ValueError("not C₀_r + Σ μ_i A_i of the constraints that move each RoI")
            return mu.numpy()
        except ValueError as err:
            raise ValueError(f"{start}: {err} (C₀ and the monitor's requirements)") from None
    mu = np.asarray(start, dtype=np.float64)
    if mu.shape != (k,) or not np.isfinite(mu).all() or (mu < 0).any():
        raise ValueError(f"the start needs {k} multipliers >= 0, got {list(start)}")
    return mu


__all__ = [
    "MONITORED",
    "Monitor",
    "base_matrix",
    "monitored_requirements",
    "start_matrix",
    "start_multipliers",
]
