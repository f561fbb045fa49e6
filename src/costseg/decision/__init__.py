"""The decision layer: the per-pixel argmin of expected cost, fast and exact.

``d(x; C) = argmin_k' Σ_k C[k', k] · p(k|x) / π(k)``, ties to the lowest class index
(docs/definitions.md §1); a matrix with a defer row adds deferring, labelled ``DEFERRED`` (255),
as the last candidate (§14). Read in this order:

* :mod:`.reference` -- the rule itself in plain float64 torch (:func:`decide_reference`), the
  definition every fast path equals on every pixel, bit for bit;
* :mod:`.api` -- :func:`decide` and :func:`decide_mixtures`: the inputs checked, then
* :mod:`.dispatch` -- the path that takes them (``triton``, ``numba``, ``torch``, ``reference``)
  and why the others do not (:func:`~.dispatch.explain`);
* :mod:`.certified` -- what the fast paths share: float32 costs with a rounding bound that
  certifies the reference's decision, the float64 re-check and the reference for the pixels
  left open; :mod:`.certificate` -- every rounding bound;
* the paths: :mod:`.tensor_ops` (any device), :mod:`.cpu` (numba), :mod:`.gpu` (Triton);
* :mod:`.counts` -- :func:`decide_counts` / :func:`count_decisions`: decide and count per image
  and RoI in one pass, no label map (a search's score of a matrix); :mod:`.subsample` -- a fixed
  share of each image's labelled pixels, for such a search.
"""

from costseg.decision.api import decide, decide_mixtures
from costseg.decision.counts import (
    CountInputs,
    DecisionCounts,
    count_decisions,
    decide_counts,
    prepare_counts,
)
from costseg.decision.dispatch import explain
from costseg.decision.label_maps import DEFERRED
from costseg.decision.reference import decide_mixtures_reference, decide_reference, expected_costs
from costseg.decision.subsample import Subsample, subsample

__all__ = [
    "DEFERRED",
    "CountInputs",
    "DecisionCounts",
    "Subsample",
    "count_decisions",
    "decide",
    "decide_counts",
    "decide_mixtures",
    "decide_mixtures_reference",
    "decide_reference",
    "expected_costs",
    "explain",
    "prepare_counts",
    "subsample",
]
