"""Meta fusion (docs/definitions.md §15, MetaFusion generalised): a rule R's extra segments,
kept where the meta classifier trusts them.

For a base rule B and a rule R, R's segments of a fused class k that share no pixel with B's
class-k pixels are the candidates; a candidate whose meta-classifier probability of being false
(iou0) is ≥ τ is dropped. The fused label map is B's, except where R predicts a fused class
inside a segment that was not dropped: there it is R's. τ = 0 drops every candidate; τ = 1 keeps
all but those the classifier is certain of.

The meta classifier of R is fitted on held-out images before the reported ones are decided
(:func:`costseg.evaluation.run.run`), then handed on in a copy of the group's decider
(:meth:`FusedRules.using`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from costseg.meta.collect import rule_segments
from costseg.meta.models import MetaModels
from costseg.rules.base import Rule, RuleGroup, needs_priors, plain_rules
from costseg.rules.named import apply_rules

FUSION_MODEL = "gradient_boosting"  # MetaFusion's
MASKED = 4
"""At most this many fused rules join the named ones in the example mask figures."""


def fused_labels(
    base: np.ndarray,
    rule: np.ndarray,
    ids: np.ndarray,
    false_probability: np.ndarray,
    classes: Sequence[int],
    taus: Sequence[float],
) -> np.ndarray:
    """(T, H, W) fused label maps of one image, one per τ.

    Args:
        base: (H, W) B's labels; ``rule``: (H, W) R's labels; ``ids``: (H, W) R's segment ids
            (0 = none, segment i is row i - 1 of ``false_probability``).
        false_probability: (n,) the meta classifier's probability that each segment is false.
        classes: the fused classes; ``taus``: the thresholds.
    """
    n = len(false_probability)
    flat_ids, flat_rule, flat_base = ids.ravel(), rule.ravel(), base.ravel()
    segment_class = np.zeros(n + 1, np.int64)
    segment_class[flat_ids] = flat_rule
    fused_class = np.isin(segment_class, classes)
    fused_class[0] = False
    agrees = np.bincount(flat_ids, weights=flat_base == flat_rule, minlength=n + 1) > 0
    candidate = fused_class & ~agrees
    out = np.repeat(base[None], len(taus), 0)
    for t, tau in enumerate(taus):
        dropped = candidate & (np.concatenate([[0.0], false_probability]) >= tau)
        keep = (fused_class & ~dropped)[ids]
        out[t][keep] = rule[keep]
    return out


@dataclass
class FusedRules:
    """``probs, priors → (B, K, H, W)``: every rule of ``fused`` fused with ``base`` at every τ
    (rule after rule, τ after τ), once :meth:`use` has given the meta models."""

    base: Rule
    fused: tuple[Rule, ...]
    taus: tuple[float, ...]
    classes: tuple[int, ...]
    models: dict[str, MetaModels] | None = field(default=None, repr=False)

    def using(self, models: dict[str, MetaModels]) -> FusedRules:
        """These rules with the meta models of the fused rules (rule name → models), fitted on
        held-out images."""
        missing = [r.name for r in self.fused if FUSION_MODEL not in models[r.name].fitted]
        if missing:
            raise ValueError(
                f"no meta classifier for {', '.join(missing)}: the held-out segments of the rule "
                "are all false or all true; use more images (--meta_split)"
            )
        return replace(self, models=models)

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None, roi=None) -> torch.Tensor:
        if self.models is None:
            raise RuntimeError("FusedRules needs its meta models (using()) before it decides")
        decided = apply_rules(probs, (self.base, *self.fused), priors).cpu().numpy()
        out = np.empty((len(probs), len(self.fused) * len(self.taus), *probs.shape[-2:]), np.uint8)
        for b in range(len(probs)):
            for r, rule in enumerate(self.fused):
                table = rule_segments(probs[b : b + 1], decided[b, r + 1], rule, priors, None)
                false = self.models[rule.name].false_probability(FUSION_MODEL, table.columns)
                block = slice(r * len(self.taus), (r + 1) * len(self.taus))
                out[b, block] = fused_labels(
                    decided[b, 0], decided[b, r + 1], table.ids, false, self.classes, self.taus
                )
        return torch.from_numpy(out).to(probs.device)


FUSED_FAMILY = "fused"


def fused_name(rule: str, tau: float) -> str:
    """``R+meta@τ``, the name of a fused rule.

    >>> fused_name("ml", 0.5)
    'ml+meta@0.5'
    """
    return f"{rule}+meta@{tau:g}"


def fusion_group(
    base: Rule, fused: Sequence[Rule], taus: Sequence[float], classes: Sequence[int]
) -> RuleGroup:
    """The fused rules as one group (results in ``fusion.csv``, curves along τ when one rule is
    fused; several τ are the candidates of ``--target`` and ``--guarantee``)."""
    if not fused:
        raise ValueError("--fuse needs at least one rule")
    plain_rules([base, *fused], "--fuse")
    taus = tuple(float(t) for t in taus)
    if any(not 0 <= t <= 1 for t in taus):
        raise ValueError(f"--fuse_tau values must lie in [0, 1], got {list(taus)}")
    names = [fused_name(r.name, t) for r in fused for t in taus]
    columns = [{"matrix": fused_name(r.name, t), "fused": r.name, "tau": t}
               for r in fused for t in taus]  # fmt: skip
    one = len(fused) == 1 and len(taus) > 1
    return RuleGroup(
        FUSED_FAMILY,
        names,
        FusedRules(base, tuple(fused), taus, tuple(classes)),
        columns,
        masks=len(names) <= MASKED,
        heatmaps=True,
        needs_priors=needs_priors((base, *fused)),
        candidates=len(names) > 1,
        output="fusion",
        line=taus if one else None,
        axis="τ (meta-classifier threshold: candidates at or above it dropped)",
        note=f"{', '.join(r.name for r in fused)} fused with {base.name} on the classes "
        f"{list(classes)}, meta classifier {FUSION_MODEL}",
    )
