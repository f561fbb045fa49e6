"""The ``numba`` path: the CPU's compiled kernels, on its cores (docs/definitions.md §1).

A single rule: one compiled pass over the matrix's sparse part, rows that share entries summed
together, certified row by row (:mod:`.sparse_rule`). Mixtures: the vertex costs of each block
of pixels computed in cache and mixed there (:mod:`.mixer`, :mod:`.mixture_kernel`). The
kernels (and numba) are imported on first use: loading them takes about 0.8 s, which pays off
at Cityscapes scale, not for one small image. A regional value system (docs/definitions.md
§21): the same single-rule kernel on the runs of pixels of each distinct matrix, in place (no
pixel is copied; a run is at most a block).
"""

from __future__ import annotations

import torch

from costseg.decision import certificate as cert
from costseg.decision import certified
from costseg.decision.cpu import VERTICES
from costseg.decision.inputs import Inputs
from costseg.decision.label_maps import empty_labels
from costseg.decision.reference import shift
from costseg.decision.regions import distinct, matrix_ids

NAME = "numba"
COMPILED_MIN_PIXELS = 1 << 20  # single rules: chosen from this image size on


def not_supported_reasons(inputs: Inputs) -> list[str]:
    """Why the kernels cannot take these inputs (none: they can)."""
    reasons = []
    if inputs.device.type != "cpu":
        reasons.append(f"probabilities on {inputs.device}: numba's kernels run on the CPU")
    if inputs.mixtures is not None and inputs.vertices > VERTICES:
        reasons.append(f"{inputs.vertices} vertex matrices: the kernel mixes at most {VERTICES}")
    if inputs.mixtures is not None and inputs.defer:
        reasons.append(
            "a defer row in mixtures: the mixture kernel takes square matrices (its candidate "
            "bits have one row per class)"
        )
    return reasons


def not_preferred_reasons(inputs: Inputs) -> list[str]:
    """Why the kernels, which could, are not chosen automatically (forcing them ignores these)."""
    if inputs.mixtures is None and inputs.pixels < COMPILED_MIN_PIXELS:
        return [
            f"{inputs.pixels} pixels per image, fewer than {COMPILED_MIN_PIXELS}: loading the "
            "kernel (about 0.8 s) does not pay off"
        ]
    if inputs.mixtures is not None and inputs.mixtures <= inputs.vertices:
        return ["no more mixtures than vertices: a few rules do not pay for loading the kernel"]
    return []


def decide(probs: torch.Tensor, cost: torch.Tensor, priors) -> torch.Tensor:
    """(B, H, W) rows of the argmin of one (1, N, N) float64 matrix (inputs checked by
    ``decide``)."""
    from costseg.decision.cpu.sparse_rule import SparseRule  # numba: loaded where used

    fast, out, shifted = certified.single_rule(probs, cost, priors)
    rule = SparseRule(fast, cost, shifted())
    certified.decide_in_chunks(fast, out, rule.step, rule.chunk, shifted)
    return out.view(len(probs), *probs.shape[2:])


def decide_regional(probs: torch.Tensor, stack: torch.Tensor, priors, roi: torch.Tensor):
    """(B, H, W) rows of a regional value system's argmins: (K, M, N) float64 stack, (B', H, W)
    RoI ids (inputs checked by ``decide``). Each chunk's runs of pixels of one distinct matrix
    are decided by that matrix's kernel (:class:`.sparse_rule.RegionalRule`); the pixels left
    open, by its ``CertifiedCosts.settle``."""
    from costseg.decision.cpu.sparse_rule import RegionalRule, SparseRule  # numba: where used

    matrices, index = distinct(stack)
    eps = cert.reference_eps(probs.shape[1], mixtures=False)
    shifted = [shift(matrices[d : d + 1]) for d in range(len(matrices))]
    fasts = [certified.prepare(m[None], probs, priors, eps) for m in matrices]
    rules = [SparseRule(f, matrices[d : d + 1], shifted[d]) for d, f in enumerate(fasts)]
    regional, step = RegionalRule(rules), rules[0].step
    b, _, h, w = probs.shape
    out = empty_labels(b, h * w, dtype=torch.long, device=probs.device)
    ids = matrix_ids(roi.cpu(), index).numpy()
    for i in range(b):
        redo, q64 = [], []
        for s, q in fasts[0].chunks(i, step):
            image_ids = ids[i if len(ids) > 1 else 0, s : s + q.shape[1]]
            left = regional.chunk(q, image_ids, out[i, s : s + q.shape[1]]) + s
            redo.append(left)
            q64.append(fasts[0].exact_q(i, left))  # while the chunk is in cache
        pixels, q64 = torch.cat(redo), torch.cat(q64)
        which = torch.from_numpy(ids[i if len(ids) > 1 else 0][pixels.numpy()])
        for d, fast in enumerate(fasts):
            mine = which == d
            if mine.any():
                out[i, pixels[mine]] = fast.settle(q64[mine], shifted[d])
    return out.view(b, h, w)


def decide_mixtures(probs, vertices, weights, priors) -> torch.Tensor:
    """(B, K, H, W) rows of the argmins of K mixtures (inputs checked by ``decide_mixtures``)."""
    from costseg.decision.cpu.mixer import NumbaMixer  # numba: loaded where used

    fast, out, mixed, weights64 = certified.mixtures(probs, vertices, weights, priors)
    mix_gamma = cert.mixed_gamma(fast.gamma, fast.u_in, weights.shape[1])
    compiled = NumbaMixer(fast, weights64(), mix_gamma, mixed())
    for i in range(len(probs)):
        for s, q in fast.chunks(i, compiled.step):
            grid, pixel = compiled.chunk(q, out[i], s)  # the image's rows: written in place
            if len(grid):
                pixels, inverse = torch.unique(pixel, return_inverse=True)
                settled = compiled.settle(fast.exact_q(i, s + pixels), grid, inverse)
                out[i, :, s : s + q.shape[1]][grid, pixel] = settled.to(out.dtype)
    return out.view(len(probs), len(weights), *probs.shape[2:])
