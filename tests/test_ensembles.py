"""Ensembles and uncertainty maps (docs/definitions.md §13): an ensemble against the mean of its
members' softmaxes written out here, entropy, expected entropy and mutual information against
NumPy loops over pixels, the runs of Monte-Carlo dropout (with test-time augmentation too), and
evaluate.py and predict.py end to end with two --ckpt_path members (the explorer's hover: in
test_explorer.py)."""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from explorer_page import page_json
from PIL import Image
from torch import nn

from costseg.checkpoints import CHECKPOINT_KEY, find_checkpoint, read_torch_file
from costseg.cli import evaluate_main, predict_main
from costseg.data.from_config import build_dataset
from costseg.networks import ImageNetwork, load_costseg_checkpoint
from costseg.networks.ensemble import Ensemble
from costseg.networks.mc_dropout import MCDropout, batch_seed
from costseg.networks.protocols import Protocol, with_protocol
from costseg.networks.sliding import SlidingWindow
from costseg.networks.sources import Source
from costseg.networks.tta import TestTimeAugmentation
from costseg.networks.uncertainty import uncertainty_maps

ROUNDING = 1e-6
"""Bound on |float32 − float64| of an entropy of ≤ 5 classes (a few ulps of log 5 ≈ 1.6)."""
SAVED = 3e-3
"""Bound on an entropy read back from float16 (the map's rounding, ≤ 2^-11 · log 19 ≈ 1.4e-3,
plus the probabilities' rounding)."""


def _net(seed: int, classes: int = 5, dropout: float = 0.0) -> ImageNetwork:
    torch.manual_seed(seed)
    layers = [nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.Conv2d(8, classes, 1)]
    return ImageNetwork(nn.Sequential(*layers, nn.Dropout(dropout)))


def _member(net: nn.Module, passes: int | None = None) -> Source:
    if passes is None:
        return Source("network", {"network": "test"}, network=net)
    return Source("probs", {"network": "test"}, network=MCDropout(net, passes, seed=3))


def _images(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (2, 3, 6, 7), generator=g).byte()


def _entropy_loop(p: np.ndarray) -> np.ndarray:
    """(N, H, W) → (H, W): −Σ_k p_k ln p_k pixel by pixel in float64 (0 ln 0 = 0)."""
    out = np.zeros(p.shape[1:])
    for y in range(p.shape[1]):
        for x in range(p.shape[2]):
            out[y, x] = -sum(float(v) * math.log(float(v)) for v in p[:, y, x] if v > 0)
    return out


def _uncertainty_loop(runs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H(p̄), E_t H(p_t) and their difference, for (N, H, W) float64 runs."""
    mean = sum(runs) / len(runs)
    expected = sum(_entropy_loop(r) for r in runs) / len(runs)
    return _entropy_loop(mean), expected, _entropy_loop(mean) - expected


def test_a_one_member_ensemble_is_the_member(one_thread):
    net, images = _net(0, dropout=0.5), _images()
    with torch.inference_mode():
        plain = Ensemble([_member(net)])
        assert torch.equal(plain(images, ["a", "b"]), net(images).softmax(1))
        assert plain.average(images).expected_entropy is None  # one run
        member = _member(net, passes=4)
        alone = member.network.average(images, ["a", "b"])
        ensemble = Ensemble([member]).average(images, ["a", "b"])
        assert torch.equal(ensemble.mean, alone.mean)
        assert torch.equal(ensemble.expected_entropy, alone.expected_entropy)


def test_two_identical_members_equal_one_and_have_no_mutual_information(one_thread):
    images = _images()
    with torch.inference_mode():
        for passes in (None, 3):  # identical members are seeded alike: identical passes too
            one = _member(_net(0, dropout=0.3), passes)
            two = Ensemble([_member(_net(0, dropout=0.3), passes) for _ in range(2)])
            runs = two.average(images, ["a", "b"])
            alone, expected = one.scores_and_entropy(images, ["a", "b"])
            assert torch.equal(runs.mean, alone if passes else alone.softmax(1))  # (p + p) / 2
            if passes:  # the runs are every member's passes: the member's own runs, twice
                assert torch.equal(runs.expected_entropy, expected)
            else:
                maps = uncertainty_maps(runs.mean, runs.expected_entropy)
                assert torch.equal(maps["mutual_information"], torch.zeros(2, 6, 7))


def test_two_members_mean_their_softmaxes_and_their_uncertainty_is_the_loops(one_thread):
    a, b, images = _net(0), _net(1), _images()
    with torch.inference_mode():
        runs = Ensemble([_member(a), _member(b)]).average(images, ["a", "b"])
        pa, pb = a(images).softmax(1), b(images).softmax(1)
    assert torch.equal(runs.mean, (pa + pb) / 2)
    maps = uncertainty_maps(runs.mean, runs.expected_entropy)
    for i in range(len(images)):
        h, e, mi = _uncertainty_loop([pa[i].double().numpy(), pb[i].double().numpy()])
        np.testing.assert_allclose(maps["entropy"][i].numpy(), h, atol=ROUNDING, rtol=0)
        np.testing.assert_allclose(maps["expected_entropy"][i].numpy(), e, atol=ROUNDING, rtol=0)
        np.testing.assert_allclose(maps["mutual_information"][i].numpy(), mi, atol=ROUNDING, rtol=0)
    assert float(maps["mutual_information"].max()) > 1e-3  # the members disagree somewhere


def test_each_member_runs_with_the_protocol_and_its_runs_are_the_members(one_thread):
    a, b, images = _net(0), _net(1), _images()
    protocol = Protocol(crop=(4, 4), stride=(2, 3), flip=True)
    members = [with_protocol(_member(n), protocol, None, 0) for n in (a, b)]
    with torch.inference_mode():
        runs = Ensemble(members).average(images, ["a", "b"])
        each = []
        for net in (a, b):  # the protocol written out: flip, windows inside each view
            windows = SlidingWindow(net, (4, 4), (2, 3))
            plain, flipped = windows(images), windows(images.flip(-1)).flip(-1)
            each.append((plain.softmax(1) + flipped.softmax(1)) / 2)
    assert torch.equal(runs.mean, (each[0] + each[1]) / 2)
    maps = uncertainty_maps(runs.mean, runs.expected_entropy)
    for i in range(len(images)):  # two runs: the members (the views make one run each)
        _, e, mi = _uncertainty_loop([p[i].double().numpy() for p in each])
        np.testing.assert_allclose(maps["expected_entropy"][i].numpy(), e, atol=ROUNDING, rtol=0)
        np.testing.assert_allclose(maps["mutual_information"][i].numpy(), mi, atol=ROUNDING, rtol=0)


def test_members_that_disagree_on_the_classes_are_refused(one_thread):
    ensemble = Ensemble([_member(_net(0)), _member(_net(1, classes=4))])
    with pytest.raises(ValueError, match=r"member 1 gives 5, member 2 .* gives 4"):
        ensemble(_images())


def _passes(view: nn.Module, images: torch.Tensor, passes: int, key: str) -> list[torch.Tensor]:
    """The softmax of each pass of one seeded stream, dropout on, drawn one after another."""
    modules = list(view.modules())
    with torch.random.fork_rng():
        torch.manual_seed(batch_seed(3, key))
        for m in modules:
            m.training = isinstance(m, nn.Dropout)
        out = [view(images).float().softmax(1) for _ in range(passes)]
        for m in modules:
            m.training = False
    return out


def test_the_runs_of_monte_carlo_dropout_are_its_passes_each_over_the_views(one_thread):
    net, images = _net(2, dropout=0.5), _images()[:1]
    with torch.inference_mode():
        runs = MCDropout(net, 4, seed=3).average(images, ["a"])
        expected = _uncertainty_loop([p[0].double().numpy() for p in _passes(net, images, 4, "a")])
        tta = TestTimeAugmentation(net, flip=True, passes=4, seed=3)
        views = tta.average(images, ["a"])
        plain = _passes(tta.views[0], images, 4, "a")
        flipped = _passes(tta.views[1], images, 4, "a flip")  # each view's own stream
    np.testing.assert_allclose(runs.expected_entropy[0].numpy(), expected[1], atol=ROUNDING)
    pass_maps = [((p + f) / 2)[0].double().numpy() for p, f in zip(plain, flipped, strict=True)]
    _, e, _ = _uncertainty_loop(pass_maps)
    np.testing.assert_allclose(views.expected_entropy[0].numpy(), e, atol=ROUNDING, rtol=0)
    np.testing.assert_allclose(views.mean[0].double().numpy(), sum(pass_maps) / 4, atol=1e-6)
    assert TestTimeAugmentation(net, flip=True).average(images).expected_entropy is None


@pytest.fixture(scope="module")
def checkpoints(tiny_run, tmp_path_factory) -> tuple[Path, Path]:
    """The tiny run's checkpoint and a copy with perturbed weights."""
    first = find_checkpoint(None, runs_dir=tiny_run[2])
    checkpoint = read_torch_file(first)
    g = torch.Generator().manual_seed(0)
    for key, value in checkpoint["state_dict"].items():
        if key.startswith("net.") and value.is_floating_point() and "running" not in key:
            checkpoint["state_dict"][key] = value + 0.05 * torch.randn(value.shape, generator=g)
    second = tmp_path_factory.mktemp("perturbed") / "perturbed.ckpt"
    torch.save(checkpoint, second)
    return first, second


def _member_probs(paths, image: torch.Tensor) -> list[np.ndarray]:
    """(N, H, W) float64 softmax of each checkpoint's network on one (3, H, W) uint8 image."""
    with torch.inference_mode():
        return [
            load_costseg_checkpoint(p).network(image[None]).softmax(1)[0].double().numpy()
            for p in paths
        ]


@pytest.mark.figures
def test_evaluate_with_two_members_records_both_and_saves_their_uncertainty(checkpoints, tmp_path):
    out = tmp_path / "eval"
    evaluate_main(["--ckpt_path", *map(str, checkpoints), "--cost", "robotistic", "--limit", "1",
                   "--num_examples", "1", "--output_dir", str(out), "--no-progress",
                   "--save-probs", "--explorer"])  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    members = [m["network"] for m in results["source"]["members"]]
    assert members == [f"costseg:{p}" for p in checkpoints]
    assert results["source"]["priors"]["member"] == 1  # the first costseg member's priors
    assert "mutual information over the 2 members" in results["source"]["uncertainty"]
    assert results["probabilities"].startswith("ensemble: mean probabilities of 2 members")
    saved = np.load(out / "probs" / "val_000000.npz")
    assert sorted(saved.files) == ["entropy", "mutual_information", "probs"]
    dataset = build_dataset(load_costseg_checkpoint(checkpoints[0]).data_config, "val")
    runs = _member_probs(checkpoints, dataset[0][0])
    probs = saved["probs"].astype(np.float64)
    np.testing.assert_allclose(probs, sum(runs) / 2, atol=1e-3, rtol=0)
    h_saved = _entropy_loop(probs)  # the entropy against the saved probabilities
    np.testing.assert_allclose(saved["entropy"].astype(np.float64), h_saved, atol=SAVED, rtol=0)
    _, _, mutual = _uncertainty_loop(runs)
    got = saved["mutual_information"].astype(np.float64)
    np.testing.assert_allclose(got, np.maximum(mutual, 0), atol=SAVED, rtol=0)
    assert mutual.max() > 1e-3
    assert (out / "figures" / "masks_0.png").is_file()
    events = b"".join(p.read_bytes() for p in out.glob("events.out.tfevents.*"))
    assert b"evaluation/uncertainty/0" in events
    page = page_json(out / "explorer.html")["examples"][0]["uncertainty"]
    for key in ("entropy", "mutual_information"):  # the hover's maps: the saved ones
        shown = np.frombuffer(base64.b64decode(page[key]), "<f2").reshape(saved[key].shape)
        np.testing.assert_array_equal(shown, saved[key])


def test_predict_with_two_members_draws_and_saves_the_uncertainty(checkpoints, tmp_path):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (40, 56, 3), dtype=np.uint8)
    Image.fromarray(image).save(tmp_path / "photo.png")
    out = tmp_path / "out"
    predict_main(["--input", str(tmp_path / "photo.png"), "--ckpt_path", *map(str, checkpoints),
                  "--cost", "egoistic", "--output_dir", str(out), "--save-probs",
                  "--no-progress", "--explorer", "--num_examples", "1"])  # fmt: skip
    source = json.loads((out / "counts.json").read_text())["source"]
    assert [m["network"] for m in source["members"]] == [f"costseg:{p}" for p in checkpoints]
    saved = np.load(out / "probs" / "photo.npz")
    runs = _member_probs(checkpoints, torch.from_numpy(image).permute(2, 0, 1))
    h, _, mutual = _uncertainty_loop(runs)
    np.testing.assert_allclose(saved["entropy"].astype(np.float64), h, atol=SAVED, rtol=0)
    got = saved["mutual_information"].astype(np.float64)
    np.testing.assert_allclose(got, np.maximum(mutual, 0), atol=SAVED, rtol=0)
    # the panel: image and rule; entropy and differences; mutual information (a third row)
    panel = np.asarray(Image.open(out / "panels" / "photo.png"))
    single = tmp_path / "single"
    predict_main(["--input", str(tmp_path / "photo.png"), "--ckpt_path", str(checkpoints[0]),
                  "--cost", "egoistic", "--output_dir", str(single), "--no-progress"])  # fmt: skip
    alone = np.asarray(Image.open(single / "panels" / "photo.png"))
    assert panel.shape[1] == alone.shape[1] and panel.shape[0] > alone.shape[0]
    example = page_json(out / "explorer.html")["examples"][0]
    assert sorted(example["uncertainty"]) == ["entropy", "mutual_information"]
    embedded = np.frombuffer(base64.b64decode(example["uncertainty"]["entropy"]), "<f2")
    np.testing.assert_array_equal(embedded.reshape(40, 56), saved["entropy"])


def test_mismatched_members_and_mixed_sources_are_one_line(checkpoints, tmp_path, capsys):
    checkpoint = read_torch_file(checkpoints[0])
    checkpoint[CHECKPOINT_KEY]["class_names"] = checkpoint[CHECKPOINT_KEY]["class_names"][:18]
    other = tmp_path / "other_classes.ckpt"
    torch.save(checkpoint, other)
    image = tmp_path / "photo.png"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(image)
    cases = [
        (evaluate_main, ["--ckpt_path", str(checkpoints[0]), str(other)], "trained on 18 classes"),
        (predict_main, ["--input", str(image), "--ckpt_path", str(checkpoints[0]), str(other)],
         "trained on 18 classes"),
        (evaluate_main, ["--probs", str(tmp_path), "--ckpt_path", str(other)], "--probs replaces"),
    ]  # fmt: skip
    for main, args, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            main(["--output_dir", str(tmp_path / "never"), *args])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_scores_without_entropy_are_the_same_mean(one_thread):
    """The forward of an ensemble of MC-dropout members (and of TTA with dropout) skips the
    entropies and gives the mean bit for bit; batches() asks for the entropy only of the first
    images."""
    from costseg.networks.sources import batches

    images, names = _images(), ["a", "b"]
    with torch.inference_mode():
        members = [_member(_net(seed, dropout=0.5), passes=3) for seed in (0, 1)]
        ensemble = Ensemble(members)
        runs = ensemble.average(images, names)
        assert torch.equal(ensemble(images, names), runs.mean)
        assert ensemble.average(images, names, keep_entropy=False).expected_entropy is None
        tta = TestTimeAugmentation(_net(2, dropout=0.5), flip=True, passes=3, seed=1)
        assert torch.equal(tta(images, names), tta.average(images, names).mean)

    class Scenes(torch.utils.data.Dataset):
        def __len__(self):
            return 4

        def __getitem__(self, i):
            return _images(i)[0], torch.zeros(6, 7, dtype=torch.long)

    source = Source("probs", {"network": "ensemble"}, network=ensemble)
    with torch.inference_mode():
        got = list(batches(source, Scenes(), range(4), 2, torch.device("cpu"), 0, None, 1))
        assert torch.equal(got[1].scores, ensemble(got[1].images, got[1].stems))
    assert [b.expected_entropy is not None for b in got] == [True, False]
