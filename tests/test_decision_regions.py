"""Regional value systems in the decision layer (docs/definitions.md §21): every path against a
loop over the RoIs that calls ``decide_reference`` with each region's matrix on that region's
pixels; a stack of equal matrices against the plain matrix; the dispatcher's reasons and the
RoI map's refusals."""

import os
import subprocess
import sys

import pytest
import torch
from decision_inputs import CPU_PATHS, VERTICES, near_ties, smooth

from costseg.costs import load_cost, with_defer
from costseg.decision import decide, decide_reference, explain, tensor_ops
from costseg.decision.cpu import numba_path
from costseg.decision.cpu.sparse_kernel import BLOCK

N = 19
STREET_PERSON = load_cost("configs/costs/street_person.yaml")


def stack_of_five(defer: bool = False) -> torch.Tensor:
    """Five distinct matrices: robotistic, altruistic, egoistic, street_person's street matrix
    and a dense random one (costs 0.1 to 100)."""
    dense = 10 ** (3 * torch.rand(N, N, generator=torch.Generator().manual_seed(3)) - 1)
    matrices = [*VERTICES, STREET_PERSON[1], dense.double().fill_diagonal_(0)]
    if defer:
        matrices = [with_defer(m, 0.05 * (1 + i) * m.mean().item()) for i, m in enumerate(matrices)]
    return torch.stack(matrices)


def blocky_roi(b: int, h: int, w: int, seed: int) -> torch.Tensor:
    """(b, h, w) RoI ids 0 … 4 in rectangles: runs of every length along the rows."""
    gen = torch.Generator().manual_seed(seed)
    coarse = torch.randint(0, 5, (b, 1, 3, 7), generator=gen).float()
    return torch.nn.functional.interpolate(coarse, size=(h, w), mode="nearest")[:, 0].long()


def loop_over_rois(probs, stack, priors, roi) -> torch.Tensor:
    """The independent reference: each RoI's pixels decided by ``decide_reference`` with that
    RoI's own matrix."""
    roi = roi.expand(len(probs), *probs.shape[2:])
    out = torch.full(roi.shape, -1, dtype=torch.long)
    for r in range(len(stack)):
        mine = roi == r
        out[mine] = decide_reference(probs, stack[r], priors)[mine]
    assert (out >= 0).all()
    return out


def hard_probs(dtype=torch.float32) -> torch.Tensor:
    """Two images of smooth probabilities with near ties of the egoistic matrix in the first
    rows, so that every path settles some pixels exactly."""
    probs = smooth((2, N, 12, 96), seed=0)
    ties = near_ties(VERTICES[2], 96, seed=1)[0, :, 0, :96]
    probs[0, :, 0, :] = ties
    probs[1, :, 1, :] = ties.flip(1)
    return probs.to(dtype)


@pytest.mark.parametrize("path", ["reference", *CPU_PATHS])
@pytest.mark.parametrize(
    ("defer", "priors", "dtype", "per_image"),
    [
        (False, None, torch.float32, False),
        (True, None, torch.float32, True),
        (False, "global", torch.float16, True),
        (True, "pixel", torch.float32, False),
        (False, "pixel", torch.float64, True),
    ],
)
def test_every_path_equals_a_loop_over_the_rois(path, defer, priors, dtype, per_image):
    probs = hard_probs(dtype)
    stack = stack_of_five(defer)
    roi = blocky_roi(2 if per_image else 1, 12, 96, seed=4)
    pi = {
        None: None,
        "global": torch.rand(N, generator=torch.Generator().manual_seed(5)) + 0.05,
        "pixel": smooth((1, N, 12, 96), seed=6)[0] + 1e-3,
    }[priors]
    expected = loop_over_rois(probs, stack, pi, roi)
    assert torch.equal(decide(probs, stack, pi, roi, path=path), expected)
    if path == "reference":
        assert torch.equal(decide_reference(probs, stack, pi, roi), expected)


@pytest.mark.parametrize("path", CPU_PATHS)
def test_runs_longer_than_a_block_and_a_map_of_one_region(path):
    probs = smooth((1, N, 3, BLOCK + 300), seed=7)
    stack = stack_of_five()
    roi = torch.zeros(1, 3, BLOCK + 300, dtype=torch.uint8)
    roi[:, 1, 5:] = 3  # a run of BLOCK + 295 pixels, then one across the row's end
    roi[:, 2, 100:] = 4
    expected = loop_over_rois(probs, stack, None, roi)
    assert torch.equal(decide(probs, stack, roi=roi, path=path), expected)
    one = torch.full_like(roi, 2)
    assert torch.equal(decide(probs, stack, roi=one, path=path), decide_reference(probs, stack[2]))


@pytest.mark.parametrize("path", CPU_PATHS)
def test_runs_of_every_length_across_the_threads_pieces(path):
    """Runs of 1 to 2000 pixels, starting anywhere against vectors, loops, blocks and the
    pieces the threads take (four per thread: boundaries every few blocks here)."""
    gen = torch.Generator().manual_seed(9)
    lengths = torch.cat([torch.randint(1, 70, (400,), generator=gen),
                         torch.randint(70, 2000, (30,), generator=gen)])  # fmt: skip
    lengths = lengths[torch.randperm(len(lengths), generator=gen)]  # 40,228 pixels
    ids = torch.randint(0, 5, (len(lengths),), generator=gen).repeat_interleave(lengths)
    height, width = 19, 2048
    roi = ids[: height * width].reshape(1, height, width).to(torch.uint8)
    probs = smooth((1, N, height, width), seed=10)
    stack = stack_of_five(defer=True)
    assert torch.equal(
        decide(probs, stack, roi=roi, path=path), loop_over_rois(probs, stack, None, roi)
    )


@pytest.mark.parametrize("path", ["reference", *CPU_PATHS])
def test_a_stack_of_equal_matrices_gives_the_plain_matrix_labels(path):
    probs = hard_probs()
    roi = blocky_roi(1, 12, 96, seed=8)
    for matrix in (VERTICES[2], with_defer(VERTICES[1], 2.0)):
        plain = decide_reference(probs, matrix)
        stack = matrix.expand(5, *matrix.shape)
        assert torch.equal(decide(probs, stack, roi=roi, path=path), plain)
        assert torch.equal(decide_reference(probs, stack, roi=roi), plain)  # no shortcut here
    # the regional file's own regions: street_person is argmax off the street
    assert torch.equal(decide(probs, STREET_PERSON, roi=torch.full_like(roi, 2)), probs.argmax(1))


def test_the_paths_regional_code_with_equal_matrices_gives_the_plain_labels():
    """``decide`` takes a stack of equal matrices as one matrix; the paths' own regional code,
    called here, must give the same labels."""
    probs = hard_probs()
    roi = (blocky_roi(1, 12, 96, seed=9) > 2).long()
    plain = decide_reference(probs, VERTICES[2])
    for module in (numba_path, tensor_ops):
        rows = module.decide_regional(probs, VERTICES[2].expand(2, N, N), None, roi)
        assert torch.equal(rows, plain), module.NAME


def test_the_dispatcher_names_the_regional_input_and_its_paths():
    probs = smooth((1, N, 4, 8), seed=10)
    roi = blocky_roi(1, 4, 8, seed=11)
    text = explain(probs, stack_of_five(), roi=roi)
    assert "with a RoI map and 5 distinct matrices" in text and "path 'torch'" in text
    assert "numba: not chosen: 32 pixels per image" in text
    big = torch.ones(1024, 1024, dtype=torch.long)
    assert "path 'numba'" in explain(smooth((1, N, 1024, 1024), seed=12), stack_of_five(), roi=big)
    assert "with a RoI map" not in explain(probs, VERTICES[0].expand(5, N, N), roi=roi)


@pytest.mark.parametrize(
    ("roi", "message"),
    [
        (None, r"a regional value system \(5 matrices\) decides with a RoI map"),
        (torch.zeros(4, 9, dtype=torch.long), r"must be \(4, 8\) or .*got \(1, 4, 9\)"),
        (torch.zeros(3, 4, 8, dtype=torch.long), r"got \(3, 4, 8\)"),
        (torch.zeros(4, 8), "must hold integer RoI ids, got torch.float32"),
        (torch.full((4, 8), 5), r"holds id 5; .* matrices for ids 0 … 4"),
        (torch.full((4, 8), -1), "holds id -1"),
    ],
)
def test_a_wrong_roi_map_is_refused_in_one_line(roi, message):
    probs = smooth((1, N, 4, 8), seed=13)
    for fn in (decide, decide_reference):
        with pytest.raises(ValueError, match=message):
            fn(probs, stack_of_five(), roi=roi)


def test_a_plain_matrix_ignores_the_roi_map():
    probs = smooth((1, N, 4, 8), seed=14)
    plain = decide_reference(probs, VERTICES[1])
    assert torch.equal(decide(probs, VERTICES[1], roi=torch.full((4, 8), 9)), plain)


def test_the_triton_kernel_region_by_region_under_the_interpreter():
    pytest.importorskip("triton")
    code = (
        "import torch, sys; sys.path.insert(0, 'tests');"
        "from test_decision_regions import *;"
        "probs, stack = hard_probs(), stack_of_five(True);"
        "roi = blocky_roi(2, 12, 96, seed=15);"
        "assert torch.equal(decide(probs, stack, roi=roi, path='triton'),"
        " loop_over_rois(probs, stack, None, roi))"
    )
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=root
    )
    assert done.returncode == 0, done.stderr[-3000:]


def test_expected_costs_of_a_regional_system_are_each_rois_own():
    from costseg.decision import expected_costs

    probs, stack, roi = hard_probs(), stack_of_five(True), blocky_roi(1, 12, 96, seed=16)
    got = expected_costs(probs, stack, roi=roi)
    for r in range(5):
        mine = (roi == r).expand(2, -1, -1)
        own = expected_costs(probs, stack[r])
        assert torch.allclose(got.permute(0, 2, 3, 1)[mine], own.permute(0, 2, 3, 1)[mine])
