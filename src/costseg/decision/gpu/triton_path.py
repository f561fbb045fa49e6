"""The ``triton`` path: one Triton kernel per image (docs/definitions.md §1).

The kernel (:mod:`.triton_kernel`) sums the costs in float64 in registers and certifies them,
K mixtures in the same read of the probabilities; the pairs it leaves open go to
``CertifiedCosts.settle``. A defer row is one more candidate row (docs/definitions.md §14); a
regional value system (§21) decides each distinct matrix's pixels, gathered, one matrix at a
time (:func:`~costseg.decision.regions.by_region`). It
runs on CUDA tensors, or on the CPU under Triton's interpreter
(``TRITON_INTERPRET=1``, set before Triton is imported: tests). Triton is optional, imported on
first use.
"""

from __future__ import annotations

import importlib.util
import os

import torch

from costseg.decision import certified
from costseg.decision.inputs import Inputs
from costseg.decision.regions import by_region

NAME = "triton"


def not_supported_reasons(inputs: Inputs) -> list[str]:
    """Why the kernel cannot take these inputs (none: it can)."""
    reasons = []
    if importlib.util.find_spec("triton") is None:
        reasons.append("triton is not installed")
    if inputs.device.type != "cuda" and not interpreted():
        reasons.append(
            f"no CUDA device: probabilities on {inputs.device} (TRITON_INTERPRET=1 runs the "
            "kernel on the CPU)"
        )
    if inputs.pixel_priors:
        reasons.append("pixel-wise priors: the kernel folds only global priors into its weights")
    return reasons


def interpreted() -> bool:
    """Whether Triton's interpreter runs kernels on the CPU."""
    return os.environ.get("TRITON_INTERPRET") == "1"


def decide(probs: torch.Tensor, cost: torch.Tensor, priors) -> torch.Tensor:
    """(B, H, W) rows of the argmin of one (1, M, N) float64 matrix, M = N or N + 1 with a defer
    row (inputs checked by ``decide``)."""
    from costseg.decision.gpu import triton_kernel  # optional: imported where used

    fast, out, shifted = certified.single_rule(probs, cost, priors)
    rule = triton_kernel.rule(
        fast.folded, torch.ones(1, 1, dtype=torch.float64), fast.eps, out.device
    )
    for i in range(len(probs)):
        opened = rule(fast.probs[i], out[i : i + 1])
        if opened is not None:
            redo = opened[0].nonzero()[:, 0]
            out[i, redo] = fast.settle(fast.exact_q(i, redo), shifted())
    return out.view(len(probs), *probs.shape[2:])


decide_regional = by_region(decide)
"""(B, H, W) rows of a regional value system's argmins: (K, M, N) stack, (B', H, W) RoI ids."""


def decide_mixtures(probs, vertices, weights, priors) -> torch.Tensor:
    """(B, K, H, W) rows of the argmins of K mixtures (inputs checked by ``decide_mixtures``)."""
    from costseg.decision.gpu import triton_kernel  # optional: imported where used

    fast, out, mixed, weights64 = certified.mixtures(probs, vertices, weights, priors)
    rule = triton_kernel.rule(fast.folded, weights, fast.eps, out.device)
    for i in range(len(probs)):
        opened = rule(fast.probs[i], out[i])
        if opened is None:
            continue
        grid, pixel = opened.nonzero().unbind(1)
        pixels, inverse = torch.unique(pixel, return_inverse=True)
        settled = fast.settle(fast.exact_q(i, pixels), mixed(), grid, weights64(), inverse)
        out[i, grid, pixel] = settled.to(out.dtype)
    return out.view(len(probs), len(weights), *probs.shape[2:])
