"""The run-time monitor (docs/definitions.md §22): the controller against the papers' update in
plain Python, its long-run bound on adversarial sequences, a stationary stream against a shifted
one, exact frame records, the evaluation's θ sequence against the public class driven frame by
frame, and the exported graph fed the monitor's matrices."""

from __future__ import annotations

import csv
import json
import math
import random
from pathlib import Path

import numpy as np
import pytest
import torch

from costseg.calibration.monitor import Controller, labelled_frames, run_stream
from costseg.calibration.stream_records import FrameRecord, record_frame
from costseg.classes import IGNORE_INDEX
from costseg.decision import decide_counts
from costseg.metrics.monitor import Monitor

REQUIRE = ["person:roi1:recall>=0.8", "building:roi3:precision>=0.8", "car:roi1:recall>=0.7"]


def _papers_loop(losses, alphas, eta, theta, delay, labelled, cap=math.inf):
    """θ_{t+1} = max(0, θ_t + η (L_t − α)) (capped), frame t's step taken before frame
    t + delay + 1, in plain Python: the θ each frame was decided with, and the last."""
    theta, out = list(theta), []
    for t in range(len(losses) + delay + 1):
        arrived = t - 1 - delay
        if 0 <= arrived < len(losses) and labelled[arrived]:
            for i, loss in enumerate(losses[arrived]):
                if not math.isnan(loss):
                    theta[i] = min(cap, max(0.0, theta[i] + eta[i] * (loss - alphas[i])))
        if t < len(losses):
            out.append(list(theta))
    return out, theta


@pytest.mark.parametrize("delay,share,cap", [(0, 1.0, math.inf), (3, 0.6, 0.8)])
def test_controller_is_the_papers_update(delay, share, cap):
    rng = random.Random(1)
    losses = [[rng.choice([math.nan, rng.random(), 1.0, 0.0]) for _ in range(2)] for _ in range(60)]
    alphas, eta = [0.2, 0.5], [0.3, 0.05]
    labelled = labelled_frames(60, share, seed=4)
    ctl = Controller(alphas, eta, np.array([0.1, 0.0]), theta_max=cap)
    trace = run_stream(lambda t, _: np.array(losses[t]), 60, ctl, delay, labelled)
    before, last = _papers_loop(losses, alphas, eta, [0.1, 0.0], delay, labelled.tolist(), cap)
    np.testing.assert_allclose(trace.theta[:-1], before, rtol=0, atol=1e-12)
    np.testing.assert_allclose(trace.theta[-1], last, rtol=0, atol=1e-12)
    assert (trace.capped > 0).any() == (cap < math.inf)


@pytest.mark.parametrize("cap", [math.inf, 0.5])
def test_long_run_bound_holds_on_an_adversarial_sequence(cap):
    """Losses chosen against θ (1 while θ is small, 0 once it is large, noise near the edge):
    at every frame the mean so far stays under the bound, and θ ends at most θ_safe + η."""
    alpha, eta, safe = 0.1, 0.2, 0.7
    rng = np.random.default_rng(0)

    def adversary(t: int, theta: np.ndarray) -> np.ndarray:
        if theta[0] >= safe:  # θ_safe: every loss <= α from here
            return np.array([0.0 if t % 2 else alpha])
        return np.array([1.0 if rng.random() < 0.9 else math.nan])

    ctl = Controller([alpha], [eta], theta_max=cap)
    trace = run_stream(adversary, 300, ctl)
    means = np.nancumsum(trace.losses[:, 0]) / np.cumsum(~np.isnan(trace.losses[:, 0]))
    assert (means <= trace.bounds[:, 0] + 1e-12).all()
    assert means[-1] <= trace.final_bound[0] + 1e-12
    if cap == math.inf:
        assert trace.theta[:, 0].max() <= safe + eta + 1e-12
        assert trace.final_bound[0] - alpha <= (safe + eta) / (eta * 250)
    else:  # θ never reaches θ_safe: the cap's cut keeps the bound true (and loose)
        assert trace.cut[0] > 0 and trace.final_bound[0] >= means[-1] - 1e-12


def test_a_stream_without_shift_keeps_theta_near_its_start_and_a_shift_moves_it():
    alpha, eta, start = 0.2, 0.05, 1.0
    rng = np.random.default_rng(2)
    calm = (rng.random(400) < alpha).astype(float)  # losses of mean α whatever θ
    shifted = np.where(np.arange(400) < 200, calm, (rng.random(400) < 0.6).astype(float))
    for losses, moved in ((calm, False), (shifted, True)):
        ctl = Controller([alpha], [eta], np.array([start]))
        trace = run_stream(lambda t, _, losses=losses: losses[t : t + 1], 400, ctl)
        drift = abs(trace.theta[-1, 0] - start)
        assert (drift > 0.5 * eta * 0.4 * 200) if moved else drift <= eta * 4 * math.sqrt(400)


def _frame(seed: int, size=(24, 40), sharpness: float = 2.0):
    """A frame whose probabilities favour its labels, the RoIs in bands."""
    gen = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, 19, size, generator=gen)
    labels[torch.rand(size, generator=gen) < 0.1] = IGNORE_INDEX
    logits = torch.randn(19, *size, generator=gen) * sharpness
    logits.scatter_add_(0, labels.clamp(max=18)[None], torch.full((1, *size), 2.5))
    roi = torch.arange(size[0])[:, None].expand(size) * 5 // size[0]
    return logits.softmax(0), labels, roi


def test_frame_record_counts_equal_every_pixels_under_matrices_of_the_box(tmp_path):
    """Also after the record's round trip through its file (the evaluation's)."""
    monitor = Monitor(REQUIRE, mu_max=20.0)
    space, classes = monitor.space(), [11, 2, 13]
    rng = np.random.default_rng(0)
    corners = [[0.0, 0.0, 0.0], [20.0, 20.0, 20.0], [20.0, 0.0, 3.0], [0.5, 20.0, 20.0]]
    for seed, sharpness in ((0, 2.0), (1, 6.0), (2, 0.5)):
        probs, labels, roi = _frame(seed, sharpness=sharpness)
        record_frame(probs, labels, roi, space, classes).save(tmp_path / f"{seed}.pt")
        frame = FrameRecord.load(tmp_path / f"{seed}.pt")
        assert frame.kept_pixels < (labels != IGNORE_INDEX).sum()
        for mu in [*corners, *(20 * rng.random((6, 3)) ** 3).tolist()]:
            matrix = monitor.matrix(np.log1p(mu))
            whole = decide_counts(probs[None], matrix, labels[None], roi)
            counts = frame.counts(matrix)
            assert torch.equal(counts.confusion, whole.confusion), (seed, mu)
            assert torch.equal(counts.agree, whole.agree), (seed, mu)


def test_a_designed_start_is_read_back_from_its_cost_file(tmp_path):
    from costseg.costs import save_cost

    mu = [2.5, 0.0, 0.75]
    designed = Monitor(REQUIRE, start=mu).matrix()
    save_cost(tmp_path / "designed.yaml", designed, "designed")
    monitor = Monitor(REQUIRE, start=tmp_path / "designed.yaml")
    np.testing.assert_allclose(monitor.mu, mu, rtol=0, atol=1e-12)
    assert torch.equal(monitor.fixed, designed)  # the file's own matrix is the fixed one


@pytest.mark.parametrize("space", ["whole", "regional"])
def test_evaluation_gives_the_theta_of_the_class_driven_frame_by_frame(space, tiny_run, tmp_path):
    """costseg.evaluate's monitor.csv (records gathered, walked once) against Monitor.update fed
    each frame's saved probabilities, labels and RoIs in order, with the delay and the labelled
    frames of the evaluation; the fixed matrix's losses too. In both spaces."""
    import costseg
    from costseg.checkpoints import find_checkpoint
    from costseg.data.priors import geometric_roi_map
    from costseg.data.toy import StreetScenes
    from costseg.networks.probs_files import load_probs

    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    dataset = StreetScenes("val", length=5, size=(64, 128))
    out = tmp_path / "eval"
    options = dict(monitor_delay=1, monitor_labelled=0.75, monitor_eta=0.7, seed=3,
                   monitor_space=space)  # fmt: skip
    costseg.evaluate(f"costseg:{ckpt}", dataset, ["robotistic"], roi="geometric",
                     output_dir=str(out), monitor_require=REQUIRE[:2], save_probs=True,
                     batch_size=2, num_examples=0, progress=False, **options)  # fmt: skip
    rows = list(csv.DictReader((out / "monitor.csv").open()))
    assert json.loads((out / "results.json").read_text())["monitor"]["space"] == space
    assert not (out / "monitor_records").exists()  # the records, one file a frame, walked
    monitor = Monitor(REQUIRE[:2], eta=0.7, space=space)
    fixed = monitor.matrix()
    labelled = labelled_frames(5, 0.75, seed=3)
    pending = []
    for t, row in enumerate(rows):
        _, labels, *_ = dataset[t]
        probs = load_probs(out / "probs" / f"{row['image']}.npz")
        roi = geometric_roi_map(tuple(labels.shape))
        for i, text in enumerate(REQUIRE[:2]):
            assert float(row[f"theta {text}"]) == pytest.approx(monitor.theta[i], abs=1e-12)
        fixed_losses = monitor.losses(probs, labels, roi, fixed)
        np.testing.assert_allclose([float(row[f"fixed loss {t}"]) for t in REQUIRE[:2]],
                                   fixed_losses, rtol=0, atol=1e-12)  # fmt: skip
        pending.append((probs, labels, roi, monitor.matrix(), labelled[t]))
        if len(pending) > 1:  # a delay of one frame
            *frame, matrix, arrives = pending.pop(0)
            if arrives:
                monitor.update(*frame, matrix=matrix)


@pytest.mark.parametrize("space", ["whole", "regional"])
def test_the_exported_graph_fed_the_monitors_matrices_decides_as_decide(space):
    """The graph's ``cost`` input is the monitor's matrix, or for a regional monitor its stack
    beside the RoI map (the graph of ``scripts/export.py --regional``)."""
    pytest.importorskip("onnxruntime")
    from torch import nn

    from costseg.export.graph import DecisionGraph
    from costseg.export.job import trace_graph
    from costseg.export.parity import parity
    from costseg.export.runtime import run_graph
    from costseg.networks.base import ImageNetwork
    from costseg.networks.onnx import onnx_session

    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 16, 3, padding=1), nn.Tanh(), nn.Conv2d(16, 19, 1))
    with torch.no_grad():
        net[2].weight.mul_(8)
    regional = space == "regional"
    graph = DecisionGraph(ImageNetwork(net), probabilities=True, regional=regional)
    session = onnx_session(trace_graph(graph).SerializeToString(), threads=1)
    monitor = Monitor([f"person:roi{int(regional)}:recall>=0.8"], eta=1.0, space=space)
    truth = torch.full((32, 48), 11)  # every pixel a person: the recall requirement pushes
    roi = (torch.arange(32)[:, None] * 5 // 32).expand(32, 48).to(torch.uint8)  # bands 0 … 4
    images = torch.randint(0, 256, (4, 1, 3, 32, 48), generator=torch.Generator().manual_seed(1),
                           dtype=torch.uint8)  # fmt: skip
    for image in images:
        matrix = monitor.matrix()
        given = {"roi": roi} if regional else {}
        labels, _, probs = run_graph(session, image, matrix, probabilities=True, **given)
        assert parity(probs, probs, labels, matrix, **given).outside == 0
        from_labels = monitor.decided_losses(labels[0], truth, roi)
        np.testing.assert_allclose(from_labels, monitor.losses(probs[0], truth, roi, matrix))
        monitor.update(from_labels)
    assert monitor.mu[0] > 1  # the matrices changed frame by frame
    if regional:  # ... only the street's
        stack = monitor.matrix()
        assert not torch.equal(stack[1], stack[0])
        assert all(torch.equal(stack[r], stack[0]) for r in (2, 3, 4))


COSTS = Path(__file__).parents[1] / "configs" / "costs"
REGIONAL = ["person:roi1:recall>=0.9", "building:roi3:precision>=0.9", "car:roi0:recall>=0.8"]


def _walk(monitor: Monitor, frames, delay: int = 0):
    """The evaluation's walk (evaluation/analyses/monitor.py): each frame's exact record
    counted at the θ the controller reached, the labels arriving ``delay`` frames later."""
    from costseg.evaluation.analyses.monitor import frame_counts

    classes = [t.cls for t in monitor.requirements.constraints]
    records = [record_frame(p, y, r, monitor.space(), classes) for p, y, r in frames]

    def losses(t, theta):
        return frame_counts(monitor, records[t], monitor.matrix(theta)).losses

    return run_stream(losses, len(frames), monitor.controller, delay)


def _regional_base():
    """A regional C₀: altruistic on the street, egoistic on the sidewalk, robotistic elsewhere."""
    from costseg.costs import load_cost, regional_cost

    regions = {"street": load_cost("altruistic"), "sidewalk": load_cost("egoistic")}
    return regional_cost(load_cost("robotistic"), regions).double()


@pytest.mark.parametrize("regional_base", [False, True])
def test_regional_monitor_losses_equal_deciding_each_region_by_hand(regional_base):
    """Constraint i moves only RoI r_i's matrix (RoI 0 every one): each frame decided at the
    controller's μ with decide_reference region by region, the losses counted by hand."""
    from costseg.costs import symmetric_cost
    from costseg.decision import decide_reference
    from costseg.rules.design_spaces import lagrangian_directions

    bases = _regional_base() if regional_base else symmetric_cost(19).double().expand(5, 19, 19)
    monitor = Monitor(REGIONAL, eta=2.0, mu_max=20.0, scale="mu", space="regional",
                      base=bases if regional_base else "robotistic")  # fmt: skip
    frames = [_frame(seed, sharpness=3.0) for seed in range(6)]
    trace = _walk(monitor, frames, delay=1)
    assert (trace.theta[-1] > 0).all() and not np.isnan(trace.losses).all(0).any()
    req = monitor.requirements.constraints
    directions = lagrangian_directions([(t.cls, t.metric) for t in req], 19)
    for t, (probs, labels, roi) in enumerate(frames):
        decided = torch.empty_like(labels)
        for r in range(5):  # C_r(μ) = C₀ + Σ_{i : r_i = r or r_i = 0} μ_i A_i
            matrix = bases[r].clone()
            for i, c in enumerate(req):
                if c.roi in (r, 0):
                    matrix = matrix + trace.theta[t, i] * directions[i]
            decided[roi == r] = decide_reference(probs[None], matrix)[0][roi == r]
        expected = []
        for c in req:
            region = (labels != IGNORE_INDEX) & ((roi == c.roi) if c.roi else True)
            hits = (region & (decided == c.cls) & (labels == c.cls)).sum().item()
            whole = region & ((labels if c.metric == "recall" else decided) == c.cls)
            expected.append(1 - hits / whole.sum().item() if whole.any() else math.nan)
        np.testing.assert_allclose(trace.losses[t], expected, rtol=0, atol=1e-12)
    assert monitor.matrix().shape == (5, 19, 19)


def test_a_regional_monitor_on_roi0_only_is_the_whole_image_one():
    require = ["person:roi0:recall>=0.9", "building:roi0:precision>=0.9"]
    frames = [_frame(seed, sharpness=3.0) for seed in range(5)]
    whole = Monitor(require, eta=1.0, mu_max=20.0)
    regional = Monitor(require, eta=1.0, mu_max=20.0, space="regional")
    a, b = _walk(whole, frames), _walk(regional, frames)
    assert (a.theta[-1] > 0).all()
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(a.losses, b.losses)
    assert all(torch.equal(m, whole.matrix()) for m in regional.matrix())


def test_a_regional_designed_start_is_read_back_and_refused_by_a_whole_monitor(tmp_path):
    from costseg.costs import save_cost

    mu, base = [2.5, 0.0, 0.75], _regional_base()
    designed = Monitor(REGIONAL, start=mu, base=base, space="regional").matrix()
    save_cost(tmp_path / "designed.yaml", designed, "designed")
    monitor = Monitor(REGIONAL, start=tmp_path / "designed.yaml", base=base, space="regional")
    np.testing.assert_allclose(monitor.mu, mu, rtol=0, atol=1e-12)
    assert torch.equal(monitor.fixed, designed)
    with pytest.raises(ValueError, match="needs --monitor_space regional"):
        Monitor(REGIONAL, start=tmp_path / "designed.yaml")
    with pytest.raises(ValueError, match=r"C₀ must be \(19, 19\), got \(5, 19, 19\)"):
        Monitor(REGIONAL, base=base)
    with pytest.raises(ValueError, match="not C₀"):  # the stack of another C₀
        Monitor(REGIONAL, start=tmp_path / "designed.yaml", space="regional")
    street = Monitor(["person:roi1:recall>=0.9"], start=COSTS / "street_person.yaml",
                     space="regional")  # fmt: skip
    assert street.mu == pytest.approx([9.0])  # missing a person on the street costs 1 + 9


def test_a_regional_monitor_without_a_roi_map_is_refused_in_one_line(cityscapes_root, capsys):
    import shutil

    from costseg.cli import evaluate_main

    shutil.rmtree(cityscapes_root / "gtFine" / "train")
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(["--data_root", str(cityscapes_root), "--monitor_require", REGIONAL[0],
                       "--monitor_space", "regional"])  # fmt: skip
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--monitor_space regional gives each RoI its own matrix" in err[0]
    probs, labels, _ = _frame(0)
    with pytest.raises(ValueError, match="RoI map"):
        Monitor(REGIONAL, space="regional").losses(probs, labels)
