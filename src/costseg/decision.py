"""The decision layer: per-pixel argmin of expected cost (SPEC §1), fast and exact.

``d(x; C) = argmin_k' Σ_k C[k', k] · p(k|x) / π(k)``, ties to the lowest class index.

**The reference** (every decision equals it, bit for bit): ``Cs = C - C.max(0)`` in float64 (a
column constant changes every row's cost alike, hence no decision), ``q = p / π`` in float64,
the costs ``Σ_k Cs[k', k] · q_k`` summed over k in ascending order (one rounded product and one
rounded sum at a time), argmin with ties to the lowest index. The shift turns the symmetric
matrix into ``-λI``, whose costs ``-λ q`` keep every tie of q: the robotistic rule *is* argmax.

**The fast path**, in three stages, each deciding only what the previous one left open:

1. on the CPU, float32 costs, one matmul per chunk of pixels that stays in cache, with
   ``C - C.min(0) >= 0`` plus a row ``T`` bounding the reference's costs: sums of nonnegative
   terms err by at most ``γ`` times their own value, so the gap between the best two certifies
   the reference's decision, or not (``_Fast``, ``_top``); for large images one compiled pass
   over the matrix's sparse part instead, rows that share entries summed together, certified
   row by row, the pixels left open decided by the reference itself where q is exactly p
   (:mod:`costseg.decision_sparse`); on a GPU, one Triton kernel
   (:mod:`costseg.decision_triton`) sums the same costs in float64 in registers and certifies
   them the same way, K mixtures in the same read of the probabilities;
2. the same certificate in float64 (matmuls again) for the few pixels left open (``_top64``);
3. the reference itself for the float64 near ties (``_reference``).

**Mixtures** ``Σ_v w_kv C_v`` (``w >= 0``): the cost is linear in C, and the vertices' shifts
differ from the mixture's by a column constant, so the V vertex cost maps are computed once and
mixed. Where every vertex picks the same class with a certified gap, so does every mixture.
Elsewhere only classes that no vertex winner beats in every vertex can win; two or three such
candidates are decided by the signs of mixed cost differences, more by mixing their costs; near
ties go to stages 2 and 3 on the mixed matrix of ``mix_costs``: the result equals ``decide`` on it.
On the CPU a compiled kernel does the same block by block of pixels, each step vectorised over
the block (:mod:`costseg.decision_numba`, :mod:`costseg.decision_mixing`); on a GPU, Triton's.
"""

from __future__ import annotations

import copy
import functools
import os

import torch

from costseg.costs import mix_costs, symmetric_cost
from costseg.decision_certified import U64, _Fast, _Mixer, _top
from costseg.label_maps import empty_labels

COMPILED_MIN_PIXELS = 1 << 20  # single rules: numba's kernel from this image size on


def _exact_precision(fn):
    """Run ``fn`` outside autocast: mixed-precision validation must not lower the costs' float32
    / float64 precision (the certificates assume it)."""

    @functools.wraps(fn)
    def wrapper(probs: torch.Tensor, *args, **kwargs):
        with torch.autocast(probs.device.type, enabled=False):
            return fn(probs, *args, **kwargs)

    return wrapper


@_exact_precision
def decide(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Cost-based decision for every pixel, equal to the float64 reference on every pixel.

    Args:
        probs: (B, N, H, W) class probabilities >= 0 (float16/bfloat16/32/64, any device).
        cost: (N, N) cost matrix, rows = predicted class, columns = true class; ``None`` means the
            symmetric matrix (argmax, or maximum likelihood when priors are given).
        priors: ``None``, (N,) global or (N, H, W) pixel-wise priors π > 0: the rule is applied to
            ``p / π`` (a per-pixel column scaling).

    Returns:
        (B, H, W) int64 class indices.

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])
    >>> decide(p, None).item(), decide(p, C).item()
    (0, 1)
    """
    n = _check(probs)
    cost = symmetric_cost(n) if cost is None else cost
    if cost.shape != (n, n):
        raise ValueError(f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}")
    cost = cost.to(torch.float64).cpu()[None]  # small: prepared on the CPU
    fast = _fast(cost, probs, _priors(priors, n, *probs.shape[2:], probs), eps=(n + 4) * U64)
    # eps: the reference's rounding per T
    b, _, h, w = probs.shape
    out = empty_labels(b, h * w, dtype=torch.long, device=probs.device)
    # the reference's matrix, for the re-checks: built once, where one is needed
    shifted = functools.cache(lambda: _shift(cost).to(probs.device))
    if kernel := _gpu_kernel(fast):
        rule = kernel.rule(fast.folded, torch.ones(1, 1, dtype=torch.float64), fast.eps, out.device)
        for i in range(b):
            opened = rule(fast.probs[i], out[i : i + 1])
            if opened is not None:
                redo = opened[0].nonzero()[:, 0]
                out[i, redo] = fast.settle(fast.exact_q(i, redo), shifted())
        return out.view(b, h, w)
    rule = _sparse_rule(fast, cost, shifted())
    for i in range(b):
        redo, q64 = [], []
        for s, q in fast.chunks(i, rule and rule.step):
            labels = out[i, s : s + q.shape[1]]
            if rule is None:
                _, open_ = _top(fast.costs(q)[0], fast.gamma, fast.eps, *fast.code, True, labels)
                open_ = open_.nonzero()[:, 0]
            else:
                open_ = rule.chunk(q, labels)
            redo.append(open_ + s)
            q64.append(fast.exact_q(i, redo[-1]))  # while the chunk is in cache
        redo = torch.cat(redo)
        if len(redo):
            out[i, redo] = fast.settle(torch.cat(q64), shifted())
    return out.view(b, h, w)


@_exact_precision
def decide_mixtures(
    probs: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Decisions for K mixtures ``Σ_v w_kv C_v`` of V vertex matrices, in one pass.

    Equals ``decide(probs, mix_costs(vertices, weights)[k], priors)`` exactly for every k, at the
    cost of V vertex cost maps plus a cheap mixing step, instead of K full evaluations.

    Args:
        probs: (B, N, H, W) class probabilities >= 0.
        vertices: (V, N, N) cost matrices.
        weights: (K, V) mixture weights >= 0, each row with a positive entry
            (e.g. :func:`costseg.costs.barycentric_grid`).
        priors: as in :func:`decide`.

    Returns:
        (B, K, H, W) class indices, uint8 when N <= 256 (K label maps are large), else int64.

    >>> from costseg.costs import barycentric_grid, load_cost
    >>> V = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    >>> decide_mixtures(torch.rand(2, 19, 4, 5).softmax(1), V, barycentric_grid(0.1)).shape
    torch.Size([2, 66, 4, 5])
    """
    n = _check(probs)
    if vertices.shape[1:] != (n, n) or weights.ndim != 2 or weights.shape[1] != len(vertices):
        raise ValueError(
            f"expected vertices ({n} x {n} matrices) and weights (K, V), got "
            f"{tuple(vertices.shape)} and {tuple(weights.shape)}"
        )
    if not bool((weights >= 0).all() and (weights > 0).any(1).all()):
        raise ValueError("mixture weights must be >= 0 with a positive entry in each row")
    vertices, weights = vertices.detach(), weights.detach()  # decisions have no gradient
    # eps: the reference's rounding on a mixed matrix (and that of mix_costs), per T.
    priors = _priors(priors, n, *probs.shape[2:], probs)
    fast = _fast(vertices.double().cpu(), probs, priors, (n + 8) * U64)
    b, _, h, w = probs.shape
    dtype = torch.uint8 if n <= 256 else torch.long  # K label maps add up
    out = empty_labels(b, len(weights), h * w, dtype=dtype, device=probs.device)
    # The reference's matrices and the weights, for the re-checks: built once, where needed.
    mixed = functools.cache(lambda: _shift(mix_costs(vertices, weights).to(probs.device)))
    weights64 = functools.cache(lambda: weights.to(probs.device, torch.float64))
    if kernel := _gpu_kernel(fast):
        rule = kernel.rule(fast.folded, weights, fast.eps, out.device)
        for i in range(b):
            opened = rule(fast.probs[i], out[i])
            if opened is None:
                continue
            grid, pixel = opened.nonzero().unbind(1)
            pixels, inverse = torch.unique(pixel, return_inverse=True)
            settled = fast.settle(fast.exact_q(i, pixels), mixed(), grid, weights64(), inverse)
            out[i, grid, pixel] = settled.to(dtype)
        return out.view(b, len(weights), h, w)
    mixed, weights64 = mixed(), weights64()
    mix = _Mixer(weights64, fast, mixed)
    compiled = _cpu_kernel(fast, mix, mixed)
    for i in range(b):
        for s, q in fast.chunks(i, compiled and compiled.step):
            labels = out[i, :, s : s + q.shape[1]]
            if compiled is None:
                exact_q = lambda pixels, i=i, s=s: fast.exact_q(i, s + pixels)  # noqa: E731
                mix.chunk(fast.costs(q), exact_q, labels)
                continue
            grid, pixel = compiled.chunk(q, out[i], s)  # the image's rows: written in place
            if len(grid):
                pixels, inverse = torch.unique(pixel, return_inverse=True)
                settled = compiled.settle(fast.exact_q(i, s + pixels), grid, inverse)
                labels[grid, pixel] = settled.to(dtype)
    return out.view(b, len(weights), h, w)


def _fast(matrices: torch.Tensor, probs: torch.Tensor, priors, eps: float) -> _Fast:
    """``_Fast(matrices, probs, priors, eps)``; its matrix part is prepared once per matrices,
    global priors, device and matmul precision (small copies to a GPU cost more than the kernel)."""
    if priors is not None and priors.ndim > 1:
        return _Fast(matrices, probs, priors, eps)
    key = None if priors is None else priors.detach().double().cpu().numpy().tobytes()
    precision = torch.get_float32_matmul_precision(), torch.backends.cuda.matmul.allow_tf32
    template = _fast_template(
        matrices.detach().numpy().tobytes(), matrices.shape, key, eps, probs.device, precision
    )
    fast = copy.copy(template)
    fast.probs, fast.priors = probs.reshape(*probs.shape[:2], -1), priors
    return fast


@functools.lru_cache(maxsize=64)
def _fast_template(matrices: bytes, shape, priors: bytes | None, eps: float, device, precision):
    """A ``_Fast`` of these matrices and global priors for a stand-in image (see ``_fast``)."""
    as_tensor = lambda data: torch.frombuffer(bytearray(data), dtype=torch.float64)  # noqa: E731
    matrices = as_tensor(matrices).view(shape)
    priors = None if priors is None else as_tensor(priors).to(device)
    return _Fast(matrices, torch.empty(1, shape[-1], 1, 1, device=device), priors, eps)


def _gpu_kernel(fast: _Fast):
    """:mod:`costseg.decision_triton` where it runs: a CUDA tensor (or Triton's interpreter, which
    runs kernels on the CPU: tests) and no pixel-wise priors; None otherwise (the chunked path)."""
    device, interpret = fast.probs.device.type, os.environ.get("TRITON_INTERPRET") == "1"
    if fast.pixel_priors is not None or not (device == "cuda" or interpret):
        return None
    try:
        from costseg import decision_triton
    except ImportError:  # a CUDA build of torch without Triton
        return None
    return decision_triton


def _sparse_rule(fast: _Fast, cost: torch.Tensor, shifted: torch.Tensor):
    """:class:`costseg.decision_sparse.SparseRule` for CPU images of at least
    ``COMPILED_MIN_PIXELS`` where numba imports, else None (matmuls and ``_top``). Importing numba
    and loading the kernel (about 0.8 s) pays off at Cityscapes scale, not for one small image."""
    probs = fast.probs
    if probs.device.type != "cpu" or probs.shape[2] < COMPILED_MIN_PIXELS or _no_numba():
        return None
    try:
        from costseg.decision_sparse import SparseRule
    except ImportError:
        return None
    return SparseRule(fast, cost, shifted)


def _cpu_kernel(fast: _Fast, mix: _Mixer, shifted: torch.Tensor):
    """:class:`costseg.decision_numba.NumbaMixer` for a grid of mixtures (more than vertices, at
    most ``VERTICES``) of CPU tensors where numba imports, else None (``_Mixer``'s tensor
    operations). A few named rules do not pay for importing numba (about 0.8 s)."""
    k, v = mix.weights64.shape
    if fast.probs.device.type != "cpu" or k <= v or _no_numba():
        return None
    try:
        from costseg.decision_numba import VERTICES, NumbaMixer
    except ImportError:
        return None
    if v > VERTICES:
        return None
    return NumbaMixer(fast, mix.weights64, mix.gamma, shifted)


def _no_numba() -> bool:
    return os.environ.get("COSTSEG_NO_NUMBA") == "1"


def _check(probs: torch.Tensor) -> int:
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(
            f"probs must be a float (B, N, H, W) tensor, got {probs.dtype} {tuple(probs.shape)}"
        )
    return probs.shape[1]


def _shift(costs: torch.Tensor) -> torch.Tensor:
    # Subtracting a per-column constant leaves every decision unchanged (see module docstring).
    return costs - costs.amax(dim=-2, keepdim=True)


def _priors(priors, n: int, h: int, w: int, probs: torch.Tensor) -> torch.Tensor | None:
    """None, (N,) or (N, H·W) priors on the probabilities' device, validated."""
    if priors is None:
        return None
    priors = torch.as_tensor(priors).to(probs.device)
    priors = priors if priors.is_floating_point() else priors.double()
    if priors.shape not in ((n,), (n, h, w)):
        raise ValueError(
            f"priors must be ({n},) or ({n}, {h}, {w}) for these probabilities, "
            f"got {tuple(priors.shape)}"
        )
    if not bool((priors > 0).all()):
        raise ValueError("priors must be > 0 everywhere (floor them, e.g. at 1e-5)")
    return priors.reshape(n, -1) if priors.ndim == 3 else priors
