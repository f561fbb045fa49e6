"""Cases for the Triton kernel of the decision layer, run by tests/test_decision_triton.py.

Run as a script under Triton's interpreter (``TRITON_INTERPRET=1``: the kernel on the CPU) or,
with ``--device cuda``, on a GPU. Each case compares ``decide`` / ``decide_mixtures`` on the
chosen device with the float64 reference of tests/test_decision.py; the last checks that the
kernel itself certifies most pixels (so the re-checks are not doing all the work).
"""

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from test_decision import VERTICES, near_ties, reference, smooth

from costseg import decision_triton
from costseg.costs import barycentric_grid, mix_costs
from costseg.decision import decide, decide_mixtures
from costseg.decision_certified import U64, _Fast


def check(device: str, every_case: bool = True) -> None:
    """Every case, or (``every_case`` False) the shortcut's: no priors, no near ties of one rule."""
    gen = torch.Generator().manual_seed(0)
    cases = [smooth((2, 19, 12, 16), 1), smooth((1, 19, 12, 16), 2, scale=1)]
    cases += [smooth((1, 19, 12, 16), 3).half(), smooth((1, 19, 12, 16), 4).bfloat16()]
    ties = torch.zeros(1, 19, 1, 3)
    ties[0, [3, 4]] = 0.4
    ties[0, [0, 11, 13], 0, [0, 1, 2]] = 0.2
    cases += [ties, torch.full((1, 19, 2, 2), 1 / 19).half()]
    priors = torch.rand(19, generator=gen) + 0.01
    for probs in cases:
        for cost in VERTICES:
            for pri in (None, priors) if every_case else (None,):
                got = decide(probs.to(device), cost, pri).cpu()
                assert torch.equal(got, reference(probs, cost, pri)), (probs.dtype, cost, pri)
    for cost in VERTICES[1:] if every_case else []:
        probs = near_ties(cost.double(), 70, seed=3)
        assert torch.equal(decide(probs.to(device), cost).cpu(), reference(probs, cost))
    weights = barycentric_grid(0.25)
    matrices = mix_costs(VERTICES, weights)
    for probs in (cases[0], cases[3], near_ties(matrices[7], 70, seed=7)):
        got = decide_mixtures(probs.to(device), VERTICES, weights).long().cpu()
        loop = torch.stack([reference(probs, c) for c in matrices], 1)
        assert torch.equal(got, loop)
    probs = smooth((1, 19, 16, 32), 6)
    got = decide_mixtures(probs.to(device), VERTICES, weights).long().cpu()
    assert torch.equal(got, torch.stack([reference(probs, c) for c in matrices], 1))
    probs = smooth((1, 19, 16, 16), 5)
    fast = _Fast(VERTICES[2:3].double(), probs.to(device), None, 23 * U64)
    labels = torch.empty(1, 256, dtype=torch.long, device=device)
    rule = decision_triton.rule(fast.folded, torch.ones(1, 1), fast.eps, device)
    opened = rule(fast.probs[0], labels)
    assert opened is None or opened.float().mean() < 0.01, opened.float().mean()
    print("all cases equal the float64 reference")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    device = parser.parse_args().device
    check(device)
    # Smaller blocks, full ones and more of them: more blocks take the kernel's shortcut (every
    # vertex agrees, all pixels certified), the others mix; both must equal the reference.
    decision_triton.CONFIG = [(16, 1), (64, 1)]
    check(device, every_case=False)
