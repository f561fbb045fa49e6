"""Inputs for the decision layer's tests: where float32 cannot decide (exact ties, ties within a
few float32 ulps, low-precision probabilities, costs spanning 0.1 to 1000), and the paths that
every test runs on."""

import torch
from hypothesis import strategies as st

from costseg.costs import load_cost

VERTICES = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
LOW_PRECISION = [torch.float32, torch.float16, torch.bfloat16]
CPU_PATHS = ["torch", "numba"]  # forced; triton: tests/test_decision_triton.py (interpreter)


def smooth(shape, seed, scale=6.0):
    """Softmax of smooth random logits (the benchmark's recipe): unsure near borders."""
    gen = torch.Generator().manual_seed(seed)
    b, n, h, w = shape
    coarse = torch.randn(b, n, max(1, h // 8), max(1, w // 8), generator=gen) * scale
    logits = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear")
    return logits.softmax(1)


def near_ties(cost, count, seed):
    """(1, N, H, W) float32 probabilities whose two best costs lie within a few float32 ulps.

    For random classes a, b the expected costs tie exactly (in float64) at ``p0 + t (e_a - e_b)``;
    rounding that to float32 and stepping p_a by -3 .. 3 ulps gives costs a hair apart.
    """
    gen = torch.Generator().manual_seed(seed)
    n = cost.shape[0]
    pixels = []
    while len(pixels) < count:
        a, b = torch.randperm(n, generator=gen)[:2].tolist()
        p0 = torch.rand(n, generator=gen, dtype=torch.float64) ** 8
        p0[a] += 1.0
        p0[b] += 1.0
        p0 /= p0.sum()
        e = torch.zeros(n, dtype=torch.float64)
        e[a], e[b] = 1.0, -1.0
        c0, slope = cost @ p0, cost @ e
        if slope[a] == slope[b]:
            continue
        tie = p0 + (c0[b] - c0[a]) / (slope[a] - slope[b]) * e
        if (tie < 0).any() or (cost @ tie).argsort()[:2].sort().values.tolist() != sorted([a, b]):
            continue
        pixels += ulp_steps(tie.float(), a)
    return torch.stack(pixels, 1).view(1, n, 1, -1)  # groups of 7 consecutive pixels


def ml_cost(priors, lam=1.0):
    """Maximum-likelihood matrix ``C[k̂, k] = λ / π(k)`` for global priors."""
    priors = torch.as_tensor(priors, dtype=torch.float64)
    return (lam / priors).expand(len(priors), -1).clone().fill_diagonal_(0.0)


@st.composite
def probabilities(draw, max_classes=6):
    """Random probabilities with many exact ties: values drawn from a few levels."""
    n = draw(st.integers(2, max_classes))
    b, h, w = draw(st.integers(1, 2)), draw(st.integers(1, 4)), draw(st.integers(1, 4))
    levels = draw(st.lists(st.sampled_from([0.0, 0.1, 0.25, 0.5, 1.0, 3.0]), min_size=1))
    raw = draw(st.lists(st.sampled_from(levels), min_size=b * n * h * w, max_size=b * n * h * w))
    raw = torch.tensor(raw, dtype=torch.float32).view(b, n, h, w) + 1e-3
    dtype = draw(st.sampled_from(LOW_PRECISION))
    return (raw / raw.sum(1, keepdim=True)).to(dtype)


def ulp_steps(p: torch.Tensor, a: int) -> list[torch.Tensor]:
    """Seven copies of (N,) ``p`` with ``p[a]`` stepped by -3 .. 3 float ulps."""
    steps = []
    for step in range(-3, 4):
        q = p.clone()
        for _ in range(abs(step)):
            q[a] = torch.nextafter(q[a], torch.tensor(2.0 if step > 0 else 0.0))
        steps.append(q)
    return steps


def defer_ties(cost, count, seed):
    """(1, N, 1, P) float32 probabilities where a class and deferring (the last row of an
    (N + 1, N) ``cost``) are the two best candidates and lie within a few float32 ulps.

    From certainty in a random class a towards random probabilities p1, a stays the best until
    the first other candidate catches up (each at a ``t`` solved in float64): where that is
    deferring, the pixel is kept, with p_a stepped by -3 .. 3 ulps as in :func:`near_ties`.
    """
    gen = torch.Generator().manual_seed(seed)
    n = cost.shape[1]
    pixels = []
    for _ in range(100 * count):
        if len(pixels) >= count:
            break
        a = int(torch.randint(n, (1,), generator=gen))
        p1 = torch.rand(n, generator=gen, dtype=torch.float64) ** 8
        p1 /= p1.sum()
        at_p1 = cost @ p1  # along the way, row r minus row a: C[r, a] - t (C[r, a] + x_a - x_r)
        rate = cost[:, a] + at_p1[a] - at_p1
        t = torch.where(rate > 0, cost[:, a] / rate, torch.inf)
        t[a] = torch.inf
        first, second = t.sort().values[:2].tolist()
        if t.argmin() != n or not 0 < first < 1 or second < first * (1 + 1e-6):
            continue
        tie = first * p1
        tie[a] += 1 - first
        pixels += ulp_steps(tie.float(), a)
    if len(pixels) < count:
        raise ValueError("deferring is rarely a best candidate here: lower the defer costs")
    return torch.stack(pixels, 1).view(1, n, 1, -1)
