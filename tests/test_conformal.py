"""Conformal prediction sets anchored on a rule (docs/definitions.md §18): sets, set sizes and
entry thresholds against a per-pixel loop that builds each set as the definition reads; image
losses against a loop over λ and pixels; λ̂ against a scan of the grid; the guarantee by
simulation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from costseg.calibration import conformal
from costseg.calibration.conformal import (
    SetCounts,
    binary_losses,
    class_weights,
    conformity_scores,
    crc_threshold,
    entry_thresholds,
    image_losses,
    lambda_grid,
    prediction_sets,
    set_losses,
    set_size_curves,
    set_sizes,
)
from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.costs import load_cost
from costseg.report.conformal import conformal_table

UNIT = 16
"""Probabilities are multiples of 1 / UNIT: every sum is exact, so λ may sit on a boundary."""
LAMBDAS = sorted([k / UNIT for k in range(UNIT + 1)] + [0.3, 0.55, 0.9])


def dyadic_probs(b: int, n: int, h: int, w: int, seed: int) -> torch.Tensor:
    """(B, N, H, W) float32 probabilities in multiples of 1 / UNIT (many ties and zeros)."""
    g = torch.Generator().manual_seed(seed)
    cuts = torch.randint(0, UNIT + 1, (b, n - 1, h, w), generator=g).sort(1).values
    edges = torch.cat([torch.zeros(b, 1, h, w), cuts.float(), torch.full((b, 1, h, w), UNIT)], 1)
    return edges.diff(dim=1) / UNIT


def decisions(probs: torch.Tensor, seed: int) -> torch.Tensor:
    """A decision that is not the argmax: a random class, or deferred (N or 255)."""
    g = torch.Generator().manual_seed(seed)
    b, n, h, w = probs.shape
    decision = torch.randint(0, n, (b, h, w), generator=g)
    deferred = torch.rand(b, h, w, generator=g)
    decision[deferred < 0.15] = n
    decision[deferred > 0.85] = 255
    return decision


def reference_set(p: list[float], d: int, lam: float, kind: str) -> set[int]:
    """The set as the definition builds it, for one pixel."""
    n = len(p)
    if kind == "lac":
        chosen = {k for k in range(n) if p[k] >= 1 - lam}
    else:
        chosen, mass = set(), 0.0
        for k in sorted(range(n), key=lambda k: (-p[k], k)):
            chosen.add(k)
            mass += p[k]
            if mass > lam:
                break
    return chosen | ({d} if d < n else set())


def pixels(probs: torch.Tensor, decision: torch.Tensor):
    """(b, i, j, probabilities, decision) of every pixel."""
    b, _, h, w = probs.shape
    for x in range(b):
        for i in range(h):
            for j in range(w):
                yield x, i, j, probs[x, :, i, j].tolist(), int(decision[x, i, j])


@pytest.mark.parametrize("kind", ["lac", "aps"])
def test_sets_sizes_and_entry_thresholds_match_a_per_pixel_loop(kind):
    probs = dyadic_probs(2, 5, 3, 4, seed=1)
    decision = decisions(probs, seed=2)
    labels = torch.randint(0, 5, (2, 3, 4), generator=torch.Generator().manual_seed(3))
    labels[0, 0, :2] = 255
    thresholds = entry_thresholds(probs, decision, labels, kind)
    for lam in LAMBDAS:
        sets = prediction_sets(probs, decision, lam, kind)
        sizes = set_sizes(probs, decision, lam, kind)
        for b, i, j, p, d in pixels(probs, decision):
            want = reference_set(p, d, lam, kind)
            assert set(sets[b, :, i, j].nonzero().flatten().tolist()) == want, (b, i, j, lam)
            assert sizes[b, i, j] == len(want)
    for b, i, j, p, d in pixels(probs, decision):  # the first λ of the 1/UNIT grid holding y
        y = int(labels[b, i, j])
        if y == 255:
            assert math.isnan(thresholds[b, i, j])
            continue
        first = next(k / UNIT for k in range(UNIT + 1) if y in reference_set(p, d, k / UNIT, kind))
        assert thresholds[b, i, j].item() == first


def test_the_decision_is_always_in_the_set_and_argmax_ties_go_to_the_lower_index():
    probs = torch.tensor([0.25, 0.25, 0.5, 0.0]).view(1, 4, 1, 1)
    aps = conformity_scores(probs, torch.tensor([[[3]]]), "aps").flatten().tolist()
    assert aps == [0.5, 0.75, 0.0, 0.0]  # class 3 (p = 0) anchored; 0 ranks before 1
    assert set_sizes(probs, torch.tensor([[[3]]]), 0.0, "lac").item() == 1
    assert set_sizes(probs, torch.tensor([[[255]]]), 0.0, "lac").item() == 0  # nothing anchors


@pytest.mark.parametrize("kind", ["lac", "aps"])
def test_float_sets_match_the_loop_and_grow_with_lambda(kind):
    g = torch.Generator().manual_seed(4)
    probs = (3 * torch.randn(2, 6, 4, 5, generator=g, dtype=torch.float64)).softmax(1)
    decision = decisions(probs, seed=5)
    previous = None
    for lam in [0.0, 0.07, 0.21, 0.5, 0.77, 0.93, 0.999]:
        sets = prediction_sets(probs, decision, lam, kind)
        for b, i, j, p, d in pixels(probs, decision):
            assert set(sets[b, :, i, j].nonzero().flatten().tolist()) == reference_set(
                p, d, lam, kind
            )
        assert previous is None or (sets | ~previous).all()  # nested: S_λ ⊇ S_λ'
        previous = sets


@pytest.mark.parametrize("kind", ["lac", "aps"])
def test_lambda_one_is_every_class_and_no_loss(kind):
    g = torch.Generator().manual_seed(6)
    probs = (8 * torch.randn(3, 19, 16, 16, generator=g)).softmax(1)  # float32 round-off
    decision = decisions(probs, seed=7)
    assert prediction_sets(probs, decision, 1.0, kind).all()
    labels = torch.randint(0, 19, (3, 16, 16), generator=g)
    thresholds = entry_thresholds(probs, decision, labels, kind)
    assert thresholds.max() <= 1
    weights = class_weights(load_cost("egoistic"))
    losses = image_losses(thresholds, labels, lambda_grid(100), weights)
    assert (losses[:, -1] == 0).all() and (losses.diff(dim=1) <= 0).all()


def test_scores_do_not_depend_on_the_chunking(monkeypatch):
    probs = dyadic_probs(2, 7, 5, 3, seed=8).double() * 0.9 + 0.1 / 7
    decision = decisions(probs, seed=9)
    whole = conformity_scores(probs, decision, "aps")
    monkeypatch.setattr(conformal, "CHUNK_PIXELS", 4)  # one row of 3 pixels at a time
    assert torch.equal(conformity_scores(probs, decision, "aps"), whole)


def reference_losses(probs, decision, labels, lambdas, kind, weights, mask, tau=None):
    """(B, L) losses by looping over images, λ and pixels, each set built by reference_set."""
    out = np.full((probs.shape[0], len(lambdas)), np.nan)
    for b in range(probs.shape[0]):
        for at, lam in enumerate(lambdas):
            missed = total = covered = count = 0.0
            for _, i, j, p, d in pixels(probs[b : b + 1], decision[b : b + 1]):
                y = int(labels[b, i, j])
                if y == 255 or (mask is not None and not mask[b, i, j]):
                    continue
                inside = y in reference_set(p, d, lam, kind)
                missed += weights[y] * (not inside)
                total += weights[y]
                covered, count = covered + inside, count + 1
            if total:
                out[b, at] = missed / total if tau is None else float(covered / count < tau)
    return out


@pytest.mark.parametrize("kind", ["lac", "aps"])
@pytest.mark.parametrize("weighted", [False, True])
def test_image_losses_match_a_loop_over_lambda_and_pixels(kind, weighted):
    probs = dyadic_probs(3, 19, 3, 5, seed=10)
    decision = decisions(probs, seed=11)
    g = torch.Generator().manual_seed(12)
    labels = torch.randint(0, 19, (3, 3, 5), generator=g)
    labels[labels > 15] = 255
    labels[2] = 255  # an image with nothing counted: NaN
    mask = torch.rand(3, 3, 5, generator=g) < 0.7
    weights = class_weights(load_cost("altruistic") if weighted else None)
    thresholds = entry_thresholds(probs, decision, labels, kind)
    got = image_losses(thresholds, labels, LAMBDAS, weights if weighted else None, mask)
    want = reference_losses(probs, decision, labels, LAMBDAS, kind, weights.tolist(), mask)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12, atol=0)
    assert got[2].isnan().all() and not got[:2].isnan().any()
    got = binary_losses(thresholds, labels, LAMBDAS, 0.8)
    want = reference_losses(probs, decision, labels, LAMBDAS, kind, [1.0] * 19, None, tau=0.8)
    np.testing.assert_array_equal(got.numpy(), want)


@pytest.mark.parametrize("loss", ["uniform", "cost", "binary"])
def test_set_losses_of_each_loss_match_the_loop(loss):
    """The loss ``evaluate.py --conformal_loss`` controls, from one rule's scores, as the loop
    over λ and pixels builds it (the cost loss weighted by the anchor rule's matrix)."""
    probs = dyadic_probs(2, 19, 3, 4, seed=20)
    decision = decisions(probs, seed=21)
    labels = torch.randint(0, 19, (2, 3, 4), generator=torch.Generator().manual_seed(22))
    mask = labels % 3 != 0
    cost = load_cost("egoistic")
    scores = conformity_scores(probs, decision, "aps")
    got = set_losses(scores, labels, LAMBDAS, loss, cost, 0.7, mask)
    weights = class_weights(cost if loss == "cost" else None).tolist()
    tau = 0.7 if loss == "binary" else None
    want = reference_losses(probs, decision, labels, LAMBDAS, "aps", weights, mask, tau)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="uniform, cost or binary"):
        set_losses(scores, labels, LAMBDAS, "hinge")


def reference_crc(losses: np.ndarray, lambdas: list[float], alpha: float, bound: float):
    """(index, reached) by scanning the grid with the formula of conformal risk control."""
    rows = [r for r in losses.tolist() if not any(math.isnan(v) for v in r)]
    n = len(rows)
    for index in range(len(lambdas)):
        risk = math.fsum(r[index] for r in rows) / n if n else math.nan
        if n and n / (n + 1) * risk + bound / (n + 1) <= alpha:
            return index, True
    return len(lambdas) - 1, False


def test_crc_threshold_matches_a_scan_of_the_grid():
    rng = np.random.default_rng(13)
    lambdas = lambda_grid(50).tolist()
    for trial in range(200):
        n, bound = int(rng.integers(1, 40)), float(rng.choice([1.0, 2.0]))
        jumps = rng.uniform(0, 1, (n, 1))
        losses = bound * np.clip(1 - np.asarray(lambdas) / jumps, 0, 1) ** rng.uniform(0.5, 3)
        losses[rng.uniform(size=n) < 0.1] = np.nan
        alpha = float(rng.uniform(0.02, 0.5)) * bound
        control = crc_threshold(losses, lambdas, alpha, bound)
        index, reached = reference_crc(losses, lambdas, alpha, bound)
        assert (control.index, control.reached) == (index, reached), trial
        assert control.lam == lambdas[index] and control.n + control.left_out == n
    control = crc_threshold(np.zeros((5, 51)), lambdas, alpha=0.1)  # 1/6 > 0.1: not reachable
    assert (control.lam, control.reached, control.n) == (1.0, False, 5)


def test_crc_bounds_the_expected_test_loss():
    """Fixed per-image losses (the share of 40 pixels whose entry threshold, Beta-distributed
    per image, lies above λ), many random calibration / test splits: the mean test loss at λ̂ is
    at most α (Monte-Carlo error: 3 standard errors) and, for these nearly continuous losses, at
    least α − 2B / (n + 1) (the paper's Thm. 2); with 10 calibration images a rule without the
    correction, the smallest λ with R̂ ≤ α, exceeds α on the same splits."""
    rng = np.random.default_rng(14)
    grid = lambda_grid(100).numpy()
    a, b = rng.uniform(0.5, 3, 400), rng.uniform(2, 12, 400)
    losses = (rng.beta(a[:, None], b[:, None], (400, 40))[..., None] > grid).mean(1)
    for alpha, n in [(0.1, 10), (0.2, 10), (0.2, 30)]:
        ours, naive = [], []
        for _ in range(1500):
            order = rng.permutation(400)
            cal, test = losses[order[:n]], losses[order[n:]]
            ours.append(test[:, crc_threshold(cal, grid, alpha).index].mean())
            naive.append(test[:, np.flatnonzero(cal.mean(0) <= alpha)[0]].mean())
        mean, error = np.mean(ours), np.std(ours) / math.sqrt(len(ours))
        assert alpha - 2 / (n + 1) <= mean <= alpha + 3 * error, (alpha, n, mean)
        if n == 10:  # few images: the correction matters
            assert np.mean(naive) > alpha + 3 * np.std(naive) / math.sqrt(len(naive))


@pytest.mark.parametrize("kind", ["lac", "aps"])
def test_set_counts_and_size_curves_match_a_loop(kind):
    probs = dyadic_probs(2, 5, 4, 4, seed=15)
    decision = decisions(probs, seed=16)
    g = torch.Generator().manual_seed(17)
    labels = torch.randint(0, 6, (2, 4, 4), generator=g)
    labels[labels == 5] = 255
    roi = torch.randint(0, 3, (4, 4), generator=g)  # ids 1, 2 and pixels of no RoI (0)
    scores = conformity_scores(probs, decision, kind)
    counts = SetCounts.zeros(num_classes=5, num_rois=2)
    for b in range(2):  # batch by batch
        counts.add(scores[b : b + 1], labels[b : b + 1], 0.5, roi)
    want = {k: np.zeros((3, 5)) for k in ("pixels", "covered", "sizes", "singletons")}
    for b, i, j, p, d in pixels(probs, decision):
        y, chosen = int(labels[b, i, j]), reference_set(p, d, 0.5, kind)
        if y == 255:
            continue
        for row in {0, int(roi[i, j])}:
            values = (1, y in chosen, len(chosen), len(chosen) == 1)
            for key, value in zip(want, values, strict=True):
                want[key][row, y] += value
    for key, value in want.items():
        np.testing.assert_array_equal(getattr(counts, key).numpy(), value, key)
    with np.errstate(invalid="ignore"):  # 0/0: NaN, as the counts give it
        coverage = want["covered"] / want["pixels"]
    np.testing.assert_allclose(counts.coverage().numpy(), coverage)
    np.testing.assert_allclose(
        counts.mean_size().numpy(), want["sizes"].sum(1) / want["pixels"].sum(1)
    )
    curves = set_size_curves(scores, LAMBDAS, labels != 255)
    for at, lam in enumerate(LAMBDAS):
        sizes = set_sizes(probs, decision, lam, kind).where(labels != 255, 0)
        assert curves.sizes[:, at].tolist() == sizes.flatten(1).sum(1).tolist()
        ones = ((sizes == 1) & (labels != 255)).flatten(1).sum(1)
        assert curves.singletons[:, at].tolist() == ones.tolist()
    assert curves.pixels.tolist() == (labels != 255).flatten(1).sum(1).tolist()


def test_bad_inputs_are_refused_with_a_clear_message():
    probs = torch.full((1, 3, 2, 2), 1 / 3)
    decision = torch.zeros(1, 2, 2, dtype=torch.long)
    with pytest.raises(ValueError, match="unknown conformal set 'raps'"):
        conformity_scores(probs, decision, "raps")
    with pytest.raises(ValueError, match="decisions must be classes 0 … 2, or 3 or 255"):
        conformity_scores(probs, decision + 4, "lac")
    with pytest.raises(ValueError, match="decisions must be \\(B, H, W\\)"):
        conformity_scores(probs, decision[0], "lac")
    with pytest.raises(ValueError, match="labels must be integer classes 0 … 2 or 255"):
        entry_thresholds(probs, decision, decision + 3, "lac")
    with pytest.raises(ValueError, match="strictly increasing"):
        image_losses(torch.zeros(1, 2, 2), decision, [0.0, 0.5, 0.5, 1.0])
    with pytest.raises(ValueError, match="end at 1"):
        crc_threshold(np.zeros((3, 2)), [0.0, 0.5], 0.1)
    with pytest.raises(ValueError, match="NaN at some λ only"):
        crc_threshold(np.array([[np.nan, 0.0]]), [0.0, 1.0], 0.1)
    with pytest.raises(ValueError, match="losses must lie in"):
        crc_threshold(np.array([[1.5, 0.0]]), [0.0, 1.0], 0.1)


def test_evaluate_conformal_matches_a_brute_force_scan(cityscapes_root, tmp_path):
    """``evaluate.py --conformal``: λ̂ from the held-out split and the reported images' loss, set
    sizes and coverage equal a scan of the grid written from the definitions, on saved
    probabilities (the altruistic anchor is not the argmax)."""
    from costseg.cli import evaluate_main
    from costseg.data.cityscapes import CityscapesSegmentation
    from costseg.decision import decide_reference
    from costseg.networks.probs_files import load_probs, save_probs
    from tests.conftest import CITYSCAPES_FILES, CITYSCAPES_SIZE

    generator = torch.Generator().manual_seed(0)
    folder = tmp_path / "probs"
    for names in CITYSCAPES_FILES.values():
        for name in names:
            logits = 3 * torch.randn(19, *CITYSCAPES_SIZE, generator=generator)
            save_probs(folder / f"{name}.npz", logits.softmax(0))
    out, alpha = tmp_path / "out", 0.4
    args = ["--probs", str(folder), "--data_root", str(cityscapes_root), "--no-progress"]
    args += ["--cost", "robotistic", "altruistic", "--calibration_split", "train"]
    evaluate_main([*args, "--conformal", str(alpha), "--output_dir", str(out)])
    record = json.loads((out / "results.json").read_text())["conformal"]["rules"]

    grid = np.linspace(0, 1, 1001)
    altruistic = load_cost("altruistic")

    def pixels_of(split: str):
        data = CityscapesSegmentation(cityscapes_root, split)
        for i, name in enumerate(CITYSCAPES_FILES[split]):
            probs = load_probs(folder / f"{name}.npz").double()
            yield probs.numpy(), data[i][1].numpy()

    def losses(split, cost, lams):  # (images, λ): share of labelled pixels not in the set
        out_ = []
        for p, y in pixels_of(split):
            d = decide_reference(torch.from_numpy(p)[None], cost)[0].numpy()
            keep = y != 255
            p_y = np.take_along_axis(p, np.where(keep, y, 0)[None], 0)[0][keep]
            anchored = (d == y)[keep]
            out_.append([1 - np.mean(anchored | (p_y >= 1 - lam)) for lam in lams])
        return np.array(out_)

    for name, cost in (("robotistic", None), ("altruistic", altruistic)):
        risk = losses("train", cost, grid).mean(0)
        n = len(CITYSCAPES_FILES["train"])
        lam = grid[np.flatnonzero(n / (n + 1) * risk + 1 / (n + 1) <= alpha)[0]]
        assert record[name]["lambda"] == pytest.approx(lam) and record[name]["reached"]
        reported = losses("val", cost, [lam])[:, 0].mean()
        assert record[name]["reported_loss"] == pytest.approx(reported, abs=1e-9)
        sizes = []
        for p, y in pixels_of("val"):
            d = decide_reference(torch.from_numpy(p)[None], cost)[0].numpy()
            sets = (p >= 1 - lam) | (np.arange(19)[:, None, None] == d)
            sizes.append(sets.sum(0)[y != 255])
        assert record[name]["mean_set_size"]["image"] == pytest.approx(np.concatenate(sizes).mean())


def test_the_table_names_each_columns_unit():
    """table.md: risk and loss as fractions (as α), set sizes in classes, shares in %; each
    header says which, and the cells follow it."""
    per_roi = dict.fromkeys(ROI_NAMES, 0.0)
    record = {
        "altruistic": {
            "lambda": 0.25,
            "reached": True,
            "calibration_images": 20,
            "calibration_risk": 0.0625,
            "reported_loss": 0.125,
            "mean_set_size": {**per_roi, ROI_NAMES[0]: 1.5, ROI_NAMES[1]: 2.0},
            "singleton_share": {**per_roi, ROI_NAMES[0]: 0.5},
            "coverage": {"person": {**per_roi, ROI_NAMES[1]: 0.93}},
        }
    }
    person = CLASS_NAMES.index("person")
    lines = conformal_table(record, 0.1, "sets", [person]).splitlines()
    header = [c.strip() for c in lines[-3].strip("|").split("|")]
    cells = [c.strip() for c in lines[-1].strip("|").split("|")]
    assert dict(zip(header, cells, strict=True)) == {
        "matrix": "altruistic",
        "λ̂": "0.250",
        "calibration images": "20",
        "calibration risk (fraction)": "0.0625",
        "reported loss (fraction)": "0.125",
        "set size (classes)": "1.5",
        "set size RoI 1 (classes)": "2",
        "singletons (%)": "50.00",
        "person covered RoI 1 (%)": "93.00",
    }
