"""Cases for the Triton kernel of the decision layer, run by tests/test_triton_kernel.py.

Run as a script under Triton's interpreter (``TRITON_INTERPRET=1``: the kernel on the CPU) or,
with ``--device cuda``, on a GPU. Each case compares ``decide`` / ``decide_mixtures`` on the
chosen device with ``decide_reference``; the last checks that the
kernel itself certifies most pixels (so the re-checks are not doing all the work).
"""

import argparse
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from decision_inputs import VERTICES, defer_ties, near_ties, smooth

from costseg.costs import barycentric_grid, mix_costs, symmetric_cost, with_defer
from costseg.decision import decide, decide_mixtures
from costseg.decision import decide_reference as reference
from costseg.decision.certificate import reference_eps
from costseg.decision.certified import CertifiedCosts
from costseg.decision.dispatch import ENV
from costseg.decision.gpu import triton_kernel


def check(device: str, every_case: bool = True) -> None:
    """Every case, or (``every_case`` False) the shortcut's: two inputs, no priors, no near ties,
    no defer row."""
    gen = torch.Generator().manual_seed(0)
    cases = [smooth((2, 19, 12, 16), 1), smooth((1, 19, 12, 16), 2, scale=1)]
    cases += [smooth((1, 19, 12, 16), 3).half(), smooth((1, 19, 12, 16), 4).bfloat16()]
    ties = torch.zeros(1, 19, 1, 3)
    ties[0, [3, 4]] = 0.4
    ties[0, [0, 11, 13], 0, [0, 1, 2]] = 0.2
    cases += [ties, torch.full((1, 19, 2, 2), 1 / 19).half()]
    priors = torch.rand(19, generator=gen) + 0.01
    for probs in cases if every_case else (cases[0], cases[3]):
        for cost in VERTICES:
            for pri in (None, priors) if every_case else (None,):
                got = decide(probs.to(device), cost, pri).cpu()
                assert torch.equal(got, reference(probs, cost, pri)), (probs.dtype, cost, pri)
    for cost in VERTICES[1:] if every_case else []:
        probs = near_ties(cost.double(), 70, seed=3)
        assert torch.equal(decide(probs.to(device), cost).cpu(), reference(probs, cost))
    weights = barycentric_grid(0.25)
    matrices = mix_costs(VERTICES, weights)
    mixed = [cases[0], cases[3], near_ties(matrices[7], 70, seed=7), smooth((1, 19, 16, 32), 6)]
    for probs in mixed if every_case else mixed[::3]:
        got = decide_mixtures(probs.to(device), VERTICES, weights).long().cpu()
        assert torch.equal(got, torch.stack([reference(probs, c) for c in matrices], 1))
    if every_case:
        check_defer(device, cases[0], priors, weights)
    probs = smooth((1, 19, 16, 16), 5)
    fast = CertifiedCosts(VERTICES[2:3].double(), probs.to(device), None, reference_eps(19, False))
    labels = torch.empty(1, 256, dtype=torch.long, device=device)
    rule = triton_kernel.rule(fast.folded, torch.ones(1, 1), fast.eps, device)
    opened = rule(fast.probs[0], labels)
    assert opened is None or opened.float().mean() < 0.01, opened.float().mean()
    print("all cases equal the float64 reference")


def check_defer(device: str, probs: torch.Tensor, priors: torch.Tensor, weights: torch.Tensor):
    """A defer row: one more candidate, labelled 255 (N = 16: 17 rows, other tiles)."""
    deferring = with_defer(VERTICES[1], torch.linspace(0.5, 20, 19, dtype=torch.float64))
    deferred = []
    for case, cost, pri in [
        (probs, deferring, priors),
        (defer_ties(deferring, 28, seed=8), deferring, None),
        (smooth((1, 16, 16, 16), 9, scale=2), with_defer(symmetric_cost(16), 0.6), None),
    ]:
        got = decide(case.to(device), cost, pri).cpu()
        assert torch.equal(got, reference(case, cost, pri)), (cost.shape, pri)
        deferred.append((got == 255).float().mean().item())
    assert all(0 < share < 1 for share in deferred), deferred
    defer_costs = [0.4, 3.0, 30.0]
    vertices = torch.stack([with_defer(v, c) for v, c in zip(VERTICES, defer_costs, strict=True)])
    got = decide_mixtures(probs.to(device), vertices, weights).long().cpu()
    loop = torch.stack([reference(probs, c) for c in mix_costs(vertices, weights)], 1)
    assert torch.equal(got, loop) and (loop == 255).any()


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    device = parser.parse_args().device
    os.environ[ENV] = "triton"  # every decision by the kernel (and its re-checks)
    check(device)
    # Smaller blocks, full ones and more of them: more blocks take the kernel's shortcut (every
    # vertex agrees, all pixels certified), the others mix; both must equal the reference.
    triton_kernel.CONFIG = [(16, 1), (64, 1)]
    check(device, every_case=False)
