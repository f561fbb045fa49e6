"""Designing by region (docs/definitions.md §21): the regional Lagrangian space against the
formula written out with plain loops, the search's exact statistics against ``decide_reference``
region by region, a design whose constraints all lie on RoI 0 against the plain Lagrangian one,
the designed regional file read back, and the refusals."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from costseg.calibration.design_search import search
from costseg.calibration.pareto_testing import pareto_testing
from costseg.costs import load_cost, save_cost, symmetric_cost
from costseg.decision import decide, decide_reference
from costseg.metrics.requirements import Requirements
from costseg.rules.design_spaces import (
    LagrangianSpace,
    RegionalLagrangianSpace,
    lagrangian_directions,
)

PERSON, CAR, BUILDING, ROAD = 11, 13, 2, 0
REQUIRE = ["person:roi1:recall>=0.5", "car:roi2:precision>=0.5", "building:roi0:precision>=0.5"]


def _scene(seed: int = 0, b: int = 4, h: int = 12, w: int = 20):
    """Probabilities, labels (a row unlabelled) and RoI ids 0 … 4 of ``b`` small images, with
    persons, cars and buildings common and often not the likeliest class."""
    g = torch.Generator().manual_seed(seed)
    probs = (2.5 * torch.randn(b, 19, h, w, generator=g)).softmax(1)
    labels = probs.argmax(1)
    for cls, share in ((PERSON, 0.25), (CAR, 0.15), (BUILDING, 0.2)):
        labels[torch.rand(labels.shape, generator=g) < share] = cls
    labels[:, 0] = 255
    return probs, labels, torch.randint(0, 5, labels.shape, generator=g)


def _space(regions, base=None, size: int = 3) -> RegionalLagrangianSpace:
    req = Requirements.parse(REQUIRE)
    pairs = [(t.cls, t.metric) for t in req.constraints]
    base = load_cost("egoistic") if base is None else base
    return RegionalLagrangianSpace(base, lagrangian_directions(pairs, 19), size, regions=regions)


def test_the_regional_matrices_follow_the_formula_of_section_21() -> None:
    """``C_r(μ) = C₀_r + Σ_{i : r_i = r or r_i = 0} μ_i A_i``, written out entry by entry: a
    recall constraint raises its class's column off the diagonal, a precision one its row."""
    base = torch.stack([load_cost(n) for n in ("robotistic", "egoistic", "altruistic")] * 2)[:5]
    regions, mu = (1, 2, 0), [3.0, 5.0, 7.0]
    kinds = [(PERSON, "column"), (CAR, "row"), (BUILDING, "row")]
    stack = _space(regions, base).matrix(mu)
    assert stack.shape == (5, 19, 19)
    for r in range(5):
        for k in range(19):
            for j in range(19):
                want = base[r, k, j].item()
                for (cls, kind), region, m in zip(kinds, regions, mu, strict=True):
                    moved = region in (r, 0)
                    on = (j == cls and k != cls) if kind == "column" else (k == cls and j != cls)
                    want += m if moved and on else 0.0
                assert stack[r, k, j].item() == want, (r, k, j)
    # a region no constraint names keeps C₀ itself: RoIs 3 and 4 only move by the RoI 0 one
    assert torch.equal(_space((1, 2, 1), base).matrix(mu)[3], base[3])


def test_every_constraint_on_roi0_searches_what_the_plain_lagrangian_space_searches() -> None:
    """With every constraint on RoI 0 each region's matrix is the plain space's: the grid and
    the continuous search score the same candidates, the same D1 losses and objective, so the
    design (Pareto Testing on them) is the plain Lagrangian design."""
    from costseg.evaluation.analyses.design import SearchImages

    probs, labels, roi = _scene()
    req = Requirements.parse([t.replace("roi1", "roi0").replace("roi2", "roi0") for t in REQUIRE])
    regional = _space((0, 0, 0))
    plain = LagrangianSpace(load_cost("egoistic"), regional.directions, regional.size)
    found = SearchImages()
    found.add_pixels(probs, labels, roi, 0.2, req, [regional.hull(), plain.hull()], [0, 1, 2, 3])
    for continuous in (False, True):
        searched = []
        for space in (regional, plain):
            losses = []
            candidates = search(space, found.scorer(req, losses.append), req.alphas, 12,
                                continuous=continuous, delta=0.1)  # fmt: skip
            searched.append((candidates, np.stack(losses, 1)))  # (n1, L, K)
        (stacks, losses_r), (matrices, losses_p) = searched
        assert np.array_equal(stacks.parameters, matrices.parameters)
        assert np.array_equal(stacks.objective, matrices.objective)
        np.testing.assert_array_equal(losses_r, losses_p)
        assert all(torch.equal(s[r], m) for s, m in zip(stacks.matrices, matrices.matrices,
                                                      strict=True) for r in range(5))  # fmt: skip
        tested = [pareto_testing(losses, losses[::-1], req.alphas, 0.5, found.objective)
                  for (found, losses) in searched]  # fmt: skip
        assert np.array_equal(tested[0].front, tested[1].front)
        assert np.array_equal(tested[0].certified, tested[1].certified)


def _loop_losses(probs, labels, roi, stack, req) -> torch.Tensor:
    """Each image decided pixel by pixel's region: ``decide_reference`` with RoI r's matrix on
    the whole image, kept where the RoI map says r; then each constraint's loss by hand."""
    out = []
    for i in range(len(probs)):
        decided = torch.full_like(labels[i], -1)
        for r in range(len(stack)):
            mine = decide_reference(probs[i : i + 1], stack[r])[0]
            decided[roi[i] == r] = mine[roi[i] == r]
        row = []
        for t in req.constraints:
            region = (labels[i] != 255) & ((roi[i] == t.roi) if t.roi else True)
            truth, said = region & (labels[i] == t.cls), region & (decided == t.cls)
            tp = (truth & said).sum().item()
            whole = {"recall": truth.sum(), "precision": said.sum()}[t.metric].item()
            row.append(1 - tp / whole if whole else float("nan"))
        out.append(row)
    return torch.tensor(out, dtype=torch.float64)


def test_the_regional_search_risks_equal_an_every_pixel_loop_region_by_region() -> None:
    """The search keeps, per RoI, only the pixels a candidate moving that RoI's matrix can
    change (fewer than the whole-image hull keeps), and its per-image losses and D1 risks equal
    the loop's on every pixel for candidates across the space."""
    from costseg.calibration.guarantee import defined_risks
    from costseg.calibration.search_pixels import constraint_pixels
    from costseg.evaluation.analyses.design import SearchImages

    probs, labels, roi = _scene(seed=4)
    req = Requirements.parse(REQUIRE)
    space = _space((1, 2, 3))
    whole = LagrangianSpace(load_cost("egoistic"), space.directions)
    needs = req.pixel_needs()
    kept = constraint_pixels(probs, labels, roi, needs, space.hull())
    assert kept.sum() < constraint_pixels(probs, labels, roi, needs, whole.hull()).sum()
    found = SearchImages()
    for part in (slice(0, 1), slice(1, 4)):  # two batches, each image its own seed
        seeds = list(range(part.start, part.stop))
        found.add_pixels(probs[part], labels[part], roi[part], 0.1, req, [space.hull()], seeds)
    g = torch.Generator().manual_seed(1)
    points = [*space.grid()[[0, 5, -1]], *(100 * torch.rand(3, 3, generator=g).pow(3))]
    for point in points:
        stack, seen = space.matrix(point), []
        risks, _, defined = found.scorer(req, seen.append)(stack)
        want = _loop_losses(probs, labels, roi, stack, req)
        torch.testing.assert_close(torch.from_numpy(seen[0]), want, equal_nan=True)
        np.testing.assert_allclose(risks, defined_risks(want.numpy())[0])
        assert defined.tolist() == (~want.isnan()).sum(0).tolist()


def test_the_designed_regional_file_read_back_decides_like_the_stack(tmp_path) -> None:
    """The regional cost file (``regions:`` for the moved RoIs only, ``default:``, the header as
    comments, a row per line) read by ``load_cost`` gives the stack, and decides like it."""
    probs, _, roi = _scene(seed=2, b=2)
    stack = _space((1, 2, 1)).matrix([0.5, 40.0, 3.0])
    path = tmp_path / "designed_cost.yaml"
    save_cost(path, stack, "designed", header="designed by a test\nsecond line")
    text = path.read_text()
    assert text.startswith("# designed by a test\n# second line\n")
    assert "  regions:" not in text and "street:" in text and "sidewalk:" in text
    assert "building:\n" not in text.split("regions:")[1]  # RoI 3 keeps the default
    assert len(text.splitlines()) < 120  # one line per matrix row
    loaded = load_cost(path)
    assert torch.equal(loaded, stack)
    assert torch.equal(decide(probs, loaded, roi=roi), decide(probs, stack, roi=roi))
    plain = torch.stack([symmetric_cost(19)] * 5)  # all equal: written as one matrix
    save_cost(path, plain, "plain")
    assert load_cost(path).shape == (19, 19)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--require", "person:roi7:recall>=0.8"], "unknown RoI 'roi7'"),
        (["--require", "person:roi1:recall>=0.8", "--data_root", "{root}"],
         "--design regional gives each RoI its own matrix and needs a RoI map"),
    ],
)  # fmt: skip
def test_a_regional_design_is_refused_in_one_line(args, message, cityscapes_root, capsys) -> None:
    """A RoI that does not exist, and data without a RoI map (no priors to count, no
    ``--roi geometric``): one line on stderr, exit 2, before anything heavy."""
    from costseg.cli import evaluate_main

    shutil.rmtree(cityscapes_root / "gtFine" / "train")
    args = [a.replace("{root}", str(cityscapes_root)) for a in args]
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(["--design", "regional", "--design_delta", "0.1", *args])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
