"""Which path decides an input, and why the others do not (docs/definitions.md §1).

Every path gives the reference's decisions; they differ in speed. In order of priority:
``triton`` (:mod:`.gpu.triton_path`), ``numba`` (:mod:`.cpu.numba_path`), ``torch``
(:mod:`.tensor_ops`), ``reference`` (:mod:`.reference`, never needed: ``torch`` always fits).
Each path module says why it cannot take an input (``not_supported_reasons``) and, where it
could but would not pay off, why it is not chosen (``not_preferred_reasons``); the first path
with neither takes the input. A regional value system with a RoI map (docs/definitions.md §21)
goes to a path's ``decide_regional``; a path without one cannot take it.
``COSTSEG_DECISION_PATH`` or ``path=`` forces one (tests, bug reports): the preferences are then
ignored, and a path that cannot take the input is an error.
Paths return the argmin's rows (a defer row: N); :func:`~.label_maps.labels_of` makes them labels.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import torch

from costseg.decision import inputs as checks
from costseg.decision import tensor_ops
from costseg.decision.cpu import numba_path
from costseg.decision.gpu import triton_path
from costseg.decision.inputs import Inputs
from costseg.decision.reference import reference_mixture_rows, reference_rows, regional_rows

ENV = "COSTSEG_DECISION_PATH"


def _reference_mixtures(probs, vertices, weights, priors) -> torch.Tensor:
    rows = reference_mixture_rows(probs, vertices, weights, priors)
    return rows.to(torch.uint8 if probs.shape[1] <= 256 else torch.long)  # as the others


REFERENCE = SimpleNamespace(
    NAME="reference",
    not_supported_reasons=lambda inputs: [],
    decide=lambda probs, cost, priors: reference_rows(probs, cost[0], priors),
    decide_mixtures=_reference_mixtures,
    decide_regional=regional_rows,
)
PATHS = {path.NAME: path for path in (triton_path, numba_path, tensor_ops, REFERENCE)}


def reasons(name: str, inputs: Inputs, automatic: bool = True) -> list[str]:
    """Why path ``name`` does not take ``inputs``: it cannot, or (``automatic``) it would not
    pay off. Empty: it takes them."""
    path = PATHS[name]
    return _cannot(path, inputs) + (_not_preferred(path, inputs) if automatic else [])


def choose(inputs: Inputs, path: str | None = None) -> SimpleNamespace:
    """The path module for ``inputs``: ``path``, else ``$COSTSEG_DECISION_PATH``, else the
    first in priority that takes them.

    Raises:
        ValueError: a forced path that is unknown or cannot take the inputs (with its reasons).
    """
    forced = path or os.environ.get(ENV) or None
    if forced is None:
        return next(PATHS[name] for name in PATHS if not reasons(name, inputs))
    if forced not in PATHS:
        raise ValueError(f"unknown decision path {forced!r} (one of {', '.join(PATHS)}; {ENV})")
    why = reasons(forced, inputs, automatic=False)
    if why:
        raise ValueError(
            f"decision path {forced!r} cannot take {inputs.describe()}: {'; '.join(why)}"
        )
    return PATHS[forced]


def explain(probs, cost=None, priors=None, weights=None, path: str | None = None, roi=None) -> str:
    """Which path ``decide(probs, cost, priors, roi)`` takes and why the others do not (for bug
    reports); with ``weights``, that of ``decide_mixtures(probs, cost, weights, priors)``
    (``cost``: the (V, N, N) or (V, N + 1, N) vertices). The inputs are checked as those
    functions check them.

    >>> print(explain(torch.rand(1, 3, 4, 4)))  # doctest: +ELLIPSIS
    decide on (1, 3, 4, 4) torch.float32 probabilities on cpu, ...: path 'torch'
      triton: cannot: ...
      numba: not chosen: 16 pixels per image, fewer than 1048576: ...
      torch: taken
      reference: fits
    """
    n = checks.check_probs(probs)
    priors = checks.check_priors(priors, n, probs)
    if weights is None:
        cost, _, regions = checks.check_regions(checks.check_cost(cost, n), roi, probs)
        inputs = Inputs.of(probs, priors, cost, regions=regions)
    else:
        checks.check_mixtures(cost, weights, n)
        inputs = Inputs.of(probs, priors, cost, len(weights))
    chosen = choose(inputs, path).NAME
    forced = " (forced by path=)" if path else f" (forced by {ENV})" if os.environ.get(ENV) else ""
    lines = [f"{inputs.describe()}: path {chosen!r}{forced}"]
    for name, module in PATHS.items():
        cannot, wont = _cannot(module, inputs), _not_preferred(module, inputs)
        status = "taken" if name == chosen else "fits"
        if name != chosen and cannot:
            status = "cannot: " + "; ".join(cannot)
        elif name != chosen and wont:
            status = "not chosen: " + "; ".join(wont)
        lines.append(f"  {name}: {status}")
    return "\n".join(lines)


def _cannot(path, inputs: Inputs) -> list[str]:
    regional = inputs.regions and not hasattr(path, "decide_regional")
    return path.not_supported_reasons(inputs) + (["no regional decision"] if regional else [])


def _not_preferred(path, inputs: Inputs) -> list[str]:
    return path.not_preferred_reasons(inputs) if hasattr(path, "not_preferred_reasons") else []
