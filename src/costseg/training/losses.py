"""Training losses (docs/definitions.md §16), chosen in a config as ``model.loss`` with
``class_path`` / ``init_args`` like the network.

Each loss is a plain ``nn.Module`` that returns :class:`LossSums`: sums over the batch's valid
pixels (label 255 ignored) and the denominator of its mean. :func:`batch_mean` divides by the
denominator of *all* processes, so two DDP processes train with the loss of one process on the
whole batch (a mean of per-process means would weigh a process's pixels by how many it has).

* :class:`CrossEntropy` — the default.
* :class:`WeightedCrossEntropy` — class weights given, or from a cost matrix (the mean cost of
  missing each class, normalised to mean 1); normalised like ``cross_entropy(weight=...)``.
* :class:`FocalLoss` — ``-(1 - p_y)^γ log p_y`` (Lin et al. 2017); γ = 0 is cross-entropy.
* :class:`LogitAdjustedCrossEntropy` — cross-entropy of ``z + τ log π`` (Menon et al. 2021),
  with global or pixel-wise priors of the training labels.
* :class:`ExpectedCostCrossEntropy` — cross-entropy plus λ times the expected cost of the soft
  decision ``Σ_k softmax(z)_k C[k, y]``.

>>> logits, labels = torch.zeros(1, 3, 1, 2), torch.tensor([[[0, 255]]])
>>> loss, terms = batch_mean(FocalLoss(gamma=0.0)(logits, labels))
>>> round(loss.item(), 4), round(terms["cross_entropy"].item(), 4)   # log 3
(1.0986, 1.0986)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.distributed as dist
from torch import Tensor, nn

from costseg.classes import IGNORE_INDEX
from costseg.costs import cost_weights, has_defer_row, load_cost, rescale

__all__ = [
    "CrossEntropy",
    "ExpectedCostCrossEntropy",
    "FocalLoss",
    "LogitAdjustedCrossEntropy",
    "LossSums",
    "SegmentationLoss",
    "WeightedCrossEntropy",
    "batch_mean",
    "cost_weights",
]


@dataclass
class LossSums:
    """A loss over one batch, as sums over its valid pixels.

    Attributes:
        total: Σ of the loss over the valid pixels (weighted by class weights where it has them).
        weight: the denominator of the loss's mean: the number of valid pixels, or Σ w_y.
        count: the number of valid pixels, the denominator of each term.
        terms: named sums over the valid pixels, shown in TensorBoard: always ``cross_entropy``
            (plain, of the unadjusted logits), and the added term of a loss made of two.
    """

    total: Tensor
    weight: Tensor
    count: Tensor
    terms: dict[str, Tensor] = field(default_factory=dict)


def batch_mean(sums: LossSums) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss to back-propagate and the mean of each term, over the valid pixels of every
    process.

    Under DDP (``torch.distributed`` initialised), whose gradients are averaged over the W
    processes, each process scales its sums by ``W / Σ_processes weight``: the averaged
    gradient, and the mean over processes of the returned values (Lightning's
    ``sync_dist``), are those of the whole batch in one process. A batch without a valid pixel
    gives 0, not NaN.
    """
    denominators = torch.stack([sums.weight, sums.count]).detach().double()
    world = 1
    if dist.is_available() and dist.is_initialized():
        world = dist.get_world_size()
        dist.all_reduce(denominators)
    weight, count = (world / d.clamp(min=1e-30) for d in denominators)
    loss = sums.total * weight.to(sums.total.dtype)
    terms = {name: value.detach() * count.to(value.dtype) for name, value in sums.terms.items()}
    return loss, terms


class SegmentationLoss(nn.Module):
    """Base of the losses: ``forward(logits, labels, priors)`` → :class:`LossSums`.

    ``uses_priors`` names the priors a loss needs from the module (``"global"`` (N,),
    ``"pixel"`` (N, H, W) at label size, or None); :meth:`for_classes` is called once with the
    model's classes, before training, and refuses settings that do not fit them.
    """

    uses_priors: Literal["global", "pixel"] | None = None

    def __init__(self) -> None:
        super().__init__()
        self.init_args: dict = {}  # the config entry that rebuilds this loss (models/entries.py)

    def for_classes(self, class_names: Sequence[str]) -> None:
        """Check (and build what depends on) the model's classes; nothing by default."""

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        raise NotImplementedError


def _nll(logits: Tensor, labels: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel ``-log softmax(z)_y`` (0 where ignored), the valid mask, and the labels with
    ignored pixels set to class 0 (safe to index with)."""
    valid = labels != IGNORE_INDEX
    safe = torch.where(valid, labels, 0)
    log_p = _at_least_float32(logits).log_softmax(1)
    nll = -log_p.gather(1, safe[:, None])[:, 0]
    return torch.where(valid, nll, 0.0), valid, safe


def _at_least_float32(x: Tensor) -> Tensor:
    """float32 for bf16 / float16 logits (autocast), float64 kept (gradient checks)."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


def _sums(total: Tensor, valid: Tensor, nll: Tensor, weight: Tensor | None = None, **terms):
    count = valid.sum().to(total.dtype)
    terms = {"cross_entropy": nll.sum(), **{k: v.sum() for k, v in terms.items()}}
    return LossSums(total, count if weight is None else weight, count, terms)


class CrossEntropy(SegmentationLoss):
    """Cross-entropy ``-log softmax(z)_y``, the mean over valid pixels (PyTorch's
    ``cross_entropy`` with ``ignore_index=255``)."""

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        nll, valid, _ = _nll(logits, labels)
        return _sums(nll.sum(), valid, nll)


class WeightedCrossEntropy(SegmentationLoss):
    """Class-weighted cross-entropy ``Σ w_y (-log p_y) / Σ w_y`` over valid pixels.

    Args:
        weights: one positive weight per class, used as given.
        cost: instead of ``weights``, a cost matrix (a preset name or a YAML file, as for
            ``evaluate.py --cost``): the weights are :func:`cost_weights` of it.
    """

    def __init__(self, weights: list[float] | None = None, cost: str | None = None) -> None:
        super().__init__()
        if (weights is None) == (cost is None):
            raise ValueError("model.loss WeightedCrossEntropy takes either weights or cost")
        self.init_args = {"weights": weights, "cost": cost}
        self.register_buffer("weights", torch.empty(0), persistent=False)

    def for_classes(self, class_names: Sequence[str]) -> None:
        if self.init_args["cost"] is not None:
            matrix = load_cost(self.init_args["cost"], class_names)
            self.weights = cost_weights(matrix).float()
            return
        given = torch.tensor(self.init_args["weights"], dtype=torch.float32)
        if given.shape != (len(class_names),) or not bool(
            (given > 0).all() & given.isfinite().all()
        ):
            raise ValueError(
                f"model.loss weights must be {len(class_names)} positive numbers (one per "
                f"class), got {self.init_args['weights']}"
            )
        self.weights = given

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        nll, valid, safe = _nll(logits, labels)
        w = torch.where(valid, self.weights.to(nll.dtype)[safe], 0.0)
        return _sums((w * nll).sum(), valid, nll, weight=w.sum())


class FocalLoss(SegmentationLoss):
    """Focal loss ``-(1 - p_y)^γ log p_y`` (Lin et al. 2017), the mean over valid pixels.

    Args:
        gamma: the focusing exponent γ >= 0 (0 = cross-entropy, bit for bit).
    """

    def __init__(self, gamma: float = 2.0) -> None:
        super().__init__()
        if not gamma >= 0:
            raise ValueError(f"model.loss FocalLoss gamma must be >= 0, got {gamma}")
        self.gamma = float(gamma)
        self.init_args = {"gamma": self.gamma}

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        nll, valid, _ = _nll(logits, labels)
        # 1 - p_y floored above 0: for 0 < γ < 1 the gradient of x^γ is infinite at 0
        focal = (1 - torch.exp(-nll)).clamp(min=1e-12) ** self.gamma * nll
        return _sums(focal.sum(), valid, nll)


class LogitAdjustedCrossEntropy(SegmentationLoss):
    """Cross-entropy of the adjusted logits ``z + τ log π`` (Menon et al., ICLR 2021); the
    network's own logits ``z`` are what it outputs at test time. Its post-hoc counterpart is
    deciding with ``p / π^τ`` (the ML rule for τ = 1).

    Args:
        tau: the strength τ (0 = cross-entropy, bit for bit).
        priors: ``global`` (the class frequencies of the training labels: the pixel-wise
            priors averaged over the image) or ``pixel`` (the pixel-wise priors, §3,
            averaged with their mirror image because training flips half the images).
    """

    def __init__(self, tau: float = 1.0, priors: Literal["global", "pixel"] = "global") -> None:
        super().__init__()
        if priors not in ("global", "pixel"):
            raise ValueError(f"model.loss priors must be 'global' or 'pixel', got {priors!r}")
        self.tau = float(tau)
        self.uses_priors = priors
        self.init_args = {"tau": self.tau, "priors": priors}

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        if priors is None:
            raise ValueError("the logit-adjusted loss needs the priors of the training labels")
        logits = _at_least_float32(logits)
        log_pi = priors.to(logits.dtype).clamp(min=1e-30).log()
        log_pi = log_pi[:, None, None] if log_pi.ndim == 1 else log_pi
        nll, valid, _ = _nll(logits, labels)
        adjusted, _, _ = _nll(logits + self.tau * log_pi, labels)
        return _sums(adjusted.sum(), valid, nll)


class ExpectedCostCrossEntropy(SegmentationLoss):
    """Cross-entropy plus λ times the expected cost of the soft decision,
    ``Σ_k softmax(z)_k C[k, y]``, both means over valid pixels.

    The matrix is scaled to unit mean off-diagonal cost (:func:`costseg.costs.rescale`), so λ
    weighs every matrix alike: the robotistic term is ``1 - p_y``.

    Args:
        cost: a cost matrix, a preset name or a YAML file (as for ``evaluate.py --cost``); a
            matrix with a defer row is refused.
        lam: the weight λ >= 0 of the expected cost.
    """

    def __init__(self, cost: str = "altruistic", lam: float = 1.0) -> None:
        super().__init__()
        if not lam >= 0:
            raise ValueError(f"model.loss ExpectedCostCrossEntropy lam must be >= 0, got {lam}")
        self.lam = float(lam)
        self.init_args = {"cost": cost, "lam": self.lam}
        self.register_buffer("cost", torch.empty(0), persistent=False)

    def for_classes(self, class_names: Sequence[str]) -> None:
        matrix = load_cost(self.init_args["cost"], class_names)
        if has_defer_row(matrix):
            raise ValueError(
                f"model.loss cost {self.init_args['cost']!r} has a defer row: a loss needs an "
                "N x N matrix"
            )
        self.cost = rescale(matrix).float()

    def forward(self, logits: Tensor, labels: Tensor, priors: Tensor | None = None) -> LossSums:
        nll, valid, safe = _nll(logits, labels)
        probs = _at_least_float32(logits).softmax(1)
        per_true = torch.einsum("bkhw,kj->bjhw", probs, self.cost.to(probs.dtype))
        expected = torch.where(valid, per_true.gather(1, safe[:, None])[:, 0], 0.0)
        total = nll.sum() + self.lam * expected.sum()
        return _sums(total, valid, nll, expected_cost=expected)
