"""Conformal prediction sets anchored on a cost rule, and conformal risk control
(docs/definitions.md §18).

A rule names one class d(x) per pixel; a set ``S_λ(x)`` names every class still plausible at a
threshold λ ∈ [0, 1]. Each class k of a pixel gets a score ``s_k(x) ∈ [0, 1]`` and
``S_λ(x) = {k : s_k(x) ≤ λ}``:

* LAC: ``s_k = 1 − p_k``, so ``S_λ = {d} ∪ {k : p_k ≥ 1 − λ}``;
* APS: ``s_k`` = the mass of the classes ranked strictly above k in decreasing p (ties: the
  lower index first), so ``S_λ`` holds the classes in that order up to and including the first
  whose cumulative mass exceeds λ (COSE's ``aps_multimask``), and d;
* the rule's decision scores 0 (``s_d = 0``): it is in every set. A deferred pixel (decision N,
  or 255) anchors nothing: its set is built from the classes alone (a LAC set may be empty).

Scores are clamped to [0, 1], so λ = 1 gives every class whatever the round-off of a cumulative
sum. A pixel's true class y enters the set at ``λ*(x) = s_y(x)`` (0 where y = d), so the loss
of an image at every λ of a grid is one histogram of λ* (:func:`image_losses`), and
:func:`crc_threshold` picks λ̂ by conformal risk control (Angelopoulos, Bates, Fisch, Lei,
Schuster, ICLR 2024, Thm. 1): ``E[L_test(λ̂)] ≤ α`` over the draw of calibration and test images.

Pure torch and numpy; nothing here knows of models, data or Lightning. Every tensor of one call
lives on one device.

>>> probs = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
>>> decision, labels = torch.tensor([[[2]]]), torch.tensor([[[1]]])
>>> set_sizes(probs, decision, 0.6, "aps").item()       # {0, 1} by mass, and the decision 2
3
>>> entry_thresholds(probs, decision, labels, "lac").item()
0.75
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES, NUM_ROIS
from costseg.costs import cost_weights
from costseg.decision.label_maps import DEFERRED

Kind = Literal["lac", "aps"]
KINDS: tuple[str, ...] = ("lac", "aps")
Loss = Literal["uniform", "cost", "binary"]
"""The losses a set's risk control may bound (:func:`set_losses`)."""
CHUNK_PIXELS = 1 << 20
"""Pixels whose APS scores are sorted at once: the sort's values and int64 indices of a chunk
take 12 · N bytes a pixel (240 MB at N = 19), whatever the image's size."""


def conformity_scores(probs: Tensor, decision: Tensor, kind: Kind) -> Tensor:
    """Every class's score ``s_k(x)``: ``k ∈ S_λ(x)`` iff ``s_k(x) ≤ λ`` (the module's
    definitions).

    Args:
        probs: (B, N, H, W) probabilities (after any scaling), any float dtype.
        decision: (B, H, W) integer decisions of a rule: a class 0 … N − 1, or N or 255 where
            the rule defers.
        kind: ``"lac"`` or ``"aps"``.

    Returns:
        (B, N, H, W) scores in [0, 1], of ``probs``' dtype.

    Raises:
        ValueError: an unknown ``kind``, mismatched shapes or a decision out of range.

    >>> probs = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
    >>> conformity_scores(probs, torch.tensor([[[2]]]), "lac").flatten().tolist()
    [0.5, 0.75, 0.0]
    >>> conformity_scores(probs, torch.tensor([[[255]]]), "aps").flatten().tolist()
    [0.0, 0.5, 0.75]
    """
    _check_inputs(probs, decision, kind)
    if kind == "lac":
        scores = (1 - probs).clamp_(0, 1)
    else:
        scores = torch.empty_like(probs)
        for b, rows in _chunks(probs):
            scores[b, :, rows] = _mass_above(probs[b, :, rows])
    return _anchor(scores, decision)


def prediction_sets(probs: Tensor, decision: Tensor, lam: float, kind: Kind) -> Tensor:
    """The sets ``S_λ(x)`` as (B, N, H, W) bool masks (λ ≥ 1: every class).

    Args:
        probs, decision, kind: as for :func:`conformity_scores`.
        lam: the threshold λ.

    >>> probs = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
    >>> prediction_sets(probs, torch.tensor([[[1]]]), 0.4, "lac").flatten().tolist()
    [False, True, False]
    """
    return conformity_scores(probs, decision, kind) <= lam


def set_sizes(probs: Tensor, decision: Tensor, lam: float, kind: Kind) -> Tensor:
    """``|S_λ(x)|``, (B, H, W) int64; arguments as for :func:`prediction_sets`.

    >>> probs = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
    >>> set_sizes(probs, torch.tensor([[[0]]]), 0.5, "aps").item()
    2
    """
    return prediction_sets(probs, decision, lam, kind).sum(1)


def entry_thresholds(probs: Tensor, decision: Tensor, labels: Tensor, kind: Kind) -> Tensor:
    """The smallest λ at which each pixel's true class enters its set, ``λ*(x) = s_y(x)``.

    Args:
        probs, decision, kind: as for :func:`conformity_scores`.
        labels: (B, H, W) true classes, 255 ignored.

    Returns:
        (B, H, W) λ* of ``probs``' dtype: 0 where y = d(x); NaN where the label is 255.

    >>> probs = torch.tensor([0.5, 0.25, 0.25]).view(1, 3, 1, 1)
    >>> entry_thresholds(probs, torch.tensor([[[0]]]), torch.tensor([[[2]]]), "aps").item()
    0.75
    """
    return label_thresholds(conformity_scores(probs, decision, kind), labels)


def label_thresholds(scores: Tensor, labels: Tensor) -> Tensor:
    """:func:`entry_thresholds` from scores computed once: (B, N, H, W) scores, (B, H, W)
    labels (255 ignored) → (B, H, W) ``s_y``, NaN where the label is 255.

    >>> label_thresholds(torch.tensor([0.0, 0.5]).view(1, 2, 1, 1), torch.tensor([[[1]]])).item()
    0.5
    """
    n = scores.shape[1]
    if scores.ndim != 4 or labels.shape != scores.shape[:1] + scores.shape[2:]:
        raise ValueError(
            f"labels must be (B, H, W) of scores (B, N, H, W) {tuple(scores.shape)}; got "
            f"{tuple(labels.shape)}"
        )
    ignored = labels == IGNORE_INDEX
    if labels.is_floating_point() or not ((labels >= 0) & (labels < n) | ignored).all():
        raise ValueError(f"labels must be integer classes 0 … {n - 1} or {IGNORE_INDEX}")
    found = scores.gather(1, labels.long().masked_fill(ignored, 0).unsqueeze(1)).squeeze(1)
    return found.masked_fill_(ignored, float("nan"))


def lambda_grid(steps: int = 1000) -> Tensor:
    """The grid Λ = {0, 1/steps, …, 1} (float64), which includes λ = 1 (every class).

    >>> lambda_grid(4).tolist()
    [0.0, 0.25, 0.5, 0.75, 1.0]
    """
    if steps < 1:
        raise ValueError(f"a λ grid needs steps >= 1; got {steps}")
    return torch.linspace(0, 1, steps + 1, dtype=torch.float64)


def class_weights(cost: Tensor | None = None, num_classes: int = NUM_CLASSES) -> Tensor:
    """The loss's class weights w_j (float64): uniform (``cost`` None: COSE's miscoverage), or
    from a matrix, ``w_j = mean_{k≠j} C[k, j]`` over its class rows (a defer row excluded),
    normalised to mean 1 (:func:`~costseg.costs.cost_weights`; the loss is a ratio, so the
    scale is immaterial).

    >>> cost = torch.tensor([[0, 1, 2], [1, 0, 2], [1, 1, 0], [9, 9, 9]])   # a defer row last
    >>> class_weights(cost).tolist(), class_weights(None, 2).tolist()
    ([0.75, 0.75, 1.5], [1.0, 1.0])
    """
    if cost is None:
        return torch.ones(num_classes, dtype=torch.float64)
    return cost_weights(torch.as_tensor(cost, dtype=torch.float64))


def image_losses(
    thresholds: Tensor,
    labels: Tensor,
    lambdas: Tensor | Sequence[float],
    weights: Tensor | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """Each image's loss at every λ of a grid,
    ``L(λ) = Σ_x w_y(x) · 1[λ < λ*(x)] / Σ_x w_y(x)`` over its counted pixels (label not 255,
    inside ``mask``): the weighted share of true classes outside the set. Non-increasing in λ,
    0 at λ = 1.

    One histogram of λ* over the grid per image (bucketize, weighted bincount, suffix sums in
    float64), so the grid's size costs nothing per pixel.

    Args:
        thresholds: (B, H, W) λ* of :func:`entry_thresholds` (NaN pixels count nowhere).
        labels: (B, H, W) true classes, 255 ignored.
        lambdas: (L,) strictly increasing grid (compared in ``thresholds``' dtype, as the sets
            compare λ with their scores).
        weights: (N,) positive class weights (:func:`class_weights`); None: uniform.
        mask: (B, H, W) or (H, W) bool, the pixels counted (e.g. one RoI); None: all.

    Returns:
        (B, L) float64 losses in [0, 1]; NaN for an image with no counted pixel (to be left
        out: :func:`crc_threshold` does).

    >>> thresholds = torch.tensor([[[0.0, 0.3, 0.6, 0.9]]])
    >>> image_losses(thresholds, torch.tensor([[[0, 1, 1, 255]]]), [0, 0.5, 1]).tolist()
    [[0.6666666666666666, 0.3333333333333333, 0.0]]
    """
    counted = _counted(thresholds, labels, mask)
    if weights is None:
        pixel_weights = counted.double()
    else:
        weights = _check_weights(weights, labels, counted).to(thresholds.device)
        classes = labels.long().masked_fill(~counted, 0)
        pixel_weights = torch.where(counted, weights[classes], 0.0)
    hist = _histogram(thresholds, pixel_weights, lambdas)
    return _ratio(_suffix(hist), hist.sum(1, keepdim=True))


def binary_losses(
    thresholds: Tensor,
    labels: Tensor,
    lambdas: Tensor | Sequence[float],
    tau: float,
    mask: Tensor | None = None,
) -> Tensor:
    """COSE's binary loss, ``1[covered share < τ]``: 1 where the share of an image's counted
    pixels whose true class is in the set falls short of τ. Arguments, NaN and monotonicity as
    for :func:`image_losses` (uniform weights).

    >>> thresholds = torch.tensor([[[0.0, 0.3, 0.6, 0.9]]])
    >>> binary_losses(thresholds, torch.tensor([[[0, 1, 1, 1]]]), [0.2, 0.5, 0.7], 0.75).tolist()
    [[1.0, 1.0, 0.0]]
    """
    if not 0 <= tau <= 1:
        raise ValueError(f"the binary loss's τ must lie in [0, 1]; got {tau}")
    missed = image_losses(thresholds, labels, lambdas, None, mask)
    return torch.where(missed.isnan(), missed, ((1 - missed) < tau).double())


def set_losses(
    scores: Tensor,
    labels: Tensor,
    lambdas: Tensor | Sequence[float],
    loss: Loss = "uniform",
    cost: Tensor | None = None,
    tau: float = 0.9,
    mask: Tensor | None = None,
) -> Tensor:
    """Each image's loss at every λ of a grid for the sets of one anchor rule, as
    ``evaluate.py --conformal_loss`` controls it: ``uniform`` (the share of counted pixels whose
    true class is outside the set: :func:`image_losses`), ``cost`` (each pixel weighted by
    :func:`class_weights` of ``cost``, the anchor rule's matrix) or ``binary`` (1 where the
    covered share falls short of ``tau``: :func:`binary_losses`).

    Args:
        scores: (B, N, H, W) the rule's :func:`conformity_scores`.
        labels: (B, H, W) true classes, 255 ignored.
        lambdas: (L,) strictly increasing grid.
        loss, cost, tau: the loss (``cost`` for ``"cost"``, ``tau`` for ``"binary"``).
        mask: (B, H, W) or (H, W) bool, the pixels counted (e.g. one RoI); None: all.

    Returns:
        (B, L) float64 losses, NaN for an image with no counted pixel.

    >>> scores = torch.tensor([[0.0, 0.4], [0.7, 0.0]]).view(1, 2, 1, 2)  # decisions 0, 1
    >>> labels = torch.tensor([[[1, 0]]])                                   # λ* = 0.4, 0.7
    >>> set_losses(scores, labels, [0.5, 1.0]).tolist()
    [[0.5, 0.0]]
    >>> set_losses(scores, labels, [0.5, 1.0], "binary", tau=0.5).tolist()
    [[0.0, 0.0]]
    """
    if loss not in ("uniform", "cost", "binary"):
        raise ValueError(f"the loss must be uniform, cost or binary; got {loss!r}")
    thresholds = label_thresholds(scores, labels)
    if loss == "binary":
        return binary_losses(thresholds, labels, lambdas, tau, mask)
    weights = class_weights(cost if loss == "cost" else None, scores.shape[1])
    return image_losses(thresholds, labels, lambdas, weights, mask)


@dataclass(frozen=True)
class RiskControl:
    """The outcome of :func:`crc_threshold`.

    Attributes:
        index: λ̂'s index in the grid.
        lam: λ̂.
        reached: whether some λ of the grid meets the bound; False: λ̂ is the grid's last point
            (1, every class), which has no guarantee when ``B / (n + 1) > α``.
        risk: (L,) float64 empirical risk ``R̂_n(λ)`` of the n images (NaN for n = 0).
        n: calibration images used.
        left_out: images left out (NaN losses: nothing counted).
        alpha, bound: α and B.
    """

    index: int
    lam: float
    reached: bool
    risk: NDArray[np.float64]
    n: int
    left_out: int
    alpha: float
    bound: float


def crc_threshold(
    losses: ArrayLike | Tensor,
    lambdas: ArrayLike | Tensor,
    alpha: float,
    bound: float = 1.0,
) -> RiskControl:
    """Conformal risk control: ``λ̂ = min{λ ∈ Λ : (n / (n + 1)) · R̂_n(λ) + B / (n + 1) ≤ α}``,
    equivalently the smallest λ with ``R̂_n(λ) ≤ α − (B − α) / n``. For losses in [0, B],
    non-increasing in λ, and exchangeable calibration and test images,
    ``E[L_test(λ̂)] ≤ α``: a bound on the expected loss, not a per-image promise.

    Args:
        losses: (n, L) per-image losses on the grid; an image whose row is NaN (nothing
            counted) is left out of n.
        lambdas: (L,) strictly increasing grid in [0, 1] whose last point is 1.
        alpha: the risk level α in (0, B).
        bound: B, the losses' upper bound.

    Returns:
        :class:`RiskControl`; when no λ meets the bound (too few images, ``B / (n + 1) > α``),
        λ̂ = 1 and ``reached`` is False.

    Raises:
        ValueError: bad shapes, a grid not ending at 1, losses outside [0, B], a row NaN at
            some λ only, or α outside (0, B).

    >>> losses = np.array([[1.0, 0.5, 0.0]] * 9 + [[1.0, 0.0, 0.0]])
    >>> control = crc_threshold(losses, [0.0, 0.5, 1.0], alpha=0.55)
    >>> control.lam, control.reached, control.n         # at 0.5: 10/11 · 0.45 + 1/11 = 0.5
    (0.5, True, 10)
    """
    values, grid = _check_crc(losses, lambdas, alpha, bound)
    nan = np.isnan(values)
    kept = values[~nan.any(1)]
    n = len(kept)
    risk = kept.mean(0) if n else np.full(len(grid), np.nan)
    meets = np.flatnonzero(n / (n + 1) * risk + bound / (n + 1) <= alpha) if n else []
    index = int(meets[0]) if len(meets) else len(grid) - 1
    return RiskControl(
        index, float(grid[index]), bool(len(meets)), risk, n, len(values) - n, alpha, bound
    )


class SizeCurves(NamedTuple):
    """Per image and λ of a grid: ``pixels`` (B,) counted; ``sizes`` (B, L) ``Σ_x |S_λ(x)|``;
    ``singletons`` (B, L) ``#{x : |S_λ(x)| = 1}``, all float64 counts over the counted pixels."""

    pixels: Tensor
    sizes: Tensor
    singletons: Tensor


def set_size_curves(
    scores: Tensor, lambdas: Tensor | Sequence[float], mask: Tensor | None = None
) -> SizeCurves:
    """The set sizes of every image at every λ of a grid, from histograms of the scores.

    Args:
        scores: (B, N, H, W) of :func:`conformity_scores`.
        lambdas: (L,) strictly increasing grid.
        mask: (B, H, W) or (H, W) bool, the pixels counted (e.g. the labelled ones); None: all.

    >>> scores = torch.tensor([[0.0, 0.0], [0.5, 0.2]]).view(1, 2, 1, 2)
    >>> curves = set_size_curves(scores, [0.0, 0.3, 1.0])
    >>> curves.sizes.tolist(), curves.singletons.tolist()
    ([[2.0, 3.0, 4.0]], [[2.0, 1.0, 0.0]])
    """
    b, n = scores.shape[:2]
    counted = torch.ones_like(scores[:, 0], dtype=torch.bool) if mask is None else mask
    weights = counted.expand(b, *scores.shape[2:]).double()
    sizes = sum(_at_most(_histogram(scores[:, k], weights, lambdas)) for k in range(n))
    smallest = scores.topk(min(n, 2), dim=1, largest=False).values
    singletons = _at_most(_histogram(smallest[:, 0], weights, lambdas))
    if n > 1:
        singletons = singletons - _at_most(_histogram(smallest[:, 1], weights, lambdas))
    return SizeCurves(weights.flatten(1).sum(1), sizes, singletons)


@dataclass
class SetCounts:
    """Counts of the sets at one λ over labelled pixels, per RoI (row 0: the whole image; row r:
    the pixels of RoI id r) and true class, summed batch by batch with :meth:`add`.

    Attributes:
        pixels: (R + 1, N) int64 labelled pixels.
        covered: (R + 1, N) int64 pixels whose true class is in the set.
        sizes: (R + 1, N) int64 Σ of the set sizes.
        singletons: (R + 1, N) int64 pixels whose set has one class.

    >>> counts = SetCounts.zeros(num_classes=2, num_rois=1)
    >>> scores = torch.tensor([[0.0, 0.0], [0.5, 0.2]]).view(1, 2, 1, 2)
    >>> counts.add(scores, torch.tensor([[[1, 255]]]), 0.3, roi=torch.tensor([[1, 1]]))
    >>> counts.coverage().tolist(), counts.mean_size().tolist()
    ([[nan, 0.0], [nan, 0.0]], [1.0, 1.0])
    """

    pixels: Tensor
    covered: Tensor
    sizes: Tensor
    singletons: Tensor

    @classmethod
    def zeros(
        cls,
        num_classes: int = NUM_CLASSES,
        num_rois: int = NUM_ROIS,
        device: torch.device | str | None = None,
    ) -> SetCounts:
        """Empty counts of N classes and R RoIs."""
        shape = (num_rois + 1, num_classes)
        return cls(*(torch.zeros(shape, dtype=torch.int64, device=device) for _ in range(4)))

    def add(self, scores: Tensor, labels: Tensor, lam: float, roi: Tensor | None = None) -> None:
        """Add one batch: (B, N, H, W) scores of :func:`conformity_scores`, (B, H, W) labels
        (255 ignored), the threshold λ, and the RoI map (H, W) or (B, H, W) of ids 1 … R
        (others count in row 0 only; None: row 0 only)."""
        sets = scores <= lam
        sizes = sets.sum(1)
        valid = labels != IGNORE_INDEX
        y = labels.long().masked_fill(~valid, 0)
        covered = sets.gather(1, y.unsqueeze(1)).squeeze(1)
        rows, n = self.pixels.shape
        index = [torch.where(valid, y, -1)]
        if roi is not None:
            inside = valid & (roi >= 1) & (roi < rows)
            index.append(torch.where(inside, roi.long() * n + y, -1))
        for total, values in zip(
            (self.pixels, self.covered, self.sizes, self.singletons),
            (torch.ones_like(sizes), covered.long(), sizes, (sizes == 1).long()),
            strict=True,
        ):
            for at in index:
                keep = at >= 0
                total.view(-1).index_add_(0, at[keep], values[keep])

    def coverage(self) -> Tensor:
        """(R + 1, N) float64 share of each class's labelled pixels whose class is in the set
        (NaN where the class has none)."""
        return _ratio(self.covered, self.pixels)

    def mean_size(self, per_class: bool = False) -> Tensor:
        """Mean set size per labelled pixel, (R + 1,) or per true class (R + 1, N); NaN for 0/0."""
        if per_class:
            return _ratio(self.sizes, self.pixels)
        return _ratio(self.sizes.sum(1), self.pixels.sum(1))

    def singleton_share(self, per_class: bool = False) -> Tensor:
        """Share of labelled pixels whose set is one class, (R + 1,) or (R + 1, N); NaN for 0/0."""
        if per_class:
            return _ratio(self.singletons, self.pixels)
        return _ratio(self.singletons.sum(1), self.pixels.sum(1))


def _check_inputs(probs: Tensor, decision: Tensor, kind: str) -> None:
    """ValueError unless (B, N, H, W) float probabilities, (B, H, W) integer decisions in
    0 … N or 255, and a known kind."""
    if kind not in KINDS:
        raise ValueError(f"unknown conformal set {kind!r}: expected one of {', '.join(KINDS)}")
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(f"probabilities must be (B, N, H, W) floats; got {tuple(probs.shape)}")
    if decision.shape != probs.shape[:1] + probs.shape[2:] or decision.is_floating_point():
        raise ValueError(
            f"decisions must be (B, H, W) integers of probabilities {tuple(probs.shape)}; got "
            f"{tuple(decision.shape)} {decision.dtype}"
        )
    n = probs.shape[1]
    if not ((decision >= 0) & (decision <= n) | (decision == DEFERRED)).all():
        raise ValueError(f"decisions must be classes 0 … {n - 1}, or {n} or {DEFERRED} (deferred)")


def _chunks(probs: Tensor) -> Iterator[tuple[int, slice]]:
    """(image, rows) blocks of at most :data:`CHUNK_PIXELS` pixels (at least one row)."""
    height, width = probs.shape[-2:]
    step = max(1, CHUNK_PIXELS // max(width, 1))
    for b in range(probs.shape[0]):
        for top in range(0, height, step):
            yield b, slice(top, top + step)


def _mass_above(probs: Tensor) -> Tensor:
    """(N, h, w) → each class's mass of the classes ranked strictly above it (decreasing p,
    ties: the lower index first, as a stable sort keeps them), clamped to [0, 1]."""
    ranked, order = probs.sort(dim=0, descending=True, stable=True)
    above = ranked.cumsum(0).roll(1, 0)
    above[0] = 0
    return torch.empty_like(probs).scatter_(0, order, above.clamp_(0, 1))


def _anchor(scores: Tensor, decision: Tensor) -> Tensor:
    """``scores`` with ``s_d = 0`` where the rule names a class (deferred pixels untouched)."""
    n = scores.shape[1]
    named = (decision < n).unsqueeze(1)
    index = decision.clamp(0, n - 1).unsqueeze(1)
    kept = scores.gather(1, index)
    return scores.scatter_(1, index, kept.masked_fill_(named, 0))


def _counted(thresholds: Tensor, labels: Tensor, mask: Tensor | None) -> Tensor:
    """(B, H, W) bool: labelled pixels with a threshold, inside ``mask``."""
    if thresholds.ndim != 3 or labels.shape != thresholds.shape:
        raise ValueError(
            f"thresholds and labels must be (B, H, W) alike; got {tuple(thresholds.shape)} and "
            f"{tuple(labels.shape)}"
        )
    counted = (labels != IGNORE_INDEX) & ~thresholds.isnan()
    return counted if mask is None else counted & mask.bool()


def _check_weights(weights: Tensor, labels: Tensor, counted: Tensor) -> Tensor:
    """float64 (N,) weights, positive and finite, with a weight for every counted label."""
    weights = torch.as_tensor(weights, dtype=torch.float64)
    if weights.ndim != 1 or not (torch.isfinite(weights) & (weights > 0)).all():
        raise ValueError(f"class weights must be (N,) finite and > 0; got {weights.tolist()}")
    if (labels[counted] >= len(weights)).any():
        raise ValueError(f"a label is beyond the {len(weights)} class weights")
    return weights


def _histogram(values: Tensor, weights: Tensor, lambdas: Tensor | Sequence[float]) -> Tensor:
    """(B, L + 1) float64: bin i of image b sums the weights of its values with exactly i grid
    points below them (``λ_{i−1} < v ≤ λ_i``)."""
    grid = torch.as_tensor(lambdas, dtype=torch.float64)
    if grid.ndim != 1 or len(grid) == 0 or not (grid.diff() > 0).all():
        raise ValueError(f"the λ grid must be 1-D and strictly increasing; got {grid.tolist()}")
    grid = grid.to(values.device, values.dtype)
    b, bins = values.shape[0], len(grid) + 1
    flat = values.reshape(b, -1)
    bucket = torch.searchsorted(grid, flat.nan_to_num(nan=2.0).contiguous(), side="left")
    bucket += torch.arange(b, device=values.device).unsqueeze(1) * bins
    return torch.bincount(bucket.view(-1), weights.reshape(-1), b * bins).view(b, bins)


def _suffix(hist: Tensor) -> Tensor:
    """(B, L): the weight of the values above each grid point, ``Σ_{i > l} hist[:, i]``."""
    return hist.flip(1).cumsum(1).flip(1)[:, 1:]


def _at_most(hist: Tensor) -> Tensor:
    """(B, L): the weight of the values at or below each grid point, ``Σ_{i ≤ l} hist[:, i]``."""
    return hist.cumsum(1)[:, :-1]


def _ratio(numerator: Tensor, denominator: Tensor) -> Tensor:
    """float64 ``numerator / denominator``, NaN where the denominator is 0."""
    numerator, denominator = numerator.double(), denominator.double()
    return torch.where(denominator > 0, numerator / denominator.clamp_min(1e-300), float("nan"))


def _check_crc(losses, lambdas, alpha: float, bound: float) -> tuple[NDArray, NDArray]:
    """float64 (n, L) losses and (L,) grid, checked for :func:`crc_threshold`."""
    values = np.asarray(losses.cpu() if isinstance(losses, Tensor) else losses, dtype=float)
    grid = np.asarray(lambdas.cpu() if isinstance(lambdas, Tensor) else lambdas, dtype=float)
    if grid.ndim != 1 or len(grid) == 0 or np.any(np.diff(grid) <= 0) or grid[-1] != 1:
        raise ValueError("the λ grid must be 1-D, strictly increasing and end at 1")
    if grid[0] < 0:
        raise ValueError(f"the λ grid must lie in [0, 1]; it starts at {grid[0]}")
    if values.ndim != 2 or values.shape[1] != len(grid):
        raise ValueError(f"losses must be (n, {len(grid)}); got {values.shape}")
    nan = np.isnan(values)
    if np.any(nan.any(1) & ~nan.all(1)):
        raise ValueError("an image's losses are NaN at some λ only: NaN must mean nothing counted")
    finite = values[~nan]
    if bound <= 0 or np.any((finite < 0) | (finite > bound)):
        raise ValueError(f"losses must lie in [0, B = {bound}]")
    if not 0 < alpha < bound:
        raise ValueError(f"α must lie in (0, B = {bound}); got {alpha}")
    return values, grid
